"""The final statuses of a chunk's fitted samples (a part of the final pass, :mod:`torchql.engine_final`).

At the estimates, from the model's own weighted Jacobian and residuals: the Gauss–Newton step
(within the bounds), whether a stalled fit is at the model's optimum after all (``CONVERGED``:
the step below ``xtol``; ``CONVERGED_SSE``: the decrease it promises below what the integration
resolves), and the Jacobian's rank and runaways (:func:`torchql.diagnosis.final_status`).
"""

from __future__ import annotations

import math

import torch

from .active_set import bounded_update
from .diagnosis import final_status, null_detail, rounding_spread
from .engine_steps import predicted_decrease
from .lstsq import solve_update, solve_update_batch
from .result import Status

__all__ = ["FinalDiagnosis", "RESOLVED"]

#: A stalled fit whose Gauss–Newton step on the model promises less than this many times the sum of
#: squares' integration error (``2 |w r| |w (atol + rtol |y|)|``, the residuals each off by their
#: local tolerance) is at its optimum as far as the solutions resolve it: their global error is
#: a few times the local tolerance (:meth:`FinalPass._stationary_on_the_model`).
RESOLVED = 10.0


class FinalDiagnosis:
    """The final statuses (mixed into :class:`torchql.engine.Engine` through
    :class:`~torchql.engine_final.FinalPass`, whose evaluation they use)."""

    def _diagnose(self, rows, J, rw, w, sse, z0, codes, detail, used, magnitudes):
        """The final statuses of samples ``rows`` from their weighted Jacobians ``J (S, R, m)`` and
        residuals ``rw`` at the estimates (weights ``w``, rows ``used (S, R)``): the Gauss–Newton step there
        (stationarity, :meth:`_stationary_on_the_model`, with the unknowns' ``magnitudes (S, m)``
        on the fitted solution) and the Jacobian's rank (:func:`torchql.diagnosis.final_status`),
        for samples that converged or ran out of iterations or stalled. Updates ``codes`` and
        ``detail``; returns ``deficient (S,)`` and the singular values ``(S, m)``."""
        spec = self.spec
        dtype, dev, m = spec.dtype, spec.device, spec.m
        L = self.L[rows]
        step, deficient, sv = solve_update_batch(J, rw, torch.ones(J.shape[:2], dtype=dtype, device=dev), spec.rcond,
                                                 None)
        deficient |= L < m
        # a fit that did not converge, tested at the accuracy of the storage grid's sensitivities
        # (sqrt(rtol)): an exactly undetermined direction measures about that, above `rcond`, and its
        # iteration wanders along it until max_iter
        loose = max(spec.rcond, math.sqrt(spec.rtol))
        failed = torch.tensor([codes[r] in (Status.MAX_ITER, Status.STALLED) for r in rows.tolist()], device=dev)
        barely = failed & ~deficient & (sv.amin(dim=1) <= loose * sv.amax(dim=1))
        deficient |= barely
        estimates = z0[rows][:, spec.unknown_index]
        scales = self._typical(rows)
        stalled = torch.tensor([codes[r] is Status.STALLED for r in rows.tolist()], dtype=torch.bool, device=dev)
        stationary = self._stationary_on_the_model(rows, J, rw, w, step, estimates, torch.maximum(scales, magnitudes),
                                                   stalled & ~deficient, codes, detail)
        sse_list = sse.tolist()
        data = self._data_sse(rows, w)
        spread = rounding_spread(torch.where(used.unsqueeze(-1), J, 0.0), estimates).tolist()
        first_sse = [None] * rows.numel() if self.start == "data" else self.first_sse[rows].tolist()
        for k, (r, short) in enumerate(zip(rows.tolist(), deficient.tolist())):
            code = codes[r]
            if stationary[k] or not (code.success or code in (Status.MAX_ITER, Status.STALLED)):
                continue
            null_text = ""
            if short:
                n_used = int(used[k].sum())
                sol = solve_update(J[k][used[k]], torch.zeros(n_used, dtype=dtype, device=dev),
                                   torch.ones(n_used, dtype=dtype, device=dev),
                                   torch.zeros(n_used, dtype=torch.bool, device=dev),
                                   loose if bool(barely[k]) else spec.rcond)
                null_text = null_detail(sol.null_vectors, spec.unknown_names)
                self.null_directions[r] = sol.null_vectors  # (torchql.saddle: the way off a saddle, if one)
            codes[r], more = final_status(
                code, rank_deficient=short, null_text=null_text, estimates=estimates[k], scale=scales[k],
                unknown_names=spec.unknown_names, sse=sse_list[k],
                sse_start=first_sse[k], step=step[k], sse_data=data[k], rounding=spread[k],
                n_values=int(used[k].sum()))
            detail[r] = more if code.success else detail[r] + more
        return deficient, sv

    def _data_sse(self, rows, w) -> list:
        """The data's own weighted sums of squares of samples ``rows`` (weights ``w``), a model
        predicting zero's; None for log-normal data (their residuals are of logarithms: log 0)."""
        if self.spec.noise == "lognormal":
            return [None] * rows.numel()
        y = self.y[rows].reshape(rows.numel(), -1)
        R = y.shape[1]
        return torch.where(self.mask[rows].reshape(-1, R), w[:, :R] * y, 0.0).square().sum(1).tolist()

    def _bounded(self, J, rw, estimates, step):
        """The Gauss–Newton step ``step (S, m)`` on the model at ``estimates (S, m)`` (weighted
        Jacobians ``J (S, R, m)``, residuals ``rw (S, R)``) as the bounds let it be taken
        (:func:`torchql.active_set.bounded_update`): an estimate on a bound that the data pull
        outside stays there. NaN where the data pull one inside from its bound."""
        bounds = self.spec.bounds
        if not bounds.active:
            return step

        def solve(rows, C, d, w):
            alpha = solve_update_batch(C, d, w, self.spec.rcond, None)[0]
            return alpha, torch.zeros_like(alpha[:, 0], dtype=torch.bool), torch.zeros_like(alpha[:, 0])

        alpha, capped, _, _ = bounded_update(bounds, solve, J, rw, torch.ones_like(rw), estimates)
        return alpha.masked_fill(bounds.leaving(estimates, alpha, capped).unsqueeze(-1), float("nan"))

    def _stationary_on_the_model(self, rows, J, rw, w, step, estimates, scales, candidates, codes, detail) -> list[bool]:
        """Samples ``rows`` that stalled (``candidates (S,)``, with a Jacobian of full rank) whose
        Gauss–Newton step on the model at the estimates, ``step (S, m)`` as the bounds let it be taken
        (:meth:`_bounded`, from ``J`` and ``rw``), is at most ``xtol`` of the
        unknowns' magnitudes ``max(|estimate|, scales)`` (the convergence test's bound) are
        converged: the iteration stopped at the model's optimum, where rounding or the
        integration's error, not the distance to it, decided its last trials (a fit that reaches
        exact data to 1e-24). Their ``codes`` become ``CONVERGED``, with a note; returns which
        samples did. So do, as ``CONVERGED_SSE``, those whose step promises a decrease of the sum
        of squares (:func:`predicted_decrease`) at most :data:`RESOLVED` times its integration
        error (:meth:`~torchql.engine_steps.StepTests._sse_error`, weights ``w``): Boehm's
        PEtab fit, whose damped steps crept at 1.4e-5 of 188 with its likelihood 2e-5 below the
        reference, was STALLED. A fit that ran out of ``max_iter`` keeps saying so."""
        if self.spec.has_exact or not bool(candidates.any()):  # the step above does not meet exact values
            return [False] * rows.numel()
        k = candidates.nonzero().flatten()
        bounded = self._bounded(J[k], rw[k], estimates[k], step[k])
        size, promised, floor = (torch.full_like(candidates, math.nan, dtype=step.dtype) for _ in range(3))
        size[k] = (bounded.abs() / torch.maximum(estimates[k].abs(), scales[k])).amax(dim=1)
        promised[k] = predicted_decrease(J[k], rw[k], torch.ones_like(rw[k]), bounded)
        floor[k] = RESOLVED * self._sse_error(rows[k], rw[k].square().sum(dim=1), w[k])
        stationary, flat = candidates & (size <= self.spec.xtol), candidates & (promised <= floor)
        for k in (stationary | flat).nonzero().flatten().tolist():
            r, said = int(rows[k]), (f"the Gauss-Newton step on the model is {float(size[k]):.2g} of their magnitudes, "
                                     "below `xtol`" if stationary[k] else _promise(float(promised[k]), float(floor[k])))
            detail[r] = (" Found on the model itself: the iteration stalled (no step it tried lowered the sum of "
                         f"squares enough), but at the estimates {said}.")
            codes[r] = Status.CONVERGED if stationary[k] else Status.CONVERGED_SSE
        return (stationary | flat).tolist()


def _promise(promised: float, floor: float) -> str:
    """What a stalled fit's Gauss–Newton step on the model promises, in words: a decrease of the sum of
    squares ``promised`` below the integration's resolution ``floor``, or none (the step as the bounds
    let it be taken raises the linear model's sum of squares)."""
    if promised <= 0:
        return ("the Gauss-Newton step on the model, as the bounds let it be taken, promises no decrease of the sum "
                "of squares")
    return (f"the Gauss-Newton step on the model promises a decrease of the sum of squares by {promised:.2g}, below "
            f"what the integration's error lets it resolve ({floor:.2g})")
