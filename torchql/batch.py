"""``fit_many``: many independent datasets fitted at once, each sample on its own iteration.

The iteration is the package's one loop (:mod:`torchql.engine`), which :func:`torchql.fit`
runs with one sample.

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

import copy
import time
import warnings
from collections.abc import Callable, Sequence

import torch

from . import _checks
from .batch_result import BatchFitError, BatchFitResult, concatenate
from .damping import Damping
from .schemes import Scheme
from .engine_run import run_engine
from .noise import run_with_noise
from .grid import make_grid
from .model import ODEModel
from .multi import experiment_result, stack_experiments, stack_observations
from .observations import Observations
from .options import FitOptions, Limits, accepts_options, recorded_options
from .parameters import apply_parameters
from .datasets import check_alike, check_data, inputs_all_or_none
from .problem import Problem
from .propagators import PROPAGATORS, LinearPropagator
from .result import IterationRecord
from .engine_evaluate import BATCHED_SOLVERS

__all__ = ["fit_many", "check_data", "check_experiment_samples", "experiments_per_sample", "raise_if_failed"]

#: Samples fitted together by default (bounds the memory: a chunk holds ``(chunk, G, M, 1 + m)``
#: solutions and ``(chunk, G, M, M)`` Jacobians).
DEFAULT_CHUNK = 4096
#: The validated problem (the former private name of :class:`torchql.problem.Problem`).
_Spec = Problem
#: The storage grid, shared with ``fit`` (:func:`torchql.grid.make_grid`).
_make_grid = make_grid


@accepts_options
def fit_many(
    model: ODEModel,
    data: Observations | Sequence[Observations],
    x0=None,
    *,
    params: Sequence[str] | None = None,
    guesses: dict | None = None,
    fixed_x0: Sequence[str] | None = None,
    t0: float | None = None,
    method: str | Scheme = "kantorovich",
    bounds: dict | None = None,
    scale: dict | None = None,
    parameters: dict | None = None,
    x0_expr: dict | None = None,
    initial_trajectory: str = "auto",
    max_iter: int = 50,
    max_time: float | None = None,
    rtol: float | None = None,
    atol: float | None = None,
    xtol: float | None = None,
    ftol: float | None = None,
    rcond: float | None = None,
    grid: int | str | torch.Tensor | None = None,
    damping: str | Damping | None = "lm",
    solver: str = "auto",
    linear_solver: "str | LinearPropagator | None" = None,
    max_steps: int | None = None,
    chunk_size: int = DEFAULT_CHUNK,
    progress: bool | Callable[[int, int], None] = False,
    callback: Callable[[int, IterationRecord], None] | None = None,
    throw: bool = False,
    conditions: Sequence[dict] | None = None,
    options: FitOptions | None = None,
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
        Several experiments per sample: a list of ``B`` lists of ``E`` Observations, sample
        ``b``'s experiments as :func:`torchql.fit` takes them (experiment ``e`` at the same times
        and with the same inputs in every sample); each sample is fitted as ``fit`` fits its
        experiments, with ``conditions``, ``t0`` per experiment and ``fixed_x0`` per experiment.
    x0 : Tensor ``(B, n_states)`` or ``(n_states,)``, optional
        Initial-state guesses at ``t0`` (one row per sample, or one row for all); with several
        experiments per sample ``(E, n_states)`` shared or ``(B, E, n_states)``. If omitted,
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
    scale : dict, optional
        ``{name: "lin" | "log" | "log10"}`` as in :func:`torchql.fit`, the same for every sample.
    parameters : dict, optional
        ``{name: torchql.Parameter or number}`` as in :func:`torchql.fit`, the same for every
        sample (``guesses`` still give per-sample values).
    x0_expr : dict, optional
        ``{state: callable(values) -> scalar}`` as in :func:`torchql.fit`: initial states that
        follow each sample's estimates.
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
    initial_trajectory : {"auto", "integrate", "data"}
        As in :func:`torchql.fit`: ``"data"`` builds each sample's first reference from its own
        data (smoothed observed states, derived hidden states, coefficients fitted to the
        slopes), with no integration from the guesses, batched over the samples; ``"auto"``
        (default) decides once for the batch and fits again, from the integrated guesses, each
        sample whose fit from the data failed.
        ``solver="auto"`` (default) decides as ``fit`` does, for each sample: ``"rodas5p"``
        where its model is stiff along its data (:mod:`torchql.stiffness`), else ``"dop853"``; a
        batch that mixes the two is fitted run by run of consecutive samples alike. With
        ``"rodas5p"`` (stiff models) every nonlinear pass is the batched implicit
        :func:`torchql.solvers.rodas5p_batch` and the grid gains early geometric nodes, as in ``fit``; ``"dop853"`` and ``"dopri5"`` are the batched Dormand–Prince pairs of eighth and
        fifth order (:func:`torchql.dopri.dopri_batch`; ``max_steps`` their trial steps per grid
        interval, as torchdiffeq counts them per output time). Another ``solver`` (``"dopri8"``,
        ``"rk4"``, ...) integrates each sample in turn by torchdiffeq, and ``fit_many`` warns so.
    linear_solver : str or LinearPropagator, optional
        As in :func:`torchql.fit` (default ``"radau"`` with a stiff solver, else ``"taylor"``).
        Propagators with a batched form (``LinearPropagator.batched``: ``"taylor"``, ``"radau"``,
        ``"exponential"``) take every sample at once; the others each sample in turn (with a warning).
    chunk_size : int
        Samples fitted together (default 4096); larger batches are fitted chunk after chunk.
        The results do not depend on it.
    progress : bool or callable
        ``True``: a progress bar (``tqdm``, from the extra ``torchql[progress]``) counting the
        samples finished and naming the phase under way (first trajectories, iterating, final
        pass); a callable receives ``(finished, total)`` as samples finish.
    conditions : list of dict, optional
        With several experiments per sample: each experiment's coefficient values, as in
        :func:`torchql.fit` (shared by the samples).
    options : FitOptions, optional
        As in :func:`torchql.fit`.
    callback : callable, optional
        Called as ``callback(sample, record)`` with each sample's :class:`IterationRecord` as it
        is completed (as :func:`torchql.fit`'s callback, with the sample's index). Every
        sample's iterates are then kept too (``batch[i].history`` holds them all).
    throw : bool
        ``True``: raise :class:`torchql.BatchFitError` (a :class:`torchql.FitError`) when some
        sample does not converge, after every sample was fitted; its ``result`` holds them all,
        its ``failed`` the failed samples' indices. Default ``False``: each sample's ``status``
        and ``message`` say it.

    Returns
    -------
    BatchFitResult
        Per-sample estimates, statuses, messages, iterations, SSE and covariance; its ``t0`` is
        a float when the samples share it, else each sample's ``(B,)``.

    Raises
    ------
    TypeError, ValueError
        For invalid arguments (naming the argument, the sample, what was expected and received).
    BatchFitError
        When ``throw=True`` and some sample does not converge.
    """
    started = time.monotonic()  # max_time counts from here: the problem's set-up (stiffness test) too
    throw = _checks.flag("throw", throw)
    if parameters is not None:
        _checks.model_class(model)
        given = apply_parameters(model, parameters, x0=x0, params=params, fixed_x0=fixed_x0, bounds=bounds,
                                 scale=scale, x0_expr=x0_expr,  # several experiments: x0 (E, n) shared
                                 rows=len(data[0]) if experiments_per_sample(data) else None, conditions=conditions)
        model, x0, params, fixed_x0, bounds, scale, x0_expr = (
            given[k] for k in ("model", "x0", "params", "fixed_x0", "bounds", "scale", "x0_expr"))
    if experiments_per_sample(data):
        return raise_if_failed(throw, _fit_experiment_samples(
            model, data, x0, params=params, guesses=guesses, fixed_x0=fixed_x0, t0=t0, bounds=bounds, scale=scale,
            x0_expr=x0_expr, grid=grid, conditions=conditions, method=method,
            initial_trajectory=initial_trajectory, max_iter=max_iter, max_time=max_time, rtol=rtol, atol=atol,
            xtol=xtol, ftol=ftol, rcond=rcond, damping=damping, solver=solver, linear_solver=linear_solver,
            max_steps=max_steps, chunk_size=chunk_size, progress=progress, callback=callback))
    if conditions is not None:
        raise ValueError("`conditions` apply to several experiments per sample: give `data` as one list of "
                         "experiments (Observations) per sample")
    def by_runs(runs):  # one problem per run of samples alike, joined in the samples' order
        return raise_if_failed(throw, _fit_runs(
            runs, model, data, x0, guesses=guesses, max_time=max_time, progress=progress, callback=callback,
            params=params, fixed_x0=fixed_x0, t0=t0, method=method, bounds=bounds, scale=scale, x0_expr=x0_expr,
            initial_trajectory=initial_trajectory, max_iter=max_iter, rtol=rtol, atol=atol, xtol=xtol, ftol=ftol,
            rcond=rcond, grid=grid, damping=damping, solver=solver, linear_solver=linear_solver,
            max_steps=max_steps, chunk_size=chunk_size, started=started))

    runs = _input_runs(data, t0, tuple(getattr(model, "input_names", ())))  # samples whose measured inputs differ
    if runs is not None:
        return by_runs(runs)
    spec = Problem(model, data, x0, params, guesses, fixed_x0, t0, max_iter, rtol, atol, xtol, ftol, rcond, grid,
                   damping, solver, max_steps, bounds, linear_solver, method, initial_trajectory, scale=scale,
                   x0_expr=x0_expr)
    runs = _stiffness_runs(spec)
    if runs is not None:  # each sample on the solver its own fit takes ("auto": stiff or not)
        return by_runs(runs)
    chunk_size = _checks.positive_int("chunk_size", chunk_size)
    max_time = Limits.resolve(max_time=max_time).max_time
    _say_one_at_a_time(spec)
    if callback is not None and not callable(callback):
        raise TypeError("`callback` must be callable (it receives each sample's index and IterationRecord); "
                        f"received {callback!r}")
    result = run_with_noise(spec, lambda problem: run_engine(
        problem, chunk_size, max_time, _progress(progress, spec.B), history=callback is not None, callback=callback,
        started=started))
    result.data = data
    result.fit_kwargs = recorded_options(
        params=params, fixed_x0=fixed_x0, t0=t0, method=method, max_iter=max_iter, max_time=max_time,
        solver=solver, rtol=rtol, atol=atol, xtol=xtol, ftol=ftol, rcond=rcond, grid=grid,
        initial_trajectory=initial_trajectory, max_steps=max_steps, damping=damping, linear_solver=linear_solver,
        bounds=bounds, scale=scale, x0_expr=x0_expr)
    return raise_if_failed(throw, result)


def raise_if_failed(throw: bool, result: BatchFitResult) -> BatchFitResult:
    """``result``, or :class:`BatchFitError` raised with it where ``throw`` and a sample failed."""
    if throw and not bool(result.success.all()):
        raise BatchFitError(result)
    return result


def _say_one_at_a_time(spec: Problem) -> None:
    """Warn where a batch's samples are integrated one after another: a ``solver`` or a
    ``linear_solver`` without a batched form (the results are the same; only the time differs)."""
    if spec.B < 2:
        return
    if spec.solver not in BATCHED_SOLVERS:
        warnings.warn(f"fit_many: solver={spec.solver!r} has no batched form, so each of the {spec.B} samples "
                      f"is integrated in turn by torchdiffeq; {', '.join(map(repr, BATCHED_SOLVERS))} integrate "
                      "them all at once", UserWarning, stacklevel=4)
    if not spec.linear_solver.batched:
        warnings.warn(f"fit_many: linear_solver={spec.linear_solver.name!r} has no batched form "
                      f"(LinearPropagator.series), so each of the {spec.B} samples' linear problems is propagated "
                      f"in turn; {', '.join(repr(name) for name, p in PROPAGATORS.items() if p.batched)} take "
                      "them all at once",
                      UserWarning, stacklevel=4)


def _stiffness_runs(spec: Problem) -> list[tuple[int, int]] | None:
    """Runs ``[start, stop)`` of consecutive samples alike in stiffness where ``solver="auto"`` found
    some samples stiff and others not; ``None`` where one problem serves. The stiff solver takes a
    batch with one stiff sample, but each non-stiff sample's own fit takes the explicit one: a van
    der Pol sample of mu = 2 beside one of mu = 1000 took 5 iterations instead of its own 13."""
    if spec.stiff_samples is None:
        return None
    flags = spec.stiff_samples.tolist()
    return _runs(len(flags), lambda start, b: flags[b] == flags[start])


def _input_runs(data, t0: float | None, names: tuple[str, ...]) -> list[tuple[int, int]] | None:
    """Runs ``[start, stop)`` of consecutive samples that share their inputs, when there are
    several (samples with other inputs are other problems); ``None`` when one problem serves.
    Each sample's signal must name the model's inputs ``names`` (where it declares any) and cover
    its times, from ``t0`` (else its first observation) to its last observation: checked here,
    where the error can name the sample (a run's own problem does not know where its samples sit
    in ``data``)."""
    if isinstance(data, Observations):
        inputs = list(data.inputs) if isinstance(data.inputs, tuple) else None
        times = [data.t if data.t.dim() == 1 else data.t[b] for b in range(data.batch_size or 1)]
        where = "`data.inputs[{b}]`"
    elif isinstance(data, (list, tuple)) and data and all(isinstance(d, Observations) for d in data):
        inputs, times, where = [d.inputs for d in data], [d.t for d in data], "`data[{b}].inputs`"
    else:
        return None  # Problem reports what is wrong with it
    if inputs is None or all(item is None for item in inputs):
        return None
    inputs_all_or_none(inputs)
    for b, (signal, t) in enumerate(zip(inputs, times)):
        if names:
            signal.select(names, where=where.format(b=b).strip("`"))
        start, end = float(t[0]) if t0 is None else min(float(t0), float(t[0])), float(t[-1])
        if not signal.covers(start, end):
            raise ValueError(f"{where.format(b=b)} must cover sample {b}'s times [{start:g}, {end:g}] (from t0 to its "
                             f"last observation); its samples span [{float(signal.t[0]):g}, {float(signal.t[-1]):g}]")
    return _runs(len(inputs), lambda start, b: inputs[b].same_as(inputs[start]))


def _runs(count: int, alike: Callable[[int, int], bool]) -> list[tuple[int, int]] | None:
    """Runs ``[start, stop)`` of consecutive samples ``b`` of ``count`` that are ``alike(start, b)``
    to their run's first; ``None`` when one run holds them all."""
    runs, start = [], 0
    for b in range(1, count + 1):
        if b == count or not alike(start, b):
            runs.append((start, b))
            start = b
    return runs if len(runs) > 1 else None


def _fit_runs(runs, model, data, x0, *, guesses, max_time, progress, callback, started: float,
              **options) -> BatchFitResult:
    """``fit_many`` over samples whose inputs or stiffness differ: one batched problem per run of
    samples alike, the results joined in the samples' order (each sample's fit is the one it gets
    alone; the runs share the time budget, counted from ``started``, the ``fit_many`` call, and the
    progress count and the callback's indices)."""
    B = runs[-1][1]
    report = _progress(progress, B)
    limit = Limits.resolve(max_time=max_time).max_time
    deadline = None if limit is None else started + limit
    parts = []
    for start, stop in runs:
        left = None if deadline is None else max(deadline - time.monotonic(), 1e-9)
        part = fit_many(model, data[start:stop], sample_rows(x0, B, start, stop),
                        guesses=sample_rows_dict(guesses, B, start, stop), max_time=left,
                        progress=lambda done, total, offset=start: report(offset + done),
                        callback=None if callback is None else (
                            lambda sample, record, offset=start: callback(offset + sample, record)),
                        **options)
        report(stop)
        parts.append(part)
    report(None)
    result = concatenate(parts)
    result.data = data
    result.fit_kwargs = dict(parts[0].fit_kwargs, max_time=limit)
    return result


def _progress(progress, total: int) -> Callable[[int | str | None], None]:
    """A function of the number of samples finished (``None``: close; a string: the phase begun,
    shown beside a bar)."""
    if progress is False or progress is None:
        return lambda done: None
    if callable(progress) and not isinstance(progress, bool):
        last = [-1]

        def call(done):
            if isinstance(done, int) and done != last[0]:
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
        elif isinstance(done, str):
            bar.set_postfix_str(done)
        elif done > bar.n:
            bar.update(done - bar.n)
    return update


def sample_rows(x0, B: int, start: int, stop: int):
    """Rows ``start:stop`` of a per-sample ``x0 (B, n)``; a shared ``(n,)`` or ``None`` as it is."""
    if x0 is None:
        return None
    x = torch.as_tensor(x0)
    return x[start:stop] if x.dim() == 2 and x.shape[0] == B else x


def sample_rows_dict(guesses, B: int, start: int, stop: int):
    """Rows ``start:stop`` of each per-sample guess ``(B, ...)``; shared values as they are."""
    if guesses is None or not isinstance(guesses, dict):
        return guesses
    out = {}
    for name, value in guesses.items():
        v = torch.as_tensor(value)
        out[name] = v[start:stop] if v.dim() >= 1 and v.shape[0] == B else v
    return out


def experiments_per_sample(data) -> bool:
    """Whether ``data`` gives several experiments per sample: a list of lists of Observations."""
    return isinstance(data, (list, tuple)) and bool(data) and all(isinstance(d, (list, tuple)) for d in data)


def check_experiment_samples(data, x0, n: int | None = None) -> tuple[int, bool]:
    """``(B, per_sample)`` of ``fit_many``'s samples of several experiments: each a list of ``E``
    Observations, experiment ``e`` at the same times (and with the same inputs) in every sample;
    ``x0`` ``None``, shared ``(E, n)`` or per sample ``(B, E, n)`` (``per_sample``; ``n``, the
    model's number of states, checked where given)."""
    B, E = len(data), len(data[0])
    for b, sample in enumerate(data):
        if len(sample) != E:
            raise ValueError(f"`data[{b}]` holds {len(sample)} experiments but `data[0]` holds {E}: every sample "
                             "needs the same experiments")
        for e, d in enumerate(sample):
            if not isinstance(d, Observations):
                raise TypeError(f"`data[{b}][{e}]` must be a torchql.Observations; received {type(d).__name__}")
            ref = data[0][e]
            if d.t.shape != ref.t.shape or not torch.equal(d.t, ref.t):
                raise ValueError(f"`data[{b}][{e}]` has other times than `data[0][{e}]`: with several experiments "
                                 "per sample, each experiment's times must be the same in every sample")
            check_alike(d, ref, f"data[{b}][{e}]", f"data[0][{e}]")
            if (d.inputs is None) != (ref.inputs is None) or (d.inputs is not None and not d.inputs.same_as(ref.inputs)):
                raise ValueError(f"`data[{b}][{e}]` has other inputs than `data[0][{e}]`: with several experiments "
                                 "per sample, each experiment's inputs must be the same in every sample")
    shape = None if x0 is None else tuple(torch.as_tensor(x0).shape)
    per_sample = shape is not None and len(shape) == 3
    if per_sample and (shape[0] != B or shape[1] != E or n is not None and shape[2] != n):
        states = "n_states" if n is None else f"n_states = {n}"
        raise ValueError(f"`x0` must have shape (E, n_states) (shared) or (B, E, n_states) with B = {B} samples of "
                         f"E = {E} experiments and {states}; received shape {shape}")
    return B, per_sample


def _fit_experiment_samples(model, data, x0, *, params, guesses, fixed_x0, t0, bounds, scale, x0_expr, grid,
                            conditions, **options) -> BatchFitResult:
    """``fit_many`` over samples of several experiments each: every sample's experiments stacked as
    :func:`torchql.fit` stacks them (:func:`torchql.multi.stack_experiments`), one batched problem."""
    B, per_sample = check_experiment_samples(data, x0, len(model.state_names))
    st = stack_experiments(model, list(data[0]), x0[0] if per_sample else x0, t0=t0, fixed_x0=fixed_x0,
                           bounds=bounds, scale=scale, x0_expr=x0_expr, grid=grid, conditions=conditions)
    names = list(model.state_names)
    dtype, device = st.data.y.dtype, st.data.y.device
    stacked = [st.data] + [stack_observations(list(sample), names, st.t0, st.span, dtype, device, st.conditions)
                           for sample in data[1:]]
    first = st.data
    if first.sigma_estimated:
        sigma = "estimate"
    elif first.sigma_function is not None:
        sigma = first.sigma_function
    else:
        sigma = torch.stack([d.sigma for d in stacked]) if first.sigma_given else None
    batch_data = Observations(first.t, torch.stack([d.y for d in stacked]), observe=first.observe, sigma=sigma,
                              exact=torch.stack([d.exact for d in stacked]), noise=first.noise,
                              sigma_groups=first.sigma_groups)
    x0_stacked = st.x0
    if per_sample:
        x0_stacked = torch.as_tensor(x0, dtype=dtype, device=device).reshape(B, -1).clone()
    result = fit_many(st.model, batch_data, x0_stacked, params=params, guesses=guesses, fixed_x0=st.fixed_x0, t0=0.0,
                      bounds=st.bounds, scale=st.scale, x0_expr=st.x0_expr, grid=grid, **options)
    experiment_result(result, model, st, data)
    result.model = copy.deepcopy(model)  # each sample's coefficients set by result.model_of(i)
    replayed = {k: v for k, v in options.items() if k not in ("chunk_size", "progress", "callback")}
    result.fit_kwargs = recorded_options(x0=None if per_sample else x0, params=params, fixed_x0=fixed_x0, t0=t0,
                                         grid=grid, bounds=bounds, scale=scale, x0_expr=x0_expr,
                                         conditions=conditions, **replayed)
    return result
