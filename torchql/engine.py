"""The quasilinearization engine: the package's one iteration loop, over ``S >= 1`` samples.

:func:`torchql.fit` runs it with one sample and keeps every iterate's record; :func:`torchql.fit_many`
runs it over a batch, chunk after chunk (:func:`run_engine`). Each sample has its own iterate,
damping, status and history; the work is vectorized over the samples still running. One iteration:

1. at a fresh iterate, the budgets (``max_iter``, ``max_time``) and the rows' finiteness;
2. the least-squares update ``alpha`` (:meth:`Engine._solve`: batched SVD with each sample's
   damping; equality-constrained per sample where values are marked ``exact``, their merit then
   an exact penalty weighted above the constraints' multipliers, :meth:`Engine._weigh_exact`;
   bounds in their transformed variables), and the convergence tests on undamped steps;
3. the trial iterate (:meth:`Engine._propose`: Kantorovich's superposed trajectory, re-linearized;
   shooting's model solution), accepted when it lowers the merit or, failing that test, the
   model's own sum of squares;
4. on rejection, Kantorovich re-anchors the undamped step about the model's own solution once,
   then Levenberg–Marquardt damping rises tenfold per rejection (skipping the raises that would
   barely shorten the step) until a step is accepted or the iteration stalls.

The final pass (:mod:`torchql.engine_final`) evaluates the fitted model itself.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from contextlib import contextmanager

import torch

from .active_set import bounded_update
from .budget import TimeBudgetExceeded, check_time, deadline, no_time_budget, time_left
from .data_start import data_reference
from .engine_evaluate import _LOOSE_RTOL, EXACT_MARGIN, INEXACT_FACTOR, Evaluation
from .engine_final import FinalPass
from .engine_steps import FLAT_DAMPING, StepTests  # noqa: F401 (FLAT_DAMPING: where it was defined)
from .engine_records import Records
from .engine_grid import AutoGrid
from .engine_state import RUNNING, LoopState, _pick, by_level, put_samples
from .grid import last_nodes
from .linearize import map_fields
from .lstsq import ExactRowsError, solve_update, solve_update_batch
from .noise import non_finite_residuals
from .problem import Problem
from .result import IterationRecord, Status
from .stiffness import stiff_along
from .trajectory import DEFECT_TRUST

__all__ = ["Engine"]

_STATUSES = list(Status)
#: The detail of a sample that ``solver="auto"``'s explicit solver found stiff during the fit.
STIFF_FOUND = (" The model became stiff as the estimates moved (the explicit solver's steps held by its stability, "
               "or the Jacobian's fastest decay rate times the span above 1e4 along an accepted iterate).")


class Engine(Evaluation, StepTests, FinalPass, AutoGrid, Records):
    """The iteration of one chunk of samples (indices ``index`` of the problem's batch)."""

    def __init__(self, spec: Problem, index: torch.Tensor, max_time: float | None = None, history: bool = False,
                 callback: Callable[[int, IterationRecord], None] | None = None, start: str | None = None,
                 guesses: torch.Tensor | None = None) -> None:
        self.spec, self.max_time, self.index = spec, max_time, index
        #: the first reference: ``"data"`` or ``"integrate"`` (default: the problem's)
        self.start = spec.initial_trajectory if start is None else start
        self.scale: torch.Tensor | None = None  # (S, m) typical magnitudes, from the first trajectory
        self.system = spec.system
        self.y, self.w, self.mask = spec.y[index], spec.weights[index], spec.mask[index]
        self.exact = spec.exact[index].reshape(index.numel(), -1)  # (S, R) rows met exactly
        #: (S,) the exact rows' weight in the merit (:meth:`_weigh_exact`)
        self.exact_weight = torch.zeros(index.numel(), dtype=spec.dtype, device=spec.device)
        self.L = spec.L[index]
        #: each sample's iterates (``torchql.fit``'s ``history``), when kept, and the open record
        self.history: list[list[IterationRecord]] | None = [[] for _ in range(index.numel())] if history else None
        self.callback = callback
        self.notified: dict = {}  # per sample, the last record handed to the callback
        self.propagation_errors: dict[int, str] = {}  # chunk row: a per-sample propagator's message
        self.stiff_met: set[int] = set()  # chunk rows whose model an explicit pair found stiff
        self.stopped_stiff: set[int] = set()  # ... and that stopped so (solver="auto" fits them again)
        self.z0_guess = spec.z0[index].clone() if guesses is None else guesses.clone()
        #: chunk row: the null directions ``(m, k)`` of a sample found not identifiable (FinalDiagnosis)
        self.null_directions: dict[int, torch.Tensor] = {}
        #: the first iterate ``(S, M)`` and its sum of squares ``(S,)`` (the guesses and NaN until it is made)
        self.first_z0 = self.z0_guess.clone()
        self.first_sse = torch.full((index.numel(),), float("nan"), dtype=spec.dtype, device=spec.device)
        self.S = index.numel()
        self.nfev = 0
        #: chunk row: (estimates, final solution) integrated with other groups' (FinalPass._share_final_solutions)
        self.shared_solutions: dict[int, tuple[torch.Tensor, torch.Tensor]] | None = None
        #: samples whose current iterate needs more grid-solver steps than a trial may take (their
        #: trials are integrated by the adaptive solvers; see Evaluation._nonlinear)
        self.coarse_grid: set[int] = set()
        #: ... whose explicit pair's steps were held by a decay most of the span (``held`` of
        #: :func:`~torchql.dopri_sensitivity.explicit_sensitivities`): their solutions with sensitivities
        #: are Rodas5P's from then on (Evaluation._solve_with_sensitivities)
        self.fast_decay: set[int] = set()
        #: ... found so in this round's trial solution: marked ``fast_decay`` if the trial is taken (a
        #: rejected trial's decay says nothing of the fit's: an SIR trial's gamma of 87, 1000 times the
        #: iterate's, made every later solve of a 17-iteration fit Rodas5P's; its stiffness, found by
        #: DOP853's test, had the fit stopped and fitted again by Rodas5P, 20 s where scipy takes 0.2)
        self.trial_decay: set[int] = set()
        #: per sample, the current iterate (its initial state's bytes) seen to fit in that budget
        self.fits_grid: dict[int, bytes] = {}
        #: samples whose automatic storage grid misses their model's change: misfit (FinalPass._missed_by_storage)
        self.storage_missed: dict[int, float] = {}
        #: samples whose final sensitivities were integrated with their solutions for their grid solver's sake
        self.joint_final: set[int] = set()
        #: the trials' linear transfers' tolerance while proposed (None: ``rtol``; see ``INEXACT_FACTOR``)
        self.trial_rtol: float | None = None
        #: (S,) samples whose trial of this round the model's own sum of squares judges whatever its
        #: merit: their step was capped at a bound's largest move, or their iterate is distrusted
        self.judged_by_model = torch.zeros(index.numel(), dtype=torch.bool, device=spec.device)
        if spec.grid_size is None:  # shared times: one grid (G,), observations at nodes (T,)
            self.grid, self.obs, self.t_obs = spec.grid, spec.obs_in_grid, spec.t_obs
        else:  # per sample: grids (S, G), trimmed to the chunk's longest, nodes (S, T)
            G = int(spec.grid_size[index].max())
            self.grid, self.obs, self.t_obs = spec.grid[index, :G], spec.obs_in_grid[index], spec.t_obs[index]
        self.G = self.grid.shape[-1]

    def _lstsq(self, idx, C, d, w, damping):
        """Damped weighted least squares of the chunk's samples ``idx``: ``alpha (S, m)``,
        ``infeasible (S,)`` and ``nu (S,)``. Batched (:func:`torchql.lstsq.solve_update_batch`); a
        sample with values marked ``exact`` by :func:`torchql.lstsq.solve_update` on its used rows,
        those rows met (a damped step: their fraction ``1 / (1 + damping)``), ``nu`` the largest
        magnitude of their multipliers (else 0), and ``infeasible`` (NaN update) where they cannot
        all be met."""
        spec = self.spec
        alpha, _, _ = solve_update_batch(C, d, w, spec.rcond, damping)
        infeasible = torch.zeros(idx.numel(), dtype=torch.bool, device=alpha.device)
        nu = torch.zeros(idx.numel(), dtype=alpha.dtype, device=alpha.device)
        if not spec.has_exact:
            return alpha, infeasible, nu
        exact, mask = self.exact[idx], self.mask[idx].reshape(idx.numel(), -1)
        for k in exact.any(dim=1).nonzero().flatten().tolist():
            used = mask[k]
            try:
                sol = solve_update(C[k][used], d[k][used], w[k][used], exact[k][used], spec.rcond, float(damping[k]))
                alpha[k], nu[k] = sol.alpha, sol.multipliers.abs().max()
            except ExactRowsError:
                alpha[k], infeasible[k] = float("nan"), True
        return alpha, infeasible, nu

    def _solve(self, idx, cur, damping):
        """The damped updates of the samples ``idx``: ``alpha (S, m)``, the change of the unknowns,
        ``capped (S, m)``, the bounded unknowns whose step was capped,
        ``infeasible (S,)``, samples whose exact values cannot all be met, and ``nu (S,)``, their
        exact rows' largest multiplier (:meth:`_lstsq`).

        With bounds, solved for the internal variables (columns times ``du/dq``) and mapped back;
        the unknowns that the step pushes onto a bound or whose step is capped are held at their
        move while the others are re-solved, and those held on a bound that the data pull inside are
        let go (:func:`torchql.active_set.bounded_update`).
        """
        spec = self.spec
        C, d, w = _pick(cur["C"], idx), _pick(cur["d"], idx), _pick(cur["w"], idx)
        bounds = spec.bounds
        if not bounds.active:
            alpha, infeasible, nu = self._lstsq(idx, C, d, w, damping)
            return alpha, torch.zeros_like(alpha, dtype=torch.bool), infeasible, nu
        u = _pick(cur["z0"], idx)[:, spec.unknown_index]
        alpha, capped, infeasible, nu = bounded_update(
            bounds, lambda rows, C_, d_, w_: self._lstsq(idx[rows], C_, d_, w_, damping[rows]), C, d, w, u)
        return alpha, capped, infeasible, nu

    def _model_merit(self, rows: torch.Tensor, cur: dict) -> torch.Tensor:
        """The model's own merit at the iterates of ``rows`` where known (shooting: the merit), else NaN."""
        return cur["merit"][rows] if self.spec.scheme.integrates_model else cur["nl_sse"][rows]

    def run(self, report, first: tuple | None = None) -> dict:
        """Iterate every sample of the chunk to its status; then the final pass. ``report``
        receives the number of samples stopped, or the name of a phase begun; ``first``: the chunk's
        first references and grid counts, made (:meth:`~torchql.engine_grid.AutoGrid._run_groups`)."""
        st = self._iterate(report, first)
        return st if isinstance(st, dict) else self._conclude(st)

    def _iterate(self, report, first: tuple | None = None) -> "LoopState | dict":
        """:meth:`run` up to the final pass: the samples' iteration state, or (samples that chose
        different grids) the groups' results."""
        st = LoopState(self, report)
        try:
            report("first trajectories")
            groups = self._start(st, first)
            if groups:  # samples that chose different grids: each group on its own
                return self._run_groups(groups, report)
            report("iterating")
            while self._iteration(st):
                pass
        except TimeBudgetExceeded:  # inside a phase: the samples still running stop where they are
            st.stop((st.status == RUNNING).nonzero().flatten(), Status.MAX_TIME)
        for r, c in enumerate(st.status.tolist()):
            if c == _STATUSES.index(Status.MAX_TIME):
                self._notify_unsent(r)
                budget = "an enclosing fit's" if self.max_time is None else f"{self.max_time:g} s"
                st.detail[r] = (f" Stopped after {int(st.iterations[r])} iterations (max_time = {budget}), not "
                                "evaluated further." + st.detail[r])
        stalled = st.status == _STATUSES.index(Status.STALLED)  # the final pass tries steps on the model itself
        st.polish = (st.undamped_stop | stalled) & (time_left() > 0)  # polishing steps only within the time budget
        return st

    def _conclude(self, st: LoopState) -> dict:
        """:meth:`run`'s final pass of the iteration state ``st``."""
        st.report("final pass")
        self.deadline = deadline()  # the polishing steps, optional, keep to it (FinalPass._polish)
        with no_time_budget():  # the samples that finished in time get their final evaluation
            return self._finish(st.z0, st.status, st.detail, st.iterations, st.final_guess, st.polish)

    def _start(self, st: LoopState, first: tuple | None = None) -> list | None:
        """The first iterate of every sample: the data-built reference, or the model integrated
        from the guesses (loosely, from a constant guess, for Kantorovich unless stiff), on each
        sample's grid (``grid="auto"``: chosen from this reference, :mod:`torchql.engine_grid`); the
        unknowns' typical magnitudes and the model's sums of squares at the guesses. Returns the
        groups of samples that chose different grids (to be fitted apart), else None."""
        spec, S, n, all_idx = self.spec, self.S, self.system.n, st.all_idx
        if first is None:
            z0, traj, z_dot, W, errors = self._first_reference(all_idx, st.z0)
            counts = self._grid_counts(traj, z_dot, errors) if spec.auto_grid else None
            if counts is not None and S > 1 and counts.unique().numel() > 1:
                return self._grid_groups(counts, (z0, traj, z_dot, W, errors))
        else:
            z0, traj, z_dot, W, errors, counts = self._given_start(first)
        if counts is not None:
            z0, traj, z_dot, W, errors = self._choose_grid(z0, traj, z_dot, W, errors, counts)
        if self.start == "data":
            check_time()  # out of time already: the samples keep their guesses, as an integrated start's do
            if spec.scheme.integrates_model:  # shooting: the model's solution from the matched estimates
                z0, traj, W, errors = self._model_from_data(all_idx, z0, traj)
                z_dot = None
        st.z0 = z0
        bad = torch.tensor([e is not None for e in errors], dtype=torch.bool, device=spec.device)
        for r in bad.nonzero().flatten().tolist():
            st.status[r] = _STATUSES.index(Status.INTEGRATION_FAILED)
            st.detail[r] = f" The solver said: {errors[r]}."
        lin = self._linearize(all_idx, traj, z_dot)
        # on the stiff path the first step is long (and an iterate propagated loosely is not taken as converged)
        with self._transfers_at(_LOOSE_RTOL if spec.stiff else None):
            st.cur = self._evaluate(all_idx, st.z0, traj, lin.f if z_dot is None else z_dot, lin,
                                    solution=spec.scheme.integrates_model, W=W)
        self._fail_integration_rows((st.cur["failed"] & ~bad).nonzero().flatten(), st.status, st.detail)
        if spec.stiff and self.start != "data" and not spec.scheme.integrates_model:
            # Kantorovich's first reference of a stiff model is the model's own solution from the
            # guesses on this grid, at the fit's tolerance: the second opinion on the first iterate,
            # and its re-anchoring, would integrate it once more
            good = (~bad).nonzero().flatten()
            if good.numel():  # (none where the model blows up from every guess)
                self._keep_model_sse(all_idx, st.cur, good, traj[good], [None] * good.numel())
                st.cur["anchored"][good] = True
        st.final_guess = st.cur["W"][:, :, :, 0].clone()
        typical = torch.cat([traj[:, :, :n].abs().amax(dim=1), st.z0[:, n:].abs()], dim=1)
        typical = torch.where(typical > 0, typical, torch.ones_like(typical))
        self.scale = typical[:, spec.unknown_index]
        # integrated from the guesses, the first iterate's SSE is the model's own there (the final diagnosis')
        self.first_z0, self.first_sse = st.z0.clone(), st.cur["sse"].clone()
        st.report_stopped()
        return None

    def _first_reference(self, idx, z0):
        """The first reference of the chunk's samples ``idx`` from their guesses ``z0 (S, M)``:
        ``(z0, traj (S, G, M), z_dot or None, W or None, errors)``. From the data (``z0`` with the
        matched coefficients, ``z_dot`` the reference's slopes), or the model integrated (``z_dot``
        None; ``W`` its sensitivities where integrated with it; the solver's ``errors``)."""
        if self.start == "data":
            traj, z_dot, z0 = self._data_start(idx, z0)
            return z0, traj, z_dot, None, [None] * idx.numel()
        kantorovich = not self.spec.scheme.integrates_model
        if kantorovich or not self._joint_sensitivities:
            guess = z0.unsqueeze(1).expand(idx.numel(), self.G, z0.shape[1]) if kantorovich else None
            # a stiff model's at the fit's tolerance: the storage's slopes f(z) multiply its error by
            # the stiffness (h |lambda| to 1e5; tests/test_stiff_fit.py's exact data with unit weights)
            traj, errors = self._nonlinear(idx, z0, loose=kantorovich and not self.spec.stiff, guess=guess)
            return z0, traj, None, None, errors
        traj, W, errors = self._solve_with_sensitivities(idx, z0)
        return z0, traj, None, W, errors

    def _iteration(self, st: LoopState) -> bool:
        """One round: every running sample tries one step (or starts its next iteration).
        ``False`` when no sample is running."""
        act = self._begin(st)
        if not act.numel():
            return False
        act, alpha, capped = self._update(st, act)
        act, alpha, capped = self._converged(st, act, alpha, capped)
        if not act.numel():
            return True
        self.judged_by_model[act] = capped | st.distrust[act]
        trial, ok = self._propose(act, st.cur, alpha)
        accept = self._accepted(st, act, trial, ok, capped)
        lost = self._lost(st, act)
        accept &= ~lost
        flat = self._flat(st, act, trial, accept, alpha)
        creeping = self._creeping(st, act, trial, accept & ~flat)
        poor = self._poor_gain(st, act, trial, accept & ~flat & ~creeping, alpha)
        self._take(st, act, trial, accept)
        self._damp_poor_gain(st, act[poor])
        self.trial_decay.difference_update(act.tolist())
        if bool(flat.any()):
            st.stop(act[flat], Status.CONVERGED_SSE)
        if bool(creeping.any()):  # the final pass goes on from here by steps on the model itself
            st.stop(act[creeping], Status.STALLED, " The steps that lowered the sum of squares were damped, and moved "
                    "the estimates by less than `xtol` or lowered it by less than `ftol` or the integration's error.")
        rejected = act[~accept & ~lost]
        if rejected.numel():
            self._reject(st, rejected, alpha[~accept & ~lost])
        if bool(lost.any()):
            self._restore_lost(st, act[lost], alpha[lost])
        return True

    def _begin(self, st: LoopState) -> torch.Tensor:
        """The time budget; for samples at a fresh iterate, ``max_iter``, the iterate's record and
        its rows' finiteness. Returns the samples still running."""
        running = st.status == RUNNING
        if time_left() <= 0 and bool(running.any()):
            st.stop(running.nonzero().flatten(), Status.MAX_TIME)
            running = st.status == RUNNING
        if self.stiff_met and self.spec.stiff_refit:  # found stiff: fitted again as such (torchql.engine_run)
            stiff = torch.tensor(sorted(self.stiff_met), device=running.device)
            stiff = stiff[running[stiff]]
            if stiff.numel():
                st.stop(stiff, Status.INTEGRATION_FAILED, STIFF_FOUND)
                self.stopped_stiff.update(stiff.tolist())
            running = st.status == RUNNING
        start = running & st.fresh
        maxed = start & (st.iterations >= self.spec.max_iter)
        if bool(maxed.any()):
            st.stop(maxed.nonzero().flatten(), Status.MAX_ITER)
        start &= ~maxed
        self._open(start.nonzero().flatten(), st.cur, st.iterations)
        st.rejected[start] = 0
        cur = st.cur
        finite = (torch.isfinite(cur["sse"]) & torch.isfinite(cur["C"]).flatten(1).all(dim=1)
                  & torch.isfinite(cur["d"]).all(dim=1))
        diverged = (start & ~finite).nonzero().flatten()
        if diverged.numel():
            st.stop(diverged, Status.DIVERGED, non_finite_residuals(self.spec.noise))
            self._notify(diverged)
        st.fresh &= ~start
        return (st.status == RUNNING).nonzero().flatten()

    def _update(self, st: LoopState, act: torch.Tensor):
        """The damped updates ``alpha`` of samples ``act`` and whether a bounded step was capped;
        samples whose exact rows cannot be met, or whose update is not finite, stop. Also their
        scaled sizes ``st.scaled``, recorded."""
        spec, cur = self.spec, st.cur
        alpha, capped_at, infeasible, nu = self._solve(act, cur, st.damping[act])
        capped = capped_at.any(dim=1)
        leaving = spec.bounds.leaving(_pick(cur["z0"], act)[:, spec.unknown_index], alpha, capped_at)
        if spec.has_exact:
            undamped = (st.damping[act] == 0) & ~infeasible
            self._weigh_exact(st, act[undamped], nu[undamped])
        if bool(infeasible.any()):
            self._stop_infeasible(st, act[infeasible])
            keep = ~infeasible
            act, alpha, capped, leaving = act[keep], alpha[keep], capped[keep], leaving[keep]
        scaled = self._scaled(act, cur, alpha)
        bad = ~(torch.isfinite(alpha).all(dim=1) & torch.isfinite(scaled))
        if bool(bad.any()):
            st.stop(act[bad], Status.DIVERGED, " The update alpha became non-finite.")
            act, alpha, scaled, capped, leaving = act[~bad], alpha[~bad], scaled[~bad], capped[~bad], leaving[~bad]
        self._annotate(act, alpha=alpha, alpha_norm=scaled, damping=st.damping[act], rejected=st.rejected[act])
        st.scaled, st.leaving = scaled, leaving
        return act, alpha, capped

    def _stop_infeasible(self, st: LoopState, rows: torch.Tensor) -> None:
        """Samples ``rows`` whose exact rows no step from the current iterate can meet: at their first
        iterate the values marked exact are dependent or contradictory (``EXACT_INFEASIBLE``); at a
        later one the iteration has moved where their sensitivities are (a pendulum damped to rest
        before the times marked), which says nothing of the data (``STALLED``)."""
        first = st.iterations[rows] == 0
        if bool(first.any()):
            st.stop(rows[first], Status.EXACT_INFEASIBLE)
        if not bool(first.all()):
            st.stop(rows[~first], Status.STALLED, " At the iterate reached, no step can meet the values marked "
                    "`exact`: their sensitivities there are linearly dependent, though they were not at the start. "
                    "The iteration moved where the model barely responds to them; the data need not contradict them.")

    def _weigh_exact(self, st: LoopState, rows: torch.Tensor, nu: torch.Tensor) -> None:
        """After undamped solves of samples ``rows`` whose exact rows' largest multiplier is ``nu
        (R,)``, their weights in the merit rise to :data:`EXACT_MARGIN` times it where below (never
        fall), and the current iterates' merits (and models' objectives, where known) follow."""
        new = torch.maximum(self.exact_weight[rows], EXACT_MARGIN * nu)
        up = new > self.exact_weight[rows]
        rows, cur = rows[up], st.cur
        if not rows.numel():
            return
        self.exact_weight[rows] = new[up]
        cur["merit"][rows] = self._ssq(rows, cur["d"][rows], cur["w"][rows], penalty=True) + cur["log"][rows]
        known = rows[torch.isfinite(cur["nl_sse"][rows])]
        if known.numel():
            cur["nl_sse"][known] = self._objective(known, cur["nl_traj"][known], cur["w"][known], cur["log"][known])
        self._annotate(rows, merit=cur["merit"][rows])

    def _converged(self, st: LoopState, act, alpha, capped):
        """The convergence tests, on undamped steps only: the scaled step below ``xtol``, or the
        SSE unchanged to ``ftol`` with the step below ``sqrt(xtol)``. Converged samples take
        their last step and stop; returns the others."""
        spec, cur, scaled = self.spec, st.cur, st.scaled
        zero = st.damping[act] == 0
        # an iterate whose transfers were integrated loosely (INEXACT_FACTOR) takes its step first
        tight = zero & (cur["rtol"][act] <= spec.rtol)
        sse = cur["sse"][act]
        tight &= ~st.leaving  # a capped step out of a bound is far from converged, however small
        conv = tight & (scaled <= spec.xtol)
        conv_sse = (tight & ~conv & torch.isfinite(st.sse_prev[act]) & (sse != 0)
                    & ((sse - st.sse_prev[act]).abs() <= spec.ftol * sse.abs()) & (scaled <= math.sqrt(spec.xtol)))
        moving = zero & ~conv & ~conv_sse
        st.sse_prev[act[moving]] = sse[moving]
        done = conv | conv_sse
        if bool(done.any()):
            rows = act[done]
            W = cur["W"][rows]
            st.z0[rows] = spec.shifted(cur["z0"][rows], alpha[done])
            st.iterations[rows] += 1
            st.final_guess[rows] = W[..., 0] + torch.einsum("sgmk,sk->sgm", W[..., 1:], alpha[done])
            self._annotate(rows, model_merit=self._model_merit(rows, cur))
            self._notify(rows)
            st.undamped_stop[rows] = True
            if bool(conv.any()):
                st.stop(act[conv], Status.CONVERGED)
            if bool(conv_sse.any()):
                st.stop(act[conv_sse], Status.CONVERGED_SSE)
        st.scaled, st.leaving = scaled[~done], st.leaving[~done]
        return act[~done], alpha[~done], capped[~done]

    def _take(self, st: LoopState, act, trial, accept) -> None:
        """The accepted trials become their samples' iterates (damping back to 0)."""
        if not bool(accept.any()):
            return
        rows = accept.nonzero().flatten()
        target = act[rows]
        self._annotate(target, model_merit=self._model_merit(target, st.cur))
        self._notify(target)
        st.prev_z0[target], st.distrust[target] = st.cur["z0"][target], False
        put_samples(st.cur, target, trial, rows)
        self.fast_decay.update(r for r in target.tolist() if r in self.trial_decay)
        st.last_damping[target] = st.damping[target]
        st.damping[target] = 0.0
        st.iterations[target] += 1
        st.fresh[target] = True
        st.z0[target] = trial["z0"][rows]
        st.final_guess[target] = _pick(trial["W"], rows)[..., 0]
        if self.spec.stiff_refit:  # "auto"'s explicit solver: is the model stiff along the new iterates,
            n, grid = self.system.n, self._grid_of(target)  # at the observations as along the data?
            stiff = stiff_along(self._at_obs(trial["lin"].jac, act)[rows], n,
                                (grid[..., -1] - grid[..., 0]).expand(rows.numel()))
            # (along references that nearly solve the model: an early superposition may pass far outside)
            self.stiff_met.update(target[stiff & (trial["defect"][rows] <= DEFECT_TRUST)].tolist())

    def _reject(self, st: LoopState, rejected, alpha) -> None:
        """Rejected trials: without a filtering damping the iteration fails; Kantorovich
        re-anchors an undamped rejection about the model's own solution once; otherwise the
        damping strategy raises the damping (:meth:`torchql.damping.Damping.retry`), and past
        its use (:meth:`~torchql.damping.Damping.stalled`) the sample has stalled."""
        spec = self.spec
        if not spec.damping.filters:  # the thesis' iteration: the step is taken, and fails
            st.z0[rejected] = spec.shifted(st.cur["z0"][rejected], alpha)
            st.iterations[rejected] += 1
            self._notify(rejected)
            st.stop(rejected, Status.INTEGRATION_FAILED,
                    " The undamped step led to a trajectory that cannot be integrated; the default "
                    "damping=\"lm\" would have shortened it.")
            return
        st.rejected[rejected] += 1
        anchored = self._reanchor(st, rejected)
        raise_rows = rejected[~torch.isin(rejected, anchored)]
        if not raise_rows.numel():
            return
        spectrum = self._damped_spectrum(st, raise_rows)
        d = spec.damping.retry(st.damping[raise_rows], st.last_damping[raise_rows], spectrum)
        st.damping[raise_rows] = d
        stalled = raise_rows[spec.damping.stalled(d)]
        if stalled.numel():
            self._annotate(stalled, rejected=st.rejected[stalled], model_merit=self._model_merit(stalled, st.cur))
            self._notify(stalled)
            st.stop(stalled, Status.STALLED)

    def _reanchor(self, st: LoopState, rejected) -> torch.Tensor:
        """Kantorovich's undamped rejections, not yet anchored, re-linearized about the model's
        own solution from their estimates (where it integrates and its transfers succeed; a stiff
        model's integrated again at the fit's tolerance); returns those samples. A sample whose
        re-linearized transfers fail (a fast layer of the model's solution inside a grid interval)
        keeps its iterate, as one whose solution does not integrate: re-anchoring is a second
        try, and the damping is raised instead."""
        cur, n = st.cur, self.system.n
        candidates = rejected[(st.damping[rejected] == 0) & ~cur["anchored"][rejected]]
        if self.spec.scheme.integrates_model or not candidates.numel():  # the model's own solution already
            return rejected[:0]
        self._nonlinear_sse(st.all_idx, cur, candidates, current=True)
        integrable = torch.isfinite(cur["nl_traj"][candidates]).flatten(1).all(dim=1)
        rows = candidates[integrable]
        if self.spec.stiff and rows.numel():  # at the fit's tolerance, as the first reference (_first_reference)
            traj, errors = self._nonlinear(st.all_idx[rows], cur["z0"][rows], loose=False, guess=cur["nl_traj"][rows])
            ok = torch.tensor([e is None for e in errors], dtype=torch.bool, device=rows.device)
            self._keep_model_sse(st.all_idx, cur, rows[ok], traj[ok], [None] * int(ok.sum()))
            rows = rows[ok]  # (one that fails keeps its iterate)
        if not rows.numel():
            return rows
        traj = cur["nl_traj"][rows]
        lin = self._linearize(rows, traj)

        def anchor(pos):  # its transfers at the tolerance of the iterate it replaces (stiff: INEXACT_FACTOR's)
            part = map_fields(lin, lambda v: _pick(v, pos))  # (the rows themselves where one tolerance has all)
            return self._evaluate(_pick(rows, pos), cur["z0"][_pick(rows, pos)], _pick(traj, pos), part.f, part), None
        anchored, _ = by_level(cur["rtol"][rows], anchor, self._transfers_at)
        anchored["anchored"][:] = True
        anchored["nl_sse"], anchored["nl_traj"] = cur["nl_sse"][rows], traj
        cur["anchored"][candidates] = True  # tried once
        keep = (~anchored["failed"]).nonzero().flatten()
        put_samples(cur, rows := rows[keep], anchored, keep)
        first = rows[st.iterations[rows] == 0]  # the first record's value, kept without a history too
        self.first_sse[first] = cur["sse"][first]
        if self.history is not None:
            for r in rows.tolist():
                record = self.history[r][-1]
                record.sse, record.merit = float(cur["sse"][r]), float(cur["merit"][r])
                record.trajectory = cur["rz"][r, :, :n].detach().clone()
        return rows

    def _fail_integration_rows(self, rows, status, detail) -> None:
        for r in rows.tolist():
            status[r] = _STATUSES.index(Status.INTEGRATION_FAILED)
            said = self.propagation_errors.get(r, "the transfer of a grid interval did not meet the tolerance or "
                                               "became non-finite")
            detail[r] = f" The solver said: {said}."

    def _propose(self, act, cur, alpha):
        """The trial iterates from ``cur``'s samples ``act`` with updates ``alpha``; ``ok`` where
        usable (the scheme's :meth:`~torchql.schemes.Scheme.propose`). On the stiff path their
        linear transfers are integrated at the inexact tolerance of each one's step
        (:data:`~torchql.engine_evaluate.INEXACT_FACTOR`), rounded down to a quarter decade, the
        samples at one tolerance together: a sample's trial is the same in a batch as alone."""
        spec = self.spec
        if not spec.stiff:
            return spec.scheme.propose(self, act, cur, alpha)
        wanted = (INEXACT_FACTOR * self._scaled(act, cur, alpha) ** 2).clamp(max=_LOOSE_RTOL)
        levels = (10 ** (torch.floor(4 * torch.log10(wanted)) / 4)).clamp(min=spec.rtol)
        return by_level(levels, lambda pos: spec.scheme.propose(self, act[pos], cur, alpha[pos]), self._transfers_at)

    def _scaled(self, act, cur, alpha) -> torch.Tensor:
        """The scaled sizes ``(S,)`` of the updates ``alpha (S, m)`` of ``cur``'s samples ``act``
        (:meth:`_scaled_step`)."""
        return self._scaled_step(act, _pick(cur["z0"], act), alpha)

    def _scaled_step(self, act, z0, alpha) -> torch.Tensor:
        """The scaled sizes ``(S,)`` of the steps ``alpha (S, m)`` in the unknowns of the chunk's
        samples ``act`` from their augmented states ``z0 (S, M)``: ``max_i |alpha_i| / max(|u_i|,
        s_i)`` (the convergence test's measure)."""
        u = z0[:, self.spec.unknown_index]
        return (alpha.abs() / torch.maximum(u.abs(), self.scale[act])).amax(dim=1)

    @contextmanager
    def _transfers_at(self, rtol: float | None):
        """Within the block, the linear transfers of the iterates evaluated are integrated at
        ``rtol`` (never below the fit's; None: at the fit's), as :attr:`trial_rtol` says."""
        self.trial_rtol = None if rtol is None else max(self.spec.rtol, rtol)
        try:
            yield
        finally:
            self.trial_rtol = None

    def _data_start(self, idx, z0):
        """Each sample's first reference from its data (:func:`torchql.data_start.data_reference`,
        as ``fit`` builds it): ``z_ref, z_dot (S, G, M)`` and the guesses ``z0 (S, M)`` with the
        coefficients from the gradient matching. A sample on its own grid gets it on its own
        nodes, the padding repeating the last one."""
        spec = self.spec
        y = torch.where(self.mask, self.y, torch.full_like(self.y, float("nan")))
        sigma = torch.where(self.mask, 1.0 / self.w.clamp(min=torch.finfo(self.w.dtype).tiny), torch.ones_like(self.w))
        ends = (last_nodes(self.grid) + 1)[idx].tolist() if self.grid.dim() == 2 else [self.G] * idx.numel()
        z_ref, z_dot, z0 = data_reference(self.system, self.grid if self.grid.dim() == 1 else self.grid[idx], ends,
                                          self.t_obs if self.t_obs.dim() == 1 else self.t_obs[idx], y[idx],
                                          sigma[idx], self.mask[idx], spec.operator.observed_states, z0,
                                          spec.unknown_index, spec.bounds, spec.rcond)
        return z_ref, z_dot, spec.initial.complete(z0)
