"""Dormand–Prince 5(4) for a batch of independent samples, each on its own error control.

:func:`dopri_batch` integrates the augmented model ``z = (x, p)`` of ``S`` samples at once: every
sample has its own time, step size and accept/reject decision, its steps land on the grid nodes
it must hit, and the other nodes are filled from each step's dense output. It is the explicit
counterpart of :func:`torchql.solvers.rodas5p_batch`; :mod:`torchql.batch_integrate` holds the
batch's other integrators.
"""

from __future__ import annotations

from typing import Callable

import torch

from .budget import check_time
from .grid import last_nodes
from .model import AugmentedSystem, BatchedCall

__all__ = ["dopri_batch"]


# Dormand–Prince 5(4) tableau (the dopri5 of torchdiffeq and scipy's RK45)
_DP_C = (0.0, 1 / 5, 3 / 10, 4 / 5, 8 / 9, 1.0, 1.0)
_DP_A = (
    (),
    (1 / 5,),
    (3 / 40, 9 / 40),
    (44 / 45, -56 / 15, 32 / 9),
    (19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729),
    (9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656),
    (35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84),
)
#: Weights of the dense output at the step's midpoint (Shampine's), over the seven slopes.
_DP_MID = (6025192743 / 30085553152 / 2, 0.0, 51252292925 / 65400821598 / 2, -2691868925 / 45128329728 / 2,
           187940372067 / 1594534317056 / 2, -1776094331 / 19743644256 / 2, 11237099 / 235043384 / 2)
#: The words of a failed sample's last step (:meth:`_DopriRun.messages`), by code.
_FAILURES = (None, "the step size underflowed to {h:.3g} at t = {t:.6g}",
             "the solution became non-finite (NaN or inf) after t = {t:.6g}; the step size underflowed to {h:.3g}",
             "the budget of {n} steps ran out at t = {t:.6g}",
             "max_steps = {k} steps between two grid nodes ran out at t = {t:.6g} (step size {h:.3g})",
             "stopped at t = {t:.6g} by the caller's test on the values so far")
#: A caller's test that ends samples at a node: ``(rows (L,), out (L, G, M), reached (L,)) -> bool (L,)``.
StopTest = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]
#: Fifth-order weights minus the embedded fourth-order ones: the local error estimate.
_DP_E = (71 / 57600, 0.0, -71 / 16695, 71 / 1920, -17253 / 339200, 22 / 525, -1 / 40)


def dopri_batch(system: AugmentedSystem, z0: torch.Tensor, grid: torch.Tensor, *, rtol: float, atol: float,
                max_steps: int = 100_000, land: torch.Tensor | None = None, messages: list | None = None,
                interval_steps: int | None = None, stop: StopTest | None = None
                ) -> tuple[torch.Tensor, torch.Tensor, int]:
    """The augmented model from ``z0 (S, M)`` over ``grid`` by Dormand–Prince 5(4), each sample its own steps.

    Every sample has its own time, step size and accept/reject decision (error in the RMS norm
    of its own states, ``atol + rtol * max(|x|, |x_new|)``, as torchdiffeq's ``dopri5``); steps
    are shortened to land on the grid nodes in ``land`` (bool ``(G,)`` or ``(S, G)``, default
    every node; the last node always), so the values there are the solver's own; any other node
    is filled by the step's fourth-order dense output (Shampine's, as torchdiffeq interpolates).
    A round advances every unfinished sample by one trial step; only those samples are evaluated.

    ``grid`` is shared, ``(G,)``, or each sample's own, ``(S, G)``: a sample stops at the first
    node of its final time (always landed on), and the nodes after it, the padding that repeats
    it, take its value. A zero-length interval inside a grid is a step of length zero (its end
    value is its start value).

    Returns ``traj (S, G, M)`` (NaN where it failed), ``ok (S,)`` (false when a sample's
    solution became non-finite, its step size underflowed, it took more than ``max_steps``
    steps, or more than ``interval_steps`` trial steps to pass from one grid node to the next:
    the user's ``max_steps``, which torchdiffeq counts per output time) and the right-hand-side
    evaluations (points). ``messages``, a list if given, gets one
    entry per sample: why it failed (where, and the step size then), or None.

    ``stop``: ``stop(rows (L,), out (L, G, M), reached (L,)) -> bool (L,)``, asked for the
    samples ``rows`` that landed on a node before their last in a step (``reached``: the next
    node each is to reach; the values before it are filled): those it answers true end there,
    failed ("stopped"). A caller that needs a solution only while some measure of the values so
    far stays below a bound (a trial's sum of squares, below the current iterate's) saves the rest.
    """
    S, M = z0.shape
    out = z0.new_full((S, grid.shape[-1], M), float("nan"))
    out[:, 0] = z0
    ok = torch.isfinite(z0).all(dim=1)
    if grid.shape[-1] == 1:
        return out, ok, 0
    run = _DopriRun(system, z0, grid, land, out, ok, rtol, atol, max_steps, interval_steps, stop)
    # a sample with one node (then padding) is done: its padding is filled below
    active = (ok if run.end is None else ok & (run.end > 1)).nonzero().flatten()
    while active.numel():
        check_time()
        active = run.advance(active)
    out, end, G = run.out, run.end, run.G
    if run.per_sample and bool((end < G).any()):  # the padding repeats each sample's last value
        last = torch.minimum(run.node_index, (end - 1).unsqueeze(1))  # (S, G)
        out = out.gather(1, last.unsqueeze(-1).expand(S, G, M))
    out[~ok] = float("nan")
    if messages is not None:
        messages[:] = run.messages()
    return out, ok, run.evals


class _DopriRun:
    """The loop state of :func:`dopri_batch`: per sample ``x (S, M)``, ``t``, slope ``k1 (S, M)``, step ``h``, next
    ``node``, ``steps`` (and ``since``, those since its last node); the landing tables; ``out (S, G, M)``
    and ``ok (S,)`` (written in place), ``evals``."""

    def __init__(self, system: AugmentedSystem, z0: torch.Tensor, grid: torch.Tensor, land: torch.Tensor | None,
                 out: torch.Tensor, ok: torch.Tensor, rtol: float, atol: float, max_steps: int,
                 interval_steps: int | None = None, stop: StopTest | None = None) -> None:
        S, n = z0.shape[0], system.n
        dtype, device = z0.dtype, z0.device
        self.S, self.G, self.n, self.grid, self.out, self.ok = S, grid.shape[-1], n, grid, out, ok
        self.rtol, self.atol, self.max_steps, self.interval_steps = rtol, atol, max_steps, interval_steps
        self.stop = stop
        self.per_sample = grid.dim() == 2
        self.fv = BatchedCall(system.f)  # one model call per stage where the model takes it
        self.x = x = z0.clone()
        self.t = grid[:, 0].clone() if self.per_sample else grid[0].expand(S).clone()
        self.node = torch.ones(S, dtype=torch.long, device=device)  # next node to reach
        self.k1 = self.fv(self.t, self.x)
        self.evals = S
        # initial step (Hairer's heuristic, per sample)
        scale = atol + rtol * x[:, :n].abs()
        d0 = (x[:, :n] / scale).square().mean(dim=1).sqrt()
        d1 = (self.k1[:, :n] / scale).square().mean(dim=1).sqrt()
        span = grid[..., -1] - grid[..., 0]
        h = torch.where((d0 > 1e-5) & (d1 > 1e-5), 0.01 * d0 / d1, torch.full_like(d0, 1e-6))
        self.h = torch.minimum(h, span).clamp(min=torch.finfo(dtype).tiny)
        self.steps = torch.zeros(S, dtype=torch.long, device=device)
        self.since = torch.zeros(S, dtype=torch.long, device=device)
        self.failure = torch.zeros(S, dtype=torch.long, device=device)  # _FAILURES' index, 0: none
        # the tableau's rows as tensors: each stage's combination of the slopes is one contraction
        self.rows_a = [torch.tensor(_DP_A[i], dtype=dtype, device=device) for i in range(7)]
        self.row_e, self.row_mid = (torch.tensor(row, dtype=dtype, device=device) for row in (_DP_E, _DP_MID))
        self._landing_tables(land, device)

    def _landing_tables(self, land: torch.Tensor | None, device: torch.device) -> None:
        """Bool ``landing`` (nodes steps land on), ``next_land`` (``(G,)`` or ``(S, G)``), ``end (S,)``, ``dense``."""
        S, G, grid = self.S, self.G, self.grid
        self.node_index = torch.arange(G, device=device)
        if self.per_sample:  # flat tables, read at base + node (base: the sample's first entry)
            self.end = last_nodes(grid) + 1  # nodes each sample reaches
            self.base = torch.arange(S, device=device) * G
            landing = (torch.ones(S, G, dtype=torch.bool, device=device) if land is None
                       else land.to(device).expand(S, G).clone())
            landing[torch.arange(S, device=device), self.end - 1] = True
            landing[:, -1] = True
            next_land = torch.where(landing, self.node_index, G).flip(-1).cummin(dim=-1).values.flip(-1)
            self.grid_flat, self.landing_flat = grid.reshape(-1), landing.reshape(-1)
            self.next_flat = next_land.reshape(-1)
        else:
            self.end = self.base = None
            landing = torch.ones(G, dtype=torch.bool, device=device) if land is None else land.to(device).clone()
            landing[-1] = True
            next_land = torch.where(landing, self.node_index, G).flip(0).cummin(dim=0).values.flip(0)
        self.landing, self.next_land = landing, next_land
        self.dense = not bool(landing[..., 1:].all())

    def _passes(self, passed: torch.Tensor, base_a: torch.Tensor | None, node_a: torch.Tensor,
                t_new: torch.Tensor) -> torch.Tensor:
        """``passed (A,)`` where the node ``node_a`` (clamped to the last) is before ``t_new`` and not landed on."""
        clamped = node_a.clamp(max=self.G - 1)
        if base_a is None:
            return passed & (self.grid[clamped] < t_new) & ~self.landing[clamped]
        return passed & (self.grid_flat[base_a + clamped] < t_new) & ~self.landing_flat[base_a + clamped]

    def advance(self, active: torch.Tensor) -> torch.Tensor:
        """One trial step of the samples ``active (A,)``; returns those still unfinished and not failed."""
        G, node = self.G, self.node
        everyone = active.numel() == self.S  # no gathering while no sample has finished or failed
        xa, ta, ka, ha = ((self.x, self.t, self.k1, self.h) if everyone
                          else (self.x[active], self.t[active], self.k1[active], self.h[active]))
        node_a = node if everyone else node[active]
        before = node_a.clone() if self.interval_steps is not None else None
        if self.per_sample:
            base_a = self.base if everyone else self.base[active]
            target = self.grid_flat[base_a + self.next_flat[base_a + node_a]]
        else:
            base_a = None
            target = self.grid[self.next_land[node_a]]
        gap = target - ta
        clipped = ha >= gap
        he = torch.where(clipped, gap, ha)
        K, x_new, hc = self._stages(xa, ta, ka, he)
        self.evals += 6 * active.numel()
        accept, h_next = self._control(xa, x_new, K, hc, he, ha, clipped)
        # accepted steps advance; those landing on a node record it
        t_new = torch.where(clipped, target, ta + he)
        take = accept.unsqueeze(-1)
        if everyone:
            self.x, self.t, self.k1, self.h = (torch.where(take, x_new, xa), torch.where(accept, t_new, ta),
                                               torch.where(take, K[6], ka), h_next)
            self.steps += 1
        else:
            self.x[active] = torch.where(take, x_new, xa)
            self.t[active] = torch.where(accept, t_new, ta)
            self.k1[active] = torch.where(take, K[6], ka)
            self.h[active] = h_next
            self.steps[active] += 1
        if self.dense:  # nodes passed inside accepted steps, from the dense output
            self._dense_output(active, accept, node_a, base_a, xa, ta, x_new, K, he, hc, t_new)
        landed = accept & clipped
        if bool(landed.any()):
            rows = active[landed]
            self.out[rows, node[rows]] = x_new[landed]
            node[rows] += 1
        finished = node[active] >= (G if self.end is None else self.end[active])
        underflow = h_next <= 10 * torch.finfo(xa.dtype).eps * ta.abs().clamp(min=1.0)
        over = (self.steps[active] >= self.max_steps) & ~finished
        stuck = torch.zeros_like(over)
        if before is not None:  # trial steps since the last node passed, against the user's budget
            since = torch.where(node[active] > before, 0, self.since[active] + 1)
            self.since[active] = since
            stuck = (since >= self.interval_steps) & ~finished
        ended = None if self.stop is None else self._stopped(active, landed & ~finished)  # the caller's test
        bad = (underflow & ~finished) | over | stuck
        if ended is not None:
            bad = bad | ended
        if bool(bad.any()):
            reason = torch.where(stuck, 4, torch.where(over, 3, torch.where(torch.isfinite(x_new).all(dim=1), 1, 2)))
            if ended is not None:
                reason = torch.where(ended, 5, reason)
            self.failure[active[bad]] = reason[bad]
            self.ok[active[bad]] = False
        return active[self.ok[active] & ~finished]

    def _stopped(self, active: torch.Tensor, ask: torch.Tensor) -> torch.Tensor:
        """``(A,)`` bool: the samples ``active[ask]`` (landed on a node before their last) that the
        caller's ``stop`` test ends."""
        ended = torch.zeros_like(ask)
        if bool(ask.any()):
            rows = active[ask]
            ended[ask] = self.stop(rows, self.out[rows], self.node[rows])
        return ended

    def messages(self) -> list:
        """Each sample's failure in words (None where it did not fail in a step)."""
        out = []
        for s, (code, good) in enumerate(zip(self.failure.tolist(), self.ok.tolist())):
            if good:
                out.append(None)
            elif code == 0:
                out.append("the initial state is not finite")
            else:
                out.append(_FAILURES[code].format(t=float(self.t[s]), h=float(self.h[s]), n=self.max_steps,
                                                  k=self.interval_steps))
        return out

    def _stages(self, xa: torch.Tensor, ta: torch.Tensor, ka: torch.Tensor,
                he: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Slopes ``K (7, A, M)`` (``K[0] = ka``), ``x_new (A, M)``, ``hc (A, 1)`` of steps ``he (A,)`` from ``xa``."""
        hc = he.unsqueeze(-1)
        K = xa.new_empty(7, *xa.shape)
        K[0] = ka
        for i in range(1, 7):
            xi = torch.addcmul(xa, hc, _combine(self.rows_a[i], K[:i]))
            K[i] = self.fv(ta + _DP_C[i] * he, xi)
        return K, xi, hc  # the last stage is evaluated at the fifth-order solution (first same as last)

    def _control(self, xa: torch.Tensor, x_new: torch.Tensor, K: torch.Tensor, hc: torch.Tensor, he: torch.Tensor,
                 ha: torch.Tensor, clipped: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Whether each trial step ``he (A,)`` from ``xa (A, M)`` is accepted, bool ``(A,)``, and the next step size."""
        n = self.n
        err = hc * _combine(self.row_e, K)
        sc = self.atol + self.rtol * torch.maximum(xa[:, :n].abs(), x_new[:, :n].abs())
        ratio = (err[:, :n] / sc).square().mean(dim=1).sqrt()
        finite = torch.isfinite(x_new).all(dim=1) & torch.isfinite(ratio)
        accept = finite & (ratio <= 1.0)
        factor = torch.where(ratio > 0, 0.9 * ratio.clamp(min=1e-10) ** -0.2, torch.full_like(ratio, 10.0))
        # a non-finite trial (NaN ratio, which the test above sends to 10) shrinks the step, so that a
        # blow-up ends in a step-size underflow instead of retrying the same step until max_steps
        factor = torch.where(finite, factor, torch.full_like(factor, 0.2)).clamp(0.2, 10.0)
        factor = torch.where(accept, factor, factor.clamp(max=1.0))
        h_next = he * factor
        return accept, torch.where(accept & clipped, torch.maximum(h_next, ha), h_next)

    def _dense_output(self, active: torch.Tensor, accept: torch.Tensor, node_a: torch.Tensor,
                      base_a: torch.Tensor | None, xa: torch.Tensor, ta: torch.Tensor, x_new: torch.Tensor,
                      K: torch.Tensor, he: torch.Tensor, hc: torch.Tensor, t_new: torch.Tensor) -> None:
        """The nodes not landed on that accepted steps ``ta -> t_new`` passed: into ``out`` by the dense output."""
        passed = self._passes(accept, base_a, node_a, t_new)
        if not bool(passed.any()):
            return
        rows = passed.nonzero().flatten()
        first = node_a[rows]
        # the passed nodes of each step: from its next node up to (not including) the first node at
        # or after its end, never beyond the node it lands on; all of them in one evaluation
        if base_a is None:
            stop = torch.searchsorted(self.grid, t_new[rows].contiguous())
            stop = torch.minimum(stop, self.next_land[first])
        else:
            stop = torch.searchsorted(self.grid[active[rows]], t_new[rows].unsqueeze(1).contiguous()).squeeze(1)
            stop = torch.minimum(stop, self.next_flat[base_a[rows] + first])
        counts = (stop - first).clamp(min=1)
        which = torch.repeat_interleave(torch.arange(rows.numel(), device=rows.device), counts)
        offsets = torch.cumsum(counts, 0) - counts
        nodes = first[which] + torch.arange(which.numel(), device=rows.device) - offsets[which]
        step_rows = rows[which]
        t_node = self.grid[nodes] if base_a is None else self.grid_flat[base_a[step_rows] + nodes]
        theta = ((t_node - ta[step_rows]) / he[step_rows]).unsqueeze(-1)
        y_mid = torch.addcmul(xa[rows], hc[rows], _combine(self.row_mid, K[:, rows]))
        quartic = _quartic(xa[rows], x_new[rows], y_mid, K[0, rows], K[6, rows], hc[rows])
        value = quartic[4][which]
        for coefficient in quartic[3::-1]:
            value = value * theta + coefficient[which]
        self.out[active[step_rows], nodes] = value
        self.node[active[rows]] += counts


def _combine(weights: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """``sum_i weights[i] K[i]``: ``(A, M)`` from ``weights (i,)`` and slopes ``K (i, A, M)``, one
    matrix-vector product (``torch.tensordot``'s Python wrapper cost a fifth of a step on one sample)."""
    return (weights @ K.reshape(K.shape[0], -1)).reshape(K.shape[1:])


def _quartic(y0, y1, y_mid, f0, f1, h):
    """Power-basis coefficients ``(c0, .., c4)`` in ``theta = (t - t0) / h`` of the quartic through
    ``y0``, ``y_mid`` and ``y1`` with slopes ``f0``, ``f1`` at the ends (the dense output of a step)."""
    return (y0, h * f0, h * (f1 - 4 * f0) - 11 * y0 - 5 * y1 + 16 * y_mid,
            h * (5 * f0 - 3 * f1) + 18 * y0 + 14 * y1 - 32 * y_mid,
            2 * h * (f1 - f0) - 8 * (y1 + y0) + 16 * y_mid)
