"""Tolerances and limits of a fit: every default written once, validated once.

``fit`` and ``fit_many`` resolve their keyword arguments here, so that the same arguments give
the same numbers in both, and a default changes in one place.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from . import _checks
from .integrate import default_tolerances

__all__ = ["DAMPINGS", "DAMPING_START", "DAMPING_MIN", "DAMPING_MAX", "METHODS", "INITIAL_TRAJECTORIES", "Tolerances",
           "Limits", "check_damping", "check_scheme"]

#: The damping strategies: ``"lm"`` (Levenberg–Marquardt, default) or ``None`` (the thesis' iteration).
DAMPINGS = ("lm", None)
#: Levenberg–Marquardt damping after the first rejected step, and its limits (relative to the
#: largest squared singular value of the scaled least-squares matrix), for every damped solve.
DAMPING_START = 1e-3
DAMPING_MIN = 1e-10
DAMPING_MAX = 1e12
#: The iteration schemes.
METHODS: tuple[str, ...] = ("kantorovich", "shooting")
#: How the first Kantorovich reference is made: integrated from the guesses, or built from the data.
INITIAL_TRAJECTORIES: tuple[str, ...] = ("integrate", "data")


@dataclass(frozen=True)
class Tolerances:
    """The tolerances of a fit in a given precision.

    Attributes
    ----------
    rtol, atol : float
        Integrator tolerances: ``1e-10``/``1e-12`` in float64, ``1e-6``/``1e-8`` below.
    xtol : float
        Step test: converged when the scaled update is at most ``xtol``; default
        ``max(1e-8, 100 rtol)`` in float64, ``max(1e-4, 100 rtol)`` below (no finer than the
        integration can resolve).
    ftol : float
        Sum-of-squares test: default ``1e-12`` in float64, ``1e-6`` below.
    rcond : float
        Relative singular-value threshold of the rank tests: default ``max(1e3 rtol, 1e3 eps)``.
    """

    rtol: float
    atol: float
    xtol: float
    ftol: float
    rcond: float

    @classmethod
    def resolve(cls, dtype: torch.dtype, rtol: float | None = None, atol: float | None = None,
                xtol: float | None = None, ftol: float | None = None, rcond: float | None = None) -> "Tolerances":
        """The given tolerances, validated (positive numbers), and the defaults of ``dtype`` for the rest."""
        rtol, atol = default_tolerances(dtype, rtol, atol)
        rtol, atol = _checks.positive_number("rtol", rtol), _checks.positive_number("atol", atol)
        double = dtype == torch.float64
        eps = torch.finfo(dtype).eps
        return cls(
            rtol=rtol, atol=atol,
            xtol=_checks.positive_number("xtol", xtol) if xtol is not None else max(1e-8 if double else 1e-4, 100 * rtol),
            ftol=_checks.positive_number("ftol", ftol) if ftol is not None else (1e-12 if double else 1e-6),
            rcond=_checks.positive_number("rcond", rcond) if rcond is not None else max(1e3 * rtol, 1e3 * eps),
        )


@dataclass(frozen=True)
class Limits:
    """The budgets of a fit: ``max_iter`` updates, ``max_steps`` solver steps per grid interval
    (None: the solver's own), ``max_time`` seconds of wall-clock time (None: no budget)."""

    max_iter: int = 50
    max_steps: int | None = None
    max_time: float | None = None

    @classmethod
    def resolve(cls, max_iter: int = 50, max_steps: int | None = None, max_time: float | None = None) -> "Limits":
        """Validated limits (``max_iter >= 0``, ``max_steps >= 1``, ``max_time > 0``)."""
        return cls(
            max_iter=_checks.positive_int("max_iter", max_iter, minimum=0),
            max_steps=None if max_steps is None else _checks.positive_int("max_steps", max_steps),
            max_time=None if max_time is None else _checks.positive_number("max_time", max_time),
        )


def check_damping(damping) -> str | None:
    """``damping`` if it is one of :data:`DAMPINGS`, else ``ValueError`` naming them."""
    if damping is not None and not isinstance(damping, str) or damping not in DAMPINGS:
        raise ValueError(f"`damping` must be one of {DAMPINGS}; received {damping!r}")
    return damping


def check_scheme(method, initial_trajectory) -> tuple[str, str]:
    """``(method, initial_trajectory)`` validated: each a string among :data:`METHODS` and
    :data:`INITIAL_TRAJECTORIES` (``TypeError``/``ValueError`` naming the valid ones), and the
    data-built start with Kantorovich only."""
    for arg, value, allowed in (("method", method, METHODS), ("initial_trajectory", initial_trajectory,
                                                              INITIAL_TRAJECTORIES)):
        if not isinstance(value, str):
            raise TypeError(f"`{arg}` must be a string, one of {allowed}; received {type(value).__name__}")
        if value not in allowed:
            raise ValueError(f"`{arg}` must be one of {allowed}; received {value!r}")
    if initial_trajectory == "data" and method != "kantorovich":
        raise ValueError('`initial_trajectory="data"` applies to method="kantorovich" only')
    return method, initial_trajectory
