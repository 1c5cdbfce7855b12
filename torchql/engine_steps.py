"""Which trial steps the engine takes, and which end a fit: the acceptance test (the merits, or the
model's own sums of squares), a flat minimum reached by damped steps (``CONVERGED_SSE``), and
damped steps that creep (``STALLED``, for the final pass to go on by steps on the model)."""

from __future__ import annotations

import math

import torch

from .damping import POOR_GAIN
from .engine_state import LoopState, _pick, not_above
from .lstsq import relative_spectrum
from .trajectory import DEFECT_TRUST

__all__ = ["StepTests", "FLAT_DAMPING", "predicted_decrease"]

#: The most damping (relative to the largest squared singular value) of a step that may end a fit
#: by :meth:`Engine._flat`'s test: larger damping shortens every step, and a short step's small
#: predicted decrease says little about the minimum.
FLAT_DAMPING = 1e-3
#: :meth:`StepTests._poor_gain` judges a step whose predicted decrease is at least this many times
#: what the sum of squares resolves (``ftol`` of it, or its integration error).
GAIN_RESOLVED = 10.0


def predicted_decrease(C: torch.Tensor, d: torch.Tensor, w: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """The linear model's predicted decrease of the weighted sum of squares by steps ``alpha (S, m)``:
    ``|w d|^2 - |w (d - C alpha)|^2``, ``(S,)``, for matrices ``C (S, L, m)``, misfits ``d`` and
    weights ``w (S, L)``."""
    left = d - (C @ alpha.unsqueeze(-1)).squeeze(-1)
    return ((d * w) ** 2).sum(dim=1) - ((left * w) ** 2).sum(dim=1)


class StepTests:
    """The step tests (mixed into :class:`torchql.engine.Engine`, whose ``spec`` and evaluation they use)."""

    def _flat(self, st: LoopState, act, trial, accept, alpha) -> torch.Tensor:
        """Which accepted damped steps end their fits at a flat minimum (CONVERGED_SSE): as MINPACK's
        ``ftol`` test, both the merit's actual change and the linear model's predicted decrease
        ``|w d|^2 - |w (d - C alpha)|^2`` at most ``ftol`` relative, with damping at most
        :data:`FLAT_DAMPING`. Undamped steps have :meth:`torchql.engine.Engine._converged`'s tests;
        this one serves a fit whose Gauss–Newton steps along directions the data barely determine are too long to be
        accepted undamped, so that no undamped step ever comes to be tested (damped by rejections: a
        step damped after a poor gain, :meth:`_poor_gain`, is followed by an undamped one, tested)."""
        spec, cur = self.spec, st.cur
        damping = st.damping[act]
        flat = accept & (damping > 0) & (damping <= FLAT_DAMPING) & (st.rejected[act] > 0)
        if not spec.damping.filters or spec.has_exact or not bool(flat.any()):
            return torch.zeros_like(accept)
        predicted = predicted_decrease(_pick(cur["C"], act), _pick(cur["d"], act), _pick(cur["w"], act), alpha)
        new = trial["merit"]
        tol = spec.ftol * new.abs()
        return flat & (predicted <= tol) & ((cur["merit"][act] - new).abs() <= tol)

    def _creeping(self, st: LoopState, act, trial, accept) -> torch.Tensor:
        """Which accepted steps damped more than :data:`FLAT_DAMPING` (those :meth:`_flat` does not
        judge) end their fits as ``STALLED``: the step's scaled size at most ``xtol``, or the merit
        (the model's own sum of squares where both are known: what accepted the step) lowered by at
        most ``ftol`` of it or than the integration's error can tell (``2 sqrt(SSE)`` times the root of
        :meth:`_integration_floor`: the sum of squares' own error, to first order),
        or raised within the acceptance's slack. Where the iteration's linear problems and the model
        disagree at the last digits (a measured input's step inside a stiff model's fast layer),
        the undamped steps are rejected and heavily damped ones creep; the final pass takes
        Gauss–Newton steps on the model itself from there. A lightly damped step that lowers the
        merit little is progress along a curved valley, not a creep."""
        damped = accept & (st.damping[act] > FLAT_DAMPING) & (st.rejected[act] > 0)
        if self.spec.has_exact or not bool(damped.any()):  # (exact values: the final pass would not judge it)
            return torch.zeros_like(damped)
        new, old = trial["merit"], st.cur["merit"][act]
        model_new, model_old = trial["nl_sse"], st.cur["nl_sse"][act]
        known = torch.isfinite(model_new) & torch.isfinite(model_old)  # the model's own decided: it is the measure
        new, old = torch.where(known, model_new, new), torch.where(known, model_old, old)
        floor = self._sse_error(act, st.cur["sse"][act], st.cur["w"][act])
        small = (((st.scaled <= self.spec.xtol) & ~st.leaving)
                 | (old - new <= torch.maximum(self.spec.ftol * new.abs(), floor)))
        return damped & small

    def _poor_gain(self, st: LoopState, act, trial, accept, alpha) -> torch.Tensor:
        """Which accepted undamped steps of samples ``act`` lowered the merit by less than
        :data:`~torchql.damping.POOR_GAIN` of their linear model's predicted decrease
        (:func:`predicted_decrease`): their successors start damped
        (:meth:`~torchql.damping.Damping.after_poor_gain`, applied by :meth:`_damp_poor_gain` once
        the steps are taken). ``alpha (A, m)`` are the steps in the unknowns' own units, as taken
        (a bounded one capped: its capped move, the others re-solved). Not judged: steps that exact
        values constrain (their merit is a penalty's), Kantorovich trials far from solving the model
        (their merit is no sum of squares of it), and steps whose predicted decrease is within
        :data:`GAIN_RESOLVED` times what the sum of squares resolves (near the optimum both
        decreases are the integration's noise)."""
        spec = self.spec
        poor = accept & (st.damping[act] == 0)
        if not spec.damping.filters or spec.has_exact or not bool(poor.any()):
            return torch.zeros_like(accept)
        if not spec.scheme.integrates_model:
            poor &= trial["defect"] <= DEFECT_TRUST
        cur = st.cur
        predicted = predicted_decrease(_pick(cur["C"], act), _pick(cur["d"], act), _pick(cur["w"], act), alpha)
        poor &= (cur["merit"][act] - trial["merit"] < POOR_GAIN * predicted) & (predicted > 0)
        if not bool(poor.any()):  # (the usual case: the step gained as its model said)
            return poor
        # near the optimum both decreases are the integration's noise, and their ratio says nothing
        noise = torch.maximum(spec.ftol * trial["merit"].abs(), self._sse_error(act, cur["sse"][act], cur["w"][act]))
        return poor & (predicted > GAIN_RESOLVED * noise)

    def _damp_poor_gain(self, st: LoopState, rows) -> None:
        """The fresh iterates of samples ``rows`` (reached by steps :meth:`_poor_gain` found) start
        with the damping strategy's :meth:`~torchql.damping.Damping.after_poor_gain`."""
        if not rows.numel():
            return
        st.damping[rows] = self.spec.damping.after_poor_gain(st.last_damping[rows], self._damped_spectrum(st, rows))

    def _damped_spectrum(self, st: LoopState, rows) -> torch.Tensor:
        """The relative spectrum ``(R, k)`` of the current iterates' damped problems of samples ``rows``
        (:func:`torchql.lstsq.relative_spectrum`, in the bounds' internal variables, as damped),
        which a damping strategy reads to choose a damping; all NaN (no skipping) for a sample with
        values marked exact."""
        spec, cur = self.spec, st.cur
        u = _pick(cur["z0"], rows)[:, spec.unknown_index]
        C = spec.bounds.internal_columns(_pick(cur["C"], rows), u)
        spectrum = relative_spectrum(C, _pick(cur["w"], rows), spec.rcond)
        if spec.has_exact:
            spectrum[self.exact[rows].any(dim=1)] = float("nan")
        return spectrum

    def _lost(self, st: LoopState, act) -> torch.Tensor:
        """Bool ``(A,)``: Kantorovich iterates of samples ``act``, taken on their linear merit, from
        whose estimates the model itself turned out not to integrate (its sum of squares, found
        while judging their trials, is inf): an SIR iterate whose infected fraction crossed zero,
        from where the model blows up in finite time while the linear trajectory stayed smooth.
        Any finite trial would beat it; the previous iterate is restored instead
        (:meth:`_restore_lost`)."""
        if self.spec.scheme.integrates_model or not self.spec.damping.filters:
            return torch.zeros_like(act, dtype=torch.bool)
        return torch.isposinf(st.cur["nl_sse"][act]) & (st.iterations[act] > 0)

    def _restore_lost(self, st: LoopState, rows, alpha) -> None:
        """The samples ``rows`` whose iterate was lost (:meth:`_lost`) go back to their previous
        estimates, re-linearized about the model's own solution there, and retry with damping
        (the undamped step led where the model does not integrate). Where that solution does not
        integrate either, the samples are rejected as usual."""
        cur = st.cur
        lost = {key: cur[key][rows].clone() for key in ("z0", "anchored", "nl_sse", "nl_traj")}
        lost_damping = st.damping[rows].clone()
        records = {} if self.history is None else {r: self.history[r][-1] for r in rows.tolist()}
        said = {r: (h.sse, h.merit, h.trajectory) for r, h in records.items()}
        cur["z0"][rows], cur["anchored"][rows] = st.prev_z0[rows], False
        traj, errors = self._nonlinear(st.all_idx[rows], st.prev_z0[rows], loose=True)  # (not from the lost one's)
        self._keep_model_sse(st.all_idx, cur, rows, traj, errors)
        st.damping[rows] = 0.0
        back = torch.isin(rows, self._reanchor(st, rows))
        for r, (sse, merit, trajectory) in said.items():  # the lost iterate's record keeps its values
            records[r].sse, records[r].merit, records[r].trajectory = sse, merit, trajectory
            records[r].model_merit = math.inf
        if not bool(back.all()):  # no restoring: the lost iterate stays, its trial rejected as usual
            stay = rows[~back]
            for key, value in lost.items():
                cur[key][stay] = value[~back]
            st.damping[stay] = lost_damping[~back]
            self._reject(st, stay, alpha[~back])
        rows = rows[back]
        if rows.numel():  # the restored iterate gets a record of its own, and its next trial is damped
            st.z0[rows], st.fresh[rows], st.distrust[rows] = cur["z0"][rows], True, True
            st.damping[rows] = self.spec.damping.raised(torch.zeros_like(st.damping[rows]), st.last_damping[rows])

    def _integration_floor(self, rows, w) -> torch.Tensor:
        """``sum (w (atol + rtol |y|))^2`` over the values used of samples ``rows``, weights ``w (R, L)``:
        ``(R,)``, the squared size of the weighted residuals' integration error (used by
        :meth:`_creeping` and by the final pass's :meth:`~torchql.engine_final.FinalPass._not_minimal`)."""
        spec = self.spec
        y, used = self.y[rows].reshape(rows.numel(), -1), self.mask[rows].reshape(rows.numel(), -1)
        scale = w[:, :y.shape[1]] * (spec.atol + spec.rtol * y.abs())
        return torch.where(used, scale, torch.zeros_like(scale)).square().sum(dim=1)

    def _sse_error(self, rows, sse, w) -> torch.Tensor:
        """The error ``(R,)`` of sums of squares ``sse (R,)`` of samples ``rows`` (weights ``w``) that
        the integration's tolerance allows, to first order: ``2 sqrt(sse)`` times the root of
        :meth:`_integration_floor` (every residual off by its local tolerance)."""
        return 2 * sse.abs().sqrt() * self._integration_floor(rows, w).sqrt()

    def _accepted(self, st: LoopState, act, trial, ok, capped) -> torch.Tensor:
        """Which trials lower the sum of squares. The merits decide (Kantorovich: the particular
        solutions' sums of squares) for trials near solving the model whose step was not capped
        at a bound's largest internal move; otherwise the model's own sums of squares, integrated
        from both estimates (:meth:`~torchql.engine_evaluate.Evaluation._model_not_above`). A
        damping that does not filter (``damping=None``): every integrable trial."""
        spec, cur = self.spec, st.cur
        if not spec.damping.filters:
            return ok
        lower = not_above(trial["merit"], cur["merit"][act])
        if spec.scheme.integrates_model:  # the merit is the model's own sum of squares
            return ok & lower
        better = lower & (trial["defect"] <= DEFECT_TRUST) & ~capped & ~st.distrust[act]
        better |= trial.get("by_model", torch.zeros_like(better))  # judged so before it was propagated
        check = ok & ~better
        if bool(check.any()):
            rows = check.nonzero().flatten()
            better[rows] = self._model_not_above(st.all_idx, cur, act, trial, rows)
        return ok & better

    def _evaluate_unless_rejected(self, act, cur: dict, z0, z, z_dot, lin, defect, finite) -> dict:
        """Kantorovich's trial iterates from ``z0 (A, M)`` about their references ``z (A, G, M)``
        (slopes ``z_dot``, linearization ``lin``, :func:`~torchql.trajectory.model_defect`
        ``defect (A,)``, ``finite (A,)``), evaluated (:meth:`_evaluate`) but for those that
        :meth:`_accepted` would reject whatever their propagation gave: the trials that the model's
        own sum of squares judges (their step capped at a bound's largest move, their iterate
        distrusted, :attr:`judged_by_model`, or their trajectory too far from solving the model,
        ``defect`` above :data:`~torchql.trajectory.DEFECT_TRUST`) are judged first, and those
        whose model is above their current iterate's are not propagated (marked failed). Far from
        solving the model, a trajectory's linearization may change a thousand times faster than the
        iterate's: an SIR fit's rejected trials took 1,024 substeps in every interval, 7.5 of its 8.4 s.

        ``by_model (A,)`` says which trials the model found not above (:meth:`_accepted` takes them
        where they propagate); their model solutions are kept (``nl_sse``, ``nl_traj``)."""
        A = act.numel()
        judged = (self.judged_by_model[act] | ~(defect <= DEFECT_TRUST)) & finite
        if not self.spec.damping.filters or not bool(judged.any()):
            trial = self._evaluate(act, z0, z, z_dot, lin)
            trial["by_model"] = torch.zeros(A, dtype=torch.bool, device=z0.device)
            return trial
        rows = judged.nonzero().flatten()
        before = self._unpropagated(act, z0, z)
        better = self._model_not_above(torch.arange(self.S, device=act.device), cur, act, before, rows)
        keep = ~judged
        keep[rows[better]] = True
        trial = self._evaluate(act, z0, z, z_dot, lin, propagate=keep)
        trial["nl_sse"][rows], trial["nl_traj"][rows] = before["nl_sse"][rows], before["nl_traj"][rows]
        trial["by_model"] = torch.zeros(A, dtype=torch.bool, device=z0.device)
        trial["by_model"][rows[better]] = True
        return trial

    def _unpropagated(self, act, z0, z) -> dict:
        """What :meth:`_model_not_above` reads of trial iterates from ``z0 (A, M)`` about ``z (A, G,
        M)`` before their propagation: estimates, weights, log terms, the model's sums of squares
        and solutions (unknown: NaN), and ``W``'s particular solution (the reference ``z``, the grid
        solver's first guess)."""
        R = self.w[0].numel()
        m = len(self.spec.unknown_index)
        _, _, w, log = self._weighted(act, z0, z0.new_zeros(act.numel(), R, m), z0.new_zeros(act.numel(), R))
        nan = float("nan")
        return dict(z0=z0, W=z.unsqueeze(-1), w=w, log=log, nl_sse=torch.full_like(log, nan),
                    nl_traj=torch.full_like(z, nan))
