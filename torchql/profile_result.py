"""What :func:`torchql.profile` returns: a profile-likelihood interval with its points."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

__all__ = ["ProfileResult"]


@dataclass
class ProfileResult:
    """What :func:`torchql.profile` found.

    Attributes
    ----------
    name : str
        The profiled unknown.
    level : float
        Confidence level of :attr:`interval`.
    estimate : float
        Its estimate in the free fit.
    sse_min : float
        The free fit's SSE.
    threshold : float
        The SSE at which the interval ends: ``sse_min + s^2 t^2`` (estimated variance) or
        ``sse_min + z^2`` (known ``sigma``).
    interval : tuple of float
        ``(lower, upper)``; ``-inf``/``inf`` on a side where the profile did not cross the
        threshold within the search, or the fit's own bound where it reached that (see
        :attr:`closed` and :attr:`message`).
    closed : tuple of bool
        Whether each side's end was found.
    wald : tuple of float
        The Wald interval at the same level, for comparison (``FitResult.confidence_intervals``:
        for a bounded unknown, in its internal variable and mapped back).
    values : Tensor ``(K,)``
        The fixed values of the unknown at which the profile was evaluated, increasing
        (the estimate and the root-finding evaluations included).
    sse : Tensor ``(K,)``
        The optimal SSE at each value; for a fit with estimated sigmas or log-normal noise, twice
        its negative log-likelihood (so are ``sse_min`` and ``threshold``: a likelihood profile).
    estimates : Tensor ``(K, m)``
        The optimal unknowns at each value, in :attr:`unknown_names` order (the profiled
        unknown's column holds :attr:`values`).
    unknown_names : list of str
        The fit's unknowns.
    message : str
        What was found, and for an open side why (search range exhausted, bound reached, or
        re-fits failing there).
    n_fits : int
        Number of re-fits made.
    failures : list of (float, str)
        Values at which a re-fit failed, with its status name.
    sigma_known : bool
    residual_variance : float
        ``s^2`` used (1 when ``sigma`` is known).
    likelihood : bool
        Whether ``sse``, ``sse_min`` and ``threshold`` are twice the negative log-likelihood (a fit
        with estimated sigmas, a ``sigma(p)`` function or log-normal noise) rather than the SSE.
    """

    name: str
    level: float
    estimate: float
    sse_min: float
    threshold: float
    interval: tuple[float, float]
    closed: tuple[bool, bool]
    wald: tuple[float, float]
    values: torch.Tensor
    sse: torch.Tensor
    estimates: torch.Tensor
    unknown_names: list[str]
    message: str
    n_fits: int
    failures: list = field(default_factory=list)
    sigma_known: bool = False
    residual_variance: float = 1.0
    likelihood: bool = False

    @property
    def tau(self) -> torch.Tensor:
        """Signed root statistic ``sign(value - estimate) sqrt(max(SSE - sse_min, 0) / s^2)``, ``(K,)``.

        For a model linear in its unknowns it is a straight line of slope ``1 / stderr``; its
        curvature shows the nonlinearity (Bates & Watts' profile t plot).
        """
        excess = (self.sse - self.sse_min).clamp_min(0.0) / self.residual_variance
        return torch.sign(self.values - self.estimate) * excess.sqrt()

    def plot(self, ax=None):
        """Plot the profile, threshold and intervals; see :func:`torchql.plotting.plot_profile`."""
        from .plotting import plot_profile

        return plot_profile(self, ax=ax)

    def __repr__(self) -> str:
        lo, hi = self.interval
        return (f"ProfileResult(name={self.name!r}, estimate={self.estimate:.6g}, level={self.level:g}, "
                f"interval=({lo:.6g}, {hi:.6g}), closed={self.closed}, points={self.values.numel()})")
