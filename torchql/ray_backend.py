"""``fit_many_ray``: a very large collection of datasets fitted on a Ray cluster, in batches.

The datasets are split into consecutive batches of ``batch_size``; each batch is one Ray task
running :func:`torchql.fit_many` on a worker, and the results are gathered in input order
into one :class:`~torchql.BatchFitResult`. Each sample's result is the one ``fit_many``
gives it (the samples are independent), so the split changes nothing but the wall time.

Ray is an optional dependency: ``pip install "torchql[ray]"``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import torch

from . import _checks
from .batch import (check_data, check_experiment_samples, experiments_per_sample, fit_many, raise_if_failed,
                    sample_rows, sample_rows_dict)
from .batch_result import BatchFitResult, concatenate
from .model import ODEModel
from .observations import Observations
from .options import FitOptions

__all__ = ["fit_many_ray"]


def _import_ray():
    try:
        import ray
    except ImportError as exc:  # pragma: no cover - exercised only without ray installed
        raise ImportError('torchql.fit_many_ray needs Ray: pip install "torchql[ray]"') from exc
    return ray


def fit_many_ray(
    model: ODEModel,
    data: Observations | Sequence[Observations],
    x0=None,
    *,
    guesses: dict | None = None,
    batch_size: int = 1024,
    address: str | None = None,
    num_cpus: int | None = None,
    num_cpus_per_task: float = 1,
    torch_threads: int = 1,
    progress: bool | Callable[[int, int], None] = False,
    **options,
) -> BatchFitResult:
    """Fit ``B`` independent datasets on a Ray cluster: :func:`torchql.fit_many` per batch, results in input order.

    Parameters
    ----------
    model, data, x0, guesses
        As in :func:`torchql.fit_many` (``data`` one Observations holding a batch, values
        ``(B, T, K)`` with times ``(T,)`` or per sample ``(B, T)``, sliced into batches that keep
        their samples' times, a list of ``B`` Observations, or a list of ``B`` lists of experiments;
        ``x0`` ``(B, n_states)`` or ``(n_states,)``, with experiments ``(B, E, n_states)`` or
        ``(E, n_states)``; ``guesses`` values ``(B, ...)`` or shared).
    batch_size : int
        Datasets per Ray task (default 1024). Larger batches vectorize better; more batches
        than workers keep every worker busy.
    address : str, optional
        Ray cluster to connect to (``"auto"``, ``"ray://host:10001"``). Without it, and if Ray is
        not initialized yet, a local instance is started with ``num_cpus`` CPUs (and shut down
        at the end); an already initialized Ray is used as it is.
    num_cpus : int, optional
        CPUs of the local instance started here (default: all).
    num_cpus_per_task : float
        CPUs Ray reserves per task (default 1).
    torch_threads : int
        ``torch.set_num_threads`` in each task (default 1: one task per reserved CPU).
    progress : bool or callable
        As in ``fit_many``, counting the datasets of the batches finished.
    **options
        Any other keyword of :func:`torchql.fit_many` (``params``, ``fixed_x0``, ``t0``,
        ``max_iter``, tolerances, ``grid``, ...), the same for every batch.

    Returns
    -------
    BatchFitResult
        One result for all ``B`` datasets, in input order (``nfev`` summed over the batches).

    Raises
    ------
    ImportError
        When Ray is not installed (``pip install "torchql[ray]"``).
    TypeError, ValueError
        For invalid arguments, before any task is submitted.
    BatchFitError
        When ``throw=True`` and some dataset's fit does not converge (after all were fitted).
    """
    ray = _import_ray()
    throw = _checks.flag("throw", options.pop("throw", False))  # raised once, for the whole batch
    batch_size = _checks.positive_int("batch_size", batch_size)
    torch_threads = _checks.positive_int("torch_threads", torch_threads)
    if experiments_per_sample(data):  # B lists of experiments: x0 shared (E, n) or per sample (B, E, n)
        datasets = list(data)
        if check_experiment_samples(datasets, x0)[1]:
            x0 = torch.as_tensor(x0)
            rows = (lambda start, stop: x0[start:stop])
        else:
            rows = (lambda start, stop: x0)
    else:
        datasets = check_data(data)  # a batched Observations or a list: both are sliced into batches below
        rows = (lambda start, stop: sample_rows(x0, len(datasets), start, stop))
    B = len(datasets)
    # validate the other arguments once, here, so that a bad one fails before the cluster is used
    given = options.get("options")  # a FitOptions' max_iter is the one replaced (a keyword would clash)
    probe = ({**options, "options": dataclasses.replace(given, max_iter=0)} if isinstance(given, FitOptions)
             else {**options, "max_iter": 0})
    fit_many(model, datasets[:1], rows(0, 1), guesses=sample_rows_dict(guesses, B, 0, 1), **probe)

    started = False
    if not ray.is_initialized():
        if address is None:
            ray.init(num_cpus=num_cpus, include_dashboard=False, log_to_driver=False)
        else:
            ray.init(address=address, log_to_driver=False)
        started = True
    try:
        task = ray.remote(num_cpus=num_cpus_per_task)(_fit_batch)
        model_ref = ray.put(model)
        pending = {}
        for start in range(0, B, batch_size):
            stop = min(B, start + batch_size)
            ref = task.remote(model_ref, datasets[start:stop], rows(start, stop),
                              sample_rows_dict(guesses, B, start, stop), options, torch_threads)
            pending[ref] = (start, stop)
        report = _reporter(progress, B)
        parts: dict[int, BatchFitResult] = {}
        done = 0
        waiting = list(pending)
        while waiting:
            ready, waiting = ray.wait(waiting, num_returns=1)
            for ref in ready:
                start, stop = pending[ref]
                parts[start] = ray.get(ref)
                done += stop - start
                report(done)
        report(None)
    finally:
        if started:
            ray.shutdown()
    result = concatenate([parts[k] for k in sorted(parts)])
    result.data = datasets
    return raise_if_failed(throw, result)


def _fit_batch(model, datasets, x0, guesses, options, torch_threads) -> BatchFitResult:
    """One Ray task: ``fit_many`` on one batch (runs on a worker)."""
    torch.set_num_threads(torch_threads)
    return fit_many(model, datasets, x0, guesses=guesses, **options)


def _reporter(progress, total: int):
    from .batch import _progress

    return _progress(progress, total)
