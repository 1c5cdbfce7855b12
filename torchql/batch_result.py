"""The result of :func:`torchql.fit_many`: per-sample estimates, statuses and statistics."""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import torch

from .result import Status

if TYPE_CHECKING:  # pragma: no cover
    from .model import ODEModel

__all__ = ["BatchFitResult", "SampleResult"]


@dataclass
class SampleResult:
    """One sample of a :class:`BatchFitResult` (the fields of :class:`torchql.FitResult` it has).

    Attributes
    ----------
    index : int
        The sample's position in the batch.
    success, status, message, params, x0, estimates, iterations, sse, covariance,
    n_observations, dof, residual_variance, unknown_names, t0, sigma_known
        As in :class:`BatchFitResult`, for this sample (``params`` values of the buffers' own
        shapes, ``x0 (n_states,)``, ``estimates (m,)``, ``covariance (m, m)``).
    lower, upper : Tensor ``(m,)`` or None
        Bounds of the unknowns, as in :class:`torchql.FitResult` (``fit_many`` takes no bounds:
        ``None``).
    """

    index: int
    success: bool
    status: Status
    message: str
    params: dict[str, torch.Tensor]
    x0: torch.Tensor
    estimates: torch.Tensor
    iterations: int
    sse: float
    covariance: torch.Tensor
    n_observations: int
    dof: int
    residual_variance: float
    unknown_names: list[str]
    t0: float
    sigma_known: bool
    lower: torch.Tensor | None = None
    upper: torch.Tensor | None = None

    @property
    def stderr(self) -> dict[str, float]:
        """Standard error of every unknown, by name."""
        diag = torch.diagonal(self.covariance).clamp_min(0).sqrt()
        return {name: float(v) for name, v in zip(self.unknown_names, diag)}

    def confidence_intervals(self, level: float = 0.95) -> dict[str, tuple[float, float]]:
        """Wald intervals ``estimate -/+ q * stderr`` at confidence ``level``, by name.

        As :meth:`torchql.FitResult.confidence_intervals`: ``q`` is Student's t quantile with
        ``dof`` degrees of freedom when the residual variance was estimated, the normal
        quantile when ``sigma`` was known; NaN ends when the sample's fit did not succeed (but
        for a ``NOT_IDENTIFIABLE`` one's determined unknowns) or an unknown has no standard
        error; a bounded unknown's (``lower``/``upper``) in its internal variable, mapped back.
        """
        from .uncertainty import wald_intervals

        valid = self.success or self.status is Status.NOT_IDENTIFIABLE
        return wald_intervals(self.unknown_names, self.estimates, self.stderr, self.dof, self.sigma_known, level,
                              lower=self.lower, upper=self.upper, valid=valid)

    def __repr__(self) -> str:
        est = ", ".join(f"{name}={value:.6g}" for name, value in zip(self.unknown_names, self.estimates.tolist()))
        return (f"SampleResult(index={self.index}, success={self.success}, status={self.status.name}, "
                f"iterations={self.iterations}, sse={self.sse:.6g}, {est})")


@dataclass
class BatchFitResult:
    """What :func:`torchql.fit_many` found for each of ``B`` independent datasets.

    Attributes
    ----------
    success : bool Tensor ``(B,)``
        Whether each sample converged.
    status : list of Status
        Why each sample stopped (the same statuses as :class:`torchql.FitResult`).
    message : list of str
        Each sample's ``status.value`` plus details.
    params : dict of str to Tensor ``(B, *shape)``
        Every floating-point buffer per sample (estimated ones at their estimates).
    x0 : Tensor ``(B, n_states)``
        Estimated (or fixed) initial states at ``t0``.
    t0 : float or Tensor ``(B,)``
        Time of ``x0``: a float when the samples share it, else each sample's own (with
        per-sample observation times and ``t0`` not given, each sample's first time).
    unknown_names : list of str
        Names of the ``m`` unknowns, in the order of ``estimates``' last axis.
    estimates : Tensor ``(B, m)``
        The estimated unknowns.
    iterations : Tensor ``(B,)`` of int
        Updates applied to each sample (a converged sample stops iterating).
    sse : Tensor ``(B,)``
        Weighted sum of squared residuals of each fitted model (NaN where it failed).
    covariance : Tensor ``(B, m, m)``
        Covariance of each sample's estimates: NaN rows/columns for undetermined unknowns, all
        NaN for a sample whose iteration did not converge (as :attr:`torchql.FitResult.covariance`).
    n_observations : Tensor ``(B,)`` of int
        Values used per sample (NaNs skipped).
    dof : Tensor ``(B,)`` of int
        ``n_observations - m``.
    residual_variance : Tensor ``(B,)``
        ``sse / dof`` when ``sigma`` was not given, else 1.
    sigma_known : bool
        Whether the data's ``sigma`` was given.
    nfev : int
        Right-hand-side evaluations (points of the batched calls, all samples together).
    model : ODEModel
        A copy of the user's model holding the guesses (sample ``i``'s fitted model:
        :meth:`model_of`).
    """

    success: torch.Tensor
    status: list[Status]
    message: list[str]
    params: dict[str, torch.Tensor]
    x0: torch.Tensor
    t0: float | torch.Tensor
    unknown_names: list[str]
    estimates: torch.Tensor
    iterations: torch.Tensor
    sse: torch.Tensor
    covariance: torch.Tensor
    n_observations: torch.Tensor
    dof: torch.Tensor
    residual_variance: torch.Tensor
    sigma_known: bool
    nfev: int
    model: "ODEModel" = field(repr=False)

    def __len__(self) -> int:
        return int(self.success.shape[0])

    def _index(self, i: int) -> int:
        B = len(self)
        if isinstance(i, bool) or not isinstance(i, int):
            raise TypeError(f"a sample index must be an int; received {type(i).__name__}")
        if not -B <= i < B:
            raise IndexError(f"sample index {i} is out of range for a batch of {B}")
        return i % B

    def sample(self, i: int) -> SampleResult:
        """Sample ``i``'s values (negative indices count from the end)."""
        i = self._index(i)
        return SampleResult(
            index=i, success=bool(self.success[i]), status=self.status[i], message=self.message[i],
            params={k: v[i].clone() for k, v in self.params.items()}, x0=self.x0[i].clone(),
            estimates=self.estimates[i].clone(), iterations=int(self.iterations[i]), sse=float(self.sse[i]),
            covariance=self.covariance[i].clone(), n_observations=int(self.n_observations[i]), dof=int(self.dof[i]),
            residual_variance=float(self.residual_variance[i]), unknown_names=list(self.unknown_names),
            t0=float(self.t0[i]) if isinstance(self.t0, torch.Tensor) else self.t0,
            sigma_known=self.sigma_known)

    def __getitem__(self, i: int) -> SampleResult:
        return self.sample(i)

    def __iter__(self):
        return (self.sample(i) for i in range(len(self)))

    @property
    def stderr(self) -> torch.Tensor:
        """Standard errors ``(B, m)`` of the estimates (NaN where undetermined)."""
        return torch.diagonal(self.covariance, dim1=-2, dim2=-1).clamp_min(0).sqrt()

    def model_of(self, i: int) -> "ODEModel":
        """A copy of the model whose buffers hold sample ``i``'s estimates."""
        import copy

        from .model import _set_buffer

        i = self._index(i)
        fitted = copy.deepcopy(self.model)
        for name, value in self.params.items():
            _set_buffer(fitted, name, value[i].clone())
        return fitted

    def summary(self) -> str:
        """A short text summary: statuses counted, iterations, and the spread of the estimates."""
        B = len(self)
        ok = self.success
        lines = [f"fit_many: {B} samples, {int(ok.sum())} converged, {B - int(ok.sum())} not"]
        for status, count in Counter(s.name for s in self.status).most_common():
            lines.append(f"  {status:<18} {count}")
        it = self.iterations.to(torch.float64)
        lines.append(f"iterations: min {int(it.min())}, median {float(it.median()):g}, max {int(it.max())}")
        if bool(ok.any()):
            est = self.estimates[ok]
            lines.append(f"{'unknown':<14} {'mean':>13} {'std':>13} {'min':>13} {'max':>13}  (converged samples)")
            for k, name in enumerate(self.unknown_names):
                col = est[:, k]
                std = float(col.std()) if col.numel() > 1 else math.nan
                lines.append(f"{name:<14} {float(col.mean()):13.6g} {std:13.6g} {float(col.min()):13.6g} "
                             f"{float(col.max()):13.6g}")
        failed = [i for i in range(B) if not bool(ok[i])]
        if failed:
            shown = ", ".join(f"{i} ({self.status[i].name})" for i in failed[:10])
            lines.append(f"not converged: {shown}" + (" ..." if len(failed) > 10 else ""))
        return "\n".join(lines)

    def __repr__(self) -> str:
        return (f"BatchFitResult(B={len(self)}, converged={int(self.success.sum())}, "
                f"unknowns={self.unknown_names})")
