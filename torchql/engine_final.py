"""The engine's final pass: each sample's model integrated at its estimates, with sensitivities.

The reported SSE, residuals, Jacobian, singular values, status diagnosis and covariance are those
of the fitted model itself, not of the last linear problem.
"""

from __future__ import annotations

import math

import torch

from .bounds import at_bound_note, moved_guesses_note
from .diagnosis import final_status, null_detail, typical_magnitudes
from .lstsq import solve_update, solve_update_batch
from .result import Status
from .solvers import STIFF_SOLVERS
from .uncertainty import covariance

__all__ = ["FinalPass"]

_STATUSES = list(Status)


class FinalPass:
    """The final evaluation (mixed into :class:`torchql.engine.Engine`)."""

    def _finish(self, z0, status, detail, iterations, final_guess) -> dict:
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
        codes = [_STATUSES[int(c)] for c in status.tolist()]
        converged = torch.tensor([c.success for c in codes], dtype=torch.bool, device=dev)
        final = torch.tensor([c not in (Status.DIVERGED, Status.INTEGRATION_FAILED, Status.MAX_TIME) for c in codes],
                             dtype=torch.bool, device=dev)
        rows, traj, W = self._final_solutions(final.nonzero().flatten(), z0, final_guess, codes, detail)
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
            exact = self.exact[rows]
            exact_residual[rows] = torch.where(exact, resid.abs(), torch.zeros_like(resid)).amax(dim=1)
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
            rows, J, s, rw, J_info = rows[keep], J[keep], s[keep], rw[keep], J_info[keep]
        if rows.numel():
            used = self._used(rows)
            deficient, singular_values[rows] = self._diagnose(rows, J, rw, s, z0, codes, detail, used)
            exact = torch.cat([self.exact[rows], torch.zeros_like(used[:, self.exact.shape[1]:])], dim=1)
            cov[rows] = _covariance(J_info, used, s, self.L[rows], spec, deficient | exact.any(dim=1), exact)
            cov[~converged] = float("nan")  # as fit: no error bars about estimates that are not an optimum
        if self.history is not None:  # the estimates returned, unevaluated, where the final pass did not run
            for r in range(S):
                last = self.history[r][-1] if self.history[r] else None
                if last is None or last.iteration != int(iterations[r]) or not torch.equal(last.x0, z0[r, :self.system.n]):
                    self.history[r].append(self._record(r, int(iterations[r]), z0[r], float("nan")))
        for k, r in enumerate(self.index.tolist()):
            if spec.bounds.active:
                detail[k] += at_bound_note(spec.bounds.at_bound(z0[k, spec.unknown_index]))
            if r in spec.moved_guesses:
                detail[k] += " " + moved_guesses_note(spec.moved_guesses[r])
        messages = [c.value + d for c, d in zip(codes, detail)]
        return dict(z0=z0, sse=sse, cov=cov, iterations=iterations, status=codes, message=messages,
                    residuals=residuals, jacobian=jacobian, singular_values=singular_values,
                    exact_residual=exact_residual, history=self.history,
                    sse_start=self.first_sse, z0_start=self.first_z0)

    def _final_solutions(self, rows, z0, final_guess, codes, detail):
        """The model integrated at the estimates ``z0`` of samples ``rows`` (from ``final_guess``,
        a prediction of the trajectory), with its sensitivities: ``(rows, traj, W)`` of the samples
        that integrated; the others' ``codes`` become INTEGRATION_FAILED with the solver's words."""
        dev = z0.device
        if not rows.numel():
            return rows, None, None
        W = None
        if self._joint_sensitivities or self.spec.solver in STIFF_SOLVERS:
            # the solution and its sensitivities on the same adaptive steps: for a stiff model the
            # grid's transfers may miss a fast change inside an interval, and the status and the
            # covariance are only as true as this Jacobian
            traj, W, errors = self._solve_with_sensitivities(rows, z0[rows])
        else:
            traj, errors = self._nonlinear(rows, z0[rows], loose=False, guess=final_guess[rows])
        for k, r in enumerate(rows.tolist()):
            if errors[k] is not None:
                codes[r] = Status.INTEGRATION_FAILED
                detail[r] = f" The solver said, at the final estimates: {errors[k]}."
        good = torch.tensor([e is None for e in errors], dtype=torch.bool, device=dev)
        rows, traj = rows[good], traj[good]
        if W is not None:
            return rows, traj, W[good]
        if not rows.numel():
            return rows, traj, None
        lin = self._linearize(rows, traj)
        W, failed = self._propagate(rows, traj, lin.f, lin, self.spec.columns(z0[rows]))
        for r in rows[failed].tolist():
            codes[r] = Status.INTEGRATION_FAILED
            detail[r] = (" The solver said, at the final estimates: the transfer of a grid interval did not "
                         "meet the tolerance.")
        return rows[~failed], traj[~failed], W[~failed]

    def _used(self, rows) -> torch.Tensor:
        """The rows in use of samples ``rows``: the values present ``(S, R)``, and with a ``sigma(p)``
        function the log rows of those values after them ``(S, 2 R)``."""
        used = self.mask[rows].reshape(rows.numel(), -1)
        return used if self.spec.sigma_function is None else torch.cat([used, used], dim=1)

    def _diagnose(self, rows, J, rw, sse, z0, codes, detail, used):
        """The final statuses of samples ``rows`` from their weighted Jacobians ``J (S, R, m)`` and
        residuals ``rw`` at the estimates (rows ``used (S, R)``): the Gauss–Newton step there
        (stationarity) and the Jacobian's rank (:func:`torchql.diagnosis.final_status`), for
        samples that converged or ran out of iterations or stalled. Updates ``codes`` and
        ``detail``; returns ``deficient (S,)`` and the singular values ``(S, m)``."""
        spec = self.spec
        dtype, dev, m = spec.dtype, spec.device, spec.m
        L = self.L[rows]
        step, deficient, sv = solve_update_batch(J, rw, torch.ones(J.shape[:2], dtype=dtype, device=dev), spec.rcond,
                                                 None)
        deficient |= L < m
        for k, r in enumerate(rows.tolist()):
            code = codes[r]
            if not (code.success or code in (Status.MAX_ITER, Status.STALLED)):
                continue
            null_text = ""
            if bool(deficient[k]):
                n_used = int(used[k].sum())
                sol = solve_update(J[k][used[k]], torch.zeros(n_used, dtype=dtype, device=dev),
                                   torch.ones(n_used, dtype=dtype, device=dev),
                                   torch.zeros(n_used, dtype=torch.bool, device=dev), spec.rcond)
                null_text = null_detail(sol.null_vectors, spec.unknown_names)
            codes[r], more = final_status(
                code, rank_deficient=bool(deficient[k]), null_text=null_text,
                estimates=z0[r, spec.unknown_index],
                scale=typical_magnitudes(self.z0_guess[r, spec.unknown_index],
                                         None if self.scale is None else self.scale[r]),
                unknown_names=spec.unknown_names,
                sse=float(sse[k]), sse_start=None if self.start == "data" else float(self.first_sse[r]),
                step=step[k])
            detail[r] = more if code.success else detail[r] + more
        return deficient, sv


def _fisher_rows(C_mean: torch.Tensor, w: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """The rows ``(S, 2R, m)`` whose ``J^T J`` is the expected (Fisher) information of a fit with a
    ``sigma(p)`` function: the mean's sensitivities over sigma, ``C_mean (S, R, m)`` times the data
    rows' weights (the first ``R`` of ``w``), then ``sqrt(2)`` times the log rows ``g = d log sigma /
    d unknowns (S, R, m)`` (a Gaussian value's information about ``log sigma`` is 2)."""
    R = C_mean.shape[1]
    return torch.cat([C_mean * w[:, :R].unsqueeze(-1), math.sqrt(2.0) * g], dim=1)


def _covariance(J, used, sse, L, spec, deficient, exact) -> torch.Tensor:
    """Per-sample covariance ``(S, m, m)`` as :func:`torchql.uncertainty.covariance`: batched, and
    per sample (``deficient``) where a direction is undetermined or values are met ``exact (S, R)``."""
    S, _, m = J.shape
    dof = (L - m).to(J.dtype)
    s2 = (torch.ones_like(sse) if spec.sigma_known
          else torch.where(dof > 0, sse / dof.clamp(min=1), torch.full_like(sse, float("nan"))))
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
