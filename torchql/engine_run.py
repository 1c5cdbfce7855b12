"""A problem's fit, chunk after chunk of samples: the engine (:mod:`torchql.engine`) and its second fits.

:func:`torchql.fit` (one sample) and :func:`torchql.fit_many` both run :func:`run_engine`. Each
chunk is fitted by one :class:`~torchql.engine.Engine`; then, per sample,

- ``initial_trajectory="auto"`` fits again from the other first reference a sample whose fit from
  the first failed or was misled (:func:`torchql.data_start.fallback_rows`), keeping the better fit;
- ``solver="auto"``, which chose an explicit solver because the model is not stiff along the data at
  the guesses, fits again as a stiff model a sample whose model became stiff where the iterates
  went (a relaxation rate guessed at 1 and fitted at 1.5e4): found by the explicit pair's own test
  (:func:`torchql.dopri.found_stiff`) or by :func:`torchql.stiffness.stiff_along` at an accepted
  iterate. The engine stops such a sample at once (:meth:`~torchql.engine.Engine._begin`), without
  a final pass: its explicit steps there are held by stability, and every trial crawls. Its second fit is the one ``solver="auto"`` makes of a model it finds stiff
  (:meth:`torchql.problem.Problem.stiff_variant`: Rodas5P, the stiff linear propagator, the stiff
  grid and first reference), from the guesses; the result keeps the better fit and records its
  solver (``batch[i].solver_options``).
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from .batch_result import BatchFitResult
from .budget import time_budget
from .data_start import START_WORDS, STIFF_REFIT, fallback_rows, keep_the_better_fit
from .engine import Engine
from .engine_state import shifted_report
from .problem import Problem
from .result import IterationRecord, Status
from .saddle import SADDLE_WORDS

__all__ = ["run_engine"]


def run_engine(spec: Problem, chunk_size: int, max_time: float | None, report: Callable[[int | str | None], None],
               history: bool = False, callback: Callable[[int, IterationRecord], None] | None = None,
               started: float | None = None) -> BatchFitResult:
    """Fit the validated problem ``spec``, chunk after chunk of samples: the iteration of
    :func:`torchql.fit` (one sample) and :func:`fit_many` alike.

    ``report`` receives the number of samples finished (``None``: done; a string: the phase begun);
    ``history`` keeps every iterate's record; ``callback(sample, record)`` receives each record.
    ``max_time`` counts from ``started`` (``time.monotonic()`` at the fit's call; default now).
    """
    B, m = spec.B, spec.m
    out_z0 = torch.empty(B, spec.system.M, dtype=spec.dtype, device=spec.device)
    R = spec.weights.reshape(B, -1).shape[1]
    shapes = dict(sse=(B,), cov=(B, m, m), residuals=(B, R), jacobian=(B, R, m), singular_values=(B, m),
                  sse_start=(B,), sse_end=(B,), z0_start=(B, spec.system.M), exact_residual=(B,),
                  redundant_exact=(B,))
    out = {key: torch.empty(shape, dtype=spec.dtype, device=spec.device) for key, shape in shapes.items()}
    out["iterations"] = torch.empty(B, dtype=torch.long, device=spec.device)
    statuses: list[Status] = [Status.MAX_ITER] * B
    messages: list[str] = [""] * B
    histories: list[list[IterationRecord]] | None = [] if history else None
    solvers = [spec.solver] * B  # each sample's: the stiff solver's where its second fit won
    refit = _StiffRefit(spec, max_time, history, callback)
    finished = 0
    try:
        with time_budget(max_time, since=started):
            for start in range(0, B, chunk_size):
                index = torch.arange(start, min(B, start + chunk_size), device=spec.device)
                chunk = _fit_chunk(spec, index, max_time, shifted_report(report, finished), history, callback,
                                   refit)
                for k in refit(chunk, index):
                    solvers[int(index[k])] = refit.spec.solver
                out_z0[index] = chunk["z0"]
                for key in out:
                    out[key][index] = chunk[key]
                for k, i in enumerate(index.tolist()):
                    statuses[i], messages[i] = chunk["status"][k], chunk["message"][k]
                if histories is not None:
                    histories.extend(chunk["history"])
                finished += index.numel()
                report(finished)
    finally:
        report(None)
    result = spec.result(out_z0, out, statuses, messages, refit.nfev)
    result.history = histories
    if any(solver != spec.solver for solver in solvers):
        result.sample_solver_options = [dict(result.solver_options, solver=solver) for solver in solvers]
    return result


def _fit_chunk(spec: Problem, index: torch.Tensor, max_time: float | None, report, history: bool, callback,
               counter: "_StiffRefit") -> dict:
    """The engine's fit of the samples ``index`` (a chunk) of ``spec``, with ``"auto"``'s second
    first reference where the first failed or misled (:func:`~torchql.data_start.fallback_rows`;
    not for a sample the explicit solver found stiff where ``solver="auto"`` fits it again as a
    stiff model): the chunk's results, ``stiff_met`` marking the samples an explicit pair found
    stiff in either fit. Adds the model's evaluations to ``counter.nfev``."""
    engine = Engine(spec, index, max_time, history=history, callback=callback)
    chunk = engine.run(report)
    counter.nfev += engine.nfev
    retry, above = fallback_rows(chunk, spec.start_fallback)
    if spec.stiff_refit:
        retry = [k for k in retry if not bool(chunk["stiff_met"][k])]
    if retry:  # "auto": where the first reference failed or misled, the fit from the other one
        again = Engine(spec, index[retry], max_time, history=history, callback=callback, start=spec.start_fallback)
        stiff_met = chunk["stiff_met"].clone()
        other = again.run(lambda count: None)
        won = _keep_better(chunk, retry, other, START_WORDS[spec.start_fallback], index, callback, above)
        _cut_short(chunk, [k for k in retry if k in above], won, other, retry,
                   "The fit succeeded where its start was suspect (it ended above the sum of squares at the guesses, "
                   "or after a long path), and the fit from the other first reference, which would have told, ran "
                   "out of `max_time`: the estimates are the first fit's.")
        stiff_met[retry] |= other["stiff_met"]
        chunk["stiff_met"] = stiff_met
        counter.nfev += again.nfev
    _leave_saddles(spec, index, chunk, max_time, history, callback, counter)
    return chunk


def _leave_saddles(spec: Problem, index: torch.Tensor, chunk: dict, max_time: float | None, history: bool,
                   callback, counter: "_StiffRefit") -> None:
    """The samples of ``chunk`` (indices ``index``) that ended on a saddle (``chunk["off_saddle"]``, a
    lower point a step along their null directions: :func:`torchql.saddle.off_saddle`), fitted again
    from that point, integrated; each keeps the better fit. A fit made again that won and ended on
    another saddle is fitted again from there, at most once per unknown."""
    for _ in range(spec.m):
        rows = (~torch.isnan(chunk["off_saddle"][:, 0])).nonzero().flatten().tolist()
        if not rows:
            return
        again = Engine(spec, index[rows], max_time, history=history, callback=callback, start="integrate",
                       guesses=chunk["off_saddle"][rows])
        other = again.run(lambda count: None)
        counter.nfev += again.nfev
        won = _keep_better(chunk, rows, other, SADDLE_WORDS, index, callback)
        _cut_short(chunk, rows, won, other, rows, "The fit ended where the data could not separate some unknowns, "
                   "but a step along them lowered the sum of squares (a saddle), and the fit made again from there "
                   "ran out of `max_time`: the estimates are the saddle's.")
        chunk["off_saddle"][[k for k in rows if k not in won]] = float("nan")  # (a winner's: its own fit's)


def _cut_short(chunk: dict, rows: list[int], won: list[int], other: dict, refitted: list[int], why: str) -> None:
    """The chunk's ``rows`` whose first fit was kept (not in ``won``) because their second fit
    (``other``, in the order of ``refitted``) ran out of ``max_time``, where the first fit's end is
    known or suspected to be no optimum, end ``MAX_TIME``: the fit did not finish. ``why`` says so."""
    for k in rows:
        if k not in won and other["status"][refitted.index(k)] is Status.MAX_TIME:
            first, chunk["status"][k] = chunk["status"][k], Status.MAX_TIME
            chunk["message"][k] = (f"{Status.MAX_TIME.value} {why} The first fit ended {first.name} (SSE "
                                   f"{float(chunk['sse'][k]):.6g}).")
            chunk["cov"][k] = float("nan")  # (as every MAX_TIME fit's: no error bars about an unfinished fit)


def _keep_better(chunk: dict, rows: list[int], other: dict, words, index: torch.Tensor, callback,
                 above: set[int] = frozenset()) -> list[int]:
    """:func:`~torchql.data_start.keep_the_better_fit` of the chunk's ``rows`` (indices ``index``)
    against their second fits ``other`` (``words``, ``above`` as it takes them); returns the rows the
    second fit won. Where the first fit was kept, the ``callback`` receives its last record again,
    so that the last record it received for each sample is the result's (it received the second
    fit's as they were made)."""
    won = keep_the_better_fit(chunk, rows, other, words, above)
    if callback is not None and chunk.get("history") is not None:
        for k in rows:
            if k not in won and chunk["history"][k]:
                callback(int(index[k]), chunk["history"][k][-1])
    return won


class _StiffRefit:
    """``solver="auto"``'s second fit, as a stiff model, of the samples of a chunk that its explicit
    solver found stiff and that did not succeed (see the module's docstring); counts the model's
    evaluations of every fit of the problem (``nfev``)."""

    def __init__(self, spec: Problem, max_time: float | None, history: bool, callback) -> None:
        self.base, self.max_time, self.history, self.callback = spec, max_time, history, callback
        self.spec: Problem | None = None  # the stiff variant, made when first needed
        self.nfev = 0

    def __call__(self, chunk: dict, index: torch.Tensor) -> list[int]:
        """Fit the chunk's samples ``index`` found stiff again, keep the better fits in ``chunk``;
        returns the rows where the stiff fit won."""
        if not self.base.stiff_refit:
            return []
        rows = [k for k in chunk["stiff_met"].nonzero().flatten().tolist()  # (no time is left after MAX_TIME)
                if not chunk["status"][k].success and chunk["status"][k] is not Status.MAX_TIME]
        if not rows:
            return []
        if self.spec is None:
            self.spec = self.base.stiff_variant()
        other = _fit_chunk(self.spec, index[rows], self.max_time, lambda count: None, self.history, self.callback,
                           self)
        return _keep_better(chunk, rows, other, STIFF_REFIT, index, self.callback)
