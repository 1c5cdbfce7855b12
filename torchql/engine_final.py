"""The engine's final pass: each sample's model integrated at its estimates, with sensitivities.

The reported SSE, residuals, Jacobian, singular values, status diagnosis and covariance are those
of the fitted model itself, not of the last linear problem.

A converged fit's estimates are a fixed point of the iteration's own discretization: Kantorovich's
linear problems carry the storage grid's interpolation error (of order ``h^4`` in the interval
width), so on a coarse grid they may sit a little off the model's own optimum. The final pass
therefore checks them on the model itself: where the Gauss–Newton step from its accurate
residuals is larger than the step bound of the convergence test that stopped the fit (``xtol``,
or ``sqrt(xtol)`` for the sum-of-squares test; scaled as the iteration's steps), or promises to
lower the sum of squares by more than ``ftol`` of it and the integration's own floor, it is
taken, as a shooting iteration, each kept only if it lowers the model's merit, until the step
falls below that bound. On the default grid the step is far below it and nothing is taken; a step
short enough (:data:`LINEAR_STEP`) is taken along the sensitivities, with no new integration.
Where the grid misses a fast change of the model (a steep ``tanh``), the fixed point may be several
steps away: a fit whose steps on the model still exceed the bound when ``max_iter`` or
:data:`POLISH_STEPS` runs out is not converged, and says so (``MAX_ITER`` or ``STALLED``).

The grid's sensitivities miss such a change too, and Gauss–Newton with them may see no step left
where there is one. So on an automatic grid the final solution checks the storage's interpolants
against the model between the nodes (:mod:`torchql.storage_check`), and a sample whose grid
misses its model gets its sensitivities integrated with its solution (:meth:`FinalPass._jointly`)
for all its steps and its covariance; elsewhere a second needed step takes them.
"""

from __future__ import annotations

import math

import torch

from .bounds import at_bound_note, moved_guesses_note
from .data_start import sse_at_guesses
from .diagnosis import RUNAWAY_FACTOR, negligible_columns, typical_magnitudes
from .budget import TimeBudgetExceeded, no_time_budget, until
from .dopri import dopri_batch
from .dopri_sensitivity import HELD_STEP
from .engine_state import not_above
from .engine_steps import predicted_decrease
from .saddle import off_saddle
from .engine_diagnosis import FinalDiagnosis
from .engine_grid import pad_nodes
from .result import Status
from .solvers import STIFF_SOLVERS
from .stiffness import STIFF_LINEAR_SOLVER
from .storage_check import interpolation_misfit, storage_misses
from .transfer import interval_coefficients
from .uncertainty import covariance, redundant_exact, residual_variance

__all__ = ["FinalPass"]

_STATUSES = list(Status)
#: The statuses whose samples get no final evaluation (nothing to evaluate, or no time left).
_NOT_EVALUATED = tuple(_STATUSES.index(s) for s in (Status.DIVERGED, Status.INTEGRATION_FAILED, Status.MAX_TIME))
#: Most Gauss–Newton steps on the model itself that the final pass takes from converged estimates
#: (from a storage grid's fixed point one step usually reaches the model's optimum; a grid that
#: misses a fast change of the model may leave several, each a shooting iteration).
POLISH_STEPS = 20
#: A polishing step whose scaled size is at most this fraction of ``sqrt(rtol)`` moves the solution
#: and its residuals by their linear prediction (the sensitivities times the step) instead of a new
#: integration: the second-order remainder, the step's square times the trajectory's relative
#: curvature in the unknowns, stays below ``rtol`` where that curvature is below 100.
LINEAR_STEP = 0.1
#: The longest polishing step, in the unknowns' scale: a longer Gauss–Newton step on the model is
#: shortened to it along its direction (the linearization is not trusted further from a fixed point).
POLISH_MAX_STEP = 1.0


class FinalPass(FinalDiagnosis):
    """The final evaluation (mixed into :class:`torchql.engine.Engine`)."""

    def _finish(self, z0, status, detail, iterations, final_guess, polish) -> dict:
        """The final evaluation of the estimates ``z0 (S, M)`` (changed in place by the polishing
        steps of the samples ``polish (S,)`` allows, counted in ``iterations``)."""
        spec, S = self.spec, self.S
        m = spec.m
        dtype, dev = spec.dtype, spec.device
        sse = torch.full((S,), float("nan"), dtype=dtype, device=dev)
        cov = torch.full((S, m, m), float("nan"), dtype=dtype, device=dev)
        R = self.w.reshape(S, -1).shape[1]
        residuals = torch.full((S, R), float("nan"), dtype=dtype, device=dev)
        jacobian = torch.full((S, R, m), float("nan"), dtype=dtype, device=dev)
        singular_values = torch.full((S, m), float("nan"), dtype=dtype, device=dev)
        exact_residual = torch.full((S,), float("nan"), dtype=dtype, device=dev)
        redundant = torch.zeros(S, dtype=dtype, device=dev)  # exact values that fix nothing more (their dof's)
        objective = torch.full((S,), float("nan"), dtype=dtype, device=dev)  # the last record's value
        codes = [_STATUSES[int(c)] for c in status.tolist()]
        converged = torch.tensor([c.success for c in codes], dtype=torch.bool, device=dev)
        rows, traj, W = self._final_solutions(_evaluated(status, self.stopped_stiff), z0, final_guess, codes, detail)
        if rows.numel():
            traj, W = self._polish(rows, traj, W, z0, iterations, codes, polish, detail)
            converged &= torch.tensor([c is not Status.MAX_TIME for c in codes], dtype=torch.bool, device=dev)
        if rows.numel():
            traj_obs = self._at_obs(traj, rows)
            C_mean, _, resid = self._rows(rows, traj_obs, traj_obs, self._at_obs(W, rows)[..., 1:])
            C, d, w, log_term = self._weighted(rows, z0[rows], C_mean, resid)
            J = C * w.unsqueeze(-1)  # R rows, and with a sigma(p) function R more (its log term's)
            rw = d * w
            R = resid.shape[1]
            J_info = J if spec.sigma_function is None else _fisher_rows(C_mean, w, C[:, R:])
            s = self._ssq(rows, resid, w)
            sse[rows] = s
            s = s + log_term  # the objective (with a sigma(p) function, not a sum of squares)
            objective[rows] = s
            exact_residual[rows], unmet = self._exact_misfit(rows, resid)
            self._note_unmet_exact(rows, exact_residual, unmet, codes, detail)
            if self.history is not None:
                for k, r in enumerate(rows.tolist()):
                    self.history[r].append(self._record(r, int(iterations[r]), z0[r], float(s[k]), traj[k]))
                    self._notify(r)
            residuals[rows], jacobian[rows] = rw[:, :R], J_info[:, :R]
            nonfinite = ~torch.isfinite(s)
            for r in rows[nonfinite].tolist():
                codes[r] = Status.DIVERGED
                detail[r] = " The fitted trajectory is non-finite."
            keep = ~nonfinite
            magnitudes = self._magnitudes(traj)[keep]
            rows, J, s, rw, J_info, w = rows[keep], J[keep], s[keep], rw[keep], J_info[keep], w[keep]
        if rows.numel():
            used = self._used(rows)
            J, J_info = self._without_negligible(rows, z0, J, J_info)
            deficient, singular_values[rows] = self._diagnose(rows, J, rw, w, s, z0, codes, detail, used, magnitudes)
            converged |= torch.tensor([c.success for c in codes], dtype=torch.bool, device=dev)
            exact = torch.cat([self.exact[rows], torch.zeros_like(used[:, self.exact.shape[1]:])], dim=1)
            for k in exact.any(dim=1).nonzero().flatten().tolist():
                redundant[rows[k]] = redundant_exact(J_info[k][used[k]], exact[k][used[k]], spec.rcond)
            cov[rows] = _covariance(J_info, used, s, self.L[rows] - redundant[rows], spec,
                                    deficient | exact.any(dim=1), exact)
            cov[~converged] = float("nan")  # as fit: no error bars about estimates that are not an optimum
        if self.history is not None:  # the estimates returned, unevaluated, where the final pass did not run
            for r in range(S):
                last = self.history[r][-1] if self.history[r] else None
                if last is None or last.iteration != int(iterations[r]) or not torch.equal(last.x0, z0[r, :self.system.n]):
                    self.history[r].append(self._record(r, int(iterations[r]), z0[r], float("nan")))
                    self._notify(r)  # (a fit stopped by its time budget before its first step)
        self._storage_notes(detail)
        for k, r in enumerate(self.index.tolist()):
            if spec.bounds.active:
                stderr = cov[k].diagonal().clamp_min(0).sqrt()  # (NaN where not converged: none named)
                detail[k] += at_bound_note(spec.bounds.at_bound(z0[k, spec.unknown_index], stderr=stderr))
            if r in spec.moved_guesses:
                detail[k] += " " + moved_guesses_note(spec.moved_guesses[r])
            if spec.stiff and not spec.linear_solver.stiff_stable and not codes[k].success:
                detail[k] += (f" The model is stiff on the data's span (solver {spec.solver!r}), and linear_solver="
                              f"{spec.linear_solver.name!r} propagates explicitly: its transfers crawl or fail there; "
                              f"the default for stiff models, linear_solver={STIFF_LINEAR_SOLVER!r}, suits them.")
        messages = [c.value + d for c, d in zip(codes, detail)]
        return dict(z0=z0, sse=sse, cov=cov, iterations=iterations, status=codes, message=messages,
                    residuals=residuals, jacobian=jacobian, singular_values=singular_values,
                    exact_residual=exact_residual, redundant_exact=redundant, history=self.history,
                    sse_start=self.first_sse, sse_end=objective, z0_start=self.first_z0,
                    sse_guesses=sse_at_guesses(self, codes, sse, residuals, iterations),
                    off_saddle=off_saddle(self, codes, z0, sse),
                    stiff_met=torch.tensor([k in self.stiff_met for k in range(S)], dtype=torch.bool, device=dev))

    def _storage_notes(self, detail: list) -> None:
        """Say in ``detail`` of each sample whose storage grid misses its model (its interpolants stray
        between the nodes, ``storage_missed``, or its model needs more than the grid solver's steps
        in an interval, ``coarse_grid``, finally evaluated so) that the final pass integrated its
        sensitivities with its solution."""
        for k, misfit in self.storage_missed.items():
            detail[k] += (f" The automatic storage grid misses a change of the model between its nodes (its "
                          f"interpolants stray by {misfit:.2g} of the states over an interval): the final pass "
                          "integrated the sensitivities with the solution; a finer `grid` makes the iterations "
                          "faithful too.")
        for k in sorted(self.joint_final - set(self.storage_missed)):
            by = (" (Rodas5P's with their sensitivities: a decay held most of DOP853's steps, "
                  f"h max(-Re lambda) >= {HELD_STEP:g})" if k in self.fast_decay else "")
            detail[k] += (" The storage grid misses a change of the model between its nodes, or the model is faster "
                          "than the grid: an interval needed more steps than the grid solver takes. The model's "
                          f"solutions were integrated by the adaptive solver{by}, and the final pass integrated the "
                          "sensitivities with the solution; a finer `grid`, or `linear_solver=\"rodas5p\"` (the "
                          "sensitivities integrated with every solution), makes the iterations faster.")

    def _exact_misfit(self, rows, resid) -> tuple[torch.Tensor, torch.Tensor]:
        """The largest absolute residual ``(R,)`` of the samples ``rows`` over their values marked
        ``exact`` (residuals ``resid (R, K)``), and whether it is unmet: above ``rtol`` times their
        largest magnitude (at least 1), the accuracy of the model's own solution."""
        exact = self.exact[rows]
        misfit = torch.where(exact, resid.abs(), torch.zeros_like(resid)).amax(dim=1)
        y = torch.where(exact, self.y[rows].reshape(rows.numel(), -1).abs(), 0.0).amax(dim=1)
        return misfit, misfit > self.spec.rtol * y.clamp(min=1.0)

    def _note_unmet_exact(self, rows, exact_residual, unmet, codes, detail) -> None:
        """Say so in the detail of the samples ``rows`` that did not converge where their values marked
        ``exact`` are not met (``unmet``, :meth:`_exact_misfit`): the largest misfit ``exact_residual (S,)``."""
        if not self.spec.has_exact:
            return
        for k, r in enumerate(rows.tolist()):
            if bool(unmet[k]) and not codes[r].success:
                detail[r] += (f" The values marked `exact` are not met: the largest misfit is "
                              f"{float(exact_residual[r]):.3g}.")

    def _share_final_solutions(self, parts: list) -> None:
        """The final solutions of several groups of the chunk's samples (``parts``: ``[(engine,
        iteration state)]``, the engines of groups that chose different grids) in one batched
        Dormand–Prince call, where each group's final pass would make one: its cost is in its
        rounds, each advancing every sample at once, so one call for all the groups costs about
        what one group's does. Each sample keeps its own steps and output nodes (its grid padded by
        its last node), so its solution is the one its group's call would give; the engines keep
        them (``shared_solutions``) for their final passes."""
        items = []
        for engine, st in parts:
            rows = _evaluated(st.status, engine.stopped_stiff)
            if rows.numel() and engine._final_by_dopri(rows.numel()):
                items.append((engine, st, rows))
        if len(items) < 2:
            return
        width = max(engine.G for engine, _, _ in items)
        grids, lands = [], []
        for engine, _, rows in items:
            grids.append(pad_nodes(engine._grid_of(rows).expand(rows.numel(), engine.G), width))
            land = torch.zeros(rows.numel(), width, dtype=torch.bool, device=engine.grid.device)
            land[:, :engine.G] = engine._landing(rows, explicit=True)
            lands.append(land)
        z0 = torch.cat([st.z0[rows] for _, st, rows in items])
        with no_time_budget(), torch.no_grad():
            traj, ok, evals = dopri_batch(self.system, z0, torch.cat(grids), rtol=self.spec.rtol, atol=self.spec.atol,
                                          land=torch.cat(lands), interval_steps=self.spec.max_steps,
                                          method=self.spec.solver)
        self.nfev += evals
        start = 0
        for engine, st, rows in items:
            engine.shared_solutions = {r: (st.z0[r].clone(), traj[start + k, :engine.G])
                                       for k, r in enumerate(rows.tolist()) if bool(ok[start + k])}
            start += rows.numel()

    def _final_by_dopri(self, count: int) -> bool:
        """Whether this chunk's final pass integrates ``count`` samples by the batched Dormand–Prince
        (:meth:`~torchql.engine_evaluate.Evaluation._nonlinear`'s choice, without joint sensitivities)."""
        return self._batched_dopri() and not self._grid_solves(count) and not self._joint_sensitivities

    def _final_solutions(self, rows, z0, final_guess, codes, detail):
        """The model integrated at the estimates ``z0`` of samples ``rows`` (from ``final_guess``,
        a prediction of the trajectory), with its sensitivities: ``(rows, traj, W)`` of the samples
        that integrated; the others' ``codes`` become INTEGRATION_FAILED with the solver's words."""
        if not rows.numel():
            return rows, None, None
        # a sample whose model is too fast for its grid's solver (``coarse_grid``) is too fast for its
        # grid's sensitivities too: they are integrated with its solution (Gauss-Newton with the
        # grid's stopped a relaxation rate grown 100-fold from its guess 2.5e-5 short of its optimum)
        joint = self._in_coarse_grid(rows)
        good, traj, W, errors = self._model_at(rows, z0[rows], final_guess[rows], joint=joint)
        self.joint_final = set(rows[joint & good].tolist())
        for k, r in enumerate(rows.tolist()):
            if errors[k] is not None:
                codes[r] = Status.INTEGRATION_FAILED
                detail[r] = f" The solver said, at the final estimates: {errors[k]}."
        return rows[good], traj[good], W[good]

    def _model_at(self, rows, z0, guess, joint=None):
        """The model integrated from ``z0 (S, M)`` of samples ``rows`` (``guess (S, G, M)``: a
        prediction of the trajectory), with its sensitivities: ``(good (S,), traj (S, G, M),
        W (S, G, M, 1 + m), errors)``, the solver's words for each sample that failed (None: good).
        ``joint (S,)``: samples whose sensitivities are integrated with their solutions whatever
        the propagator (:meth:`_jointly`).
        """
        if joint is not None and bool(joint.any()):
            return self._model_at_mixed(rows, z0, guess, joint)
        if self._joint_sensitivities or self.spec.solver in STIFF_SOLVERS:
            # the solution and its sensitivities on the same adaptive steps: for a stiff model the
            # grid's transfers may miss a fast change inside an interval, and the status and the
            # covariance are only as true as this Jacobian
            return self._jointly(rows, z0)
        traj, errors = self._nonlinear(rows, z0, loose=False, guess=guess)
        good = [e is None for e in errors]
        traj = torch.where(torch.tensor(good, device=z0.device).reshape(-1, 1, 1), traj, guess)
        lin = self._linearize(rows, traj)
        spec = self.spec
        checked = spec.auto_grid and traj.shape[1] > 1  # (storage_check) the storage's coefficients, built once
        coefficients = (interval_coefficients(self._grid_of(rows), traj, lin.f, lin, spec.linear_solver.hermite_degree)
                        if checked and spec.linear_solver.batched else None)
        W, failed = self._propagate(rows, traj, lin.f, lin, spec.columns(z0), coefficients=coefficients)
        for k in failed.nonzero().flatten().tolist():
            errors[k] = errors[k] or "the transfer of a grid interval did not meet the tolerance"
        good = torch.tensor([e is None for e in errors], dtype=torch.bool, device=z0.device)
        missed = self._missed_by_storage(rows, traj, lin, good, coefficients) if checked else torch.zeros_like(good)
        if bool(missed.any()):  # the sensitivities integrated with the solution, where the grid misses the model
            j = missed.nonzero().flatten()
            ok, traj[j], W[j], errors_j = self._jointly(rows[j], z0[j])
            good[j] = ok
            for i, e in zip(j.tolist(), errors_j):
                errors[i] = e
        return good, traj, W, errors

    def _missed_by_storage(self, rows, traj, lin, good, coefficients=None) -> torch.Tensor:
        """Of the samples ``rows`` whose model integrated (``good (S,)``), with their solutions
        ``traj (S, G, M)`` on an automatic storage grid and its linearization ``lin``, those whose
        storage misses a change of the model between its nodes (:mod:`torchql.storage_check`):
        their sensitivities are integrated with their solutions from then on
        (``self.storage_missed``), and their messages say so."""
        misfit = interpolation_misfit(self.system.f, self._grid_of(rows), traj, lin,
                                      self.spec.linear_solver.hermite_degree, self.system.n, coefficients,
                                      floor=self.spec.atol / self.spec.rtol)
        missed = storage_misses(misfit, self.spec.rtol) & good
        for k in missed.nonzero().flatten().tolist():
            self.storage_missed[int(rows[k])] = float(misfit[k])
        return missed

    def _model_at_mixed(self, rows, z0, guess, joint):
        """:meth:`_model_at` where the samples ``joint (S,)`` get their sensitivities integrated with
        their solutions and the others the propagator's."""
        S = z0.shape[0]
        good = torch.zeros(S, dtype=torch.bool, device=z0.device)
        traj, W, errors = guess.clone(), None, [None] * S
        for j, together in ((joint.nonzero().flatten(), True), ((~joint).nonzero().flatten(), False)):
            if not j.numel():
                continue
            ok, traj_j, W_j, errors_j = (self._jointly(rows[j], z0[j]) if together
                                         else self._model_at(rows[j], z0[j], guess[j]))
            W = W_j.new_empty((S, *W_j.shape[1:])) if W is None else W
            good[j], traj[j], W[j] = ok, traj_j, W_j
            for i, e in zip(j.tolist(), errors_j):
                errors[i] = e
        return good, traj, W, errors

    def _polish(self, rows, traj, W, z0, iterations, codes, polish, detail):
        """Gauss–Newton steps on the model itself from the estimates ``z0`` of the converged
        samples among ``rows`` that ``polish (S,)`` allows, with their solutions ``traj (R, G, M)``
        and ``W (R, G, M, 1 + m)`` (see the module's description). A step is taken where its scaled
        size exceeds ``xtol`` and kept where it lowers the merit; ``z0``, ``iterations`` and the
        samples' records follow. The steps are optional, so they keep to the fit's time budget
        (``self.deadline``); those it stops end as :meth:`_out_of_time` says. Returns the solutions
        at the estimates kept."""
        accurate = torch.zeros_like(polish)  # samples whose sensitivities are integrated with their solutions
        accurate[list(self.storage_missed) + sorted(self.coarse_grid)] = True
        trying: dict[int, float] = {}  # the samples whose needed step is being taken: its scaled size
        try:
            with until(getattr(self, "deadline", None)):
                for step in range(POLISH_STEPS + 1 if POLISH_STEPS else 0):  # the last pass only checks
                    if not self._polish_round(step, rows, traj, W, z0, iterations, codes, polish, detail, accurate,
                                              trying):
                        break
        except TimeBudgetExceeded:
            self._out_of_time(trying, codes, detail)
        return traj, W

    def _polish_round(self, step, rows, traj, W, z0, iterations, codes, polish, detail, accurate, trying) -> bool:
        """Polishing step number ``step`` of :meth:`_polish` (its arguments, changed in place; ``trying``
        gets the samples whose step is needed). Returns whether a sample may take another."""
        spec = self.spec
        take = polish[rows].clone()
        take &= torch.tensor([codes[r].success or codes[r] is Status.STALLED for r in rows.tolist()],
                             dtype=torch.bool, device=take.device)
        if not bool(take.any()):
            return False
        k = take.nonzero().flatten()
        r = rows[k]
        here, alpha, infeasible, scaled, need = self._polish_step(r, z0, traj[k], W[k], codes)
        trying.clear()
        trying.update(zip(r[need].tolist(), scaled[need].tolist()))
        again = need & ~accurate[r] if step >= 1 and not self._joint_sensitivities else torch.zeros_like(need)
        if bool(again.any()):  # a second step: the grid's sensitivities did not land the first
            j = again.nonzero().flatten()
            fresh, traj_j, W_j, _ = self._jointly(r[j], z0[r[j]])
            traj[k[j[fresh]]], W[k[j[fresh]]] = traj_j[fresh], W_j[fresh]
            accurate[r[j]] = True
            if bool(fresh.any()):
                here, alpha, infeasible, scaled, need = self._polish_step(r, z0, traj[k], W[k], codes)
        polish[r[~need]] = False
        out = self._out_of_steps(r, need, scaled, iterations, codes, detail, step == POLISH_STEPS, z0)
        polish[r[out]] = False
        need &= ~out
        trying.clear()
        trying.update(zip(r[need].tolist(), scaled[need].tolist()))
        if not bool(need.any()):
            return False
        k, r, alpha, scaled = k[need], r[need], alpha[need], scaled[need]
        # a longer step is no polish of a fixed point: its direction, as far as the linearization is
        # trusted (a stalled fit's rank-deficient step reached 1e15 of the scale, whose model took
        # 10^5 explicit steps to fail)
        alpha = alpha * (POLISH_MAX_STEP / scaled).clamp(max=1.0).unsqueeze(-1)
        scaled = scaled.clamp(max=POLISH_MAX_STEP)
        z0_new = spec.shifted(z0[r], alpha)
        guess = traj[k] + torch.einsum("sgmk,sk->sgm", W[k][..., 1:], alpha)
        # a step this short is the linear prediction's: its second-order remainder is below the tolerance
        linear = scaled <= LINEAR_STEP * math.sqrt(spec.rtol)
        good, traj_new, W_new = torch.ones_like(linear), guess, W[k].clone()
        W_new[..., 0] = guess
        far = (~linear).nonzero().flatten()
        if far.numel():
            good[far], traj_new[far], W_new[far], _ = self._model_at(r[far], z0_new[far], guess[far],
                                                                     joint=accurate[r[far]])
        merit = torch.full_like(scaled, float("inf"))
        g = good.nonzero().flatten()
        if g.numel():
            merit[g] = self._evaluate(r[g], z0_new[g], traj_new[g], None, None, solution=True, W=W_new[g])["merit"]
        accept = good & not_above(merit, here["merit"][need])
        polish[r[~accept]] = False
        a = accept.nonzero().flatten()
        if self.history is not None:
            sse = here["sse"][need]
            for j in a.tolist():
                record = self._record(int(r[j]), int(iterations[r[j]]), z0[r[j]], float(sse[j]), traj[k[j]])
                record.alpha, record.alpha_norm = alpha[j].detach().clone(), float(scaled[j])
                record.merit = record.model_merit = float(here["merit"][need][j])
                self.history[int(r[j])].append(record)
                self._notify(int(r[j]))
        z0[r[a]], traj[k[a]], W[k[a]] = z0_new[a], traj_new[a], W_new[a]
        iterations[r[a]] += 1
        trying.clear()
        return True

    def _out_of_time(self, trying: dict, codes, detail) -> None:
        """The samples ``trying`` (sample: the scaled size of its needed step) whose polishing steps the
        time budget stopped keep their estimates, evaluated: a converged one is not confirmed on the
        model (``MAX_TIME``, without a covariance), a stalled one says so."""
        budget = "an enclosing fit's" if self.max_time is None else f"{self.max_time:g} s"
        for r, size in trying.items():
            text = (f"the final pass's Gauss–Newton steps on the model were stopped by the time budget (max_time = "
                    f"{budget}): the next would move the unknowns by {size:.2g} of their scale.")
            if codes[r].success:
                codes[r] = Status.MAX_TIME
                detail[r] = (" The iteration had converged, and the sum of squares and residuals are the model's at "
                             "these estimates, but " + text + detail[r])
            else:
                detail[r] += " " + text[0].upper() + text[1:]

    def _polish_step(self, r, z0, traj, W, codes):
        """The Gauss–Newton step on the model of samples ``r`` from ``z0[r]`` with their solutions
        ``traj`` and ``W``: ``(here, alpha, infeasible, scaled, need)``, the evaluation there, the
        step, its scaled size and whether it is needed (above the step bound of the test that
        stopped the fit, ``xtol`` or the sum-of-squares test's ``sqrt(xtol)``, or not minimal)."""
        spec = self.spec
        here = self._evaluate(r, z0[r], traj, None, None, solution=True, W=W)
        alpha, _, infeasible, _ = self._solve(r, here, torch.zeros_like(here["sse"]))
        u = z0[r][:, spec.unknown_index]
        magnitude = torch.maximum(u.abs(), torch.maximum(self.scale[r], self._magnitudes(traj)))
        scaled = (alpha.abs() / magnitude).amax(dim=1)
        bound = torch.tensor([math.sqrt(spec.xtol) if codes[i] is Status.CONVERGED_SSE else spec.xtol
                              for i in r.tolist()], dtype=scaled.dtype, device=scaled.device)
        need = ~infeasible & torch.isfinite(scaled) & ((scaled > bound) | self._not_minimal(r, here, alpha))
        if spec.has_exact:  # a step below the bound of the sum-of-squares test may leave them unmet
            traj_obs = self._at_obs(traj, r)
            resid = self._rows(r, traj_obs, traj_obs, self._at_obs(W, r)[..., 1:])[2]
            need |= ~infeasible & self._exact_misfit(r, resid)[1]
        return here, alpha, infeasible, scaled, need

    def _jointly(self, rows, z0):
        """The model integrated from ``z0 (S, M)`` of samples ``rows`` with its sensitivities, the two
        together (:meth:`~torchql.engine_evaluate.Evaluation._solve_with_sensitivities`), as
        :meth:`_model_at` returns them: ``(good, traj, W, errors)``. Where a grid misses a fast change
        of the model its transfers' sensitivities miss it too, and Gauss–Newton with them converges
        to the wrong point."""
        traj, W, errors = self._solve_with_sensitivities(rows, z0)
        return torch.tensor([e is None for e in errors], dtype=torch.bool, device=z0.device), traj, W, errors

    def _out_of_steps(self, rows, need, scaled, iterations, codes, detail, last: bool, z0) -> torch.Tensor:
        """Of the samples ``rows`` whose next step on the model is needed (``need``; its scaled size
        ``scaled``), those that may not take it (``max_iter`` reached, the ``last`` pass, or estimates
        ``z0[rows]`` run away: an unknown beyond :data:`~torchql.diagnosis.RUNAWAY_FACTOR` times its
        typical magnitude, which the diagnosis calls a divergence whatever a further step does): their
        fits are not converged on the model: ``MAX_ITER`` where ``max_iter`` ran out, else
        ``STALLED`` (:data:`POLISH_STEPS` is no user's limit), with the step's size in the message.
        (Steps of a fit whose optimum lies at infinity doubled an initial state from 1e6 to 4e11,
        each at the same sum of squares, each a solve with sensitivities.)"""
        away = ~(z0[rows][:, self.spec.unknown_index].abs() <= RUNAWAY_FACTOR * self._typical(rows)).all(dim=1)
        maxed = iterations[rows] >= self.spec.max_iter
        out = need & (maxed | last | away)
        remedy = "" if self.spec.scheme.integrates_model else ' or `method="shooting"`'
        for j in out.nonzero().flatten().tolist():
            r = int(rows[j])
            codes[r] = Status.MAX_ITER if bool(maxed[j]) else Status.STALLED
            if bool(away[j]):
                detail[r] = (" The final pass's Gauss–Newton steps on the model were stopped with the estimates beyond "
                             f"{RUNAWAY_FACTOR:g} times their typical magnitudes.")
                continue
            detail[r] = (" The iteration's fixed point was off the model's optimum (the storage grid misses a "
                         "change of the model), and the final pass's Gauss–Newton steps on the model stopped before "
                         f"converging: the next would move the unknowns by {float(scaled[j]):.2g} of their scale; a "
                         f"finer `grid`{remedy} reaches the optimum.")
        return out

    def _not_minimal(self, rows, here: dict, alpha: torch.Tensor) -> torch.Tensor:
        """Whether the Gauss–Newton steps ``alpha (S, m)`` of the evaluated iterates ``here`` of
        samples ``rows`` promise a decrease of the sum of squares ``|w d|^2 - |w (d - C alpha)|^2``
        above ``ftol`` of it and above the integration's own floor, ``sum (w (atol + rtol |y|))^2``
        over the values used: a storage grid's fixed point whose step is small in the unknowns'
        scale (an initial state far below its trajectory's magnitude) but whose residuals are not
        yet the model's least."""
        predicted = predicted_decrease(here["C"], here["d"], here["w"], alpha)
        floor = self._integration_floor(rows, here["w"])  # (StepTests')
        return predicted > self.spec.ftol * here["sse"].abs() + floor

    def _used(self, rows) -> torch.Tensor:
        """The rows in use of samples ``rows``: the values present ``(S, R)``, and with a ``sigma(p)``
        function the log rows of those values after them ``(S, 2 R)``."""
        used = self.mask[rows].reshape(rows.numel(), -1)
        return used if self.spec.sigma_function is None else torch.cat([used, used], dim=1)

    def _magnitudes(self, traj: torch.Tensor) -> torch.Tensor:
        """The unknowns' magnitudes ``(R, m)`` on solutions ``traj (R, G, M)``: an initial state's, its
        trajectory's largest; 0 for a coefficient. With the iteration's typical magnitudes they scale
        the final pass's steps: a state guessed at 0, whose first reference stayed near 0, is
        measured on the solution fitted (a product that reaches 100 from 0)."""
        n = self.system.n
        magnitudes = torch.zeros(traj.shape[0], traj.shape[-1], dtype=traj.dtype, device=traj.device)
        magnitudes[:, :n] = traj[..., :n].abs().amax(dim=1)
        return magnitudes[:, self.spec.unknown_index]

    def _typical(self, rows) -> torch.Tensor:
        """The typical magnitudes ``(S, m)`` of the unknowns of samples ``rows``
        (:func:`torchql.diagnosis.typical_magnitudes`). A coefficient guessed nonzero is measured
        by its guess, also from a data-built start, whose matched coefficients may themselves
        have run away (Michaelis–Menten matched to slopes of its linear regime: V and Km 1e8
        times their guesses, as the model's fit from the guesses runs away too)."""
        idx = self.spec.unknown_index
        guess = self.z0_guess[rows][:, idx]
        first = None if self.scale is None else self.scale[rows]
        if first is not None and self.start == "data":
            first = torch.where((idx >= self.system.n) & (guess != 0), guess.abs(), first)
        return typical_magnitudes(guess, first)

    def _without_negligible(self, rows, z0, *jacobians):
        """The weighted Jacobians ``(S, R, m)`` of samples ``rows`` at the estimates ``z0`` with
        their columns below rounding (:func:`torchql.diagnosis.negligible_columns`, judged on the
        first) set to zero: the rank test, the status and the covariance treat those unknowns as
        ones the data do not determine. The reported Jacobian keeps its values."""
        zero = negligible_columns(jacobians[0], z0[rows][:, self.spec.unknown_index], self._typical(rows))
        return tuple(torch.where(zero.unsqueeze(1), torch.zeros_like(J), J) for J in jacobians)


def _fisher_rows(C_mean: torch.Tensor, w: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """The rows ``(S, 2R, m)`` whose ``J^T J`` is the expected (Fisher) information of a fit with a
    ``sigma(p)`` function: the mean's sensitivities over sigma, ``C_mean (S, R, m)`` times the data
    rows' weights (the first ``R`` of ``w``), then ``sqrt(2)`` times the log rows ``g = d log sigma /
    d unknowns (S, R, m)`` (a Gaussian value's information about ``log sigma`` is 2)."""
    R = C_mean.shape[1]
    return torch.cat([C_mean * w[:, :R].unsqueeze(-1), math.sqrt(2.0) * g], dim=1)


def _covariance(J, used, sse, L, spec, deficient, exact) -> torch.Tensor:
    """Per-sample covariance ``(S, m, m)`` as :func:`torchql.uncertainty.covariance`: batched, and
    per sample (``deficient``) where a direction is undetermined or values are met ``exact (S, R)``;
    ``L (S,)`` the values used less the redundant exact ones."""
    S, _, m = J.shape
    s2 = residual_variance(sse, L - m, spec.sigma_known)
    scale = torch.linalg.vector_norm(J, dim=1)
    safe_scale = torch.where(scale > 0, scale, torch.ones_like(scale))
    _, Sv, Vh = torch.linalg.svd(J / safe_scale.unsqueeze(1), full_matrices=False)
    inner = (Vh.transpose(1, 2) / Sv.unsqueeze(1) ** 2) @ Vh
    inner = inner / safe_scale.unsqueeze(-1) / safe_scale.unsqueeze(-2)
    cov = s2.reshape(-1, 1, 1) * inner
    cov = 0.5 * (cov + cov.transpose(1, 2))
    for k in deficient.nonzero().flatten().tolist():  # rare: undetermined unknowns get NaN, as fit reports
        rows = used[k]
        cov[k] = covariance(J[k][rows], exact[k][rows], float(sse[k]), spec.sigma_known, spec.rcond).matrix
    return cov


def _evaluated(status: torch.Tensor, skipped: set[int] = frozenset()) -> torch.Tensor:
    """The samples (indices) whose status ``(S,)`` (codes of ``Status``) gets a final evaluation, less
    those in ``skipped`` (samples stopped as stiff: ``solver="auto"`` fits them again)."""
    rows = (~torch.isin(status, torch.tensor(_NOT_EVALUATED, device=status.device))).nonzero().flatten()
    if skipped:
        rows = rows[~torch.isin(rows, torch.tensor(sorted(skipped), device=status.device))]
    return rows
