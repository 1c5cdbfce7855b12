"""Embedded explicit Runge–Kutta pairs for a batch of independent samples, each on its own error control.

:func:`dopri_batch` integrates the augmented model ``z = (x, p)`` of ``S`` samples at once: every
sample has its own time, step size and accept/reject decision, its steps land on the grid nodes
it must hit, and the other nodes are filled from each step's dense output. The pair is
Dormand–Prince 5(4) (``"dopri5"``) or Hairer's eighth-order DOP853 (``"dop853"``), from
:mod:`torchql.rk_pairs`; the loop, the step-size control and the landing are the same for both. It is the explicit
counterpart of :func:`torchql.solvers.rodas5p_batch`; :mod:`torchql.batch_integrate` holds the
batch's other integrators.
"""

from __future__ import annotations

from typing import Callable

import torch

from .budget import check_time
from .grid import last_nodes
from .model import AugmentedSystem, BatchedCall
from .rk_pairs import PAIRS, combine
from .solvers.rosenbrock import precision_note

__all__ = ["dopri_batch", "STIFF", "found_stiff", "LANDED_OBSERVATIONS", "thin_landings"]


_STIFF_WORDS = "the problem became stiff"
#: The words of a failed sample's last step (:meth:`_DopriRun.messages`), by code.
_FAILURES = (None, "the step size underflowed to {h:.3g} at t = {t:.6g}",
             "the solution became non-finite (NaN or inf) after t = {t:.6g}; the step size underflowed to {h:.3g}",
             "the budget of {n} steps ran out at t = {t:.6g}",
             "max_steps = {k} steps between two grid nodes ran out at t = {t:.6g} (step size {h:.3g})",
             "stopped at t = {t:.6g} by the caller's test on the values so far",
             _STIFF_WORDS + " at t = {t:.6g}: the step size ({h:.3g}) is held by the explicit "
             "method's stability, not by its accuracy (an implicit solver, solver=\"rodas5p\", integrates it)")
#: The code of :data:`_FAILURES` for a sample found stiff (:meth:`_DopriRun._stiff`).
STIFF = 6


def found_stiff(message: str | None) -> bool:
    """Whether a sample's failure ``message`` (:func:`dopri_batch`'s ``messages``) is the stiffness test's."""
    return bool(message) and message.startswith(_STIFF_WORDS)


#: Hairer's stiffness test (DOP853, DOPRI5): every this many accepted steps, and at every step once
#: one has failed; a sample is stiff after :data:`STIFF_HITS` failures with fewer than
#: :data:`STIFF_CALM` passes in a row between them.
STIFF_EVERY, STIFF_HITS, STIFF_CALM = 1000, 15, 6
#: At most about this many observation times a sample's steps land on; denser ones come from the
#: dense output (of the pair's order, DOP853's seventh). Each landing ends a step: 21,000
#: observations of an oscillation over 14 time units took 21,000 steps a solve where its accuracy
#: asks about 300, 25 s a fit against 0.23 s at 19,000 (on the grid solver) and scipy's 0.17 s.
LANDED_OBSERVATIONS = 256


def thin_landings(land: torch.Tensor, most: int = LANDED_OBSERVATIONS) -> torch.Tensor:
    """Of the nodes ``land`` (bool ``(G,)`` or ``(S, G)``: a sample's observation times), every
    ``k``-th, ``k = ceil(count / most)`` for each sample's ``count``, and its last: at most about
    ``most`` a sample, unchanged where it has no more."""
    count = land.sum(dim=-1, keepdim=True)
    every = (count + most - 1) // most
    rank = land.long().cumsum(dim=-1)
    return land & ((rank % every.clamp(min=1) == 0) | (rank == count))


#: A caller's test that ends samples at a node: ``(rows (L,), out (L, G, M), reached (L,)) -> bool (L,)``.
StopTest = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]


def dopri_batch(system: AugmentedSystem, z0: torch.Tensor, grid: torch.Tensor, *, rtol: float, atol: float,
                max_steps: int = 100_000, land: torch.Tensor | None = None, messages: list | None = None,
                interval_steps: int | None = None, stop: StopTest | None = None, method: str = "dopri5",
                norm=None, first_step: float | None = None, steps: list | None = None,
                stiff_every: int = STIFF_EVERY) -> tuple[torch.Tensor, torch.Tensor, int]:
    """The augmented model from ``z0 (S, M)`` over ``grid`` by an embedded Runge–Kutta pair, each sample
    its own steps.

    ``method``: the pair (:data:`torchql.rk_pairs.PAIRS`), ``"dopri5"`` (Dormand–Prince 5(4)) or
    ``"dop853"`` (Hairer's DOP853, eighth order: far fewer steps at tight tolerances). ``norm``:
    the error norm of a sample's scaled errors, ``(A, n) -> (A,)`` (default the RMS norm);
    ``first_step``: every sample's first trial step (default Hairer's estimate, per sample).

    Every sample has its own time, step size and accept/reject decision (error in the RMS norm
    of its own states, ``atol + rtol * max(|x|, |x_new|)``, as torchdiffeq's ``dopri5``; DOP853's
    own norm); steps are shortened to land on the grid nodes in ``land`` (bool ``(G,)`` or
    ``(S, G)``, default every node; the last node always), so the values there are the solver's
    own; any other node is filled by the step's dense output (Shampine's quartic for ``"dopri5"``,
    as torchdiffeq interpolates; DOP853's of seventh order).
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

    ``steps``, a list if given, gets each round's accepted steps, ``(sample, t, h, end, x, K)``
    (:meth:`torchql.solvers.steps.StepRecord.join` takes them; ``K`` the pair's slopes), to
    differentiate them (:mod:`torchql.dopri_sensitivity`).

    ``stiff_every``: the stiffness test's period in accepted steps (:meth:`_DopriRun._stiff`;
    Hairer's :data:`STIFF_EVERY` by default, 1 to test every step).
    """
    S, M = z0.shape
    out = z0.new_full((S, grid.shape[-1], M), float("nan"))
    out[:, 0] = z0
    ok = torch.isfinite(z0).all(dim=1)
    if grid.shape[-1] == 1:  # nothing to integrate: every sample's message is its state's finiteness
        if messages is not None:
            messages.extend(None if good else "the initial state is not finite" for good in ok.tolist())
        return out, ok, 0
    run = _DopriRun(system, z0, grid, land, out, ok, rtol, atol, max_steps, interval_steps, stop, PAIRS[method],
                    norm, first_step)
    run.kept, run.stiff_every = steps, stiff_every
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
                 interval_steps: int | None, stop: StopTest | None, pair, norm=None,
                 first_step: float | None = None) -> None:
        S, n = z0.shape[0], system.n
        dtype, device = z0.dtype, z0.device
        self.S, self.G, self.n, self.grid, self.out, self.ok = S, grid.shape[-1], n, grid, out, ok
        self.rtol, self.atol, self.max_steps, self.interval_steps = rtol, atol, max_steps, interval_steps
        self.stop = stop
        self.kept: list | None = None  # the accepted steps, where the caller keeps them
        self.stiff_every = STIFF_EVERY
        self.per_sample = grid.dim() == 2
        self.fv = BatchedCall(system.f)  # one model call per stage where the model takes it
        self.time_sign = getattr(system, "time_sign", 1.0)  # -1: integrated in reversed time (messages say t)
        self.x = x = z0.clone()
        self.t = grid[:, 0].clone() if self.per_sample else grid[0].expand(S).clone()
        self.node = torch.ones(S, dtype=torch.long, device=device)  # next node to reach
        self.k1 = self.fv(self.t, self.x)
        self.evals = S
        span = grid[..., -1] - grid[..., 0]
        if first_step is None:  # Hairer's heuristic, per sample
            scale = atol + rtol * x[:, :n].abs()
            d0 = (x[:, :n] / scale).square().mean(dim=1).sqrt()
            d1 = (self.k1[:, :n] / scale).square().mean(dim=1).sqrt()
            h = torch.where((d0 > 1e-5) & (d1 > 1e-5), 0.01 * d0 / d1, torch.full_like(d0, 1e-6))
        else:
            h = torch.full((S,), first_step, dtype=dtype, device=device)
        self.h = torch.minimum(h, span).clamp(min=torch.finfo(dtype).tiny)
        self.steps = torch.zeros(S, dtype=torch.long, device=device)
        self.since = torch.zeros(S, dtype=torch.long, device=device)
        self.failure = torch.zeros(S, dtype=torch.long, device=device)  # _FAILURES' index, 0: none
        # the stiffness test's accepted steps, its failures and its passes since the last failure
        self.accepted, self.hits, self.calm = (torch.zeros(S, dtype=torch.long, device=device) for _ in range(3))
        self.pair = pair(dtype, device)  # a pair of :data:`~torchql.rk_pairs.PAIRS`
        self.norm = _rms if norm is None else norm
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
        # the step the clock takes, ``fl(t + h) - t``: at t ~ 1e9 the rounding of each step's end
        # (an ulp of t, 1e-7) had been lost between the state and the clock, 5e-7 over a simulation
        he = torch.where(clipped, gap, (ta + ha) - ta)
        hc = he.unsqueeze(-1)
        K, x_new = self.pair.step(self.fv, xa, ta, ka, hc)
        self.evals += self.pair.evals * active.numel()
        accept, h_next = self._control(xa, x_new, K, hc, he, ha, clipped)
        # accepted steps advance; those landing on a node record it
        t_new = torch.where(clipped, target, ta + he)
        if self.kept is not None and bool(accept.any()):
            self.kept.append((active[accept], ta[accept], he[accept], t_new[accept], xa[accept], K[:, accept]))
        take = accept.unsqueeze(-1)
        if everyone:
            self.x, self.t, self.k1, self.h = (torch.where(take, x_new, xa), torch.where(accept, t_new, ta),
                                               torch.where(take, K[-1], ka), h_next)
            self.steps += 1
        else:
            self.x[active] = torch.where(take, x_new, xa)
            self.t[active] = torch.where(accept, t_new, ta)
            self.k1[active] = torch.where(take, K[-1], ka)
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
        stiff = self._stiff(active, accept, xa, K, he, x_new) & ~finished
        bad = (underflow & ~finished) | over | stuck | stiff
        if ended is not None:
            bad = bad | ended
        if bool(bad.any()):
            reason = torch.where(stuck, 4, torch.where(over, 3, torch.where(torch.isfinite(x_new).all(dim=1), 1, 2)))
            reason = torch.where(stiff, STIFF, reason)
            if ended is not None:
                reason = torch.where(ended, 5, reason)
            self.failure[active[bad]] = reason[bad]
            self.ok[active[bad]] = False
        return active[self.ok[active] & ~finished]

    def _stiff(self, active: torch.Tensor, accept: torch.Tensor, xa: torch.Tensor, K: torch.Tensor,
               he: torch.Tensor, x_new: torch.Tensor) -> torch.Tensor:
        """``(A,)`` bool: the samples ``active`` found stiff by Hairer's test (DOP853's and DOPRI5's
        ``nstiff``, E. Hairer, G. Wanner, *Solving ODEs II*, section IV.2) on their accepted steps:
        ``h lambda ~ |h| |k_j - k_i| / |x_new - u_i|`` from two slopes at the step's end (stage ``i``'s
        argument ``u_i`` and the new solution) beyond the bound of the pair's stability, tested every
        ``stiff_every`` (:data:`STIFF_EVERY`) accepted steps and at every step once it has failed, :data:`STIFF_HITS`
        times with fewer than :data:`STIFF_CALM` passes in a row between. An explicit method then
        takes steps its stability holds far below its accuracy's (Robertson's kinetics: 100,000
        steps over ``t < 151``)."""
        i, j, bound = self.pair.stiffness
        n = self.n
        count = self.accepted[active] + accept.long()
        self.accepted[active] = count
        check = accept & ((count % self.stiff_every == 0) | (self.hits[active] > 0))
        found = torch.zeros_like(accept)
        if not bool(check.any()):
            return found
        rows = check.nonzero().flatten()
        a = active[rows]
        u = torch.addcmul(xa[rows], he[rows].unsqueeze(-1), combine(self.pair.rows_a[i], K[:i, rows]))
        slopes = (K[j, rows, :n] - K[i, rows, :n]).square().sum(dim=1)
        states = (x_new[rows, :n] - u[:, :n]).square().sum(dim=1)
        h_lambda = he[rows].abs() * (slopes / states).sqrt()
        hit = (states > 0) & (h_lambda > bound)
        self.hits[a] = torch.where(hit, self.hits[a] + 1, self.hits[a])
        self.calm[a] = torch.where(hit, 0, self.calm[a] + 1)
        calmed = self.calm[a] >= STIFF_CALM
        self.hits[a] = torch.where(calmed, 0, self.hits[a])
        found[rows] = self.hits[a] >= STIFF_HITS
        return found

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
                t = self.time_sign * float(self.t[s])
                out.append(_FAILURES[code].format(t=t, h=float(self.h[s]), n=self.max_steps, k=self.interval_steps)
                           + (precision_note(t, self.t.dtype) if code == 1 else ""))
        return out

    def _control(self, xa: torch.Tensor, x_new: torch.Tensor, K: torch.Tensor, hc: torch.Tensor, he: torch.Tensor,
                 ha: torch.Tensor, clipped: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Whether each trial step ``he (A,)`` from ``xa (A, M)`` is accepted, bool ``(A,)``, and the next step size."""
        sc = self.atol + self.rtol * torch.maximum(xa[:, :self.n].abs(), x_new[:, :self.n].abs())
        ratio = self.pair.error_ratio(K, hc, sc, self.norm)
        finite = torch.isfinite(x_new).all(dim=1) & torch.isfinite(ratio)
        accept = finite & (ratio <= 1.0)
        factor = torch.where(ratio > 0, 0.9 * ratio.clamp(min=1e-10) ** self.pair.exponent,
                             torch.full_like(ratio, 10.0))
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
        at = self.pair.dense(self.fv, xa[rows], ta[rows], x_new[rows], K[:, rows], hc[rows])
        self.evals += self.pair.dense_evals * rows.numel()
        self.out[active[step_rows], nodes] = at(theta, which)
        self.node[active[rows]] += counts


def _rms(x: torch.Tensor) -> torch.Tensor:
    """The RMS norm of each row of ``x (A, n)``, ``(A,)``."""
    return x.square().mean(dim=1).sqrt()
