"""Standard deviations that depend on the unknowns: ``Observations(..., sigma=lambda p: ...)``.

Some noise is a function of the model's coefficients: a Western blot's error scales with the gel's
own scaling factor ``s``, which also scales the prediction (``h = s x``, ``sigma = s sigma_rel``);
a noise parameter may be shared by some outputs and not others. ``sigma(p) -> (K,)`` gives each
output's standard deviation from the coefficients ``p`` by name, the unknown ones at their current
estimates.

**The objective.** With ``r_i = (y_i - h_i) / sigma_i``, the negative log-likelihood is
``sum_i log sigma_i + 1/2 sum_i r_i^2`` plus a constant, so the engine minimizes

    F = sum_i r_i^2 + 2 sum_i log sigma_i

(twice the negative log-likelihood less ``n log(2 pi)``; it may be negative). It is no longer a sum
of squares, so the iteration's linear problem is built as Gauss–Newton's on two kinds of rows:

* the data rows ``r_i``, whose linearization in the update ``alpha`` gains the change of
  ``1 / sigma_i``: with ``d_i`` the linear problem's residual and ``C_i`` its row,
  ``r_i(alpha) ~ (d_i - (C_i + d_i g_i) alpha) / sigma_i``, ``g_i = d log sigma_i / d alpha``;
* one row per value for the log term, ``1 + g_i alpha``, whose square ``1 + 2 g_i alpha +
  (g_i alpha)^2`` has the log term's gradient ``2 g_i`` exactly.

So a step of zero is a stationary point of ``F``: the fixed points are the maximum-likelihood
estimates. At the optimum the curvature of both rows about ``log sigma``, ``r_i^2 + 1``, is in
expectation the Gaussian's information 2. The covariance of the estimates is the inverse of the
expected (Fisher) information, ``sum_i (dh_i/du)(dh_i/du)^T / sigma_i^2 + 2 g_i g_i^T`` (the
result's ``jacobian`` holds the first rows, ``dh/du / sigma``), with no residual-variance factor.
(AMICI and pyPESTO use residuals ``sqrt(2 log sigma + c)`` for the same term; this form needs no
constant ``c`` and is exact at the stationary point.)
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch
from torch.func import jacrev, vmap

__all__ = ["SigmaFunction", "NoiseRows", "noise_rows"]


class SigmaFunction:
    """``sigma(p) -> (K,)`` read from augmented states of ``system`` (an
    :class:`torchql.model.AugmentedSystem`), with its derivative in the augmented state.

    Parameters
    ----------
    function : callable
        ``sigma(p)``: ``p`` a dict of the model's coefficients by name (tensors), returning the
        ``K`` outputs' standard deviations, shape ``(K,)``, positive, differentiable with torch.func.
    system : AugmentedSystem
        Whose coefficient values ``p`` are read from an augmented state ``z (M,)``.
    K : int
        Number of outputs.
    """

    def __init__(self, function: Callable[[dict], torch.Tensor], system, K: int) -> None:
        self.function, self.system, self.K = function, system, K

    def check(self, z: torch.Tensor) -> None:
        """Validate on one augmented state ``z (M,)``: shape ``(K,)``, its dtype, finite and positive."""
        try:
            out = self.function(self.system.coefficient_values(z))
        except Exception as exc:  # noqa: BLE001 - report any failure of user code clearly
            raise ValueError(f"`sigma` function failed on the model's coefficients: "
                             f"{type(exc).__name__}: {exc}") from exc
        if not isinstance(out, torch.Tensor) or out.shape != (self.K,):
            shape = tuple(out.shape) if isinstance(out, torch.Tensor) else type(out).__name__
            raise ValueError(f"`sigma` function must return one standard deviation per output, shape (K,) = "
                             f"({self.K},); received {shape}")
        if out.dtype != z.dtype:
            raise TypeError(f"`sigma` function must return dtype {z.dtype}; received {out.dtype}")
        if not bool(torch.isfinite(out).all()) or bool((out <= 0).any()):
            raise ValueError(f"`sigma` function must return finite, positive values at the guesses; received "
                             f"{out.tolist()}")
        try:
            vmap(jacrev(self._sigma))(z.unsqueeze(0))
        except Exception as exc:  # noqa: BLE001
            raise ValueError(f"`sigma` function could not be differentiated with torch.func (jacrev under vmap): "
                             f"{exc}. Avoid .item(), in-place updates and Python branching on tensor values.") from exc

    def _sigma(self, z: torch.Tensor) -> torch.Tensor:
        return self.function(self.system.coefficient_values(z))

    def evaluate(self, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``sigma (S, K)`` at augmented states ``z (S, M)``, and ``d log sigma / dz (S, K, M)``."""
        def with_value(zi):
            out = self._sigma(zi)
            return out, out

        jac, sigma = vmap(jacrev(with_value, has_aux=True))(z)
        return sigma, jac / sigma.unsqueeze(-1)


class NoiseRows(NamedTuple):
    """The linear problem of a fit whose sigmas depend on the unknowns (see the module's notes)."""

    C: torch.Tensor  #: ``(S, 2R, m)``: the data rows (with the change of 1 / sigma), then the log rows
    d: torch.Tensor  #: ``(S, 2R)``: the data rows' residuals, then -1 for each log row in use
    w: torch.Tensor  #: ``(S, 2R)``: 1 / sigma of the data rows, then 1 for each log row in use
    log_term: torch.Tensor  #: ``(S,)``: ``2 sum_i log sigma_i`` over the values in use


def noise_rows(C: torch.Tensor, d: torch.Tensor, w_base: torch.Tensor, used: torch.Tensor, sigma: torch.Tensor,
               dlog: torch.Tensor) -> NoiseRows:
    """The rows of :class:`NoiseRows` from a linear problem of fixed weights.

    ``C (S, R, m)`` and ``d (S, R)``: rows and residuals of the values (``R = T K``, row ``t K + k``),
    zero where unused; ``w_base (S, R)``: 1 over the data's own ``sigma`` (zero where unused);
    ``used (S, R)``: the values in use; ``sigma (S, K)`` and ``dlog (S, K, m)``: the function's
    values and its log-derivative in the unknowns.
    """
    S, R = d.shape
    T = R // sigma.shape[1]
    sigma_rows, g = sigma.repeat(1, T), dlog.repeat(1, T, 1)  # (S, R), (S, R, m)
    zero = torch.zeros((), dtype=d.dtype, device=d.device)
    g = torch.where(used.unsqueeze(-1), g, zero)
    ones = used.to(d.dtype)
    C_all = torch.cat([C + d.unsqueeze(-1) * g, g], dim=1)
    d_all = torch.cat([d, -ones], dim=1)
    w_all = torch.cat([w_base / sigma_rows, ones], dim=1)
    log_term = 2 * torch.where(used, torch.log(w_base.reciprocal() * sigma_rows), zero).sum(dim=1)
    return NoiseRows(C_all, d_all, w_all, log_term)
