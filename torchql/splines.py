"""Cubic splines shared by the data smoother, the inputs' interpolation and the automatic grid: the
not-a-knot knot slopes, the cubic Hermite basis, and its evaluation for samples each on its own knots."""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["knot_slopes", "hermite_basis", "hermite_per_sample"]


def hermite_basis(s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Cubic Hermite basis ``(h00, h10, h01, h11)`` at local coordinate ``s`` in ``[0, 1]``."""
    s2 = s * s
    s3 = s2 * s
    return 2 * s3 - 3 * s2 + 1, s3 - 2 * s2 + s, -2 * s3 + 3 * s2, s3 - s2


def knot_slopes(t: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Slopes ``(T,)`` (or ``(T, N)``) at the knots of the not-a-knot cubic spline through ``(t, y)``,
    ``T >= 2``, for one series ``y (T,)`` or ``N`` series ``y (T, N)``, at the same knots ``t (T,)``
    or each at its own, ``t (T, N)``.

    Two points: the chord; three: the interpolating parabola (not-a-knot with one interior
    knot); more: the tridiagonal system of slope continuity with not-a-knot ends (the third
    derivative continuous at the second and the second-to-last knot), by the Thomas algorithm,
    elementwise across the columns (a column's slopes are the same bits alone or with others).
    """
    T = t.shape[0]
    h = np.diff(t, axis=0)
    if t.ndim < y.ndim:
        h = h.reshape(-1, *([1] * (y.ndim - 1)))  # (T-1, 1...) against the columns
    delta = np.diff(y, axis=0) / h
    if T == 2:
        return np.stack([delta[0], delta[0]])
    if T == 3:
        curvature = (delta[1] - delta[0]) / (t[2] - t[0])  # half the parabola's second derivative
        return np.stack([delta[0] - curvature * h[0], delta[0] + curvature * h[0], delta[1] + curvature * h[1]])
    lower, diag, upper = (np.zeros((T, *h.shape[1:])) for _ in range(3))
    rhs = np.zeros(y.shape)
    lower[1:-1], diag[1:-1], upper[1:-1] = h[1:], 2 * (h[:-1] + h[1:]), h[:-1]
    rhs[1:-1] = 3 * (h[1:] * delta[:-1] + h[:-1] * delta[1:])
    span = t[2] - t[0]
    diag[0], upper[0] = h[1], span
    rhs[0] = ((h[0] + 2 * span) * h[1] * delta[0] + h[0] ** 2 * delta[1]) / span
    span = t[-1] - t[-3]
    diag[-1], lower[-1] = h[-2], span
    rhs[-1] = (h[-1] ** 2 * delta[-2] + (2 * span + h[-1]) * h[-2] * delta[-1]) / span
    for i in range(1, T):  # forward elimination
        factor = lower[i] / diag[i - 1]
        diag[i] -= factor * upper[i - 1]
        rhs[i] -= factor * rhs[i - 1]
    slopes = np.empty(y.shape)
    slopes[-1] = rhs[-1] / diag[-1]
    for i in range(T - 2, -1, -1):
        slopes[i] = (rhs[i] - upper[i] * slopes[i + 1]) / diag[i]
    return slopes


def hermite_per_sample(knots: torch.Tensor, values: torch.Tensor, slopes: torch.Tensor, tq: torch.Tensor,
                       count: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Cubic Hermite interpolation of ``S`` samples, each on its own knots: values and derivatives.

    ``knots (S, N)`` increasing over each sample's first ``count (S,)`` entries (default all;
    the rest may pad them); ``values, slopes (S, N, m)`` at the knots; ``tq (S, Q)`` query times
    within each sample's knots. Returns ``(S, Q, m)`` values and ``(S, Q, m)`` first derivatives.
    """
    S, N = knots.shape
    last = torch.full((S,), N - 2, dtype=torch.long, device=knots.device) if count is None else count - 2
    index = torch.searchsorted(knots.contiguous(), tq.contiguous(), right=True) - 1
    index = torch.minimum(index.clamp(min=0), last.clamp(min=0).unsqueeze(1))  # (S, Q)
    k0, k1 = knots.gather(1, index), knots.gather(1, index + 1)
    h = (k1 - k0).unsqueeze(-1)
    s = ((tq - k0).unsqueeze(-1) / h)
    b00, b10, b01, b11 = hermite_basis(s)
    s2 = s * s
    d00, d10, d01, d11 = (6 * s2 - 6 * s) / h, 3 * s2 - 4 * s + 1, (6 * s - 6 * s2) / h, 3 * s2 - 2 * s

    def at(x, i):
        return x.gather(1, i.unsqueeze(-1).expand(S, i.shape[1], x.shape[-1]))

    y0, y1, f0, f1 = at(values, index), at(values, index + 1), at(slopes, index), at(slopes, index + 1)
    return (b00 * y0 + b10 * h * f0 + b01 * y1 + b11 * h * f1,
            d00 * y0 + d10 * f0 + d01 * y1 + d11 * f1)
