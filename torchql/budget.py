"""A wall-clock budget for a fit, checked between iterations and inside long phases.

``fit(..., max_time=s)`` and ``fit_many(..., max_time=s)`` run under :func:`time_budget`. The
iteration loops call :func:`time_left` between iterations; the places where one phase can run
long (every right-hand-side evaluation of an integrated system, every step of the batched
Dormand–Prince solver, every Newton iteration of the grid solver) call :func:`check_time`,
which raises :class:`TimeBudgetExceeded` once the budget is spent. The loops catch it and end
with ``Status.MAX_TIME``, keeping the last accepted iterate.

The deadline lives in a context variable, so that nested calls (a profile's re-fits, the
threads of a backend) each see their own, and code outside a budget pays one lookup per check.
"""

from __future__ import annotations

import contextlib
import contextvars
import math
import time
from collections.abc import Iterator

__all__ = ["TimeBudgetExceeded", "time_budget", "no_time_budget", "check_time", "time_left", "deadline", "until"]

_DEADLINE: contextvars.ContextVar[float | None] = contextvars.ContextVar("torchql_deadline", default=None)


class TimeBudgetExceeded(Exception):
    """The wall-clock budget of the current fit is spent (internal: fits turn it into a status)."""


@contextlib.contextmanager
def time_budget(seconds: float | None, since: float | None = None) -> Iterator[None]:
    """Run the body under a deadline ``seconds`` from now, or from the moment ``since`` (a
    ``time.monotonic()`` value: a fit's call, whose checks and set-up count too) (``None``: no
    budget, or the enclosing one).

    A budget inside another never extends it: the earlier deadline wins.
    """
    if seconds is None:
        yield
        return
    deadline = (time.monotonic() if since is None else since) + seconds
    outer = _DEADLINE.get()
    token = _DEADLINE.set(deadline if outer is None else min(deadline, outer))
    try:
        yield
    finally:
        _DEADLINE.reset(token)


@contextlib.contextmanager
def no_time_budget() -> Iterator[None]:
    """Run the body without a deadline (a batch's final evaluation of the samples that finished in time)."""
    token = _DEADLINE.set(None)
    try:
        yield
    finally:
        _DEADLINE.reset(token)


def deadline() -> float | None:
    """The current budget's deadline, in ``time.monotonic()`` seconds (None without a budget)."""
    return _DEADLINE.get()


@contextlib.contextmanager
def until(moment: float | None) -> Iterator[None]:
    """Run the body under the deadline ``moment`` (a value of :func:`deadline`; None: no budget),
    whatever the enclosing one: a phase inside :func:`no_time_budget` that is optional (the final
    pass's polishing steps) keeps the fit's own deadline this way."""
    token = _DEADLINE.set(moment)
    try:
        yield
    finally:
        _DEADLINE.reset(token)


def time_left() -> float:
    """Seconds left of the current budget (``inf`` without one; negative once spent)."""
    deadline = _DEADLINE.get()
    return math.inf if deadline is None else deadline - time.monotonic()


def check_time() -> None:
    """Raise :class:`TimeBudgetExceeded` when the current budget is spent."""
    deadline = _DEADLINE.get()
    if deadline is not None and time.monotonic() > deadline:
        raise TimeBudgetExceeded
