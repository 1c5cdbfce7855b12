"""Smoothing of measured values, for a first trajectory built from the data.

A discrete smoothing spline (Whittaker–Henderson): the values ``z`` at the observation times
minimize

    sum_i w_i (y_i - z_i)^2 + lam * sum_i (second divided difference of z at t_i)^2 * h_i,

with ``w_i = 1 / sigma_i^2`` and ``h_i`` the local spacing, and ``lam`` chosen by generalized
cross-validation (GCV; Craven & Wahba 1979) over a logarithmic range. Exact data keep a tiny
``lam`` (nearly interpolation); noisy data are smoothed just enough that their derivative,
which a first linearization needs, is not dominated by the noise.

Between the observation times the smoothed values are joined by a cubic spline with
not-a-knot ends (:func:`interpolate`): its slopes are continuous, so the states derived from
them (a velocity from a sampled position) and their own slopes are usable even when the data
are sparse (a handful of samples per period), where straight lines between the samples would
give piecewise-constant slopes and derivatives that vanish between the samples.
"""

from __future__ import annotations

import torch

from .splines import hermite, knot_slopes

__all__ = ["smooth", "interpolate", "MAX_SMOOTHED_POINTS", "SUMMED_POINTS", "SUMMED_SERIES"]

#: Longer series are not smoothed (the dense GCV would cost too much); they are used as given.
MAX_SMOOTHED_POINTS = 2000
#: Series of at most this many points are smoothed together, their sums accumulated point by point
#: (longer ones series by series, with matrix products).
SUMMED_POINTS = 64
#: Series smoothed together in one block (its arrays hold points x lams x series values).
SUMMED_SERIES = 2048


def _second_differences(t: torch.Tensor) -> torch.Tensor:
    """``D (T-2, T)``: second divided differences on the (possibly uneven) times ``t``, scaled by sqrt(h)."""
    T = t.shape[0]
    h = t[1:] - t[:-1]
    D = torch.zeros(T - 2, T, dtype=t.dtype, device=t.device)
    rows = torch.arange(T - 2, device=t.device)
    a, b = h[:-1], h[1:]
    width = (a + b) / 2
    D[rows, rows] = 1 / (a * width)
    D[rows, rows + 1] = -(1 / a + 1 / b) / width
    D[rows, rows + 2] = 1 / (b * width)
    return D * width.sqrt().unsqueeze(-1)


def smooth(t: torch.Tensor, y: torch.Tensor, weights: torch.Tensor | None = None,
           lams: torch.Tensor | None = None) -> torch.Tensor:
    """Smoothed values of one series ``y (T,)``, or of ``N`` series ``y (T, N)`` at the same times
    with the same weights (each with its own smoothing parameter).

    Parameters
    ----------
    t : Tensor ``(T,)``
        Strictly increasing times.
    y : Tensor ``(T,)`` or ``(T, N)``
        Values (finite).
    weights : Tensor ``(T,)``, optional
        ``1 / sigma^2`` per value (default ones), shared by the series.
    lams : Tensor, optional
        Candidate smoothing parameters (default a logarithmic range scaled to the data's time
        span); each series takes its GCV minimizer (the first, in a tie).

    Returns
    -------
    Tensor, the shape of ``y``
        The smoothed values (``y`` itself for fewer than 4 or more than
        :data:`MAX_SMOOTHED_POINTS` points).
    """
    T = t.shape[0]
    if T < 4 or T > MAX_SMOOTHED_POINTS:
        return y.clone()
    Y = y.reshape(T, -1)
    w = torch.ones_like(t) if weights is None else weights
    D = _second_differences(t)
    P = D.T @ D
    span = float(t[-1] - t[0])
    if lams is None:
        # lam * span^-3-ish balances the roughness term against one squared residual per point
        lams = torch.logspace(-12, 2, 29, dtype=t.dtype) * span ** 3 / T
    # one eigendecomposition serves every lam and series: with u = sqrt(w) z the hat matrix is
    # (I + lam Pw)^-1, Pw = W^-1/2 P W^-1/2, diagonal in Pw's eigenvectors
    r = w.sqrt()
    evals, Q = torch.linalg.eigh(P / r.unsqueeze(0) / r.unsqueeze(1))
    evals = evals.clamp_min(0)
    shrink = (1 / (1 + lams.to(evals).unsqueeze(0) * evals.unsqueeze(1)))  # (T, L)
    dof = T - shrink.sum(dim=0)  # (L,)
    usable = dof > 1e-9
    out = Y.clone()
    # a series gives the same values bit for bit whatever others are smoothed with it (fit_many's
    # data start is fit's): short series all at once, their sums over the points accumulated one
    # point at a time (elementwise, so each series' arithmetic is its own); long ones series by
    # series, every lam at once
    if T <= SUMMED_POINTS:
        for start in range(0, Y.shape[1], SUMMED_SERIES):
            block = slice(start, start + SUMMED_SERIES)
            _smooth_block(Y[:, block], out[:, block], w, r, Q, shrink, usable, dof)
        return out.reshape(y.shape)
    for j in range(Y.shape[1]):
        Z = (Q @ (shrink * (Q.T @ (r * Y[:, j])).unsqueeze(1))) / r.unsqueeze(1)  # (T, L)
        rss = (w.unsqueeze(1) * (Y[:, j:j + 1] - Z) ** 2).sum(dim=0)  # (L,)
        _take_best(Z.unsqueeze(-1), rss.unsqueeze(-1), usable, dof, T, out[:, j:j + 1])
    return out.reshape(y.shape)


def _smooth_block(Y: torch.Tensor, out: torch.Tensor, w: torch.Tensor, r: torch.Tensor, Q: torch.Tensor,
                  shrink: torch.Tensor, usable: torch.Tensor, dof: torch.Tensor) -> None:
    """GCV smoothing of the series ``Y (T, N)`` into ``out (T, N)``, every sum over the points
    accumulated point by point: ``Z = Q diag(shrink) Q^T (r Y) / r`` for every lam, ``(T, L, N)``.
    ``w, r (T,)``: the weights and their square roots; ``Q (T, T)``: the eigenvectors of the
    weighted roughness matrix; ``shrink (T, L)``; ``usable, dof (L,)``: the lams with some degrees
    of freedom left, and those degrees."""
    T = Y.shape[0]
    rY = r.unsqueeze(1) * Y
    U = Q[0].unsqueeze(1) * rY[0]  # (T, N): Q^T (r Y), summed over the points k
    for k in range(1, T):
        U = U + Q[k].unsqueeze(1) * rY[k]
    V = shrink.unsqueeze(-1) * U.unsqueeze(1)  # (T, L, N)
    Z = Q[:, 0].reshape(T, 1, 1) * V[0]
    for i in range(1, T):
        Z = Z + Q[:, i].reshape(T, 1, 1) * V[i]
    Z = Z / r.reshape(T, 1, 1)
    rss = w[0] * (Y[0] - Z[0]) ** 2  # (L, N)
    for k in range(1, T):
        rss = rss + w[k] * (Y[k] - Z[k]) ** 2
    _take_best(Z, rss, usable, dof, T, out)


def _take_best(Z: torch.Tensor, rss: torch.Tensor, usable: torch.Tensor, dof: torch.Tensor, T: int,
               out: torch.Tensor) -> None:
    """Each series' values ``Z (T, L, N)`` at its GCV minimizer over the lams (the first, in a tie;
    none where no lam is usable: the series stays as given), into ``out (T, N)``; ``rss (L, N)``:
    the weighted sums of squared residuals of every lam and series."""
    score = torch.where(usable.unsqueeze(1), T * rss / dof.clamp_min(1e-9).unsqueeze(1) ** 2,
                        torch.full_like(rss, float("inf")))  # (L, N)
    best = torch.argmin(score, dim=0)  # (N,)
    found = torch.isfinite(score.gather(0, best.unsqueeze(0)))[0]
    chosen = Z.gather(1, best.reshape(1, 1, -1).expand(Z.shape[0], 1, -1))[:, 0]
    out.copy_(torch.where(found.unsqueeze(0), chosen, out))


def interpolate(t: torch.Tensor, y: torch.Tensor, tq: torch.Tensor) -> torch.Tensor:
    """Not-a-knot cubic spline through ``(t, y)``, evaluated at ``tq``.

    Parameters
    ----------
    t : Tensor ``(T,)``
        Strictly increasing knots (times).
    y : Tensor ``(T,)`` or ``(T, N)``
        Finite values at the knots: one series, or ``N`` at the same knots.
    tq : Tensor ``(Q,)``
        Query times.

    Returns
    -------
    Tensor ``(Q,)`` or ``(Q, N)``
        The spline's values (the chord for two knots, the parabola for three); constant at
        the end values outside ``[t[0], t[-1]]``, and ``y[0]`` everywhere for one knot.
    """
    if t.shape[0] == 1:
        return y[:1].expand(tq.shape[0], *y.shape[1:]).clone()
    Y = y.reshape(t.shape[0], -1)
    slopes = torch.as_tensor(knot_slopes(t.detach().cpu().double().numpy(), Y.detach().cpu().double().numpy()),
                             dtype=y.dtype, device=y.device)
    inside = tq.clamp(t[0], t[-1])
    j = (torch.searchsorted(t, inside, right=True) - 1).clamp(0, t.shape[0] - 2)
    out = hermite(t, Y, slopes, j, inside)
    return out.reshape(tq.shape[0], *y.shape[1:])
