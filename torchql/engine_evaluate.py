"""The engine's evaluations: linearizations, linear propagations, rows, nonlinear solutions.

:class:`Evaluation` is the part of :class:`torchql.engine.Engine` that turns iterates into
numbers for the chunk's samples ``idx``: the model linearized about a trajectory, the particular
and homogeneous solutions propagated about it, the least-squares rows at the observations, and
the model's own solution (by the grid solver, batched Dormand–Prince, Rodas5P or torchdiffeq).
"""

from __future__ import annotations

import math

import torch

from .batch_integrate import integrate_each, propagate_linear_batch
from .dopri import dopri_batch, found_stiff, thin_landings
from .dopri_sensitivity import explicit_sensitivities
from .engine_grid_solve import GridSolve
from .engine_state import _pick, bound_of, members, not_above
from .grid import DEFAULT_INTERVALS
from .integrate import IntegrationError
from .linearize import Linearization, linearize, map_fields
from .rk_pairs import PAIRS
from .sigma_function import noise_rows
from .solvers import STIFF_SOLVERS
from .solvers.sensitivity import rodas5p_model, rodas5p_sensitivities
from .superposition import propagate_linear
from .trajectory import LinearizedReference

__all__ = ["Evaluation", "BATCHED_EXPLICIT", "BATCHED_SOLVERS"]

#: The ``solver`` names that :meth:`Evaluation._adaptive` integrates by the batched explicit
#: integrator (:func:`~torchql.dopri.dopri_batch`, with that pair).
BATCHED_EXPLICIT = tuple(PAIRS)
#: The solvers that integrate every sample of a batch at once (any other: torchdiffeq, each in turn).
BATCHED_SOLVERS = (*BATCHED_EXPLICIT, *STIFF_SOLVERS)

#: Largest ``samples x intervals`` for which the final nonlinear solution is found by multiple
#: shooting from the last linear prediction (all intervals at once, Newton on the node defects,
#: with Jacobians); above it the batched Dormand–Prince integrator, whose rounds advance every
#: sample at once, costs less.
_SHOOTING_POINTS = 20_000
#: Most RK4 steps per grid interval in that solver: an interval that needs more (a trajectory
#: that blows up, a stiff stretch) is left to the adaptive solver rather than subdivided further.
_GRID_SUBSTEPS, _GRID_SUBSTEPS_LOOSE = 32, 16
#: Fewest intervals the grid solver integrates over: on a coarser storage grid (``grid="smooth"``,
#: a small ``grid=``) each interval is split into equal sub-intervals, further shooting nodes solved
#: in parallel from the guess's cubic Hermite interpolant, instead of many sequential RK4 steps each.
_GRID_SOLVE_INTERVALS = DEFAULT_INTERVALS
#: RK4 steps over the whole span beyond which a trial step's trajectory counts as a blow-up
#: (spread over the grid's intervals; on the default grid the per-interval caps above bind).
_BLOWUP_STEPS = 16384
#: Tolerance of the first Kantorovich reference, integrated from the guesses.
_LOOSE_RTOL = 1e-6
#: On the stiff path a trial's linear transfers are integrated at ``INEXACT_FACTOR`` times the square
#: of its step's scaled size (between ``rtol`` and :data:`_LOOSE_RTOL`): near a solution the next
#: step is of the order of that square, and the transfers' error moves it by about their tolerance,
#: so early, long steps need no more (inexact Newton). A stiff interval's Radau IIA substeps grow as
#: the tolerance's cube root: on Robertson kinetics the first transfers took most of a fit's time.
INEXACT_FACTOR = 1e-2
#: The exact rows' weight in the merit, ``mu``, is at least ``EXACT_MARGIN`` times the largest magnitude
#: of their Lagrange multipliers seen (:meth:`Evaluation._ssq`): above the multipliers, the exact
#: penalty's minimum is the constrained one.
EXACT_MARGIN = 2.0


#: Whether a second opinion (:meth:`Evaluation._model_not_above`) or a shooting trial stops integrating a
#: model solution once it cannot win the comparison; ``False`` integrates every one whole (the same decisions).
STOP_EARLY = True


class Evaluation(GridSolve):
    """Evaluations of a chunk's iterates (mixed into :class:`torchql.engine.Engine`, whose
    attributes ``spec``, ``system``, ``grid``, ``obs``, ``t_obs``, ``G``, ``y``, ``w``, ``mask``,
    ``exact``, ``nfev``, ``propagation_errors``, ``coarse_grid`` and ``fits_grid`` it uses)."""

    def _grid_of(self, idx: torch.Tensor) -> torch.Tensor:
        """The grid of the chunk's samples ``idx``: the shared one ``(G,)``, or theirs ``(S, G)``."""
        return self.grid if self.grid.dim() == 1 else _pick(self.grid, idx)

    def _at_obs(self, x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        """Values ``x (S, G, ...)`` of the chunk's samples ``idx`` at their observation nodes: ``(S, T, ...)``."""
        if self.obs.dim() == 1:
            return x[:, self.obs]
        rows = torch.arange(x.shape[0], device=x.device).unsqueeze(1)
        return x[rows, _pick(self.obs, idx)]

    def _linearize(self, idx: torch.Tensor, z: torch.Tensor, z_dot: torch.Tensor | None = None) -> Linearization:
        """The linearization about ``z (S, G, M)`` (slopes ``z_dot``) of the chunk's samples ``idx``, at their nodes."""
        S, G, M = z.shape
        t = self.grid.repeat(S) if self.grid.dim() == 1 else _pick(self.grid, idx).reshape(-1)
        lin = linearize(self.system, t, z.reshape(-1, M), None if z_dot is None else z_dot.reshape(-1, M),
                        second=self.spec.linear_solver.jacobian_degree > 3)
        self.nfev += S * G
        return map_fields(lin, lambda v: v.reshape(S, G, *v.shape[1:]))

    def _rows(self, idx, z_ref_obs, zp_obs, Z_obs):
        """``C (S, R, m)``, ``d (S, R)``, residuals ``(S, R)`` at the observations (zero where missing)."""
        n, K = self.spec.operator.width, self.spec.K  # the states, or for h(x, p) the augmented state
        S, T = z_ref_obs.shape[:2]
        x_ref = z_ref_obs[..., :n]
        h_ref, H = self.spec.operator.value_and_jacobian(x_ref.reshape(-1, n))
        h_ref, H = h_ref.reshape(S, T, K), H.reshape(S, T, K, n)
        predicted = h_ref + torch.einsum("stkn,stn->stk", H, zp_obs[..., :n] - x_ref)
        C = torch.einsum("stkn,stnm->stkm", H, Z_obs[:, :, :n, :])
        mask, y = _pick(self.mask, idx), _pick(self.y, idx)
        zero = torch.zeros((), dtype=y.dtype, device=y.device)
        d = torch.where(mask, y - predicted, zero)
        resid = torch.where(mask, y - h_ref, zero)
        C = torch.where(mask.unsqueeze(-1), C, zero)
        # an unknown that the values read only through a cancellation below the integration's
        # accuracy is not read: at every value |C| <= rcond (|H| |Z|), its row's terms cancelling
        # to their error. Scaled to a unit column that error reads as a direction of its own (the
        # sum y = x1 + x2 of two compartments with equal rates does not depend on their exchange
        # rate, whose column was 1.6e-10 of the others' and whose step 6e8 times its scale)
        size = torch.einsum("stkn,stnm->stkm", H.abs(), Z_obs[:, :, :n, :].abs())
        unread = (C.abs() <= self.spec.rcond * size).flatten(1, 2).all(dim=1)  # (S, m)
        C = C.masked_fill(unread.unsqueeze(1).unsqueeze(1), 0.0)
        return C.reshape(S, T * K, -1), d.reshape(S, -1), resid.reshape(S, -1)

    def _weighted(self, idx, z0, C, d):
        """The weighted linear problem of the chunk's samples ``idx`` at the iterates ``z0 (S, M)``
        from its rows ``C (S, R, m)`` and residuals ``d (S, R)``: ``(C, d, w, log_term)``.

        With fixed sigmas ``C`` and ``d`` as they are, ``w (S, R)`` the data's weights and
        ``log_term`` zero; with a ``sigma(p)`` function, the rows of
        :func:`torchql.sigma_function.noise_rows` (``2 R`` of them) at the iterates' sigmas, and
        ``log_term (S,)`` the objective's ``2 sum log sigma``.
        """
        w = _pick(self.w, idx).reshape(d.shape)
        sigma_function = self.spec.sigma_function
        if sigma_function is None:
            return C, d, w, torch.zeros(d.shape[0], dtype=d.dtype, device=d.device)
        sigma, dlog = sigma_function.evaluate(z0)
        return noise_rows(C, d, w, w > 0, sigma, dlog[..., self.spec.unknown_index])

    def _ssq(self, idx, residual, w, penalty: bool = False):
        """Weighted sums of squares ``(S,)`` of ``residual (S, R)`` with weights ``w (S, R')`` (the
        first ``R`` apply), the exact rows left out; with ``penalty``, the merit: plus the exact
        rows' weighted misfits ``|w r|`` summed, times the chunk's samples' weights ``mu``
        (``exact_weight``).

        The step meets the exact rows as constraints (:func:`torchql.lstsq.solve_update`), and
        this is Han's exact penalty for such steps: with ``mu`` above the multipliers' magnitudes
        (:data:`EXACT_MARGIN`) the constrained optimum is the merit's minimum and every undamped
        step descends it. (A penalty on the squared misfit has its minimum off the exact values, by
        the multiplier over twice its weight, where no step that meets them could be accepted.)
        """
        wr = residual * w[:, :residual.shape[1]]
        if not self.spec.has_exact:
            return (wr ** 2).sum(dim=1)
        exact = _pick(self.exact, idx)
        zero = torch.zeros((), dtype=wr.dtype, device=wr.device)
        total = torch.where(exact, zero, wr ** 2).sum(dim=1)
        return total + self.exact_weight[idx] * torch.where(exact, wr.abs(), zero).sum(dim=1) if penalty else total

    def _evaluate(self, idx, z0, z, z_dot, lin, solution: bool = False, W: torch.Tensor | None = None,
                  propagate: torch.Tensor | None = None) -> dict:
        """Propagate each sample's linear system from ``z0 (S, M)`` about ``z``; rows at the observations.

        ``solution``: ``z`` is the model's own solution from ``z0`` (shooting), which then stands
        for the particular solution (its propagation would only add the propagator's error).
        ``W (S, G, M, 1 + m)``: the solutions already found (:meth:`_solve_with_sensitivities`),
        not propagated again. ``propagate (S,)`` bool: the samples propagated (default all); the
        others' solutions are NaN, and they are marked ``failed``.
        """
        spec = self.spec
        rtol = spec.rtol if self.trial_rtol is None or W is not None else self.trial_rtol
        if W is None and propagate is not None and not bool(propagate.all()):
            W = z.new_full((*z.shape, 1 + len(spec.unknown_index)), float("nan"))
            failed = ~propagate
            if bool(propagate.any()):
                k = propagate
                W[k], failed[k] = self._propagate(idx[k], z[k], z_dot[k], map_fields(lin, lambda v: v[k]),
                                                  spec.columns(z0[k]), rtol)
        elif W is None:
            W, failed = self._propagate(idx, z, z_dot, lin, spec.columns(z0), rtol)
        else:
            failed = torch.zeros(z.shape[0], dtype=torch.bool, device=z.device)
        if solution:
            W[..., 0] = z
        W_obs = self._at_obs(W, idx)
        C, d, resid = self._rows(idx, self._at_obs(z, idx), W_obs[..., 0], W_obs[..., 1:])
        C_w, d_w, w, log_term = self._weighted(idx, z0, C, d)
        sse, merit = self._ssq(idx, resid, w) + log_term, self._ssq(idx, d, w, penalty=True) + log_term
        S = idx.numel()
        return dict(z0=z0, rz=z, rzd=z_dot, lin=lin, W=W, C=C_w, d=d_w, w=w, log=log_term, sse=sse, merit=merit,
                    failed=failed, rtol=torch.full_like(sse, rtol),
                    anchored=torch.zeros(S, dtype=torch.bool, device=z0.device),
                    nl_sse=torch.full_like(sse, float("nan")), nl_traj=torch.full_like(z, float("nan")))

    def _propagate(self, idx, z, z_dot, lin, w0, rtol: float | None = None, coefficients=None):
        """The particular and homogeneous solutions ``W (S, G, M, 1 + m)`` of the chunk's samples
        ``idx`` about ``z`` from ``w0 (S, M, 1 + m)``, and ``failed (S,)``, at ``rtol`` (default the
        fit's; ``atol`` scaled alike); ``coefficients``: the intervals', if already built.

        A propagator with a batched form takes every sample at once
        (:func:`~torchql.batch_integrate.propagate_linear_batch`); another one each sample in turn
        (:func:`torchql.superposition.propagate_linear`), a failure marking that sample.
        """
        spec = self.spec
        rtol = spec.rtol if rtol is None else rtol
        atol = spec.atol * rtol / spec.rtol
        if spec.linear_solver.batched:
            W, failed, evals = propagate_linear_batch(self._grid_of(idx), z, z_dot, lin, w0, rtol=rtol, atol=atol,
                                                      propagator=spec.linear_solver, coefficients=coefficients)
            self.nfev += evals
            return W, failed
        S, G = z.shape[:2]
        W = z.new_full((S, G, *w0.shape[1:]), float("nan"))
        failed = torch.zeros(S, dtype=torch.bool, device=z.device)
        grid = self._grid_of(idx)
        for k in range(S):
            t = grid if grid.dim() == 1 else grid[k]
            reference = LinearizedReference(t, z[k], z_dot[k], map_fields(lin, lambda v: v[k]))
            try:
                W[k], evals = propagate_linear(reference, w0[k], solver=spec.solver, rtol=rtol, atol=atol,
                                               max_steps=spec.max_steps, linear_solver=spec.linear_solver)
                self.nfev += evals
            except IntegrationError as exc:
                failed[k] = True
                self.propagation_errors[int(idx[k])] = str(exc)
        return W, failed

    def _nonlinear(self, idx, z0, loose: bool, guess=None, budget_is_final: bool = False, reference=None,
                   stop=None, max_steps: int | None = None, note_stiff: bool = True):
        """The model integrated from ``z0 (S, M)`` over the grid of the chunk's samples ``idx``: ``traj (S, G, M)``
        and error messages (None: ok).

        ``loose`` integrates at ``_LOOSE_RTOL`` (or ``rtol`` if looser): enough for a first
        reference, or to rank two iterates far from the optimum. With a ``guess (S, G, M)`` (a
        prediction of the solution at the nodes: the last linear solution) and a problem of at
        most ``_SHOOTING_POINTS`` sample-intervals, by multiple shooting
        (:func:`~torchql.grid_solve.solve_on_grid_batch`: every interval at once by RK4, at
        most ``_GRID_SUBSTEPS`` steps each, ``_GRID_SUBSTEPS_LOOSE`` when ``loose``, and no more
        than the user's ``max_steps``). A sample whose interval needs more is, with
        ``budget_is_final``, a blow-up and fails (a trial step: an adaptive solver would only crawl
        to the same failure, or through a stiff stretch that a step far from the current iterate
        led into; the damping shortens the step instead), an interval then being allowed
        ``_BLOWUP_STEPS / (G - 1)`` steps if that is more, so that a coarse grid does not turn a
        smooth trial into a blow-up. Given the current iterate, ``reference = (z0 (S, M), traj (S,
        G, M))``, solved on the grid with the same budget: where it needs more steps too, the grid
        is too coarse for the sample's model (a rough measured input, a fast mode), not the trial
        divergent, and the sample's trials are integrated by the adaptive solvers from then on;
        where it does not, the trial is tried by the adaptive solver, within a budget of steps
        (:meth:`~torchql.engine_grid_solve.GridSolve._over_budget`). The other samples, or all
        without a guess, are integrated by :func:`~torchql.dopri.dopri_batch` (``"dop853"``, ``"dopri5"``), the implicit
        :func:`~torchql.solvers.rodas5p_batch` (a stiff ``solver``), or each alone by torchdiffeq.
        ``stop``: the adaptive solvers' test of a sample (positions ``(L,)`` in ``idx``, its augmented
        states ``(L, G, M)`` so far, the next node) that ends it early, as a failure.
        ``max_steps``: the batched Dormand–Prince solver's limit on a sample's steps (default its own).
        ``note_stiff``: an explicit pair's stiffness marks the sample (:meth:`_adaptive`).
        """
        spec = self.spec
        rtol = max(spec.rtol, _LOOSE_RTOL) if loose else spec.rtol
        atol = spec.atol * rtol / spec.rtol
        S, G = z0.shape[0], self.G
        traj = torch.full((S, G, self.system.M), float("nan"), dtype=z0.dtype, device=z0.device)
        ok = torch.zeros(S, dtype=torch.bool, device=z0.device)
        errors: list = [None] * S
        substeps = _GRID_SUBSTEPS_LOOSE if loose else _GRID_SUBSTEPS
        fine = (G - 1) * self._split
        if budget_is_final and G > 1:
            substeps = max(substeps, 1 << max(0, (_BLOWUP_STEPS // fine).bit_length() - 1))
        if spec.max_steps is not None:  # the user's step budget per grid interval binds this solver too
            substeps = min(substeps, 1 << (spec.max_steps.bit_length() - 1))
        with torch.no_grad():
            if guess is not None and self._grid_solves(S) and substeps >= 2:
                coarse = self._in_coarse_grid(idx)
                if bool(coarse.any()):
                    guess = torch.where(coarse.reshape(-1, 1, 1), torch.full_like(guess, float("nan")), guess)
                self._on_grid(idx, z0, guess, rtol, atol, substeps, budget_is_final, traj, ok, errors, reference, stop)
            self._adaptive(idx, z0, rtol, atol, traj, ok, errors, stop, max_steps, note_stiff)
        return traj, errors

    def _grid_solves(self, count: int) -> bool:
        """Whether :meth:`_nonlinear` takes ``count`` samples (with a guess) to the grid solver: at most
        ``_SHOOTING_POINTS`` sample-intervals, a propagator that allows it, a non-stiff ``solver``."""
        spec = self.spec
        return (count * (self.G - 1) * self._split <= _SHOOTING_POINTS and spec.linear_solver.grid_solver
                and spec.solver not in STIFF_SOLVERS)

    def _batched_dopri(self) -> bool:
        """Whether :meth:`_adaptive` integrates by the batched Dormand–Prince (``solver="dop853"`` or ``"dopri5"``;
        a ``max_steps`` is its step budget per grid interval), one sample as several: ``fit``'s
        solutions are those of each ``fit_many`` sample."""
        return self.spec.solver in BATCHED_EXPLICIT

    @property
    def _split(self) -> int:
        """Sub-intervals per grid interval in the grid solver (see :data:`_GRID_SOLVE_INTERVALS`)."""
        return max(1, math.ceil(_GRID_SOLVE_INTERVALS / max(1, self.G - 1)))

    def _adaptive(self, idx, z0, rtol, atol, traj, ok, errors, stop=None, max_steps: int | None = None,
                  note_stiff: bool = True) -> None:
        """:meth:`_nonlinear`'s adaptive solvers for the samples not solved and not failed yet:
        Rodas5P (a stiff ``solver``), the batched Dormand–Prince (``"dop853"``, ``"dopri5"``, at most
        ``max_steps`` steps a sample if given), or torchdiffeq per sample; fills ``traj``, ``ok`` and
        ``errors`` in place; with ``note_stiff``, marks the samples the explicit pair found stiff
        (:meth:`_note_stiff`)."""
        spec = self.spec
        grid = self._grid_of(idx)
        shared = grid.dim() == 1

        def grid_of(sub):
            return grid if shared else grid[sub]

        def pending():
            return (~ok & torch.tensor([e is None for e in errors], dtype=torch.bool, device=ok.device)).nonzero().flatten()
        sub = pending()
        stiff, batched = spec.solver in STIFF_SOLVERS, self._batched_dopri()

        def asked(sub):  # ``stop`` on the positions ``sub`` in ``idx`` that a solver integrates
            return None if stop is None else (lambda rows, y, reached: stop(sub[rows], y, reached))
        if sub.numel() and stiff:  # every sample by the implicit solver; its message kept for a failure
            self._rodas(sub, z0, grid_of(sub), rtol, atol, self._landing(idx[sub]), traj, ok, errors, asked(sub))
            return
        if sub.numel() and batched:
            self._take_shared_solutions(idx, sub, z0, rtol, traj, ok)
            sub = pending()
        if sub.numel() and batched:
            messages: list = []
            tr, good, evals = dopri_batch(self.system, z0[sub], grid_of(sub), rtol=rtol, atol=atol,
                                          land=self._landing(idx[sub], explicit=True), messages=messages,
                                          interval_steps=spec.max_steps, stop=asked(sub), method=spec.solver,
                                          **({} if max_steps is None else {"max_steps": max_steps}))
            self.nfev += evals
            traj[sub[good]], ok[sub[good]] = tr[good], True
            for k, s in enumerate(sub.tolist()):
                errors[s] = messages[k]
            if note_stiff:
                self._note_stiff(idx[sub], messages)
            sub = pending()
        if sub.numel():
            hit = self.t_obs if shared else self.t_obs[idx[sub]]
            tr, errs, evals = integrate_each(self.system, z0[sub], grid_of(sub), solver=spec.solver, rtol=rtol,
                                             atol=atol, hit=hit, max_steps=spec.max_steps)
            self.nfev += evals
            for k, s in enumerate(sub.tolist()):
                if errs[k] is None and bool(torch.isfinite(tr[k]).all()):
                    traj[s], ok[s] = tr[k], True
                else:
                    errors[s] = errs[k] or "the solution became non-finite (NaN or inf)"

    def _note_stiff(self, idx, messages: list) -> None:
        """Mark (``stiff_met``) the chunk's samples ``idx`` whose explicit pair's failure ``messages``
        (one each, None where it did not fail) is its stiffness test's: ``solver="auto"`` fits them
        again as stiff models."""
        self.stiff_met.update(int(i) for i, e in zip(idx.tolist(), messages) if found_stiff(e))

    def _take_shared_solutions(self, idx, sub, z0, rtol, traj, ok) -> None:
        """Fill ``traj`` and ``ok`` of the samples ``sub`` (chunk indices ``idx[sub]``, states ``z0``) whose solution at
        these estimates and ``rtol`` was integrated with other groups' (:meth:`FinalPass._share_final_solutions`)."""
        if not self.shared_solutions or rtol != self.spec.rtol:
            return
        for s in sub.tolist():
            kept = self.shared_solutions.get(int(idx[s]))
            if kept is not None and torch.equal(kept[0], z0[s]):
                traj[s], ok[s] = kept[1], True

    def _rodas(self, sub, z0, grid, rtol, atol, land, traj, ok, errors, stop=None) -> None:
        """Samples ``sub`` by :func:`~torchql.solvers.sensitivity.rodas5p_model` on ``grid`` (``stop``:
        as :func:`~torchql.dopri.dopri_batch`'s, over the samples ``sub``)."""
        sol, y = rodas5p_model(self.system, z0[sub], grid, rtol=rtol, atol=atol, land=land,
                               interval_steps=self.spec.max_steps, stop=stop)
        self.nfev += sol.n_f
        good = sol.ok
        traj[sub[good]], ok[sub[good]] = y[good], True
        for k, s in enumerate(sub.tolist()):
            if not bool(good[k]):
                errors[s] = sol.message(k)

    @property
    def _joint_sensitivities(self) -> bool:
        """Whether the model's solutions and their sensitivities are integrated together
        (:meth:`_solve_with_sensitivities`): the linear propagator says so (``"rodas5p"``)."""
        return self.spec.linear_solver.with_solution

    def _solve_with_sensitivities(self, idx, z0, trial: bool = False) -> tuple[torch.Tensor, torch.Tensor, list]:
        """The model integrated from ``z0 (S, M)`` together with its sensitivities to the unknowns,
        the solver's steps differentiated, on the grid of the chunk's samples ``idx``: by Rodas5P
        (:mod:`torchql.solvers.sensitivity`, landing as :meth:`_landing` says) for a stiff model,
        the ``"rodas5p"`` propagator and the samples in ``fast_decay`` (a decay held most of the
        explicit pair's steps in an earlier such solve, with ``solver="auto"``), else by the
        batched explicit pair of ``solver``
        (:mod:`torchql.dopri_sensitivity`, landing on every node). Returns ``traj (S, G, M)``,
        ``W (S, G, M, 1 + m)`` (``W[..., 0]`` the solution, then the homogeneous columns from
        :meth:`~torchql.problem.Problem.columns`) and error messages (None: ok). A sample that
        failed keeps its initial state and columns at every node: a finite stand-in, as a failed
        trial needs one. ``trial``: solutions from trial estimates, whose decay marks their samples
        only once the trial is taken (``trial_decay``).
        """
        first = self.spec.columns(z0)
        if self._joint_sensitivities or not self._batched_dopri():  # (a stiff solver is not batched dopri)
            implicit = torch.ones(idx.numel(), dtype=torch.bool, device=idx.device)
        else:
            implicit = members(self.fast_decay, idx)
        if bool(implicit.all()) or not bool(implicit.any()):
            z, V, errors = self._sensitivities_by(idx, z0, first, bool(implicit[0]), trial)
        else:  # samples whose decay held DOP853's steps, and the others
            G = self._grid_of(idx).shape[-1]
            z = z0.new_empty(idx.numel(), G, z0.shape[1])
            V = z0.new_empty(idx.numel(), G, first.shape[1], first.shape[2] - 1)
            errors = [None] * idx.numel()
            for rodas in (True, False):
                rows = (implicit == rodas).nonzero().flatten()
                z[rows], V[rows], part_errors = self._sensitivities_by(idx[rows], z0[rows], first[rows], rodas,
                                                                       trial)
                for k, e in zip(rows.tolist(), part_errors):
                    errors[k] = e
        W = torch.cat([z.unsqueeze(-1), V], dim=-1)
        failed = torch.tensor([e is not None for e in errors], dtype=torch.bool, device=z0.device)
        z = torch.where(failed.reshape(-1, 1, 1), z0.unsqueeze(1).expand_as(z), z)
        W = torch.where(failed.reshape(-1, 1, 1, 1), first.unsqueeze(1).expand_as(W), W)
        return z, W, errors

    def _sensitivities_by(self, idx, z0, first, rodas: bool, trial: bool = False
                          ) -> tuple[torch.Tensor, torch.Tensor, list]:
        """:meth:`_solve_with_sensitivities` of the samples ``idx`` from ``z0``, columns ``first``,
        by Rodas5P (``rodas``) or by the batched explicit pair: ``z``, ``V`` and error messages."""
        spec = self.spec
        with torch.no_grad():
            if rodas:
                sol, z, V = rodas5p_sensitivities(self.system, z0, first[..., 1:], self._grid_of(idx), rtol=spec.rtol,
                                                  atol=spec.atol, land=self._landing(idx),
                                                  interval_steps=spec.max_steps)
                self.nfev += sol.n_f
                return z, V, [None if bool(sol.ok[k]) else sol.message(k) for k in range(z0.shape[0])]
            held = [] if spec.stiff_refit else None  # "auto": where a decay held most steps, Rodas5P's from now on
            z, V, errors, evals = explicit_sensitivities(self.system, z0, first[..., 1:], self._grid_of(idx),
                                                         rtol=spec.rtol, atol=spec.atol, method=spec.solver,
                                                         interval_steps=spec.max_steps, held=held)
        self.nfev += evals
        if not trial:  # (a trial's stiff stretch fails it: rejected, it says nothing of the fit's)
            self._note_stiff(idx, errors)
        if held is not None:
            found = (int(i) for i, part, e in zip(idx.tolist(), held, errors) if part > 0.5 and e is None)
            (self.trial_decay if trial else self.fast_decay).update(found)
        return z, V, errors

    def _model_from_data(self, idx, z0, reference):
        """Shooting's first iterate from the data: the model integrated from the coefficients that
        the data start matched, ``z0 (S, M)``, and the data's own initial states (the reference
        ``(S, G, M)`` at ``t0``, moved inside their bounds; expressions of the coefficients where
        given), the reference the grid solver's guess; the solution with its sensitivities where
        the propagator integrates them together. Returns ``(z0, traj, W or None, errors)``."""
        spec, n = self.spec, self.system.n
        states = spec.unknown_index[spec.unknown_index < n]
        if states.numel():
            z0 = z0.clone()
            start = reference[:, 0, states]
            z0[:, states] = torch.where(torch.isfinite(start), start, z0[:, states])
            if spec.bounds.active:
                z0[:, spec.unknown_index] = spec.bounds.move_inside(z0[:, spec.unknown_index])[0]
            if spec.initial:
                z0 = spec.initial.complete(z0)
        if self._joint_sensitivities:
            traj, W, errors = self._solve_with_sensitivities(idx, z0)
            return z0, traj, W, errors
        traj, errors = self._nonlinear(idx, z0, loose=False, guess=reference)
        return z0, traj, None, errors

    def _landing(self, rows: torch.Tensor, explicit: bool = False) -> torch.Tensor:
        """The nodes that an adaptive solver's steps land on for the samples of chunk indices
        ``rows``: their observation times (for the ``explicit`` pairs at most about
        :data:`~torchql.dopri.LANDED_OBSERVATIONS` of them, :func:`~torchql.dopri.thin_landings`)
        and the nodes at an input's breakpoints (where its steps restart, as torchdiffeq's
        ``jump_t``), ``(G,)`` on a shared grid or ``(S, G)`` (the other nodes come from the dense
        output)."""
        shared = self.grid.dim() == 1
        grid = self.grid if shared else self.grid[rows]
        land = torch.zeros(grid.shape, dtype=torch.bool, device=grid.device)
        land.scatter_(-1, self.obs if shared else self.obs[rows], True)
        if explicit:
            land = thin_landings(land)
        breakpoints = self.spec.breakpoints
        if breakpoints is not None:
            inner = breakpoints.to(grid).expand(*grid.shape[:-1], -1).contiguous()
            at = torch.searchsorted(grid, inner).clamp(max=grid.shape[-1] - 1)
            on = (grid.gather(-1, at) == inner).to(torch.uint8)  # a user's grid may not hold them all
            land |= torch.zeros_like(land, dtype=torch.uint8).scatter_reduce_(-1, at, on, "amax").bool()
        return land

    def _model_not_above(self, all_idx, cur: dict, act, trial: dict, rows: torch.Tensor) -> torch.Tensor:
        """Whether the model's objective from the trials ``rows`` (positions in ``act``) is not above
        that from their current iterates (``cur``'s samples ``act[rows]``), bool ``(R,)``.

        The current iterate's is integrated first (cached: usually known from when it was a
        trial), then the trial's only until it exceeds it (:meth:`_nonlinear_sse`). Where the
        implicit solver integrates and neither is known yet (a start built from the data), both
        are integrated together (:meth:`_race`): which of the two is dear (a jump inside the
        window) is not known beforehand.
        """
        better = torch.zeros(rows.numel(), dtype=torch.bool, device=rows.device)
        rest = torch.ones_like(better)
        if self.spec.stiff:
            both = (torch.isnan(cur["nl_sse"][act[rows]]) & torch.isnan(trial["nl_sse"][rows])).nonzero().flatten()
            if both.numel():
                better[both] = self._race(all_idx, cur, act, trial, rows[both])
                rest[both[better[both]]] = False
        rows = rows[rest]
        c_sse = self._nonlinear_sse(all_idx, cur, act[rows], current=True)
        # (a trial's stiff stretch, where its sum of squares is inf, says nothing of the fit's: not marked)
        t_sse = self._nonlinear_sse(act, trial, rows, above=bound_of(c_sse) if STOP_EARLY else None, note_stiff=False)
        better[rest] = not_above(t_sse, c_sse)
        return better

    def _race(self, all_idx, cur: dict, act, trial: dict, rows: torch.Tensor) -> torch.Tensor:
        """The model from the current iterates ``act[rows]`` and from their trials ``rows`` integrated
        together, each stopped once its objective over the data passed exceeds the other's whole
        one (known once that one passed the last observation). What finished is cached
        (:meth:`_keep_model_sse`; a stopped trial: inf, rejected). Returns bool ``(R,)``: the
        current iterates stopped, whose trials are then better; their own objectives stay unknown."""
        R = rows.numel()
        chunk = all_idx[act[rows]].repeat(2)
        z0 = torch.cat([cur["z0"][act[rows]], trial["z0"][rows]])
        w, log = torch.cat([cur["w"][act[rows]], trial["w"][rows]]), torch.cat([cur["log"][act[rows]], trial["log"][rows]])
        last = (self.obs if self.obs.dim() == 1 else self.obs[chunk]).amax(dim=-1).expand(2 * R)
        whole = torch.full((2 * R,), math.nan, dtype=z0.dtype, device=z0.device)
        stopped = torch.zeros(2 * R, dtype=torch.bool, device=z0.device)

        def stop(k, traj, reached):  # k: positions in the race, the current iterates first
            value = self._objective(chunk[k], traj, w[k], log[k], reached)
            complete = reached > last[k]
            whole[k[complete]] = value[complete]
            other = whole[(k + R) % (2 * R)]
            ended = ~complete & torch.where(k < R, value > other, value > bound_of(other)) & STOP_EARLY
            stopped[k[ended]] = True
            return ended
        guess = torch.cat([cur["W"][act[rows]][..., 0], trial["W"][rows][..., 0]])
        traj, errors = self._nonlinear(chunk, z0, loose=True, guess=guess, budget_is_final=True, stop=stop)
        kept = (~stopped[:R]).nonzero().flatten()
        if kept.numel():
            self._keep_model_sse(all_idx, cur, act[rows][kept], traj[kept], [errors[k] for k in kept.tolist()])
        self._keep_model_sse(act, trial, rows, traj[R:], errors[R:])
        return stopped[:R]

    def _nonlinear_sse(self, idx, it: dict, rows: torch.Tensor, above: torch.Tensor | None = None,
                       current: bool = False, note_stiff: bool = True) -> torch.Tensor:
        """Cached nonlinear sums of squares of ``it``'s samples ``rows`` (inf when not integrable;
        with a ``sigma(p)`` function, the objective at the iterate's sigmas).

        As ``torchql.fit``'s second opinion: integrated at the loose tolerance, on the grid from
        the iterate's particular solution (its prediction of the trajectory) where that settles.
        ``above (R,)``: the objectives that matter only up to these (a trial must not exceed the
        current iterate's). The implicit solver stops a sample once its objective over the data
        passed so far exceeds its bound (the remaining terms only add to it; a ``sigma(p)``
        function's log term is the sample's own constant), whose objective is then inf.
        ``current``: the samples' accepted iterates, whose need of more grid-solver steps than a trial
        may take means a grid too coarse for their model (:meth:`_nonlinear`'s ``reference``).
        ``note_stiff``: as :meth:`_nonlinear`'s."""
        need = rows[torch.isnan(it["nl_sse"][rows])]
        if need.numel():
            stop = None if above is None else self._exceeds(idx[need], it["w"][need], it["log"][need],
                                                            above[torch.isnan(it["nl_sse"][rows])])
            guess = it["W"][need][..., 0]
            traj, errors = self._nonlinear(idx[need], it["z0"][need], loose=True, guess=guess, budget_is_final=True,
                                           stop=stop, reference=(it["z0"][need], guess) if current else None,
                                           note_stiff=note_stiff)
            self._keep_model_sse(idx, it, need, traj, errors)
        return it["nl_sse"][rows]

    def _exceeds(self, chunk, w, log, bound):
        """The stop test (:func:`~torchql.dopri.dopri_batch`'s) that ends the solution of the chunk's
        samples ``chunk (R,)`` (weights ``w``, log terms ``log (R,)``) once its objective over the
        data passed exceeds ``bound (R,)``: the terms still to come only add to it."""
        def stop(k, traj, reached):  # k: positions in ``chunk``
            return self._objective(chunk[k], traj, w[k], log[k], reached) > bound[k]
        return stop

    def _objective(self, chunk, traj, w, log, reached: torch.Tensor | None = None) -> torch.Tensor:
        """The objective ``(R,)`` of the chunk's samples ``chunk (R,)`` along the model's solutions
        ``traj (R, G, M)``, with weights ``w`` and log terms ``log (R,)``; with ``reached (R,)``,
        over the observations at the nodes before it only (the others' values need not exist)."""
        n = self.spec.operator.width
        x = self._at_obs(traj, chunk)[..., :n]
        y, mask = self.y[chunk], self.mask[chunk]
        if reached is not None:
            nodes = self.obs.expand(chunk.numel(), -1) if self.obs.dim() == 1 else self.obs[chunk]
            seen = nodes < reached.unsqueeze(1)  # (R, T)
            x = torch.where(seen.unsqueeze(-1), x, torch.zeros((), dtype=x.dtype, device=x.device))
            mask = mask & seen.reshape(seen.shape + (1,) * (mask.dim() - 2))
        value, _ = self.spec.operator.value_and_jacobian(x.reshape(-1, n))
        resid = torch.where(mask, y - value.reshape(y.shape), torch.zeros((), dtype=y.dtype, device=y.device))
        return self._ssq(chunk, resid.reshape(chunk.numel(), -1), w, penalty=True) + log

    def _keep_model_sse(self, idx, it: dict, rows: torch.Tensor, traj: torch.Tensor, errors: list) -> None:
        """Keep in ``it`` the model's solutions ``traj (R, G, M)`` from the estimates of its samples
        ``rows`` (``errors``: the solver's, None where it succeeded) and their sums of squares
        (inf where not integrable), as :meth:`_nonlinear_sse` caches them."""
        sse = self._objective(idx[rows], traj, it["w"][rows], it["log"][rows])
        failed = torch.tensor([e is not None for e in errors], dtype=torch.bool, device=sse.device)
        sse = torch.where(failed | ~torch.isfinite(sse), torch.full_like(sse, math.inf), sse)
        it["nl_sse"][rows] = sse
        it["nl_traj"][rows] = traj

