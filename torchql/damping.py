"""Damping strategies: which trial iterates a fit accepts, and what a rejected trial does.

``damping=`` of :func:`torchql.fit` and :func:`torchql.fit_many` takes a registered name
(:data:`DAMPINGS`: ``"lm"``, the default, or ``None``, the thesis' undamped iteration) or a
:class:`Damping` object. Adding a strategy is a subclass registered by :func:`register_damping`.

The damping enters the iteration's least-squares update as ``lambda`` in ``min ||C a - d||^2 +
lambda s_max^2 ||a||^2`` (``s_max`` the largest singular value of the scaled matrix,
:func:`torchql.lstsq.solve_update_batch`): raised by the strategy after each rejected trial of an
iterate, back to zero once a trial is accepted, and zero for a fresh iterate unless the undamped
step that reached it lowered the sum of squares much less than its linear model predicted
(:meth:`Damping.after_poor_gain`).
"""

from __future__ import annotations

import torch

from .registry import Registry

__all__ = ["Damping", "LevenbergMarquardt", "Undamped", "DAMPINGS", "DAMPING_START", "DAMPING_MIN", "DAMPING_MAX",
           "RETRY_SHORTENING", "POOR_GAIN", "register_damping", "damping_strategy"]

#: Levenberg–Marquardt damping after the first rejected step, and its limits (relative to the
#: largest squared singular value of the scaled least-squares matrix), for every damped solve.
DAMPING_START = 1e-3
DAMPING_MIN = 1e-10
DAMPING_MAX = 1e12
#: A retry's damping must shorten the rejected trial's step at least this much along some direction
#: (:meth:`Damping.retry`); raises that shorten it less are skipped.
RETRY_SHORTENING = 0.3
#: An accepted undamped step whose actual decrease of the sum of squares is below this fraction of
#: its linear model's predicted decrease (the gain ratio, as in Moré's trust-region update, where
#: 0.25 shrinks the region) leaves its successor damped (:meth:`Damping.after_poor_gain`). There the
#: Gauss–Newton model misjudges the curvature: an SIR fit with its contact rate on a bound, whose
#: residuals stay large, overshot the recovery rate by 1.86 times each step, gamma's error flipping
#: sign at 0.86 of its size for 50 iterations (``tests/test_engine_steps.py``).
POOR_GAIN = 0.25


class Damping:
    """A damping strategy.

    Attributes
    ----------
    name : str or None
        The name ``damping=`` takes.
    filters : bool
        Whether a trial iterate must lower the sum of squares to be accepted. Without the
        filter every trial that integrates is taken, and one that does not ends the fit.
    """

    name: str | None = "base"
    filters: bool = True

    def raised(self, damping: torch.Tensor, last: torch.Tensor) -> torch.Tensor:
        """The damping ``(S,)`` after a rejected trial made with ``damping (S,)`` (0: undamped);
        ``last (S,)`` is the damping of the previous iterate's accepted trial."""
        raise NotImplementedError

    def stalled(self, damping: torch.Tensor) -> torch.Tensor:
        """Bool ``(S,)``: the samples whose ``damping`` is past use (their fit has stalled)."""
        raise NotImplementedError

    def retry(self, damping: torch.Tensor, last: torch.Tensor, spectrum: torch.Tensor) -> torch.Tensor:
        """The damping ``(S,)`` of the retry after rejected trials made with ``damping (S,)``:
        :meth:`raised`, and raised again while it would shorten the step by less than
        :data:`RETRY_SHORTENING` along every direction (as a trust region shrinks by a fixed
        factor after a failed step).

        ``spectrum (S, k)``: the squared singular values ``r_i`` of the damped problem relative
        to the largest (:func:`torchql.lstsq.relative_spectrum`; NaN: a dropped direction; all
        NaN: no skipping), along which damping ``lambda`` scales the step by ``r_i / (r_i +
        lambda)``. A raise that barely shortens the step (the first tenfold raises of a
        well-conditioned problem, all of whose ``r_i`` exceed it) retries nearly the same trial,
        for nearly the same outcome at the cost of a whole evaluation. ``last``: as
        :meth:`raised`'s."""
        new = self.raised(damping, last)
        for _ in range(32):  # (a bound: each raise at least tenfold)
            ratio = torch.where(torch.isnan(spectrum), 1.0, (spectrum + damping.unsqueeze(-1)) /
                                (spectrum + new.unsqueeze(-1)))
            same = (~self.stalled(new) & (new > damping) & (ratio.amin(dim=1) > 1 - RETRY_SHORTENING)
                    & ~torch.isnan(spectrum).all(dim=1))
            if not bool(same.any()):
                break
            new = torch.where(same, self.raised(new, last), new)
        return new

    def after_poor_gain(self, last: torch.Tensor, spectrum: torch.Tensor) -> torch.Tensor:
        """The damping ``(S,)`` of a fresh iterate reached by an undamped step whose gain ratio was
        below :data:`POOR_GAIN` (where it was not, a fresh iterate starts undamped). ``last (S,)``:
        the damping of that step (zero), ``spectrum (S, k)`` the fresh iterate's, as :meth:`retry`'s.
        The base strategy starts it as a retry of a rejected undamped trial: the first damping that
        shortens the step by :data:`RETRY_SHORTENING` along some direction. Such a step is not a
        creeping one (the engine's ``STALLED`` test judges the damping that rejections raised)."""
        return self.retry(torch.zeros_like(last), last, spectrum)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r})"


class LevenbergMarquardt(Damping):
    """Levenberg–Marquardt: a rejected trial is retried with more damping.

    The first raise of an iterate starts from a tenth of the previous iterate's accepted damping
    (at least ``minimum``), or from ``start`` where that one was undamped; every further
    rejection raises it tenfold; past ``maximum`` the fit has stalled. The engine retries with
    the first of these that shortens the step enough (:meth:`Damping.retry`).
    """

    name = "lm"

    def __init__(self, start: float = DAMPING_START, minimum: float = DAMPING_MIN,
                 maximum: float = DAMPING_MAX) -> None:
        if not 0 < minimum <= start <= maximum:
            raise ValueError(f"Levenberg–Marquardt damping needs 0 < minimum <= start <= maximum; received "
                             f"minimum={minimum!r}, start={start!r}, maximum={maximum!r}")
        self.start, self.minimum, self.maximum = float(start), float(minimum), float(maximum)

    def _settings(self) -> tuple[float, float, float]:
        return self.start, self.minimum, self.maximum

    def __eq__(self, other) -> bool:
        """Equal settings are one strategy (a ``FitOptions`` field and a keyword that give them agree)."""
        return type(other) is type(self) and other._settings() == self._settings()

    def __hash__(self) -> int:
        return hash((type(self), self._settings()))

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(start={self.start:g}, minimum={self.minimum:g}, "
                f"maximum={self.maximum:g})")

    def raised(self, damping: torch.Tensor, last: torch.Tensor) -> torch.Tensor:
        first = torch.where(last > 0, torch.clamp(last / 10, min=self.minimum), self.start)
        return torch.where(damping == 0, first, 10 * damping)

    def stalled(self, damping: torch.Tensor) -> torch.Tensor:
        return damping > self.maximum


class Undamped(Damping):
    """The thesis' iteration: every trial is taken; one that cannot be integrated ends the fit."""

    name = None
    filters = False

    def raised(self, damping: torch.Tensor, last: torch.Tensor) -> torch.Tensor:
        return torch.zeros_like(damping)

    def stalled(self, damping: torch.Tensor) -> torch.Tensor:
        return torch.zeros_like(damping, dtype=torch.bool)


_REGISTRY = Registry(Damping, "torchql.damping.Damping", "a damping strategy")


def register_damping(strategy: Damping) -> Damping:
    """Register ``strategy`` under its :attr:`~Damping.name` (replacing one of that name); returns it."""
    return _REGISTRY.register(strategy)


register_damping(LevenbergMarquardt())
register_damping(Undamped())

#: The registered damping names (``None``: undamped).
DAMPINGS: tuple[str | None, ...] = _REGISTRY.names


def damping_strategy(damping) -> Damping:
    """The strategy ``damping`` names, or ``damping`` itself when it is a :class:`Damping`;
    ``ValueError`` listing the registered names otherwise."""
    found = _REGISTRY.find(damping)
    if found is None:
        raise ValueError(f"`damping` must be one of {_REGISTRY.names} or a {_REGISTRY.public_name}; "
                         f"received {damping!r}")
    return found
