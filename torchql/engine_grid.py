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
from torch.func import vmap

from .engine_state import shifted_report
from .grid import (AUTO_COUNTS, AUTO_PROBE, AUTO_SAFETY, auto_counts, coarse_index, geometric_nodes, last_nodes, make_grids,
                   nearest_nodes, needed_intervals, uniform_nodes)
from .linearize import flow_rates
from .splines import hermite_per_sample

__all__ = ["AutoGrid", "fourth_derivative_scale", "derivative_scale", "pad_nodes"]


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
            child.stiff_met = {k for k, r in enumerate(rows.tolist()) if r in self.stiff_met}  # (first references')
            children.append((rows, child, child._iterate(shifted_report(report, done), first)))
            done += rows.numel()
        report("final pass")  # the groups' final solutions, together
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
                pieces.append((rows, make_grids(c, t0[rows], t_obs[rows], stiff=spec.stiff,
                                                breakpoints=spec.breakpoints)[0]))
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
        shooting reference, and a stiff model's integrated one (whose interpolant across the
        probe's wide intervals misses its fast layers), is the model's own solution, found again
        from that prediction (at the fit's tolerance, as :meth:`Engine._first_reference` says)."""
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
        if self.start == "data" or not self.spec.scheme.integrates_model and not self.spec.stiff:
            return errors  # an interpolant (shooting's from the data is solved on the whole grid after)
        if W is not None:  # the solution with its sensitivities, on the new grid
            traj[fine], W[fine], again = self._solve_with_sensitivities(fine, z0[fine])
        else:
            traj[fine], again = self._nonlinear(fine, z0[fine], loose=False, guess=values)
        errors = list(errors)
        for k, e in zip(fine.tolist(), again):
            errors[k] = e
        return errors

    def _grid_counts(self, traj: torch.Tensor, z_dot: torch.Tensor | None, errors: list) -> torch.Tensor:
        """Each sample's uniform intervals ``(S,)``, a count of :data:`AUTO_COUNTS`, from the model's
        slopes and their rates of change along its first reference ``traj (S, G, M)`` at the probe
        grid's uniform nodes (:func:`fourth_derivative_scale`), or for a stiff model from the
        interpolation error of that reference itself (:meth:`_stiff_counts`); the probe's own count
        where the reference failed (``errors``, one per sample), and for a stiff model's reference
        built from the data (which is as smooth as the data allow, not as the model's solutions:
        on van der Pol's it asked for the most intervals, where the model's solution asks for the
        fewest)."""
        n, S = self.system.n, self.S
        if self.spec.stiff:
            counts = (self._stiff_counts(traj) if self.start != "data"
                      else torch.full((S,), AUTO_PROBE, dtype=torch.long, device=traj.device))
            failed = torch.tensor([e is not None for e in errors], dtype=torch.bool, device=counts.device)
            return torch.where(failed, torch.full_like(counts, AUTO_PROBE), counts)
        t0, t_end, probe = self._probe_nodes()
        times = self.grid.expand(S, self.G).gather(1, probe)
        nodes = traj.gather(1, probe.unsqueeze(-1).expand(S, -1, traj.shape[-1]))  # (S, P + 1, M)
        # x' = f and x'' = f_t + f_x f along the model's flow through the nodes
        slopes, rates = flow_rates(self.system.f, times.reshape(-1), nodes.reshape(-1, nodes.shape[-1]), n)
        slopes, rates = slopes.reshape(nodes.shape)[..., :n], rates.reshape(*nodes.shape[:-1], n)
        degree = self.spec.linear_solver.storage_degree
        derivative = (fourth_derivative_scale(slopes, rates) if degree == 3
                      else derivative_scale(slopes, rates, degree + 1))
        rtol = AUTO_SAFETY * math.sqrt(self.spec.rtol)
        needed = needed_intervals(derivative, traj[..., :n], rtol, self.spec.atol * rtol / self.spec.rtol,
                                  span=t_end - t0, degree=degree)
        counts = auto_counts(needed)
        failed = torch.tensor([e is not None for e in errors], dtype=torch.bool, device=counts.device)
        return torch.where(failed, torch.full_like(counts, AUTO_PROBE), counts)

    def _stiff_counts(self, traj: torch.Tensor) -> torch.Tensor:
        """A stiff model's uniform intervals ``(S,)``: the fewest of the counts dividing
        :data:`AUTO_PROBE` whose grid (its uniform nodes, the observation times and the geometric
        early nodes) interpolates the first reference ``traj (S, G, M)`` at every node of the probe
        within :data:`AUTO_SAFETY` times ``sqrt(rtol)``, the slopes at its nodes by differences of
        the reference's values (:func:`difference_slopes`).

        Why not the model's slopes, or its fourth derivative as for the other models: a stiff
        component's value off its slow manifold by the solver's error ``delta`` has the slope
        error ``lambda delta``, and over a grid interval ``h`` an interpolation error
        ``h lambda delta`` (Robertson: 1e4 times the tolerance at ``t = 1500``), which says
        nothing of how finely the trajectory must be stored; and the fourth-derivative estimate
        takes the fastest time scale anywhere (the initial layer, which the geometric nodes
        resolve) as everywhere's. Beyond the probe's count the needed count is extrapolated from
        the error at half of it (the error falls as the fourth power of the width)."""
        n, S = self.system.n, self.S
        grid = self.grid.expand(S, self.G)
        z_dot = difference_slopes(grid, traj[..., :n])
        rtol = AUTO_SAFETY * math.sqrt(self.spec.rtol)
        tol = self.spec.atol * rtol / self.spec.rtol + rtol * traj[..., :n].abs().amax(dim=1, keepdim=True)
        _, _, probe = self._probe_nodes()
        counts = torch.full((S,), AUTO_PROBE, dtype=torch.long, device=traj.device)
        found = torch.zeros(S, dtype=torch.bool, device=traj.device)
        ratio = torch.full((S,), math.inf, dtype=traj.dtype, device=traj.device)
        for c in sorted(c for c in AUTO_COUNTS if AUTO_PROBE % c == 0 and c < AUTO_PROBE):
            keep = self._kept_nodes(probe, torch.full_like(counts, c), torch.ones_like(found))
            index = coarse_index(keep)
            values, _ = hermite_per_sample(grid.gather(1, index), _gather(traj, index)[..., :n],
                                           _gather(z_dot, index), grid, count=keep.sum(dim=1))
            ratio = ((values - traj[..., :n]).abs() / tol).amax(dim=(1, 2)).nan_to_num(nan=math.inf)
            counts = torch.where(~found & (ratio <= 1), c, counts)
            found |= ratio <= 1
        # the last ratio is the largest count's below the probe's (its half): beyond the probe, extrapolated
        beyond = auto_counts(AUTO_PROBE / 2 * ratio.clamp(max=1e30) ** 0.25)
        return torch.where(found, counts, torch.maximum(beyond, torch.full_like(counts, AUTO_PROBE)))

    def _kept_nodes(self, probe, counts, coarse) -> torch.Tensor:
        """``(S, G)`` bool: the probe grid's nodes a coarsened sample keeps (every ``P / count``-th
        uniform node, the first, the observation nodes, the breakpoints and a stiff model's
        geometric nodes); the first node only for the others (their grids are built anew)."""
        S, G = self.S, self.G
        keep = torch.zeros(S, G, dtype=torch.bool, device=probe.device)
        step = torch.where(coarse, AUTO_PROBE // counts, torch.ones_like(counts))
        every = (torch.arange(AUTO_PROBE + 1, device=probe.device).unsqueeze(0) % step.unsqueeze(1)) == 0
        keep.scatter_(1, torch.where(every, probe, probe[:, :1]), True)
        keep.scatter_(1, self.obs.expand(S, -1), True)
        if self.spec.stiff:
            t0, t_end, _ = self._probe_nodes()
            keep.scatter_(1, nearest_nodes(self.grid, geometric_nodes(t0, t_end)), True)
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
    return derivative_scale(slopes, rates, 4)


def derivative_scale(slopes: torch.Tensor, rates: torch.Tensor, order: int) -> torch.Tensor:
    """The size ``(S, 1, n)`` of the derivatives of order ``order >= 2`` of trajectories from their first
    and second derivatives ``slopes, rates (S, P, n)``: ``max |x''| / tau^(order - 2)`` with the
    fastest time scale ``tau = max |x'| / max |x''|`` (see :func:`fourth_derivative_scale`; the sixth,
    ``max |x''|^5 / max |x'|^4``, sizes the grid of quintic storage)."""
    first = slopes.abs().amax(dim=1, keepdim=True)
    second = rates.abs().amax(dim=1, keepdim=True)
    tiny = torch.finfo(slopes.dtype).tiny
    k = order - 2
    return torch.where(first > 0, second ** (k + 1) / first.clamp(min=tiny) ** k, torch.zeros_like(first))


def difference_slopes(grid: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Slopes ``(S, G, n)`` of values ``x (S, G, n)`` on grids ``(S, G)`` by second-order differences:
    the three-point formula of a node and its uneven neighbours, one-sided (the node and the next
    two on its side) at the ends and at a padded grid's last node; first order where a grid has
    only one interval on that side."""
    tiny = torch.finfo(x.dtype).tiny
    h = torch.cat([torch.zeros_like(grid[:, :1]), grid[:, 1:] - grid[:, :-1], torch.zeros_like(grid[:, :1])], dim=1)
    pad = torch.cat([x[:, :1], x, x[:, -1:]], dim=1)  # neighbours, repeated at the ends (their h is 0)
    left, right = h[:, :-1].unsqueeze(-1), h[:, 1:].unsqueeze(-1)  # (S, G, 1) each
    dl, dr = x - pad[:, :-2], pad[:, 2:] - x
    central = (left * left * dr + right * right * dl) / (left * right * (left + right)).clamp(min=tiny)
    # one-sided: the slope of the interval on the node's side, corrected by its neighbour interval's
    h2 = torch.cat([h[:, 2:], torch.zeros_like(h[:, :2])], dim=1)[:, :-1].unsqueeze(-1)  # (S, G, 1): next-but-one
    h2b = torch.cat([torch.zeros_like(h[:, :2]), h[:, :-2]], dim=1)[:, 1:].unsqueeze(-1)  # previous-but-one
    x2 = torch.cat([x[:, 2:], x[:, -1:].expand(-1, 2, -1)], dim=1)
    x2b = torch.cat([x[:, :1].expand(-1, 2, -1), x[:, :-2]], dim=1)
    forward = dr / right.clamp(min=tiny)
    backward = dl / left.clamp(min=tiny)
    forward2 = forward - right * ((x2 - pad[:, 2:]) / h2.clamp(min=tiny) - forward) / (right + h2).clamp(min=tiny)
    backward2 = backward + left * (backward - (pad[:, :-2] - x2b) / h2b.clamp(min=tiny)) / (left + h2b).clamp(min=tiny)
    forward = torch.where(h2 > 0, forward2, forward)
    backward = torch.where(h2b > 0, backward2, backward)
    one_sided = torch.where(right > 0, forward, backward)
    return torch.where((left > 0) & (right > 0), central, torch.where((left > 0) | (right > 0), one_sided,
                                                                       torch.zeros_like(x)))


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
