"""The quasilinearization engine: the package's one iteration loop, over ``S >= 1`` samples.

:func:`torchql.fit` runs it with one sample and keeps every iterate's record;
:func:`torchql.fit_many` runs it over a batch, chunk after chunk (:func:`run_engine`). Each
sample has its own iterate, damping, status and history; the work is vectorized over the
samples still running. One iteration of a sample:

1. at a fresh iterate, the budgets (``max_iter``, ``max_time``) and the rows' finiteness;
2. the least-squares update ``alpha`` (:meth:`Engine._solve`: batched SVD with each sample's
   damping; equality-constrained per sample where values are marked ``exact``; bounds in their
   transformed variables), and the convergence tests on undamped steps;
3. the trial iterate (:meth:`Engine._propose`: Kantorovich's superposed trajectory, re-linearized;
   shooting's model solution), accepted when it lowers the merit or, failing that test, the
   model's own sum of squares;
4. on rejection, Kantorovich re-anchors the undamped step about the model's own solution once,
   then Levenberg–Marquardt damping rises tenfold per rejection until a step is accepted or the
   iteration stalls.

The final pass (:mod:`torchql.engine_final`) evaluates the fitted model itself.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

from .batch_result import BatchFitResult
from .budget import TimeBudgetExceeded, no_time_budget, time_budget, time_left
from .batch_integrate import _last_nodes
from .data_start import data_reference
from .engine_evaluate import _MERIT_SLACK, Evaluation, _pick
from .engine_final import FinalPass
from .lstsq import ExactRowsError, solve_update, solve_update_batch
from .options import DAMPING_MAX as _DAMPING_MAX, DAMPING_MIN as _DAMPING_MIN, DAMPING_START as _DAMPING_START
from .problem import Problem
from .result import IterationRecord, Status
from .trajectory import DEFECT_TRUST, model_defect

__all__ = ["Engine", "run_engine"]

_STATUSES = list(Status)
_RUNNING = -1


def run_engine(spec: Problem, chunk_size: int, max_time: float | None, report: Callable[[int | None], None],
               history: bool = False, callback: Callable[[int, IterationRecord], None] | None = None
               ) -> BatchFitResult:
    """Fit the validated problem ``spec``, chunk after chunk of samples: the iteration of
    :func:`torchql.fit` (one sample) and :func:`fit_many` alike.

    ``report`` receives the number of samples finished (``None``: done); ``history`` keeps every
    iterate's record; ``callback(sample, record)`` receives each record as it is completed.
    """
    B, m = spec.B, spec.m
    out_z0 = torch.empty(B, spec.system.M, dtype=spec.dtype, device=spec.device)
    R = spec.weights.reshape(B, -1).shape[1]
    out = dict(sse=torch.empty(B, dtype=spec.dtype, device=spec.device),
               cov=torch.empty(B, m, m, dtype=spec.dtype, device=spec.device),
               iterations=torch.empty(B, dtype=torch.long, device=spec.device),
               residuals=torch.empty(B, R, dtype=spec.dtype, device=spec.device),
               jacobian=torch.empty(B, R, m, dtype=spec.dtype, device=spec.device),
               singular_values=torch.empty(B, m, dtype=spec.dtype, device=spec.device),
               sse_start=torch.empty(B, dtype=spec.dtype, device=spec.device),
               exact_residual=torch.empty(B, dtype=spec.dtype, device=spec.device))
    statuses: list[Status] = [Status.MAX_ITER] * B
    messages: list[str] = [""] * B
    histories: list[list[IterationRecord]] | None = [] if history else None
    nfev = 0
    finished = 0
    try:
        with time_budget(max_time):
            for start in range(0, B, chunk_size):
                index = torch.arange(start, min(B, start + chunk_size), device=spec.device)
                engine = Engine(spec, index, max_time, history=history, callback=callback)

                def step(count, offset=finished):
                    report(offset + count)

                chunk = engine.run(step)
                out_z0[index] = chunk["z0"]
                for key in out:
                    out[key][index] = chunk[key]
                for k, i in enumerate(index.tolist()):
                    statuses[i], messages[i] = chunk["status"][k], chunk["message"][k]
                if histories is not None:
                    histories.extend(chunk["history"])
                nfev += engine.nfev
                finished += index.numel()
                report(finished)
    finally:
        report(None)
    result = spec.result(out_z0, out, statuses, messages, nfev)
    result.history = histories
    return result


class Engine(Evaluation, FinalPass):
    """The iteration of one chunk of samples (indices ``index`` of the problem's batch)."""

    def __init__(self, spec: Problem, index: torch.Tensor, max_time: float | None = None, history: bool = False,
                 callback: Callable[[int, IterationRecord], None] | None = None) -> None:
        self.spec, self.max_time, self.index = spec, max_time, index
        self.scale: torch.Tensor | None = None  # (S, m) typical magnitudes, from the first trajectory
        self.sse_start: torch.Tensor | None = None  # (S,) the model's sums of squares at the guesses
        self.system = spec.system
        self.y, self.w, self.mask = spec.y[index], spec.weights[index], spec.mask[index]
        self.exact = spec.exact[index].reshape(index.numel(), -1)  # (S, R) rows met exactly
        self.L = spec.L[index]
        #: each sample's iterates (``torchql.fit``'s ``history``), when kept, and the open record
        self.history: list[list[IterationRecord]] | None = [[] for _ in range(index.numel())] if history else None
        self.callback = callback
        self.propagation_errors: dict[int, str] = {}  # chunk row: a per-sample propagator's message
        self.z0_guess = spec.z0[index].clone()
        self.S = index.numel()
        self.nfev = 0
        if spec.grid_size is None:  # shared times: one grid (G,), observations at nodes (T,)
            self.grid, self.obs, self.t_obs = spec.grid, spec.obs_in_grid, spec.t_obs
        else:  # per sample: grids (S, G), trimmed to the chunk's longest, nodes (S, T)
            G = int(spec.grid_size[index].max())
            self.grid, self.obs, self.t_obs = spec.grid[index, :G], spec.obs_in_grid[index], spec.t_obs[index]
        self.G = self.grid.shape[-1]

    def _solve_exact(self, idx, cur, damping):
        """:meth:`_solve` for samples with rows met exactly: each sample by
        :func:`torchql.lstsq.solve_update` (equality-constrained), bounds as there. Also returns
        ``infeasible (S,)``: exact rows that cannot all be met (NaN updates there)."""
        spec, bounds = self.spec, self.spec.bounds
        S = idx.numel()
        alpha = cur["C"].new_full((S, spec.m), float("nan"))
        capped = torch.zeros(S, dtype=torch.bool, device=alpha.device)
        infeasible = torch.zeros_like(capped)
        for k, r in enumerate(idx.tolist()):
            used = self.mask[r].reshape(-1)
            C, d, w, exact = cur["C"][r][used], cur["d"][r][used], self.w[r].reshape(-1)[used], self.exact[r][used]
            u = cur["z0"][r, spec.unknown_index]
            Cq = C * bounds.derivative(u) if bounds.active else C
            lam = float(damping[k])
            try:
                a = solve_update(Cq, d, w, exact, spec.rcond, lam).alpha
                capped[k] = bool(bounds.capped(a))
                a, blocked = bounds.step(u, a)
                if bool(blocked.any()):  # moved onto their bounds and held; the others re-solved
                    move = a.masked_fill(~blocked, 0.0)
                    rest = solve_update(Cq.masked_fill(blocked, 0.0), d - C @ move, w, exact, spec.rcond, lam).alpha
                    rest, _ = bounds.step(u, rest.masked_fill(blocked, 0.0))
                    a = torch.where(blocked, move, rest)
                alpha[k] = a
            except ExactRowsError:
                infeasible[k] = True
        return alpha, capped, infeasible

    def _solve(self, idx, cur, damping):
        """The damped updates of the samples ``idx``: ``alpha (S, m)``, the change of the unknowns,
        and ``capped (S,)``, whether a bounded unknown's step was capped (as ``torchql.fit``).

        Without bounds, batched :func:`torchql.lstsq.solve_update` (no exact rows). With bounds,
        solved for the internal variables (columns times ``du/dq``) and mapped back; the unknowns
        that the step pushes onto a bound or whose step is capped are held at their move while
        the others are re-solved, as ``fit`` does.
        """
        spec = self.spec
        C, d, w = _pick(cur["C"], idx), _pick(cur["d"], idx), _pick(self.w, idx).reshape(idx.numel(), -1)
        bounds = spec.bounds
        if not bounds.active:
            alpha, _, _ = solve_update_batch(C, d, w, spec.rcond, damping)
            return alpha, torch.zeros(idx.numel(), dtype=torch.bool, device=alpha.device)
        u = _pick(cur["z0"], idx)[:, spec.unknown_index]
        Cq = C * bounds.derivative(u).unsqueeze(1)
        alpha_q, _, _ = solve_update_batch(Cq, d, w, spec.rcond, damping)
        capped = bounds._capped(alpha_q).any(dim=1)
        alpha, blocked = bounds.step(u, alpha_q)
        rows = blocked.any(dim=1).nonzero().flatten()
        if rows.numel():  # moved onto their bounds (or capped) and held; the others re-solved
            held = blocked[rows]
            move = alpha[rows].masked_fill(~held, 0.0)
            rhs = d[rows] - (C[rows] @ move.unsqueeze(-1)).squeeze(-1)
            rest_q, _, _ = solve_update_batch(Cq[rows].masked_fill(held.unsqueeze(1), 0.0), rhs, w[rows], spec.rcond,
                                  damping[rows])
            rest, _ = bounds.step(u[rows], rest_q.masked_fill(held, 0.0))
            alpha[rows] = torch.where(held, move, rest)
        return alpha, capped

    def _record(self, r: int, iteration: int, z0: torch.Tensor, sse: float, traj: torch.Tensor | None = None
                ) -> IterationRecord:
        """Sample ``r``'s record of an iterate: its estimates ``z0 (M,)``, ``sse`` and trajectory ``(G, M)``."""
        n = self.system.n
        grid = self.grid if self.grid.dim() == 1 else self.grid[r]
        params = {k: v.detach().clone() for k, v in self.system.unpack_params(z0[n:]).items()}
        return IterationRecord(iteration=iteration, params=params, x0=z0[:n].detach().clone(), sse=sse,
                               trajectory=None if traj is None else traj[:, :n].detach().clone(),
                               trajectory_t=None if traj is None else grid)

    def _open(self, rows: torch.Tensor, cur: dict, iterations: torch.Tensor) -> None:
        """Start the records of the iterates ``cur`` of samples ``rows``."""
        if self.history is None:
            return
        for r in rows.tolist():
            record = self._record(r, int(iterations[r]), cur["z0"][r], float(cur["sse"][r]), cur["rz"][r])
            record.merit = float(cur["merit"][r])
            self.history[r].append(record)

    def _annotate(self, rows: torch.Tensor, **values) -> None:
        """Set fields of the open records of samples ``rows`` (per-sample tensors or plain values)."""
        if self.history is None:
            return
        for k, r in enumerate(rows.tolist()):
            record = self.history[r][-1]
            for key, value in values.items():
                if isinstance(value, torch.Tensor):
                    value = value[k].detach().clone() if value.dim() > 1 else value[k].item()
                setattr(record, key, value)

    def _model_merit(self, rows: torch.Tensor, cur: dict) -> torch.Tensor:
        """The model's own merit at the iterates of ``rows`` where known (shooting: the merit), else NaN."""
        return cur["merit"][rows] if self.spec.method == "shooting" else cur["nl_sse"][rows]

    def _notify(self, rows) -> None:
        """Hand the open records of samples ``rows`` to the callback."""
        if self.callback is None or self.history is None:
            return
        for r in (rows.tolist() if isinstance(rows, torch.Tensor) else [rows]):
            self.callback(int(self.index[r]), self.history[r][-1])

    def run(self, report) -> dict:
        spec, S = self.spec, self.S
        dev, dtype = spec.device, spec.dtype
        status = torch.full((S,), _RUNNING, dtype=torch.long, device=dev)
        detail = [""] * S
        iterations = torch.zeros(S, dtype=torch.long, device=dev)
        damping = torch.zeros(S, dtype=dtype, device=dev)
        last_damping = torch.zeros(S, dtype=dtype, device=dev)
        fresh = torch.ones(S, dtype=torch.bool, device=dev)
        rejected_count = torch.zeros(S, dtype=torch.long, device=dev)
        sse_prev = torch.full((S,), float("nan"), dtype=dtype, device=dev)
        z0 = self.z0_guess.clone()
        all_idx = torch.arange(S, device=dev)

        def stop(rows, code, text=""):
            status[rows] = _STATUSES.index(code)
            for r in rows.tolist():
                detail[r] = text
            report(int((status != _RUNNING).sum()))

        final_guess = None
        try:
            n = self.system.n
            if spec.initial_trajectory == "data":  # first iterate: each sample's data-built reference
                traj, z_dot, z0 = self._data_start(all_idx, z0)
                bad = torch.zeros(S, dtype=torch.bool, device=dev)
                lin = self._linearize(all_idx, traj, z_dot)
                cur = self._evaluate(all_idx, z0, traj, z_dot, lin)
            else:  # first iterate: the model integrated (loosely, for Kantorovich) from the guesses
                kantorovich = spec.method == "kantorovich"  # from a constant guess, loosely, as a first reference
                guess = z0.unsqueeze(1).expand(S, self.G, z0.shape[1]) if kantorovich else None
                traj, errors = self._nonlinear(all_idx, z0, loose=kantorovich, guess=guess)
                bad = torch.tensor([e is not None for e in errors], dtype=torch.bool, device=dev)
                for r in bad.nonzero().flatten().tolist():
                    status[r] = _STATUSES.index(Status.INTEGRATION_FAILED)
                    detail[r] = f" The solver said: {errors[r]}."
                lin = self._linearize(all_idx, traj)
                cur = self._evaluate(all_idx, z0, traj, lin.f, lin, solution=spec.method == "shooting")
            self._fail_integration(cur["failed"] & ~bad, status, detail)
            final_guess = cur["W"][:, :, :, 0].clone()
            typical = torch.cat([traj[:, :, :n].abs().amax(dim=1), z0[:, n:].abs()], dim=1)
            typical = torch.where(typical > 0, typical, torch.ones_like(typical))
            scale = typical[:, spec.unknown_index]
            # for the final diagnosis: the model's own SSE at the guesses, when the first iterate is its solution
            self.scale = scale
            self.sse_start = None if spec.initial_trajectory == "data" else cur["sse"].clone()
            report(int((status != _RUNNING).sum()))

            while True:
                running = status == _RUNNING
                if time_left() <= 0 and bool(running.any()):
                    stop(running.nonzero().flatten(), Status.MAX_TIME)
                    running = status == _RUNNING
                # the start of an iteration: the budget, then the iterate's rows
                start = running & fresh
                maxed = start & (iterations >= spec.max_iter)
                if bool(maxed.any()):
                    stop(maxed.nonzero().flatten(), Status.MAX_ITER)
                start &= ~maxed
                self._open(start.nonzero().flatten(), cur, iterations)
                rejected_count[start] = 0
                finite = (torch.isfinite(cur["sse"]) & torch.isfinite(cur["C"]).flatten(1).all(dim=1)
                          & torch.isfinite(cur["d"]).all(dim=1))
                diverged = start & ~finite
                if bool(diverged.any()):
                    stop(diverged.nonzero().flatten(), Status.DIVERGED, " The residuals became non-finite.")
                    self._notify(diverged.nonzero().flatten())
                fresh &= ~start
                act = (status == _RUNNING).nonzero().flatten()
                if not act.numel():
                    break
                if spec.has_exact:
                    alpha, capped, infeasible = self._solve_exact(act, cur, damping[act])
                    if bool(infeasible.any()):
                        stop(act[infeasible], Status.EXACT_INFEASIBLE)
                        keep = ~infeasible
                        act, alpha, capped = act[keep], alpha[keep], capped[keep]
                else:
                    alpha, capped = self._solve(act, cur, damping[act])
                u = cur["z0"][act][:, spec.unknown_index]
                scaled = (alpha.abs() / torch.maximum(u.abs(), scale[act])).amax(dim=1)
                bad = ~(torch.isfinite(alpha).all(dim=1) & torch.isfinite(scaled))
                if bool(bad.any()):
                    stop(act[bad], Status.DIVERGED, " The update alpha became non-finite.")
                    keep = ~bad
                    act, alpha, scaled, capped = act[keep], alpha[keep], scaled[keep], capped[keep]
                self._annotate(act, alpha=alpha, alpha_norm=scaled, damping=damping[act],
                               rejected=rejected_count[act])
                # convergence, tested on undamped steps only
                zero = damping[act] == 0
                sse = cur["sse"][act]
                conv = zero & (scaled <= spec.xtol)
                conv_sse = (zero & ~conv & torch.isfinite(sse_prev[act]) & (sse > 0)
                            & ((sse - sse_prev[act]).abs() <= spec.ftol * sse) & (scaled <= math.sqrt(spec.xtol)))
                sse_prev[act[zero & ~conv & ~conv_sse]] = sse[zero & ~conv & ~conv_sse]
                done = conv | conv_sse
                if bool(done.any()):
                    rows = act[done]
                    W = cur["W"][rows]
                    z0[rows] = _shifted(cur["z0"][rows], alpha[done], spec.unknown_index)
                    iterations[rows] += 1
                    final_guess[rows] = W[..., 0] + torch.einsum("sgmk,sk->sgm", W[..., 1:], alpha[done])
                    self._annotate(rows, model_merit=self._model_merit(rows, cur))
                    self._notify(rows)
                    if bool(conv.any()):
                        stop(act[conv], Status.CONVERGED)
                    if bool(conv_sse.any()):
                        stop(act[conv_sse], Status.CONVERGED_SSE)
                    act, alpha, capped = act[~done], alpha[~done], capped[~done]
                if not act.numel():
                    continue
                trial, ok = self._propose(act, cur, alpha)
                if spec.damping is None:
                    accept = ok
                elif spec.method == "shooting":  # the merit is the model's own sum of squares
                    accept = ok & (trial["merit"] <= cur["merit"][act] * (1 + _MERIT_SLACK))
                else:
                    # as fit's _better: the linear merit decides only for trials near solving the model
                    # whose step was not capped at a bound's largest internal move
                    better = ((trial["merit"] <= cur["merit"][act] * (1 + _MERIT_SLACK))
                              & (trial["defect"] <= DEFECT_TRUST) & ~capped)
                    check = ok & ~better
                    if bool(check.any()):
                        rows = check.nonzero().flatten()
                        t_sse = self._nonlinear_sse(act, trial, rows)
                        c_sse = self._nonlinear_sse(all_idx, cur, act[rows])
                        better[rows] = t_sse <= c_sse * (1 + _MERIT_SLACK)
                    accept = ok & better
                if bool(accept.any()):
                    rows = accept.nonzero().flatten()
                    target = act[rows]
                    self._annotate(target, model_merit=self._model_merit(target, cur))
                    self._notify(target)
                    _put(cur, target, trial, rows)
                    last_damping[target] = damping[target]
                    damping[target] = 0.0
                    iterations[target] += 1
                    fresh[target] = True
                    z0[target] = trial["z0"][rows]
                    final_guess[target] = _pick(trial["W"], rows)[..., 0]
                rejected = act[~accept]
                if not rejected.numel():
                    continue
                if spec.damping is None:  # the thesis' iteration: the step is taken, and fails
                    z0[rejected] = _shifted(cur["z0"][rejected], alpha[~accept], spec.unknown_index)
                    iterations[rejected] += 1
                    self._notify(rejected)
                    stop(rejected, Status.INTEGRATION_FAILED,
                         " The undamped step led to a trajectory that cannot be integrated; the default "
                         "damping=\"lm\" would have shortened it.")
                    continue
                rejected_count[rejected] += 1
                # Kantorovich re-anchors an undamped rejection about the model's own solution
                candidates = rejected[(damping[rejected] == 0) & ~cur["anchored"][rejected]]
                if spec.method == "shooting":  # always about the model's own solution already
                    candidates = candidates[:0]
                anchored_rows = candidates[:0]
                if candidates.numel():
                    self._nonlinear_sse(all_idx, cur, candidates)
                    integrable = torch.isfinite(cur["nl_traj"][candidates]).flatten(1).all(dim=1)
                    anchored_rows = candidates[integrable]
                    if anchored_rows.numel():
                        traj = cur["nl_traj"][anchored_rows]
                        lin = self._linearize(anchored_rows, traj)
                        anchored = self._evaluate(anchored_rows, cur["z0"][anchored_rows], traj, lin.f, lin)
                        anchored["anchored"][:] = True
                        anchored["nl_sse"] = cur["nl_sse"][anchored_rows]
                        anchored["nl_traj"] = traj
                        failed = anchored["failed"]
                        if bool(failed.any()):
                            self._fail_integration_rows(anchored_rows[failed], status, detail)
                        keep = (~failed).nonzero().flatten()
                        _put(cur, anchored_rows[keep], anchored, keep)
                        done_rows = anchored_rows[keep]
                        if self.history is not None:
                            for r in done_rows.tolist():
                                record = self.history[r][-1]
                                record.sse, record.merit = float(cur["sse"][r]), float(cur["merit"][r])
                                record.trajectory = cur["rz"][r, :, :n].detach().clone()
                raise_rows = rejected[~torch.isin(rejected, anchored_rows)]
                if raise_rows.numel():
                    d = damping[raise_rows]
                    last = last_damping[raise_rows]
                    first = torch.where(last > 0, torch.clamp(last / 10, min=_DAMPING_MIN), _DAMPING_START)
                    d = torch.where(d == 0, first, 10 * d)  # as fit's _first_damping, per sample
                    damping[raise_rows] = d
                    stalled = raise_rows[d > _DAMPING_MAX]
                    if stalled.numel():
                        self._annotate(stalled, rejected=rejected_count[stalled],
                                       model_merit=self._model_merit(stalled, cur))
                        self._notify(stalled)
                        stop(stalled, Status.STALLED)
        except TimeBudgetExceeded:  # inside a phase: the samples still running stop where they are
            stop((status == _RUNNING).nonzero().flatten(), Status.MAX_TIME)
        spent = [r for r, c in enumerate(status.tolist()) if c == _STATUSES.index(Status.MAX_TIME)]
        for r in spent:
            detail[r] = (f" Stopped after {int(iterations[r])} iterations (max_time = {self.max_time:g} s)."
                         + detail[r])
        with no_time_budget():  # the samples that finished in time get their final evaluation
            return self._finish(z0, status, detail, iterations, final_guess)

    def _fail_integration(self, failed, status, detail) -> None:
        self._fail_integration_rows(failed.nonzero().flatten(), status, detail)

    def _fail_integration_rows(self, rows, status, detail) -> None:
        for r in rows.tolist():
            status[r] = _STATUSES.index(Status.INTEGRATION_FAILED)
            said = self.propagation_errors.get(r, "the transfer of a grid interval did not meet the tolerance or "
                                               "became non-finite")
            detail[r] = f" The solver said: {said}."

    def _propose(self, act, cur, alpha):
        """The trial iterates from ``cur``'s samples ``act`` with updates ``alpha``; ``ok`` where usable."""
        spec = self.spec
        W = _pick(cur["W"], act)
        z_new = W[..., 0] + torch.einsum("sgmk,sk->sgm", W[..., 1:], alpha)
        z0_new = _shifted(_pick(cur["z0"], act), alpha, spec.unknown_index)
        if spec.method == "shooting":
            return self._shoot(act, z0_new, z_new)
        finite = torch.isfinite(z_new).flatten(1).all(dim=1)
        z_ref = _pick(cur["rz"], act)
        z_safe = torch.where(finite.reshape(-1, 1, 1), z_new, z_ref)
        lin_ref = cur["lin"]
        z_dot = _pick(lin_ref.f, act) + torch.einsum("sgij,sgj->sgi", _pick(lin_ref.jac, act), z_safe - z_ref)
        lin = self._linearize(act, z_safe, z_dot)
        trial = self._evaluate(act, z0_new, z_safe, z_dot, lin)
        trial["defect"] = model_defect(lin.f, z_dot, self.system.n)
        ok = (finite & ~trial["failed"] & torch.isfinite(trial["merit"])
              & torch.isfinite(trial["C"]).flatten(1).all(dim=1))
        return trial, ok

    def _data_start(self, idx, z0):
        """Each sample's first reference from its data (:func:`torchql.data_start.data_reference`,
        as ``fit`` builds it): ``z_ref, z_dot (S, G, M)`` and the guesses ``z0 (S, M)`` with the
        coefficients from the gradient matching. A sample on its own grid gets it on its own
        nodes, the padding repeating the last one."""
        spec = self.spec
        S, M = z0.shape
        z_ref = z0.new_empty(S, self.G, M)
        z_dot = torch.zeros_like(z_ref)
        z0 = z0.clone()
        y = torch.where(self.mask, self.y, torch.full_like(self.y, float("nan")))
        sigma = torch.where(self.mask, 1.0 / self.w.clamp(min=torch.finfo(self.w.dtype).tiny), torch.ones_like(self.w))
        ends = (_last_nodes(self.grid) + 1).tolist() if self.grid.dim() == 2 else [self.G] * S
        for k, s in enumerate(idx.tolist()):
            grid = self.grid[s, :ends[k]] if self.grid.dim() == 2 else self.grid
            t_obs = self.t_obs[s] if self.t_obs.dim() == 2 else self.t_obs
            ref, slope, z0[k] = data_reference(self.system, grid, t_obs, y[s], sigma[s], self.mask[s],
                                               spec.operator.observed_states, z0[k], spec.unknown_index,
                                               spec.bounds, spec.rcond)
            z_ref[k, :ends[k]], z_ref[k, ends[k]:] = ref, ref[-1]
            z_dot[k, :ends[k]] = slope
        return z_ref, z_dot, z0

    def _shoot(self, act, z0_new, z_new):
        """Shooting's trial iterates: each sample's model integrated from ``z0_new (S, M)`` (the
        linear prediction ``z_new`` its guess), with its sensitivities; ``ok`` where it integrates."""
        guess = torch.where(torch.isfinite(z_new), z_new, z0_new.unsqueeze(1).expand_as(z_new))
        traj, errors = self._nonlinear(act, z0_new, loose=False, guess=guess, budget_is_final=True)
        integrated = torch.tensor([e is None for e in errors], dtype=torch.bool, device=z0_new.device)
        traj = torch.where(integrated.reshape(-1, 1, 1), traj, guess)  # failed samples: any finite stand-in
        lin = self._linearize(act, traj)
        trial = self._evaluate(act, z0_new, traj, lin.f, lin, solution=True)
        trial["defect"] = torch.zeros_like(trial["merit"])
        ok = (integrated & ~trial["failed"] & torch.isfinite(trial["merit"])
              & torch.isfinite(trial["C"]).flatten(1).all(dim=1))
        return trial, ok


def _shifted(z0: torch.Tensor, alpha: torch.Tensor, unknown_index: torch.Tensor) -> torch.Tensor:
    z = z0.clone()
    z[:, unknown_index] = z0[:, unknown_index] + alpha
    return z


#: Entries of a trial iterate that only decide its acceptance and are not kept.
_TRIAL_ONLY = ("failed", "defect")


def _put(cur: dict, target: torch.Tensor, new: dict, rows: torch.Tensor) -> None:
    """Copy samples ``rows`` of ``new`` into samples ``target`` of ``cur`` (sorted, distinct indices).

    When ``target`` is every sample of ``cur`` and ``rows`` every sample of ``new``, ``cur`` takes
    ``new``'s arrays instead of copying them (``new`` is not used after).
    """
    if target.numel() == cur["z0"].shape[0] and rows.numel() == new["z0"].shape[0]:
        for key, value in new.items():
            if key not in _TRIAL_ONLY:
                cur[key] = value
        return
    for key, value in new.items():
        if key in _TRIAL_ONLY:
            continue
        if key == "lin":
            for old, fresh in zip(cur["lin"], value):
                old[target] = fresh[rows]
        else:
            cur[key][target] = value[rows]
