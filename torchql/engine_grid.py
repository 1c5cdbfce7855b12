"""The engine's automatic storage grid (``grid="auto"``, the default): each sample's own intervals.

The first reference of every sample is built on the probe grid (:data:`torchql.grid.AUTO_PROBE`
uniform intervals with the observation times). From the size of the fourth derivative of the
model's solutions along it (:func:`fourth_derivative_scale`, from the model's slopes and their
rates of change along its flow at the probe's uniform nodes), the engine takes for each sample
the fewest of :data:`torchql.grid.AUTO_COUNTS` uniform intervals whose cubic Hermite
interpolation of those solutions stays within :data:`torchql.grid.AUTO_SAFETY` times
``sqrt(rtol)`` of the states (:func:`torchql.grid.needed_intervals`). A count that divides the
probe's keeps every ``k``-th of its uniform nodes and all its fixed ones (``t0``, the
observation times, an input's breakpoints), with the reference there; a larger one gets a grid
built anew (:func:`torchql.grid.make_grids`), with the probe's reference interpolated there
(shooting's solved again from that prediction).

The choice is the sample's own: ``fit`` and each sample of ``fit_many`` choose alike, and the
samples of a chunk are then stacked on per-sample grids (padded by their last node), or keep one
shared grid when they all chose the same. A smooth, slow trajectory (a coasting car) is fitted
on 20 intervals, an oscillation over a few periods on 50 to 250, where the fixed default had 1,000.
"""

from __future__ import annotations

import math

import torch
from torch.func import jvp, vmap

from .grid import (AUTO_PROBE, AUTO_SAFETY, auto_counts, coarse_index, last_nodes, make_grids, needed_intervals,
                   uniform_nodes)
from .splines import hermite_per_sample

__all__ = ["AutoGrid", "fourth_derivative_scale", "pad_nodes"]


class AutoGrid:
    """The choice of each sample's storage grid (mixed into :class:`torchql.engine.Engine`)."""

    def _probe_nodes(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Each sample's ``t0 (S,)``, final time ``(S,)`` and the probe grid's uniform nodes ``(S, P + 1)``."""
        t0 = self.spec.t0.expand(self.spec.B)[self.index]
        t_end = (self.t_obs[..., -1]).expand(self.S)
        return t0, t_end, uniform_nodes(self.grid, t0, t_end, AUTO_PROBE)

    def _grid_groups(self, counts: torch.Tensor, first: tuple) -> list:
        """The chunk's samples grouped by their grid counts ``(S,)``, each group with its part of
        the first references ``first = (z0, traj, z_dot, W, errors)``: ``[(rows, (..., counts))]``."""
        groups = []
        for c in counts.unique().tolist():
            rows = (counts == c).nonzero().flatten()
            part = tuple(None if v is None else [v[r] for r in rows.tolist()] if isinstance(v, list) else v[rows]
                         for v in first)
            groups.append((rows, (*part, counts[rows])))
        return groups

    def _given_start(self, first: tuple) -> tuple:
        """A group's first references (:meth:`_grid_groups`), on the group's probe grid (the
        chunk's may be longer, by padding only)."""
        z0, traj, z_dot, W, errors, counts = first
        G = self.G
        return (z0, traj[:, :G], None if z_dot is None else z_dot[:, :G], None if W is None else W[:, :G],
                errors, counts)

    def _run_groups(self, groups: list, report) -> dict:
        """Fit each group of the chunk's samples (:meth:`_grid_groups`) as a chunk of its own, on
        the grids its samples chose (a sample's fit is the same alone or in its group), and put
        their results together in the chunk's order. The groups' final solutions are integrated
        together (:meth:`~torchql.engine_final.FinalPass._share_final_solutions`)."""
        out: dict = {}
        done = 0
        children = []
        for rows, first in groups:
            child = type(self)(self.spec, self.index[rows], self.max_time, history=self.history is not None,
                               callback=self.callback, start=self.start)
            children.append((rows, child, child._iterate(lambda count, offset=done: report(offset + count), first)))
            done += rows.numel()
        self._share_final_solutions([(child, st) for _, child, st in children])
        for rows, child, st in children:
            part = child._conclude(st)
            self.nfev += child.nfev
            for key, value in part.items():
                if value is None:
                    out[key] = None
                elif isinstance(value, list):
                    out.setdefault(key, [None] * self.S)
                    for k, r in enumerate(rows.tolist()):
                        out[key][r] = value[k]
                else:
                    if key not in out:
                        out[key] = value.new_empty((self.S, *value.shape[1:]))
                    out[key][rows] = value
        return out

    def _choose_grid(self, z0: torch.Tensor, traj: torch.Tensor, z_dot: torch.Tensor | None, W, errors: list,
                     counts: torch.Tensor):
        """Each sample's grid of ``counts (S,)`` uniform intervals, from its first reference ``traj
        (S, G, M)`` on the probe grid (slopes ``z_dot``, columns ``W`` or None, estimates ``z0 (S,
        M)``, solver ``errors``): sets the engine's ``grid``, ``G``, ``obs`` and ``t_obs`` and
        returns the first reference on it, ``(z0, traj, z_dot, W, errors)`` (built again for the
        samples whose grid is finer than the probe)."""
        spec, S = self.spec, self.S
        t0, _, probe = self._probe_nodes()
        coarse = (AUTO_PROBE % counts == 0)
        keep = self._kept_nodes(probe, counts, coarse)
        index = coarse_index(keep)  # (S, G1): the coarsened samples' nodes (the others: placeholders)
        grid = self.grid.expand(S, self.G).gather(1, index)
        fine = (~coarse).nonzero().flatten()
        if fine.numel():  # built anew, one construction per count
            t_obs = self.t_obs.expand(S, -1)
            pieces = []
            for c in counts[fine].unique().tolist():
                rows = fine[counts[fine] == c]
                pieces.append((rows, make_grids(c, t0[rows], t_obs[rows], breakpoints=spec.breakpoints)[0]))
            width = max(grid.shape[1], *(g.shape[1] for _, g in pieces))
            grid, index = pad_nodes(grid, width), pad_nodes(index, width)
            for rows, g in pieces:
                grid[rows] = pad_nodes(g, width)
        probe_grid, probe_traj, probe_dot = self.grid.expand(S, self.G), traj, z_dot
        self._set_grid(grid)
        traj = _gather(traj, index)
        z_dot = None if z_dot is None else _gather(z_dot, index)
        W = None if W is None else _gather(W, index)
        if fine.numel():
            errors = self._finer_reference(fine, z0, probe_grid, probe_traj, probe_dot, traj, z_dot, W, errors)
        return z0, traj, z_dot, W, errors

    def _finer_reference(self, fine, z0, probe_grid, probe_traj, probe_dot, traj, z_dot, W, errors) -> list:
        """The first reference of the samples ``fine`` on their grids finer than the probe, in
        place in ``traj``, ``z_dot`` and ``W``: the probe's reference interpolated (cubic Hermite,
        with its slopes: the data's, or the model's), the Kantorovich reference as it is; a
        shooting reference is the model's own solution, found again from that prediction."""
        grid = self.grid.expand(self.S, self.G)[fine]
        slopes = probe_dot
        if slopes is None:
            with torch.no_grad():
                slopes = vmap(self.system.f)(probe_grid[fine].reshape(-1), probe_traj[fine].reshape(-1, traj.shape[-1]))
            slopes = slopes.reshape(probe_traj[fine].shape)
        else:
            slopes = slopes[fine]
        values, derivatives = hermite_per_sample(probe_grid[fine], probe_traj[fine], slopes, grid,
                                                 count=last_nodes(probe_grid[fine]) + 1)
        traj[fine] = values
        if z_dot is not None:
            z_dot[fine] = derivatives
        if not self.spec.scheme.integrates_model:
            return errors
        if W is not None:  # the solution with its sensitivities, on the new grid
            traj[fine], W[fine], again = self._solve_with_sensitivities(fine, z0[fine])
        else:
            traj[fine], again = self._nonlinear(fine, z0[fine], loose=False, guess=values)
        errors = list(errors)
        for k, e in zip(fine.tolist(), again):
            errors[k] = e
        return errors

    def _grid_counts(self, traj: torch.Tensor, errors: list) -> torch.Tensor:
        """Each sample's uniform intervals ``(S,)``, a count of :data:`AUTO_COUNTS`, from the model's
        slopes and their rates of change along its first reference ``traj (S, G, M)`` at the probe
        grid's uniform nodes (:func:`fourth_derivative_scale`); the probe's own count where the
        reference failed (``errors``, one per sample)."""
        n, S = self.system.n, self.S
        t0, t_end, probe = self._probe_nodes()
        times = self.grid.expand(S, self.G).gather(1, probe)
        nodes = traj.gather(1, probe.unsqueeze(-1).expand(S, -1, traj.shape[-1]))  # (S, P + 1, M)
        f = self.system.f

        def slope_and_rate(t, z):  # x' = f and x'' = f_t + f_x f along the model's flow through z
            return jvp(f, (t, z), (torch.ones_like(t), f(t, z)))

        with torch.no_grad():
            slopes, rates = vmap(slope_and_rate)(times.reshape(-1), nodes.reshape(-1, nodes.shape[-1]))
        fourth = fourth_derivative_scale(slopes.reshape(nodes.shape)[..., :n], rates.reshape(nodes.shape)[..., :n])
        rtol = AUTO_SAFETY * math.sqrt(self.spec.rtol)
        needed = needed_intervals(fourth, traj[..., :n], rtol, self.spec.atol * rtol / self.spec.rtol, span=t_end - t0)
        counts = auto_counts(needed)
        failed = torch.tensor([e is not None for e in errors], dtype=torch.bool, device=counts.device)
        return torch.where(failed, torch.full_like(counts, AUTO_PROBE), counts)

    def _kept_nodes(self, probe, counts, coarse) -> torch.Tensor:
        """``(S, G)`` bool: the probe grid's nodes a coarsened sample keeps (every ``P / count``-th
        uniform node, the first, the observation nodes and the breakpoints); the first node only
        for the others (their grids are built anew)."""
        S, G = self.S, self.G
        keep = torch.zeros(S, G, dtype=torch.bool, device=probe.device)
        step = torch.where(coarse, AUTO_PROBE // counts, torch.ones_like(counts))
        every = (torch.arange(AUTO_PROBE + 1, device=probe.device).unsqueeze(0) % step.unsqueeze(1)) == 0
        keep.scatter_(1, torch.where(every, probe, probe[:, :1]), True)
        keep.scatter_(1, self.obs.expand(S, -1), True)
        breakpoints = self.spec.breakpoints
        if breakpoints is not None:
            grid = self.grid.expand(S, G).contiguous()
            inner = breakpoints.to(grid)
            at = torch.searchsorted(grid, inner.expand(S, -1).contiguous()).clamp(max=G - 1)
            keep.scatter_(1, at, True)
        keep &= coarse.unsqueeze(1)
        keep[:, 0] = True
        return keep

    def _set_grid(self, grid: torch.Tensor) -> None:
        """The chunk's grids ``(S, G')`` from now on: one shared ``(G',)`` where every sample has the
        same (and the samples share their times), else per sample (``t_obs`` stacked ``(S, T)``)."""
        shared = self.t_obs.dim() == 1 and bool((grid == grid[:1]).all())
        if shared:
            self.grid = grid[0].contiguous()
            self.obs = torch.searchsorted(self.grid, self.t_obs)
        else:
            self.grid = grid.contiguous()
            self.t_obs = self.t_obs.expand(self.S, -1).contiguous()
            self.obs = torch.searchsorted(self.grid, self.t_obs)
        self.G = self.grid.shape[-1]


def fourth_derivative_scale(slopes: torch.Tensor, rates: torch.Tensor) -> torch.Tensor:
    """The size ``(S, 1, n)`` of the fourth derivatives of trajectories from their first and second
    derivatives ``slopes, rates (S, P, n)`` at nodes spread over the span: ``max |x''|^3 / max |x'|^2``
    per component.

    The trajectory's fastest time scale is ``tau = max |x'| / max |x''|``, and its fourth
    derivative about ``max |x''| / tau^2``: exact for oscillations and exponentials (``omega^4``
    and ``k^4`` times the amplitude), a ninth for a logistic curve's (where the count of
    intervals, which goes as its fourth root, is 1.7 times too small). The engine takes ``x'``
    and ``x''`` from the model along the first reference (``x'' = f_t + f_x f``, one forward-mode
    derivative at every node), not from differences of the reference: one built from the data
    has derived states that are only once differentiable (a smoothing spline's slopes), whose
    differences follow the spline's knots instead of the model (on an oscillator's exact data,
    3.5 times its fourth derivative), and higher derivatives of the model cost more than a small fit.
    """
    first = slopes.abs().amax(dim=1, keepdim=True)
    second = rates.abs().amax(dim=1, keepdim=True)
    tiny = torch.finfo(slopes.dtype).tiny
    return torch.where(first > 0, second**3 / first.clamp(min=tiny) ** 2, torch.zeros_like(first))


def pad_nodes(x: torch.Tensor, width: int) -> torch.Tensor:
    """``x (S, G, ...)`` padded along its second dimension to ``width`` by repeating its last entry."""
    if x.shape[1] >= width:
        return x.clone()
    return torch.cat([x, x[:, -1:].expand(x.shape[0], width - x.shape[1], *x.shape[2:])], dim=1)


def _gather(x: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``x (S, G, ...)`` at the nodes ``index (S, G')`` of each sample."""
    shape = index.shape + x.shape[2:]
    flat = index.reshape(*index.shape, *([1] * (x.dim() - 2))).expand(shape)
    return x.gather(1, flat)
