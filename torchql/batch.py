"""The quasilinearization engine: ``S >= 1`` samples, each on its own iteration, and ``fit_many``.

This module holds the package's one iteration loop (:class:`_Engine`). :func:`torchql.fit` runs
it with one sample and keeps every iterate's record; :func:`fit_many` runs it over a batch.

A fleet of vehicles each with its coast-down log, a Monte Carlo study of noise, a multi-start,
a parameter sweep: ``B`` datasets with the same number ``T`` of observation times, shared or
each its own (one batched :class:`~torchql.Observations`, values ``(B, T, K)`` and times
``(T,)`` or ``(B, T)``, or a list of them), fitted with one model. The iteration (Kantorovich or
shooting; the undamped quasilinearization step tried first and kept when it lowers the sum of
squares, re-anchoring and Levenberg–Marquardt damping otherwise; the convergence tests and
statuses) is vectorized over the samples with per-sample masks:

* every sample has its own coefficients as trailing components of its augmented state, so one
  vmapped Jacobian linearizes all samples at every grid node at once
  (:func:`torchql.linearize.linearize` over ``samples x nodes``);
* samples sharing their times share one storage grid ``(G,)``; samples with their own times
  each have the grid :func:`torchql.fit` builds for that dataset, stacked ``(S, G)`` and padded
  at the end by repeating the last node (zero-length intervals, transferred by the identity),
  with the observation nodes per sample ``(S, T)``;
* the linear system is propagated with each grid interval of each sample under its own error
  control (:mod:`torchql.batch_integrate`): no sample's error is diluted by another's;
* the least-squares update is a batched SVD with each sample's own damping (samples with values
  marked ``exact``: each by :func:`torchql.lstsq.solve_update`, those rows met exactly);
* each sample stops when it converges or fails, with its own status and message, and drops out
  of the work (the engine only computes on the samples still running).

Each sample's result equals that of ``torchql.fit`` on that dataset alone, which is the same
loop over one sample.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence

import torch
from torch.func import vmap

from . import _checks
from .batch_integrate import _last_nodes, integrate_each, dopri_batch, propagate_linear_batch, solve_on_grid_batch
from .batch_result import BatchFitResult
from .diagnosis import final_status, null_detail, typical_magnitudes
from .bounds import Bounds, at_bound_note, moved_guesses_note, moved_record
from .budget import TimeBudgetExceeded, no_time_budget, time_budget, time_left
from .data_start import data_reference
from .options import DAMPING_MAX as _DAMPING_MAX, DAMPING_MIN as _DAMPING_MIN, DAMPING_START as _DAMPING_START
from .grid import make_grid
from .integrate import check_solver
from .solvers import STIFF_SOLVERS, rodas5p_batch
from .stiffness import choose_solver, linear_solver_for
from .linearize import Linearization, linearize
from .lstsq import ExactRowsError, solve_update
from .propagators import LinearPropagator
from .superposition import DEFAULT_LINEAR_SOLVER, check_linear_solver
from .model import AugmentedSystem, ODEModel, coefficient_names, model_dtype_device
from .observations import ObservationOperator, Observations
from .options import Limits, Tolerances, check_damping, check_scheme
from .trajectory import DEFECT_TRUST, model_defect
from .result import IterationRecord, Status
from .integrate import IntegrationError
from .superposition import propagate_linear
from .trajectory import LinearizedReference
from .uncertainty import covariance

__all__ = ["fit_many"]

#: Samples fitted together by default (bounds the memory: a chunk holds ``(chunk, G, M, 1 + m)``
#: solutions and ``(chunk, G, M, M)`` Jacobians).
DEFAULT_CHUNK = 4096
#: Largest ``samples x intervals`` for which the final nonlinear solution is found by multiple
#: shooting from the last linear prediction (all intervals at once, Newton on the node defects,
#: with Jacobians); above it the batched Dormand–Prince integrator, whose rounds advance every
#: sample at once, costs less.
_SHOOTING_POINTS = 20_000
_STATUSES = list(Status)
_RUNNING = -1
#: Newton iterations the grid solver gets from a trajectory's linear prediction before the
#: adaptive solver takes over (from a good prediction it needs two or three).
_GRID_NEWTON = 8
#: Most RK4 steps per grid interval in that solver: an interval that needs more (a trajectory
#: that blows up, a stiff stretch) is left to the adaptive solver rather than subdivided further.
_GRID_SUBSTEPS, _GRID_SUBSTEPS_LOOSE = 32, 16
#: RK4 steps over the whole span beyond which a trial step's trajectory counts as a blow-up
#: (spread over the grid's intervals; on the default grid the per-interval caps above bind).
_BLOWUP_STEPS = 16384
#: Tolerance of the first Kantorovich reference, integrated from the guesses.
_LOOSE_RTOL = 1e-6
#: A trial step is accepted when its merit is at most ``(1 + _MERIT_SLACK)`` times the current one
#: (rounding of the sums of squares must not reject a converging step).
_MERIT_SLACK = 1e-10
#: Weight of the exact rows' squared misfit in the merit (exact values are constraints).
_EXACT_PENALTY = 1e6


def fit_many(
    model: ODEModel,
    data: Observations | Sequence[Observations],
    x0=None,
    *,
    params: Sequence[str] | None = None,
    guesses: dict | None = None,
    fixed_x0: Sequence[str] | None = None,
    t0: float | None = None,
    method: str = "kantorovich",
    bounds: dict | None = None,
    initial_trajectory: str = "integrate",
    max_iter: int = 50,
    max_time: float | None = None,
    rtol: float | None = None,
    atol: float | None = None,
    xtol: float | None = None,
    ftol: float | None = None,
    rcond: float | None = None,
    grid: int | torch.Tensor | None = None,
    damping: str | None = "lm",
    solver: str = "auto",
    linear_solver: "str | LinearPropagator | None" = None,
    max_steps: int | None = None,
    chunk_size: int = DEFAULT_CHUNK,
    progress: bool | Callable[[int, int], None] = False,
    callback: Callable[[int, IterationRecord], None] | None = None,
) -> BatchFitResult:
    """Fit ``B`` independent datasets with one model, each to its own estimates.

    Parameters
    ----------
    model : ODEModel
        The model; its coefficients' values (float buffers, and float ``nn.Parameter`` objects treated
        alike) are the guesses (unless ``guesses`` gives per-sample ones). Float32 or float64.
        Never modified.
    data : Observations holding a batch, or list of Observations
        The ``B`` datasets: one :class:`~torchql.Observations` with values ``(B, T, K)`` and
        times ``t (T,)`` shared or ``(B, T)`` per sample (validated once, the fast way to build
        many), or a list of ``B`` one-dataset Observations, stacked to values ``(B, T, K)``;
        both give the same fits. A list's datasets may have their own times ``t (T,)`` but must
        have the same number ``T`` of them, the same ``observe`` specification (the same names,
        matrix, or callable object) and all or none give ``sigma``, as a batch's do. Each sample
        has its own values, missing values (NaN) and ``sigma``; with its own times it is fitted
        on the grid ``torchql.fit`` builds for it alone. Values marked ``exact`` are met
        exactly, as in :func:`torchql.fit`.
    x0 : Tensor ``(B, n_states)`` or ``(n_states,)``, optional
        Initial-state guesses at ``t0`` (one row per sample, or one row for all). If omitted,
        every state must be observed directly at ``t0`` in every sample. Its values are copied.
    t0 : float, optional
        Time of ``x0`` (the model's time unit), shared by every sample and not later than any
        sample's first observation time. Default: each sample's own first observation time
        (the shared first time when the samples share their times).
    params : sequence of str, optional
        Coefficients to estimate (default: every float buffer and parameter not in the model's
        ``constants``).
    method : {"kantorovich", "shooting"}
        As in :func:`torchql.fit`: ``"shooting"`` integrates each sample's model from its
        updated initial state (batched) at every trial step, with its sensitivities.
    bounds : dict, optional
        ``{name: (lower, upper)}`` as in :func:`torchql.fit`, the same for every sample: bounded
        unknowns are iterated in the same transformed variables, each sample's guesses on or
        outside a bound are moved inside as ``fit`` moves them (``batch[i].moved_guesses``), and
        an estimate at a bound is named in that sample's message.
    guesses : dict of str to Tensor, optional
        Per-sample values of buffers: ``{name: (B, *shape) or (*shape)}``. For a buffer in
        ``params`` they are the guesses; for another buffer (a vehicle's mass) they are that
        sample's fixed value. Default: the model's buffers for every sample.
    max_time : float, optional
        Wall-clock budget in seconds for the whole batch, checked between iterations and inside
        long phases. When it runs out, every sample still running (or not yet started, in a
        later chunk) ends with ``Status.MAX_TIME`` at its last accepted estimates (NaN ``sse``
        and covariance); samples that finished before still get their final evaluation.
        Default: none.
    fixed_x0, max_iter, rtol, atol, xtol, ftol, rcond, grid, damping, solver, max_steps
        As in :func:`torchql.fit`.
    initial_trajectory : {"integrate", "data"}
        As in :func:`torchql.fit` (Kantorovich only): ``"data"`` builds each sample's first
        reference from its own data (smoothed observed states, derived hidden states, coefficients
        fitted to the slopes), with no integration from the guesses; one sample after another.
        ``solver="auto"`` (default) decides as ``fit`` does, once for the batch: ``"rodas5p"``
        when some sample's model is stiff along its data (:mod:`torchql.stiffness`), else
        ``"dopri5"``. With ``"rodas5p"`` (stiff models) every nonlinear pass is the batched
        implicit :func:`torchql.solvers.rodas5p_batch` and the grid gains early geometric nodes, as
        in ``fit``; otherwise ``solver`` integrates a sample on its own only when the batched
        Dormand–Prince cannot (as ``fit`` falls back to it).
    linear_solver : str or LinearPropagator, optional
        As in :func:`torchql.fit` (default ``"radau"`` with a stiff solver, else ``"taylor"``).
        Propagators with a batched form (``LinearPropagator.batched``: ``"taylor"``, ``"radau"``,
        ``"exponential"``) take every sample at once; the others each sample in turn.
    chunk_size : int
        Samples fitted together (default 4096); larger batches are fitted chunk after chunk.
        The results do not depend on it.
    progress : bool or callable
        ``True``: a progress bar (``tqdm``, from the extra ``torchql[progress]``) counting the
        samples finished; a callable receives ``(finished, total)`` as samples finish.
    callback : callable, optional
        Called as ``callback(sample, record)`` with each sample's :class:`IterationRecord` as it
        is completed (as :func:`torchql.fit`'s callback, with the sample's index).

    Returns
    -------
    BatchFitResult
        Per-sample estimates, statuses, messages, iterations, SSE and covariance; its ``t0`` is
        a float when the samples share it, else each sample's ``(B,)``.

    Raises
    ------
    TypeError, ValueError
        For invalid arguments (naming the argument, the sample, what was expected and received).
    """
    spec = _Spec(model, data, x0, params, guesses, fixed_x0, t0, max_iter, rtol, atol, xtol, ftol, rcond, grid,
                 damping, solver, max_steps, bounds, linear_solver, method, initial_trajectory)
    chunk_size = _checks.positive_int("chunk_size", chunk_size)
    max_time = Limits.resolve(max_time=max_time).max_time
    if callback is not None and not callable(callback):
        raise TypeError("`callback` must be callable (it receives each sample's index and IterationRecord); "
                        f"received {callback!r}")
    result = run_engine(spec, chunk_size, max_time, _progress(progress, spec.B), callback=callback)
    result.data = data
    result.fit_kwargs = dict(
        params=None if params is None else list(params), fixed_x0=None if fixed_x0 is None else list(fixed_x0),
        t0=t0, method=method, max_iter=max_iter, max_time=max_time, solver=solver, rtol=rtol, atol=atol,
        xtol=xtol, ftol=ftol, rcond=rcond, grid=grid, initial_trajectory=initial_trajectory, max_steps=max_steps,
        damping=damping, linear_solver=linear_solver, bounds=None if bounds is None else dict(bounds))
    return result


def run_engine(spec: "_Spec", chunk_size: int, max_time: float | None, report: Callable[[int | None], None],
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
                engine = _Engine(spec, index, max_time, history=history, callback=callback)

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


def _progress(progress, total: int) -> Callable[[int | None], None]:
    """A function of the number of samples finished (``None``: close)."""
    if progress is False or progress is None:
        return lambda done: None
    if callable(progress) and not isinstance(progress, bool):
        last = [-1]

        def call(done):
            if done is not None and done != last[0]:
                last[0] = done
                progress(done, total)
        return call
    if progress is not True:
        raise TypeError(f"`progress` must be a bool or a callable (finished, total); received {progress!r}")
    try:
        from tqdm.auto import tqdm
    except ImportError:
        warnings.warn('`progress=True` needs tqdm: pip install "torchql[progress]"; continuing without a bar',
                      UserWarning, stacklevel=3)
        return lambda done: None
    bar = tqdm(total=total, unit="fit", desc="fit_many")

    def update(done):
        if done is None:
            bar.close()
        elif done > bar.n:
            bar.update(done - bar.n)
    return update


# ----------------------------------------------------------------------------------------------
class _Spec:
    """The validated problem shared by every chunk: model, data stacked ``(B, T, K)``, guesses, grid.

    Times: ``t_obs (T,)``, ``t0 ()``, ``grid (G,)`` and ``obs_in_grid (T,)`` when the samples share
    them (``grid_size`` is ``None``); else ``t_obs (B, T)``, ``t0 ()`` or ``(B,)``, each sample's
    grid padded ``grid (B, G)`` with its own number of nodes ``grid_size (B,)``, ``obs_in_grid (B, T)``.
    """

    def __init__(self, model, data, x0, params, guesses, fixed_x0, t0, max_iter, rtol, atol, xtol, ftol, rcond,
                 grid, damping, solver, max_steps, bounds=None, linear_solver=None,
                 method="kantorovich", initial_trajectory="integrate", single: bool = False) -> None:
        self.single = single  # torchql.fit's problem: one dataset, errors worded for it
        _checks.model_class(model)
        names = tuple(model.state_names)
        n = len(names)
        if not isinstance(solver, str):
            raise TypeError(f"`solver` must be a string; received {type(solver).__name__}")
        check_solver(solver, auto=True)
        self.damping, self.solver = check_damping(damping), solver
        self.method, self.initial_trajectory = check_scheme(method, initial_trajectory)
        if linear_solver is not None:
            check_linear_solver(linear_solver)
        limits = Limits.resolve(max_iter, max_steps)
        self.max_iter, self.max_steps = limits.max_iter, limits.max_steps
        self.dtype, self.device = dtype, device = model_dtype_device(model)
        tol = Tolerances.resolve(dtype, rtol, atol, xtol, ftol, rcond)
        self.rtol, self.atol, self.xtol, self.ftol, self.rcond = tol.rtol, tol.atol, tol.xtol, tol.ftol, tol.rcond

        # --- data: (B, T, K)
        self._stack(data, dtype, device)
        B = self.B

        # --- unknowns and per-sample buffers
        available = coefficient_names(model)
        if params is None:
            params = [name for name in available if name not in tuple(model.constants)]
        else:
            params = _checks.distinct_names("params", params, available, "buffer", _checks.coefficients_text(model))
        if guesses is None:
            guesses = {}
        if not isinstance(guesses, dict):
            raise TypeError(f"`guesses` must be a dict {{buffer name: Tensor (B, ...)}}; received {type(guesses).__name__}")
        for name in guesses:
            if name not in available:
                raise ValueError(f"`guesses` names unknown buffer {name!r}; {_checks.coefficients_text(model)}")
        per_sample = list(params) + [name for name in guesses if name not in params]
        self.params = list(params)
        self.system = AugmentedSystem(model, per_sample, dtype, device)
        system = self.system
        buffers = dict(system.model.named_buffers())
        columns = []
        for name, shape in zip(per_sample, system.param_shapes):
            value = guesses.get(name, buffers[name])
            try:
                value = torch.as_tensor(value, dtype=dtype, device=device).detach()
            except (TypeError, ValueError) as exc:
                raise TypeError(f"`guesses[{name!r}]` must be a tensor of shape (B, *{tuple(shape)}) = "
                                f"{(B, *shape)}; received {type(value).__name__}") from exc
            if value.shape == shape:
                value = value.expand(B, *shape)
            elif value.shape != (B, *shape):
                raise ValueError(f"`guesses[{name!r}]` must have shape (B, *buffer shape) = {(B, *shape)} or the "
                                 f"buffer's shape {tuple(shape)}; received shape {tuple(value.shape)}")
            bad = ~torch.isfinite(value.reshape(B, -1)).all(dim=1)
            if bool(bad.any()) and name not in guesses:
                raise ValueError(f"the guesses of [{name!r}] (the model's buffers) must be finite")
            if bool(bad.any()):
                raise ValueError(f"`guesses[{name!r}]` must be finite; samples {bad.nonzero().flatten().tolist()[:10]} "
                                 "hold NaN or inf")
            columns.append(value.reshape(B, -1))
        p0 = torch.cat(columns, dim=1) if columns else torch.zeros(B, 0, dtype=dtype, device=device)
        if not bool(torch.isfinite(p0).all()):
            raise ValueError(f"the guesses of {self.params} (the model's buffers) must be finite")

        # --- times: t_obs (T,) shared or (B, T) per sample, t0 () shared or (B,) per sample
        self.t_obs = self.t
        self.t0 = self._initial_time(t0)

        # --- initial states
        self.operator = ObservationOperator(self.observe, names, self.K, dtype, device)
        if x0 is None:
            x0 = self._x0_from_data(names)
        else:
            try:
                x0 = torch.as_tensor(x0, dtype=dtype, device=device).detach()
            except (TypeError, ValueError) as exc:
                if single:
                    raise TypeError(f"`x0` must be a tensor of shape (n_states,) = ({n},); "
                                    f"received {type(x0).__name__}") from exc
                raise TypeError(f"`x0` must be a tensor of shape (B, n_states) = ({B}, {n}) or (n_states,) = "
                                f"({n},); received {type(x0).__name__}") from exc
            if single and x0.shape != (n,):
                raise ValueError(f"`x0` must have shape (n_states,) = ({n},); received shape {tuple(x0.shape)}")
            if single and not bool(torch.isfinite(x0).all()):
                raise ValueError("`x0` must be finite; received NaN or inf")
            if x0.shape == (n,):
                x0 = x0.expand(B, n)
            elif x0.shape != (B, n):
                raise ValueError(f"`x0` must have shape (B, n_states) = ({B}, {n}) or (n_states,) = ({n},); "
                                 f"received shape {tuple(x0.shape)}")
            bad = ~torch.isfinite(x0).all(dim=1)
            if bool(bad.any()):
                raise ValueError(f"`x0` must be finite; rows {bad.nonzero().flatten().tolist()[:10]} hold NaN or inf")
        self.z0 = torch.cat([x0, p0], dim=1).clone()

        fixed_x0 = _checks.distinct_names("fixed_x0", [] if fixed_x0 is None else fixed_x0, names, "state",
                                          f"the model's states are {names}")
        free = [i for i, s in enumerate(names) if s not in fixed_x0]
        n_unknown_params = sum(size for name, size in zip(per_sample, system.param_sizes) if name in self.params)
        self.unknown_index = torch.tensor(free + list(range(n, n + n_unknown_params)), dtype=torch.long,
                                          device=device)
        self.unknown_names = [f"{names[i]}(t0)" for i in free] + system.element_names[:n_unknown_params]
        self.m = m = self.unknown_index.numel()
        if m == 0:
            raise ValueError("nothing to estimate: every initial state is in `fixed_x0` and `params` is empty")
        short = (self.L < m).nonzero().flatten().tolist()
        if short and self.single:
            raise ValueError(
                f"fewer usable observations ({int(self.L[0])}) than unknowns ({m}: {self.unknown_names}); "
                "add observations, or fix some unknowns with `params=`/`fixed_x0=`")
        if short:
            i = short[0]
            raise ValueError(f"`data[{i}]` has {int(self.L[i])} usable values, fewer than the {m} unknowns "
                             f"{self.unknown_names}" + (f" (samples {short[:10]} alike)" if len(short) > 1 else "")
                             + "; remove it from the batch or fix some unknowns")
        marked = self.exact.flatten(1).sum(dim=1)
        over = (marked > m).nonzero().flatten().tolist()
        if over:
            where = "" if self.single else f"`data[{over[0]}]`: "
            raise ValueError(
                f"{where}more values are marked `exact` ({int(marked[over[0]])}) than there are unknowns ({m}); "
                "at most one exact value per unknown can be met")
        # --- bounds, the same for every sample (guesses on or outside one moved inside, per sample)
        # (the estimated coefficients come first among the per-sample ones, so the zip stops at them)
        self.bounds = Bounds.for_unknowns(bounds, self.unknown_names, len(free), self.params, system.param_sizes,
                                          list(names) + list(available), dtype, device)
        self.moved_guesses: dict[int, dict[str, tuple[float, float]]] = {}
        if self.bounds.active:
            given = self.z0[:, self.unknown_index]
            used, moved = self.bounds.move_inside(given)
            for b in moved.any(dim=1).nonzero().flatten().tolist():
                self.moved_guesses[b] = moved_record(self.unknown_names, given[b], used[b], moved[b])
            self.z0[:, self.unknown_index] = used
            x0 = self.z0[:, :n]
        self._check_model(x0[0])

        # --- the solver ("auto": stiff if some sample's model is stiff along its data)
        self.solver = choose_solver(self.solver, system, self.t_obs,
                                    torch.where(self.mask, self.y, torch.full_like(self.y, float("nan"))),
                                    self.operator.observed_states, x0, self.z0[:, n:],
                                    (self.t_obs[..., -1] - self.t0).expand(B))
        self.linear_solver = check_linear_solver(linear_solver_for(self.solver, linear_solver, DEFAULT_LINEAR_SOLVER))

        # --- grid: (G,) shared, or (B, G) per sample (each fit's own grid, padded by its last node)
        if self.t_obs.dim() == 1:
            self.grid = make_grid(grid, self.t0, self.t_obs, stiff=self.solver in STIFF_SOLVERS)
            self.grid_size = None
        else:
            self.grid, self.grid_size = _make_grids(grid, self.t0, self.t_obs, stiff=self.solver in STIFF_SOLVERS)
        self.obs_in_grid = torch.searchsorted(self.grid, self.t_obs)
        self.model = model

    def _initial_time(self, t0) -> torch.Tensor:
        """``t0``: the first observation time (each sample's own, ``(B,)``, when times are per sample)
        or the given time, shared ``()``, not later than any sample's first observation."""
        first = self.t_obs[..., 0]
        if t0 is None:
            if first.dim() == 1 and bool((first == first[0]).all()):
                first = first[0]  # the samples' times differ, not their first: t0 shared
            return first.clone()
        value = torch.as_tensor(_checks.finite_number("t0", t0), dtype=self.dtype, device=self.device)
        late = (value > first).reshape(-1).nonzero().flatten().tolist()
        if late:
            if self.t_obs.dim() == 1:
                raise ValueError(f"`t0` must not be later than the first observation time "
                                 f"{self.t_obs[0].item():g}; received {float(t0):g}")
            alike = f" (samples {late[:10]} alike)" if len(late) > 1 else ""
            raise ValueError(f"`t0` must not be later than the first observation time of any sample; `data[{late[0]}]` "
                             f"starts at {first[late[0]].item():g}{alike}, received t0 = {float(t0):g}")
        return value

    # ------------------------------------------------------------------------------------------
    def _stack(self, data, dtype, device) -> None:
        data = check_data(data)
        if isinstance(data, Observations):
            first, y, sigma, exact = data, data.y, data.sigma, data.exact
            t = data.t.to(dtype=dtype, device=device)
            low = [("data", data.y.dtype)] if _coarser(data.y.dtype, dtype) else []
        else:
            first = data[0]
            t = torch.stack([d.t.to(dtype=dtype, device=device) for d in data])
            exact = torch.stack([d.exact for d in data])
            y = torch.stack([d.y.to(dtype) for d in data])
            sigma = torch.stack([d.sigma.to(dtype) for d in data])
            low = [("data" if self.single else f"data[{i}]", d.y.dtype) for i, d in enumerate(data)
                   if _coarser(d.y.dtype, dtype)]
        self.B = y.shape[0]
        if low:
            warnings.warn(f"`{low[0][0]}` holds {low[0][1]} values but the model computes in {dtype}: the data's own "
                          "rounding limits the fit's accuracy; build the Observations from float64 tensors",
                          UserWarning, stacklevel=4)
        if t.dim() == 2 and bool((t == t[:1]).all()):
            t = t[0]  # every sample at the same times: the shared grid serves them all
        self.t = t  # (T,) or (B, T)
        self.observe = first.observe
        self.K = y.shape[-1]
        self.sigma_known = first.sigma_given
        y = y.to(dtype=dtype, device=device)
        self.mask = ~torch.isnan(y)  # (B, T, K)
        self.exact = exact.to(device) & self.mask  # (B, T, K): values to be met exactly
        self.has_exact = bool(self.exact.any())
        self.y = torch.where(self.mask, y, torch.zeros_like(y))
        self.weights = torch.where(self.mask, 1.0 / sigma.to(dtype=dtype, device=device), torch.zeros_like(y))
        self.L = self.mask.flatten(1).sum(dim=1)  # (B,)

    def _x0_from_data(self, names) -> torch.Tensor:
        early = (self.t0 != self.t_obs[..., 0]).reshape(-1)
        if bool(early.any()):
            where = "" if self.t_obs.dim() == 1 else f" (as in `data[{int(early.nonzero()[0, 0])}]`)"
            raise ValueError(f"`x0` is required when `t0` precedes the first observation{where}")
        x0 = torch.full((self.B, len(names)), float("nan"), dtype=self.dtype, device=self.device)
        for k, i in enumerate(self.operator.observed_states):
            if i is not None:
                x0[:, i] = torch.where(self.mask[:, 0, k], self.y[:, 0, k], x0[:, i])
        missing = torch.isnan(x0)
        if bool(missing.any()):
            b = int(missing.any(dim=1).nonzero()[0, 0])
            states = [names[i] for i in range(len(names)) if bool(missing[b, i])]
            if self.single:
                raise ValueError(f"`x0` is required: the states {states} are not observed directly at t0")
            raise ValueError(f"`x0` is required: in `data[{b}]` the states {states} are not observed directly at t0")
        return x0

    def _check_model(self, x0: torch.Tensor) -> None:
        """The forward on sample 0's guesses (in-place updates, shape, dtype, finite; differentiable
        with torch.func), then finite on every sample's guesses, vectorized."""
        system = self.system
        t0 = self.t0.expand(self.B)

        def check(b: int, sample: str = "") -> None:
            p = self.z0[b, system.n:]
            _checks.model_forward(lambda t, x: system.rhs(t, x, p), t0[b], self.z0[b, :system.n],
                                  system.state_names, dict(zip(system.element_names, p.tolist())), self.dtype,
                                  sample)

        check(0)
        try:
            linearize(system, t0[:1], self.z0[:1])
        except Exception as exc:  # noqa: BLE001
            raise ValueError("`model` forward could not be differentiated with torch.func (jacfwd and jvp under vmap): "
                             f"{exc}. Avoid .item(), in-place updates of inputs and Python branching on tensor "
                             "values.") from exc
        with torch.no_grad():
            finite = torch.isfinite(vmap(system.f)(t0, self.z0)).all(dim=1)
        bad = (~finite).nonzero().flatten().tolist()
        if bad:
            check(bad[0], f" of `data[{bad[0]}]`" + (f" (samples {bad[:10]} alike)" if len(bad) > 1 else ""))
        self.operator.check(x0)

    # ------------------------------------------------------------------------------------------
    def result(self, z0, out, statuses, messages, nfev) -> BatchFitResult:
        system, n, B = self.system, self.system.n, self.B
        params = self._params_of(z0)
        dof = self.L - self.m
        if self.sigma_known:
            variance = torch.ones(B, dtype=self.dtype, device=self.device)
        else:
            variance = torch.where(dof > 0, out["sse"] / dof.clamp(min=1).to(self.dtype),
                                   torch.full_like(out["sse"], float("nan")))
        return BatchFitResult(
            success=torch.tensor([s.success for s in statuses], dtype=torch.bool, device=self.device),
            status=statuses, message=messages, params=params, x0=z0[:, :n].clone(),
            t0=float(self.t0) if self.t0.dim() == 0 else self.t0.clone(),
            unknown_names=list(self.unknown_names), estimates=z0[:, self.unknown_index].clone(),
            iterations=out["iterations"], sse=out["sse"], covariance=out["cov"], n_observations=self.L.clone(),
            dof=dof, residual_variance=variance, sigma_known=self.sigma_known, nfev=nfev,
            model=system.user_model(), residuals=out["residuals"], jacobian=out["jacobian"],
            used=self.mask.reshape(B, -1).clone(), singular_values=out["singular_values"],
            exact=self.exact.reshape(B, -1).clone(), exact_residual=out["exact_residual"],
            start_params=self._params_of(self.z0), start_x0=self.z0[:, :n].clone(), sse_start=out["sse_start"],
            solver_options={"solver": self.solver, "rtol": self.rtol, "atol": self.atol},
            lower=self.bounds.lower.clone() if self.bounds.active else None,
            upper=self.bounds.upper.clone() if self.bounds.active else None,
            moved_guesses={b: dict(moved) for b, moved in self.moved_guesses.items()})


    def _params_of(self, z0: torch.Tensor) -> dict[str, torch.Tensor]:
        """Every float buffer per sample ``(B, *shape)`` for augmented states ``z0 (B, M)``."""
        system, B = self.system, self.B
        per_sample, start = {}, system.n
        for name, shape, size in zip(system.param_names, system.param_shapes, system.param_sizes):
            per_sample[name] = z0[:, start:start + size].reshape(B, *shape)
            start += size
        params = {}
        for name, value in system.model.named_buffers():
            if value.is_floating_point():
                params[name] = (per_sample[name] if name in per_sample else value.expand(B, *value.shape)).clone()
        return params


def check_data(data) -> Observations | list[Observations]:
    """``fit_many``'s ``data`` validated: one batched Observations as it is, or a list of datasets.

    A list must hold one-dataset Observations with the same number ``T`` of observation times
    (each its own times), the same ``observe`` specification and all or none giving ``sigma``
    (a batched Observations has them in common by construction). Errors name the argument and
    the dataset.
    """
    if isinstance(data, Observations):
        if data.batch_size is None:
            raise TypeError("`data` must be a list of torchql.Observations (one per dataset) or one Observations "
                            "holding a batch, values (B, T, K); received a single dataset, values "
                            f"{tuple(data.y.shape)} (a single dataset: use torchql.fit, or pass [data])")
        return data
    if not isinstance(data, (list, tuple)):
        raise TypeError("`data` must be a list of torchql.Observations (one per dataset) or one Observations "
                        f"holding a batch, values (B, T, K); received {type(data).__name__}")
    if len(data) == 0:
        raise ValueError("`data` is an empty list: give one torchql.Observations per dataset (B >= 1)")
    for i, d in enumerate(data):
        if not isinstance(d, Observations):
            raise TypeError(f"`data[{i}]` must be a torchql.Observations; received {type(d).__name__}")
        if d.batch_size is not None:
            raise ValueError(f"`data[{i}]` holds a batch of {d.batch_size} datasets, values {tuple(d.y.shape)}: "
                             "pass a batched Observations alone as `data`, not in a list")
    items = list(data)
    first = items[0]
    for i, d in enumerate(items[1:], start=1):
        if d.n_times != first.n_times:
            raise ValueError(f"`data[{i}]` has T = {d.n_times} observation times but `data[0]` has "
                             f"{first.n_times}: fit_many needs the same number of times in every dataset (each "
                             "may have its own times); fit datasets with other numbers of times in another batch")
        if not _same_observe(d.observe, first.observe) or d.n_outputs != first.n_outputs:
            raise ValueError(f"`data[{i}]` observes something else than `data[0]` (its `observe` differs); "
                             "fit_many needs one observation operator for all datasets (the same names, matrix "
                             "or callable object)")
        if d.sigma_given != first.sigma_given:
            raise ValueError(f"`data[{i}]` {'gives' if d.sigma_given else 'does not give'} `sigma` but "
                             f"`data[0]` {'does' if first.sigma_given else 'does not'}: give it for all or none")
    return items


def _coarser(data_dtype: torch.dtype, dtype: torch.dtype) -> bool:
    """Whether data of ``data_dtype`` are rounded more coarsely than the computation's ``dtype``."""
    return torch.finfo(data_dtype).eps > torch.finfo(dtype).eps


def _same_observe(a, b) -> bool:
    if a is b:
        return True
    if isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor):
        return a.shape == b.shape and torch.equal(a.to(torch.float64), b.to(torch.float64))
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return list(a) == list(b)
    try:
        import numpy as np

        if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
            return bool(np.array_equal(np.asarray(a), np.asarray(b)))
    except ImportError:  # pragma: no cover
        pass
    return False


#: The storage grid, shared with ``fit`` (:func:`torchql.grid.make_grid`).
_make_grid = make_grid


def _make_grids(grid, t0: torch.Tensor, t_obs: torch.Tensor, stiff: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Each sample's own grid, as :func:`torchql.fit` builds it for that dataset alone.

    ``t0``: shared ``()`` or per sample ``(B,)``; ``t_obs (B, T)``. Returns the grids ``(B, G)``,
    each padded at the end by repeating its last node up to the longest one's ``G`` nodes
    (zero-length intervals), and each grid's own number of nodes ``(B,)``. Samples with the
    same ``t0`` and times share one construction.
    """
    B = t_obs.shape[0]
    starts = t0.expand(B) if t0.dim() == 0 else t0
    keys, inverse = torch.unique(torch.cat([starts.unsqueeze(1), t_obs], dim=1), dim=0, return_inverse=True)
    grids = [make_grid(grid, key[0], key[1:], stiff=stiff) for key in keys]
    sizes = torch.tensor([g.numel() for g in grids], dtype=torch.long, device=t_obs.device)
    G = int(sizes.max())
    padded = torch.stack([torch.cat([g, g[-1:].expand(G - g.numel())]) for g in grids])
    return padded[inverse], sizes[inverse]


# ----------------------------------------------------------------------------------------------
class _Engine:
    """The iteration of one chunk of samples (indices ``index`` of the batch)."""

    def __init__(self, spec: _Spec, index: torch.Tensor, max_time: float | None = None, history: bool = False,
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

    # --- per-sample grids ---------------------------------------------------------------------
    def _grid_of(self, idx: torch.Tensor) -> torch.Tensor:
        """The grid of the chunk's samples ``idx``: the shared one ``(G,)``, or theirs ``(S, G)``."""
        return self.grid if self.grid.dim() == 1 else _pick(self.grid, idx)

    def _at_obs(self, x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        """Values ``x (S, G, ...)`` of the chunk's samples ``idx`` at their observation nodes: ``(S, T, ...)``."""
        if self.obs.dim() == 1:
            return x[:, self.obs]
        rows = torch.arange(x.shape[0], device=x.device).unsqueeze(1)
        return x[rows, _pick(self.obs, idx)]

    # --- building blocks ----------------------------------------------------------------------
    def _linearize(self, idx: torch.Tensor, z: torch.Tensor, z_dot: torch.Tensor | None = None) -> Linearization:
        """The linearization about ``z (S, G, M)`` (slopes ``z_dot``) of the chunk's samples ``idx``, at their nodes."""
        S, G, M = z.shape
        t = self.grid.repeat(S) if self.grid.dim() == 1 else _pick(self.grid, idx).reshape(-1)
        lin = linearize(self.system, t, z.reshape(-1, M), None if z_dot is None else z_dot.reshape(-1, M))
        self.nfev += S * G
        return Linearization(*(v.reshape(S, G, *v.shape[1:]) for v in lin))

    def _rows(self, idx, z_ref_obs, zp_obs, Z_obs):
        """``C (S, R, m)``, ``d (S, R)``, residuals ``(S, R)`` at the observations (zero where missing)."""
        n, K = self.system.n, self.spec.K
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
        return C.reshape(S, T * K, -1), d.reshape(S, -1), resid.reshape(S, -1)

    def _ssq(self, idx, residual, penalty: bool = False):
        """Weighted sums of squares ``(S,)`` of ``residual (S, R)``, the exact rows left out; with
        ``penalty``, the merit: plus ``_EXACT_PENALTY`` times their squared misfit."""
        r2 = (residual * _pick(self.w, idx).reshape(residual.shape)) ** 2
        if not self.spec.has_exact:
            return r2.sum(dim=1)
        exact = _pick(self.exact, idx)
        zero = torch.zeros((), dtype=r2.dtype, device=r2.device)
        total = torch.where(exact, zero, r2).sum(dim=1)
        return total + _EXACT_PENALTY * torch.where(exact, r2, zero).sum(dim=1) if penalty else total

    def _evaluate(self, idx, z0, z, z_dot, lin, solution: bool = False) -> dict:
        """Propagate each sample's linear system from ``z0 (S, M)`` about ``z``; rows at the observations.

        ``solution``: ``z`` is the model's own solution from ``z0`` (shooting), which then stands
        for the particular solution (its propagation would only add the propagator's error).
        """
        spec = self.spec
        W, failed = self._propagate(idx, z, z_dot, lin, _initial_columns(z0, spec.unknown_index))
        if solution:
            W[..., 0] = z
        W_obs = self._at_obs(W, idx)
        C, d, resid = self._rows(idx, self._at_obs(z, idx), W_obs[..., 0], W_obs[..., 1:])
        sse, merit = self._ssq(idx, resid), self._ssq(idx, d, penalty=True)
        S = idx.numel()
        return dict(z0=z0, rz=z, rzd=z_dot, lin=lin, W=W, C=C, d=d, sse=sse, merit=merit, failed=failed,
                    anchored=torch.zeros(S, dtype=torch.bool, device=z0.device),
                    nl_sse=torch.full_like(sse, float("nan")), nl_traj=torch.full_like(z, float("nan")))

    def _propagate(self, idx, z, z_dot, lin, w0):
        """The particular and homogeneous solutions ``W (S, G, M, 1 + m)`` of the chunk's samples
        ``idx`` about ``z`` from ``w0 (S, M, 1 + m)``, and ``failed (S,)``.

        A propagator with a batched form takes every sample at once
        (:func:`~torchql.batch_integrate.propagate_linear_batch`); another one each sample in turn
        (:func:`torchql.superposition.propagate_linear`), a failure marking that sample.
        """
        spec = self.spec
        if spec.linear_solver.batched:
            W, failed, evals = propagate_linear_batch(self._grid_of(idx), z, z_dot, lin, w0, rtol=spec.rtol,
                                                      atol=spec.atol, propagator=spec.linear_solver)
            self.nfev += evals
            return W, failed
        S, G = z.shape[:2]
        W = z.new_full((S, G, *w0.shape[1:]), float("nan"))
        failed = torch.zeros(S, dtype=torch.bool, device=z.device)
        grid = self._grid_of(idx)
        for k in range(S):
            t = grid if grid.dim() == 1 else grid[k]
            reference = LinearizedReference(t, z[k], z_dot[k], Linearization(*(v[k] for v in lin)))
            try:
                W[k], evals = propagate_linear(reference, w0[k], solver=spec.solver, rtol=spec.rtol, atol=spec.atol,
                                               max_steps=spec.max_steps, linear_solver=spec.linear_solver)
                self.nfev += evals
            except IntegrationError as exc:
                failed[k] = True
                self.propagation_errors[int(idx[k])] = str(exc)
        return W, failed

    def _nonlinear(self, idx, z0, loose: bool, guess=None, budget_is_final: bool = False):
        """The model integrated from ``z0 (S, M)`` over the grid of the chunk's samples ``idx``: ``traj (S, G, M)``
        and error messages (None: ok).

        ``loose`` integrates at ``_LOOSE_RTOL`` (or ``rtol`` if looser): enough for a first
        reference, or to rank two iterates far from the optimum. With a ``guess (S, G, M)`` (a
        prediction of the solution at the nodes: the last linear solution) and a problem of at
        most ``_SHOOTING_POINTS`` sample-intervals, by multiple shooting
        (:func:`~torchql.batch_integrate.solve_on_grid_batch`: every interval at once by RK4, at
        most ``_GRID_SUBSTEPS`` steps each, ``_GRID_SUBSTEPS_LOOSE`` when ``loose``, and no more
        than the user's ``max_steps``). A sample whose interval needs more is, with
        ``budget_is_final``, a blow-up and fails (a trial step: an adaptive solver would only crawl
        to the same failure, or through a stiff stretch that a step far from the current iterate
        led into; the damping shortens the step instead), an interval then being allowed
        ``_BLOWUP_STEPS / (G - 1)`` steps if that is more, so that a coarse grid does not turn a
        smooth trial into a blow-up. The other samples, or all without a guess, are integrated by
        :func:`~torchql.batch_integrate.dopri_batch` (``solver="dopri5"`` without a ``max_steps``), by the implicit
        :func:`~torchql.solvers.rodas5p_batch` (a stiff ``solver``), or each on its own by
        torchdiffeq with ``solver`` (another method, or where the batched Dormand–Prince fails),
        whose message is kept when it fails too.
        """
        spec = self.spec
        rtol = max(spec.rtol, _LOOSE_RTOL) if loose else spec.rtol
        atol = spec.atol * rtol / spec.rtol
        S, G = z0.shape[0], self.G
        grid = self._grid_of(idx)
        shared = grid.dim() == 1

        def grid_of(sub):
            return grid if shared else grid[sub]
        traj = torch.full((S, G, self.system.M), float("nan"), dtype=z0.dtype, device=z0.device)
        ok = torch.zeros(S, dtype=torch.bool, device=z0.device)
        errors: list = [None] * S
        substeps = _GRID_SUBSTEPS_LOOSE if loose else _GRID_SUBSTEPS
        if budget_is_final and G > 1:
            substeps = max(substeps, 1 << max(0, (_BLOWUP_STEPS // (G - 1)).bit_length() - 1))
        if spec.max_steps is not None:  # the user's step budget per grid interval binds this solver too
            substeps = min(substeps, 1 << (spec.max_steps.bit_length() - 1))
        stiff = spec.solver in STIFF_SOLVERS
        with torch.no_grad():
            if (guess is not None and S * (G - 1) <= _SHOOTING_POINTS and spec.linear_solver.grid_solver
                    and not stiff and substeps >= 2):
                usable = torch.isfinite(guess).flatten(1).all(dim=1)
                sub = usable.nonzero().flatten()
                if sub.numel():
                    tr, good, evals, over = solve_on_grid_batch(
                        self.system, z0[sub], grid_of(sub), rtol=rtol, atol=atol, guess=guess[sub],
                        max_newton=_GRID_NEWTON, max_substeps=substeps, report_budget=True)
                    self.nfev += evals
                    traj[sub[good]], ok[sub[good]] = tr[good], True
                    if budget_is_final:
                        for s in sub[over & ~good].tolist():
                            errors[s] = ("a grid interval needed more than the grid solver's "
                                         f"{substeps} steps (a blow-up)")
            todo = ~ok & torch.tensor([e is None for e in errors], dtype=torch.bool, device=z0.device)
            sub = todo.nonzero().flatten()
            if sub.numel() and (stiff or (spec.solver == "dopri5" and spec.max_steps is None)):
                land = None
                if (loose or stiff) and shared:  # onto the observation times, the rest interpolated
                    land = torch.zeros(G, dtype=torch.bool, device=z0.device)
                    land[self.obs] = True
                elif loose or stiff:
                    land = torch.zeros(sub.numel(), G, dtype=torch.bool, device=z0.device)
                    land.scatter_(1, self.obs[idx[sub]], True)
                if stiff:  # every sample by the implicit solver; its message kept for a failure
                    budget = {} if spec.max_steps is None else {"max_steps": spec.max_steps}
                    n = self.system.n
                    if sub.numel() == 1:  # one sample: its model with the coefficients bound, no vmap
                        sol = rodas5p_batch(self.system.model_with(z0[sub[0], n:]), z0[sub, :n], grid_of(sub),
                                            rtol=rtol, atol=atol, land=land, vectorize=False, **budget)
                        y = torch.cat([sol.y, z0[sub, n:].unsqueeze(1).expand(1, G, -1)], dim=2)
                    else:
                        sol = rodas5p_batch(self.system.f, z0[sub], grid_of(sub), rtol=rtol, atol=atol, land=land,
                                            error_components=n, **budget)
                        y = sol.y
                    self.nfev += sol.n_f
                    good = sol.ok
                    traj[sub[good]], ok[sub[good]] = y[good], True
                    for k, s in enumerate(sub.tolist()):
                        if not bool(good[k]):
                            errors[s] = sol.message(k)
                    return traj, errors
                tr, good, evals = dopri_batch(self.system, z0[sub], grid_of(sub), rtol=rtol, atol=atol, land=land)
                self.nfev += evals
                traj[sub[good]], ok[sub[good]] = tr[good], True
            todo = ~ok & torch.tensor([e is None for e in errors], dtype=torch.bool, device=z0.device)
            sub = todo.nonzero().flatten()
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
        return traj, errors

    def _nonlinear_sse(self, idx, it: dict, rows: torch.Tensor) -> torch.Tensor:
        """Cached nonlinear sums of squares of ``it``'s samples ``rows`` (inf when not integrable).

        As ``torchql.fit``'s second opinion: integrated at the loose tolerance, on the grid from
        the iterate's particular solution (its prediction of the trajectory) where that settles.
        """
        need = rows[torch.isnan(it["nl_sse"][rows])]
        if need.numel():
            traj, errors = self._nonlinear(idx[need], it["z0"][need], loose=True, guess=it["W"][need][..., 0],
                                           budget_is_final=True)
            n = self.system.n
            value, _ = self.spec.operator.value_and_jacobian(self._at_obs(traj, idx[need])[..., :n].reshape(-1, n))
            y, mask = self.y[idx[need]], self.mask[idx[need]]
            resid = torch.where(mask, y - value.reshape(y.shape), torch.zeros((), dtype=y.dtype, device=y.device))
            sse = self._ssq(idx[need], resid.reshape(need.numel(), -1), penalty=True)
            failed = torch.tensor([e is not None for e in errors], dtype=torch.bool, device=sse.device)
            sse = torch.where(failed | ~torch.isfinite(sse), torch.full_like(sse, math.inf), sse)
            it["nl_sse"][need] = sse
            it["nl_traj"][need] = traj
        return it["nl_sse"][rows]

    # --- the least-squares update -------------------------------------------------------------
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
            alpha, _, _ = _lstsq(C, d, w, spec.rcond, damping)
            return alpha, torch.zeros(idx.numel(), dtype=torch.bool, device=alpha.device)
        u = _pick(cur["z0"], idx)[:, spec.unknown_index]
        Cq = C * bounds.derivative(u).unsqueeze(1)
        alpha_q, _, _ = _lstsq(Cq, d, w, spec.rcond, damping)
        capped = bounds._capped(alpha_q).any(dim=1)
        alpha, blocked = bounds.step(u, alpha_q)
        rows = blocked.any(dim=1).nonzero().flatten()
        if rows.numel():  # moved onto their bounds (or capped) and held; the others re-solved
            held = blocked[rows]
            move = alpha[rows].masked_fill(~held, 0.0)
            rhs = d[rows] - (C[rows] @ move.unsqueeze(-1)).squeeze(-1)
            rest_q, _, _ = _lstsq(Cq[rows].masked_fill(held.unsqueeze(1), 0.0), rhs, w[rows], spec.rcond,
                                  damping[rows])
            rest, _ = bounds.step(u[rows], rest_q.masked_fill(held, 0.0))
            alpha[rows] = torch.where(held, move, rest)
        return alpha, capped

    # --- the iterates' records (torchql.fit's history) -----------------------------------------
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

    # --- the iteration ------------------------------------------------------------------------
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

    # --- the final pass -----------------------------------------------------------------------
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
        rows = final.nonzero().flatten()
        if rows.numel():
            guess = final_guess[rows]
            traj, errors = self._nonlinear(rows, z0[rows], loose=False, guess=guess)
            for k, r in enumerate(rows.tolist()):
                if errors[k] is not None:
                    codes[r] = Status.INTEGRATION_FAILED
                    detail[r] = f" The solver said, at the final estimates: {errors[k]}."
            good = torch.tensor([e is None for e in errors], dtype=torch.bool, device=dev)
            rows, traj = rows[good], traj[good]
        if rows.numel():
            lin = self._linearize(rows, traj)
            W, failed = self._propagate(rows, traj, lin.f, lin, _initial_columns(z0[rows], spec.unknown_index))
            for r in rows[failed].tolist():
                codes[r] = Status.INTEGRATION_FAILED
                detail[r] = (" The solver said, at the final estimates: the transfer of a grid interval did not "
                             "meet the tolerance.")
            rows, traj, W = rows[~failed], traj[~failed], W[~failed]
        if rows.numel():
            traj_obs = self._at_obs(traj, rows)
            C, _, resid = self._rows(rows, traj_obs, traj_obs, self._at_obs(W, rows)[..., 1:])
            w = self.w[rows].reshape(rows.numel(), -1)
            J = C * w.unsqueeze(-1)
            rw = resid * w
            s = self._ssq(rows, resid)
            sse[rows] = s
            exact = self.exact[rows]
            exact_residual[rows] = torch.where(exact, resid.abs(), torch.zeros_like(resid)).amax(dim=1)
            if self.history is not None:
                for k, r in enumerate(rows.tolist()):
                    self.history[r].append(self._record(r, int(iterations[r]), z0[r], float(s[k]), traj[k]))
                    self._notify(r)
            residuals[rows], jacobian[rows] = rw, J
            nonfinite = ~torch.isfinite(s)
            for r in rows[nonfinite].tolist():
                codes[r] = Status.DIVERGED
                detail[r] = " The fitted trajectory is non-finite."
            keep = ~nonfinite
            rows, J, s, rw = rows[keep], J[keep], s[keep], rw[keep]
        if rows.numel():
            L = self.L[rows]
            # the Gauss-Newton steps at the estimates (their stationarity), and the Jacobians' ranks
            step, deficient, sv = _lstsq(J, rw, torch.ones(J.shape[:2], dtype=dtype, device=dev), spec.rcond, None)
            singular_values[rows] = sv
            deficient |= L < m
            for k, r in enumerate(rows.tolist()):
                code = codes[r]
                if not (code.success or code in (Status.MAX_ITER, Status.STALLED)):
                    continue
                null_text = ""
                if bool(deficient[k]):
                    used = self.mask[r].reshape(-1)
                    sol = solve_update(J[k][used], torch.zeros(int(L[k]), dtype=dtype, device=dev),
                                       torch.ones(int(L[k]), dtype=dtype, device=dev),
                                       torch.zeros(int(L[k]), dtype=torch.bool, device=dev), spec.rcond)
                    null_text = null_detail(sol.null_vectors, spec.unknown_names)
                codes[r], more = final_status(
                    code, rank_deficient=bool(deficient[k]), null_text=null_text,
                    estimates=z0[r, spec.unknown_index],
                    scale=typical_magnitudes(self.z0_guess[r, spec.unknown_index],
                                             None if self.scale is None else self.scale[r]),
                    unknown_names=spec.unknown_names,
                    sse=float(s[k]), sse_start=None if self.sse_start is None else float(self.sse_start[r]),
                    step=step[k])
                detail[r] = more if code.success else detail[r] + more
            cov[rows] = _covariance(J, self.mask[rows].reshape(rows.numel(), -1), s, L, spec,
                                    deficient | self.exact[rows].any(dim=1), self.exact[rows])
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
                    sse_start=self.sse_start if self.sse_start is not None else torch.full_like(sse, float("nan")))


# ----------------------------------------------------------------------------------------------
def _initial_columns(z0: torch.Tensor, unknown_index: torch.Tensor) -> torch.Tensor:
    """``W(t0) = [z0, e_{i_1}, ..., e_{i_m}]`` per sample: ``(S, M, 1 + m)``."""
    S, M = z0.shape
    m = unknown_index.numel()
    E = torch.zeros(M, m, dtype=z0.dtype, device=z0.device)
    E[unknown_index, torch.arange(m, device=z0.device)] = 1.0
    return torch.cat([z0.unsqueeze(-1), E.expand(S, M, m)], dim=2)


def _shifted(z0: torch.Tensor, alpha: torch.Tensor, unknown_index: torch.Tensor) -> torch.Tensor:
    z = z0.clone()
    z[:, unknown_index] = z0[:, unknown_index] + alpha
    return z


def _pick(x: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``x[index]`` for sorted, distinct sample indices; ``x`` itself (no copy) when they are all of them.

    Most iterations keep every sample of a chunk running, and the gathers of its largest arrays
    (the propagated columns, the linearization) would copy them whole. The result may be ``x``:
    callers only read it.
    """
    return x if index.numel() == x.shape[0] else x[index]


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


def _lstsq(C, d, w, rcond: float, damping):
    """Batched weighted least squares by SVD with Levenberg–Marquardt filter factors.

    ``C (S, R, m)``, ``d (S, R)``, weights ``w (S, R)`` (0 for missing values), ``damping (S,)``
    relative to the largest squared singular value (or ``None``). Returns ``alpha (S, m)``,
    ``deficient (S,)`` (a singular value below ``rcond`` times the largest, or a zero column)
    and the singular values ``(S, m)``. Samples with non-finite rows get NaN.
    """
    Cw = C * w.unsqueeze(-1)
    dw = d * w
    finite = torch.isfinite(Cw).flatten(1).all(dim=1) & torch.isfinite(dw).all(dim=1)
    Cw = torch.where(finite.reshape(-1, 1, 1), Cw, torch.zeros_like(Cw))
    dw = torch.where(finite.reshape(-1, 1), dw, torch.zeros_like(dw))
    scale = torch.linalg.vector_norm(Cw, dim=1)
    zero_cols = scale == 0
    scale = torch.where(zero_cols, torch.ones_like(scale), scale)
    A = Cw / scale.unsqueeze(1)
    U, Sv, Vh = torch.linalg.svd(A, full_matrices=False)
    keep = Sv > rcond * Sv[:, :1]
    safe = torch.where(keep, Sv, torch.ones_like(Sv))
    if damping is not None:
        safe = safe + damping.unsqueeze(-1) * Sv[:, :1] ** 2 / safe
    coeff = torch.where(keep, (U.transpose(1, 2) @ dw.unsqueeze(-1)).squeeze(-1) / safe, torch.zeros_like(Sv))
    alpha = (Vh.transpose(1, 2) @ coeff.unsqueeze(-1)).squeeze(-1) / scale
    alpha = torch.where(finite.unsqueeze(-1), alpha, torch.full_like(alpha, float("nan")))
    deficient = (~keep).any(dim=1) | zero_cols.any(dim=1)
    return alpha, deficient, Sv


def _covariance(J, used, sse, L, spec: _Spec, deficient, exact) -> torch.Tensor:
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
