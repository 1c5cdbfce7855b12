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

from .budget import check_time
from .splines import hermite_per_sample, knot_slopes

__all__ = ["smooth", "smooth_each", "interpolate", "interpolate_each", "MAX_SMOOTHED_POINTS", "SMOOTHED_MEANS",
           "SUMMED_POINTS", "SUMMED_SERIES"]

#: Longer series are smoothed as the weighted means of runs of consecutive points, at most
#: :data:`SMOOTHED_MEANS` of them (the dense GCV's eigendecomposition is cubic in the points: 0.16 s
#: at 1,000, 1.1 s at 2,000), the smoothed means' spline read back at every time. (Used as given,
#: 20,000 noisy values of an oscillation started its data-built fit at 400 times its frequency squared.)
MAX_SMOOTHED_POINTS = 1000
#: At most this many means of a longer series are smoothed (about 3 ms).
SMOOTHED_MEANS = 250
#: Series of at most this many points are smoothed together, their sums accumulated point by point
#: (longer ones series by series, with matrix products).
SUMMED_POINTS = 64
#: Series smoothed together in one block (its arrays hold points x lams x series values).
SUMMED_SERIES = 2048


def _roughness(t: torch.Tensor) -> torch.Tensor:
    """``P = D^T D (N, T, T)``: the roughness penalty of series on the times ``t (N, T)``, ``D (T-2, T)``
    their second divided differences on the (possibly uneven) times, each row scaled by the
    square root of its local spacing.

    ``P`` is pentadiagonal; its diagonals are summed from each row's three coefficients elementwise,
    so that a series' penalty has the same bits whichever series share its batch."""
    h = t[:, 1:] - t[:, :-1]
    a, b = h[:, :-1], h[:, 1:]
    width = (a + b) / 2
    scale = width.sqrt()
    c0, c1, c2 = scale / (a * width), -scale * (1 / a + 1 / b) / width, scale / (b * width)  # (N, T-2)
    zero = torch.zeros_like(t[:, :2])
    pad = lambda x, before: torch.cat([zero[:, :before], x, zero[:, :2 - before]], dim=1)  # noqa: E731  (N, T)
    diag = pad(c0 * c0, 0) + pad(c1 * c1, 1) + pad(c2 * c2, 2)
    upper1 = pad(c0 * c1, 0)[:, :-1] + pad(c1 * c2, 1)[:, :-1]  # (i, i + 1): rows i and i - 1
    upper2 = (c0 * c2)  # (i, i + 2): row i
    P = t.new_zeros(t.shape[0], t.shape[1], t.shape[1])
    for offset, band in ((0, diag), (1, upper1), (-1, upper1), (2, upper2), (-2, upper2)):
        P.diagonal(offset, dim1=1, dim2=2).copy_(band)
    return P


def _operators(t: torch.Tensor, w: torch.Tensor, lams: torch.Tensor | None):
    """The GCV smoother of series on the times ``t (N, T)`` with weights ``w (N, T)``: ``(r (N, T),
    Q (N, T, T), shrink (N, T, L), dof (N, L), usable (N, L))``, the square roots of the weights,
    the eigenvectors of the weighted roughness matrix, the factor of each eigen-direction for each
    candidate ``lam``, the degrees of freedom left, and whether they are some.

    With ``u = sqrt(w) z`` the hat matrix is ``(I + lam Pw)^-1``, ``Pw = W^-1/2 P W^-1/2``, diagonal
    in ``Pw``'s eigenvectors: one eigendecomposition serves every lam. ``lams`` (default a
    logarithmic range scaled to each series' span, ``(N, L)``) are the candidates."""
    T = t.shape[1]
    if lams is None:
        # lam * span^-3-ish balances the roughness term against one squared residual per point, of
        # the series' mean weight: sigmas all s times larger ask lam / s^2 (their range at unit
        # weights, else a sigma of 1e6 left only flat smoothings, and the fit from them ran to max_iter)
        span = (t[:, -1] - t[:, 0]).unsqueeze(1)
        lams = (torch.logspace(-12, 2, 29, dtype=t.dtype, device=t.device).unsqueeze(0) * span ** 3 / T
                * w.mean(dim=1, keepdim=True))
    r = w.sqrt()
    # one eigendecomposition per series, each copied to a buffer of its own by eigh: in one batched
    # call a series' matrix sits at an offset that LAPACK's kernels may take another path for (MKL
    # on some CPUs, where T is odd), and its bits would then depend on the series batched with it
    # (the time budget is checked before each: one of MAX_SMOOTHED_POINTS takes about 0.16 s)
    pairs = []
    for matrix in _roughness(t) / r.unsqueeze(1) / r.unsqueeze(2):
        check_time()
        pairs.append(torch.linalg.eigh(matrix))
    evals, Q = torch.stack([e for e, _ in pairs]), torch.stack([q for _, q in pairs])
    evals = evals.clamp_min(0)
    shrink = 1 / (1 + lams.to(evals).reshape(-1, 1, lams.shape[-1]) * evals.unsqueeze(2))  # (N, T, L)
    dof = T - shrink.sum(dim=1)
    return r, Q, shrink, dof, dof > 1e-9


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
    lams : Tensor ``(L,)``, optional
        Candidate smoothing parameters (default a logarithmic range scaled to the data's time
        span); each series takes its GCV minimizer (the first, in a tie).

    Returns
    -------
    Tensor, the shape of ``y``
        The smoothed values (``y`` itself for fewer than 4 points; beyond
        :data:`MAX_SMOOTHED_POINTS`, those of the runs' means, :func:`_smooth_means`).
    """
    T = t.shape[0]
    if T < 4:
        return y.clone()
    if T > MAX_SMOOTHED_POINTS:
        return _smooth_means(t, y, weights, lams)
    Y = y.reshape(T, -1).T  # (N, T)
    w = torch.ones_like(t) if weights is None else weights
    operators = _operators(t.unsqueeze(0), w.unsqueeze(0), None if lams is None else lams.unsqueeze(0))
    return _smooth_series(Y, w.expand_as(Y), operators).T.reshape(y.shape)


def _smooth_means(t: torch.Tensor, y: torch.Tensor, weights: torch.Tensor | None, lams) -> torch.Tensor:
    """:func:`smooth` of a series longer than :data:`MAX_SMOOTHED_POINTS`: the weighted means of runs of
    ``k = ceil(T / SMOOTHED_MEANS)`` consecutive points (their weights summed, at their weighted
    mean times) smoothed, and their spline (:func:`interpolate`) read at every time ``t`` (beyond the
    first and last means' times, along the end chords)."""
    T = t.shape[0]
    k = -(-T // SMOOTHED_MEANS)
    w = torch.ones_like(t) if weights is None else weights
    run = torch.arange(T, device=t.device) // k
    count = int(run[-1]) + 1
    w_sum = torch.zeros(count, dtype=t.dtype, device=t.device).index_add_(0, run, w)
    t_mean = torch.zeros_like(w_sum).index_add_(0, run, w * t) / w_sum
    Y = y.reshape(T, -1)
    y_mean = torch.zeros(count, Y.shape[1], dtype=y.dtype, device=y.device).index_add_(0, run, w.unsqueeze(1) * Y)
    smoothed = smooth(t_mean, y_mean / w_sum.unsqueeze(1), w_sum, lams)
    out = interpolate(t_mean, smoothed, t)
    # before the first mean's time and after the last (half a run): along the end chords, not constant
    for end, near, outside in ((0, 1, t < t_mean[0]), (-1, -2, t > t_mean[-1])):
        slope = (smoothed[near] - smoothed[end]) / (t_mean[near] - t_mean[end])
        out[outside] = smoothed[end] + (t[outside] - t_mean[end]).unsqueeze(1) * slope
    return out.reshape(y.shape)


def smooth_each(t: torch.Tensor, y: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Smoothed values ``(N, T)`` of ``N`` series ``y (N, T)``, each on its own times ``t (N, T)``
    with its own weights ``weights (N, T)``: row ``n`` is ``smooth(t[n], y[n], weights[n])``, bit for
    bit, at the cost of one eigendecomposition per series and (short series) one pass over the points."""
    N, T = y.shape
    if T < 4:
        return y.clone()
    if T > SUMMED_POINTS:
        return torch.stack([smooth(t[n], y[n], weights[n]) for n in range(N)])
    out = torch.empty_like(y)
    for start in range(0, N, SUMMED_SERIES):
        block = slice(start, start + SUMMED_SERIES)
        out[block] = _smooth_series(y[block], weights[block], _operators(t[block], weights[block], None))
    return out


def _smooth_series(Y: torch.Tensor, w: torch.Tensor, operators: tuple) -> torch.Tensor:
    """GCV-smoothed series ``Y (N, T)`` with weights ``w (N, T)``, by the smoothers ``operators``
    (:func:`_operators`, of ``N`` series or one shared by all).

    A series gives the same values bit for bit whatever others are smoothed with it (fit_many's
    data start is fit's): short series in blocks whose sums over the points are accumulated one
    point at a time (elementwise, so each series' arithmetic is its own); long ones series by
    series, every lam at once."""
    N, T = Y.shape
    r, Q, shrink, dof, usable = (x.expand(N, *x.shape[1:]) for x in operators)
    out = Y.clone()
    if T <= SUMMED_POINTS:
        for start in range(0, N, SUMMED_SERIES):
            b = slice(start, start + SUMMED_SERIES)
            _smooth_block(Y[b], out[b], w[b], r[b], Q[b], shrink[b], usable[b], dof[b])
        return out
    for j in range(N):
        Z = (Q[j] @ (shrink[j] * (Q[j].T @ (r[j] * Y[j])).unsqueeze(1))) / r[j].unsqueeze(1)  # (T, L)
        rss = (w[j].unsqueeze(1) * (Y[j].unsqueeze(1) - Z) ** 2).sum(dim=0)  # (L,)
        _take_best(Z.unsqueeze(0), rss.unsqueeze(0), usable[j:j + 1], dof[j:j + 1], T, out[j:j + 1])
    return out


def _smooth_block(Y: torch.Tensor, out: torch.Tensor, w: torch.Tensor, r: torch.Tensor, Q: torch.Tensor,
                  shrink: torch.Tensor, usable: torch.Tensor, dof: torch.Tensor) -> None:
    """GCV smoothing of the series ``Y (N, T)`` into ``out (N, T)``, every sum over the points
    accumulated point by point: ``Z = Q diag(shrink) Q^T (r Y) / r`` for every lam, ``(N, T, L)``.
    ``w, r (N, T)``: the weights and their square roots; ``Q (N, T, T)``: the eigenvectors of the
    weighted roughness matrices; ``shrink (N, T, L)``; ``usable, dof (N, L)``: the lams with some
    degrees of freedom left, and those degrees."""
    T = Y.shape[1]
    rY = r * Y
    U = Q[:, 0] * rY[:, :1]  # (N, T): Q^T (r Y), summed over the points k
    for k in range(1, T):
        U = U + Q[:, k] * rY[:, k:k + 1]
    V = shrink * U.unsqueeze(2)  # (N, T, L)
    Z = Q[:, :, :1] * V[:, :1]
    for i in range(1, T):
        Z = Z + Q[:, :, i:i + 1] * V[:, i:i + 1]
    Z = Z / r.unsqueeze(2)
    rss = w[:, :1] * (Y[:, :1] - Z[:, 0]) ** 2  # (N, L)
    for k in range(1, T):
        rss = rss + w[:, k:k + 1] * (Y[:, k:k + 1] - Z[:, k]) ** 2
    _take_best(Z, rss, usable, dof, T, out)


def _take_best(Z: torch.Tensor, rss: torch.Tensor, usable: torch.Tensor, dof: torch.Tensor, T: int,
               out: torch.Tensor) -> None:
    """Each series' values ``Z (N, T, L)`` at its GCV minimizer over the lams (the first, in a tie;
    none where no lam is usable: the series stays as given), into ``out (N, T)``; ``rss (N, L)``:
    the weighted sums of squared residuals of every series and lam."""
    score = torch.where(usable, T * rss / dof.clamp_min(1e-9) ** 2, torch.full_like(rss, float("inf")))  # (N, L)
    best = torch.argmin(score, dim=1)  # (N,)
    found = torch.isfinite(score.gather(1, best.unsqueeze(1)))[:, 0]
    chosen = Z.gather(2, best.reshape(-1, 1, 1).expand(-1, Z.shape[1], 1))[:, :, 0]
    out.copy_(torch.where(found.unsqueeze(1), chosen, out))


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
    Y = y.reshape(t.shape[0], -1).T  # (N, T)
    N = Y.shape[0]
    out = interpolate_each(t.expand(N, -1), Y, tq.expand(N, -1))  # (N, Q)
    return out.T.reshape(tq.shape[0], *y.shape[1:])


def interpolate_each(t: torch.Tensor, y: torch.Tensor, tq: torch.Tensor) -> torch.Tensor:
    """:func:`interpolate` of ``N`` series, each on its own knots: ``y (N, T)`` at ``t (N, T)``
    (strictly increasing rows), evaluated at ``tq (N, Q)``: ``(N, Q)``, row ``n`` the same bits as
    ``interpolate(t[n], y[n], tq[n])`` (``y[n, 0]`` everywhere for one knot)."""
    if t.shape[1] == 1:
        return y.expand(-1, tq.shape[1]).clone()
    slopes = torch.as_tensor(knot_slopes(t.detach().cpu().double().numpy().T, y.detach().cpu().double().numpy().T).T,
                             dtype=y.dtype, device=y.device)
    inside = torch.minimum(torch.maximum(tq, t[:, :1]), t[:, -1:])
    values, _ = hermite_per_sample(t, y.unsqueeze(-1), slopes.unsqueeze(-1), inside)
    return values[..., 0]
