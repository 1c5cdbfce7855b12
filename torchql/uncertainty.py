"""Uncertainty of the estimates: covariance from the final Jacobian, and Wald intervals.

At convergence the homogeneous solutions at the observation times are the Jacobian ``J`` of
the (weighted) observations with respect to the unknowns. The covariance of the estimates is
``s^2 N (N^T J^T J N)^{-1} N^T``, where ``N`` spans the directions left free by the values
marked exact (``N = I`` without them) and ``s^2`` is the residual variance: ``SSE / dof``
when the data's ``sigma`` is not given, ``1`` when it is (the residuals are then already in
units of their standard deviation). ``dof = L - m``: the least-squares values minus the
unknowns that the exact values do not already fix. The inverse is taken through an SVD of the
column-scaled ``J N``, never by forming ``J^T J``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

__all__ = ["Covariance", "covariance", "redundant_exact", "residual_variance", "normal_quantile", "student_t_quantile",
           "wald_intervals"]


class Covariance(NamedTuple):
    """Result of :func:`covariance`.

    Attributes
    ----------
    matrix : Tensor ``(m, m)``
        Covariance of the unknowns (NaN rows and columns for unknowns the data cannot determine).
    dof : int
        Degrees of freedom of the residuals.
    residual_variance : float
        ``s^2`` used (1 when ``sigma`` is known; NaN when ``dof <= 0`` and it is not).
    """

    matrix: torch.Tensor
    dof: int
    residual_variance: float


def residual_variance(sse: torch.Tensor, dof: torch.Tensor, sigma_known: bool) -> torch.Tensor:
    """The residual variance ``s^2 (S,)`` of fits with sums of squares ``sse (S,)`` and degrees of
    freedom ``dof (S,)``: 1 where the data's sigma is known (the residuals are then in units of
    their standard deviations), else ``SSE / dof``, NaN where no degree of freedom is left."""
    if sigma_known:
        return torch.ones_like(sse)
    dof = dof.to(sse.dtype)
    return torch.where(dof > 0, sse / dof.clamp(min=1), torch.full_like(sse, float("nan")))


def covariance(jacobian: torch.Tensor, exact: torch.Tensor, sse: float, sigma_known: bool,
               rcond: float) -> Covariance:
    """Covariance of the estimates from the weighted Jacobian at the optimum.

    Parameters
    ----------
    jacobian : Tensor ``(L, m)``
        Weighted sensitivities of every used value (exact ones included).
    exact : bool Tensor ``(L,)``
        Values met exactly.
    sse : float
        Weighted sum of squares over the least-squares values.
    sigma_known : bool
        Whether the weights are true standard deviations.
    rcond : float
        Relative singular-value threshold. Unknowns with a component along a direction whose
        singular value falls below it get NaN variances and covariances; the others keep theirs.
        A zero column (an unknown, or a combination left free by the exact values, that moves no
        value) is such a direction, with singular value 0: it takes only its own unknowns' error bars.
    """
    L, m = jacobian.shape
    nan = torch.full((m, m), float("nan"), dtype=jacobian.dtype, device=jacobian.device)
    free, redundant = _exact_null_space(jacobian, exact, rcond)
    dof = L - m - redundant
    s2 = 1.0 if sigma_known else sse / dof if dof > 0 else float("nan")  # (residual_variance, for one fit)
    if free is None:
        return Covariance(nan, dof, s2)
    A = jacobian[~exact] @ free
    if A.shape[1] == 0:
        return Covariance(torch.zeros_like(nan), dof, s2)
    scale = torch.linalg.vector_norm(A, dim=0)
    # a zero column is a direction the data do not see: its singular value is 0 and it is
    # dropped like any other below ``rcond``, so only the unknowns along it lose their variance
    scale = torch.where(scale > 0, scale, torch.ones_like(scale))
    _, S, Vh = torch.linalg.svd(A / scale, full_matrices=True)
    r = S.shape[0]
    keep = S > rcond * S[0]
    rows = Vh[:r][keep]
    inner = (rows.T / S[keep] ** 2) @ rows / scale.unsqueeze(-1) / scale.unsqueeze(0)
    cov = s2 * free @ inner @ free.T
    cov = 0.5 * (cov + cov.T)
    null = torch.cat([Vh[:r][~keep], Vh[r:]], dim=0)  # scaled directions the data cannot determine
    if null.shape[0]:
        # an unknown is determined only if it has no component along an undetermined direction;
        # the others keep their (pseudo-inverse) variance, as lmfit reports what it can
        directions = free @ (null.T / scale.unsqueeze(-1))
        directions = directions / torch.linalg.vector_norm(directions, dim=0, keepdim=True)
        undetermined = (directions.abs() > 1e-6).any(dim=1)
        cov[undetermined, :] = float("nan")
        cov[:, undetermined] = float("nan")
    return Covariance(cov, dof, s2)


def redundant_exact(jacobian: torch.Tensor, exact: torch.Tensor, rcond: float) -> int:
    """How many of the values marked ``exact (L,)`` repeat what the others fix: their count less the
    rank of their rows of ``jacobian (L, m)`` (a known initial state also marked exact, or one state
    seen by two sensors marked exact at one time, fixes nothing more). Each independent exact value
    fixes one unknown and is no least-squares value; a redundant one fixes none, and the fit's
    ``dof`` is ``L - m`` less their number (with a full-rank ``dof = L - m``, ``L`` every used value).
    Ranked with the columns scaled to unit norm over all rows (:func:`_column_scale`)."""
    return _exact_null_space(jacobian, exact, rcond)[1]


def _exact_null_space(jacobian: torch.Tensor, exact: torch.Tensor, rcond: float) -> tuple[torch.Tensor | None, int]:
    """The directions ``(m, f)`` that the rows ``exact (L,)`` of ``jacobian (L, m)`` leave free (their
    null space, ranked in unknowns of unit columns: :func:`_column_scale`; all ``m`` without exact
    values), and how many of those rows repeat the others (:func:`redundant_exact`). ``(None, 0)``
    for a Jacobian that is not finite."""
    m = jacobian.shape[1]
    if not bool(torch.isfinite(jacobian).all()):
        return None, 0
    if not bool(exact.any()):
        return torch.eye(m, dtype=jacobian.dtype, device=jacobian.device), 0
    units = _column_scale(jacobian)  # (ranked in unknowns of unit columns: not in the units' sizes)
    _, S_e, Vh_e = torch.linalg.svd(jacobian[exact] / units, full_matrices=True)
    rank = _rank(S_e, rcond)
    return Vh_e[rank:].T / units.unsqueeze(-1), int(exact.sum()) - rank


def _column_scale(jacobian: torch.Tensor) -> torch.Tensor:
    """Each column's norm ``(m,)`` of ``jacobian (L, m)`` (1 where it is zero): the unknowns' scaling
    in which ranks do not depend on their units (a rate in 1/s, 1e-8, against an initial value of 1
    had an independent exact value counted as repeating the other)."""
    norms = torch.linalg.vector_norm(jacobian, dim=0)
    return torch.where(norms > 0, norms, torch.ones_like(norms))


def _rank(singular_values: torch.Tensor, rcond: float) -> int:
    """The number of ``singular_values`` (decreasing) above ``rcond`` times the largest (0 if all vanish)."""
    if not singular_values.numel() or float(singular_values[0]) == 0.0:
        return 0
    return int((singular_values > rcond * singular_values[0]).sum())


def normal_quantile(p: float) -> float:
    """Quantile of the standard normal distribution."""
    return float(torch.special.ndtri(torch.tensor(p, dtype=torch.float64)))


def _betacf(a: float, b: float, x: float) -> float:
    """Continued fraction of the regularized incomplete beta function (modified Lentz)."""
    tiny = 1e-300
    qab, qap, qam = a + b, a + 1.0, a - 1.0
    c, d = 1.0, 1.0 - qab * x / qap
    d = 1.0 / (d if abs(d) > tiny else tiny)
    h = d
    for k in range(1, 500):
        k2 = 2 * k
        aa = k * (b - k) * x / ((qam + k2) * (a + k2))
        d = 1.0 + aa * d
        d = 1.0 / (d if abs(d) > tiny else tiny)
        c = 1.0 + aa / c if abs(1.0 + aa / c) > tiny else tiny
        h *= d * c
        aa = -(a + k) * (qab + k) * x / ((a + k2) * (qap + k2))
        d = 1.0 + aa * d
        d = 1.0 / (d if abs(d) > tiny else tiny)
        c = 1.0 + aa / c if abs(1.0 + aa / c) > tiny else tiny
        delta = d * c
        h *= delta
        if abs(delta - 1.0) < 1e-15:
            break
    return h


def _betainc(a: float, b: float, x: float, y: float) -> float:
    """Regularized incomplete beta function ``I_x(a, b)``, given ``x`` and ``y = 1 - x`` (both accurate)."""
    if x <= 0.0:
        return 0.0
    if y <= 0.0:
        return 1.0
    front = math.exp(math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b) + a * math.log(x) + b * math.log(y))
    if x < (a + 1.0) / (a + b + 2.0):
        return front * _betacf(a, b, x) / a
    return 1.0 - front * _betacf(b, a, y) / b


def _student_t_cdf(t: float, dof: float) -> float:
    half = 0.5 * _betainc(0.5, 0.5 * dof, t * t / (dof + t * t), dof / (dof + t * t))
    return 0.5 + half if t >= 0 else 0.5 - half


def student_t_quantile(p: float, dof: float) -> float:
    """Quantile of Student's t distribution with ``dof`` degrees of freedom (bisection on the CDF)."""
    if not 0.0 < p < 1.0:
        raise ValueError(f"`p` must lie strictly between 0 and 1; received {p!r}")
    if dof <= 0:
        raise ValueError(f"`dof` must be positive; received {dof!r}")
    lo, hi = -1.0, 1.0
    while _student_t_cdf(lo, dof) > p:
        lo *= 2.0
    while _student_t_cdf(hi, dof) < p:
        hi *= 2.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if _student_t_cdf(mid, dof) < p:
            lo = mid
        else:
            hi = mid
        if hi - lo <= 1e-13 * max(1.0, abs(mid)):
            break
    return 0.5 * (lo + hi)


#: A bounded unknown whose mapped interval reaches further from the estimate than this many times the
#: Wald half-width ``q * stderr`` (in its own units, whatever its scale), or whose internal variable's
#: half-width exceeds :data:`NEAR_BOUND_WIDTH` (two bounds: the interval spans their range), gets the
#: interval about the estimate clipped to its bounds instead (a positive rate whose interval crosses
#: 0 reaches twice as far).
NEAR_BOUND_REACH = 20.0
NEAR_BOUND_WIDTH = 3.0


def wald_intervals(names, estimates, stderr: dict, dof: int, sigma_known: bool, level: float,
                   lower: torch.Tensor | None = None, upper: torch.Tensor | None = None,
                   valid: bool = True, log: torch.Tensor | None = None,
                   kinds: dict | None = None) -> dict[str, tuple[float, float]]:
    """Wald intervals at confidence ``level``, by name (and in ``kinds``, if given, each interval's
    kind by name: ``"wald"``, ``"mapped"`` from the internal variable, or ``"clipped"``).

    An unbounded unknown gets ``estimate -/+ q * stderr``. A bounded one (``lower``/``upper``,
    Tensors ``(m,)`` in the order of ``names``, infinite where a side is open; ``None``: all
    unbounded) gets the Wald interval of its internal variable ``q`` of
    :class:`torchql.bounds.Bounds` (``log(u - lo)``, ``log(hi - u)`` or ``logit((u - lo) / (hi - lo))``),
    ``q_hat -/+ q * stderr / |du/dq|``, mapped back to ``u``: it lies inside the bounds and is
    asymmetric about the estimate (the delta method's standard error of ``q``). So does an
    unknown on a log scale (``log (m,)`` bool, ``None``: none), whose ``q`` is in ``log u``. An
    estimate on its bound (:meth:`~torchql.bounds.Bounds.at_bound`), where ``du/dq`` vanishes, or
    so near one that the mapped interval reaches past :data:`NEAR_BOUND_REACH` times ``q * stderr``
    or the internal half-width past :data:`NEAR_BOUND_WIDTH`, gets ``estimate -/+ q * stderr``
    clipped to the bounds (and to 0 on a log scale).

    ``q`` is Student's t quantile with ``dof`` degrees of freedom when the residual variance
    was estimated (NaN without degrees of freedom), the normal quantile when ``sigma`` was
    known. ``estimates`` is in the order of ``names``; ``stderr`` maps a name to its standard
    error. With ``valid`` False (the fit did not converge), and for an unknown without a finite
    standard error, both ends are NaN.
    """
    if not (isinstance(level, float) and 0.0 < level < 1.0):
        raise ValueError(f"`level` must be a float strictly between 0 and 1; received {level!r}")
    p = 0.5 + 0.5 * level
    if sigma_known:
        q = normal_quantile(p)
    else:
        q = student_t_quantile(p, dof) if dof > 0 else float("nan")
    names = list(names)
    nan = float("nan")
    if not valid:
        return {name: (nan, nan) for name in names}
    u = torch.as_tensor(estimates).detach().reshape(-1)
    ses = [float(stderr[name]) for name in names]
    out = {name: (float(v) - q * s, float(v) + q * s) for name, v, s in zip(names, u, ses)}
    kinds = {} if kinds is None else kinds
    kinds.update((name, "wald") for name in names)
    if lower is not None or upper is not None or (log is not None and bool(log.any())):
        from .bounds import Bounds

        inf = torch.full_like(u, math.inf)
        bounds = Bounds.of(-inf if lower is None else lower.to(u), inf if upper is None else upper.to(u), names,
                           log)
        bounded = bounds.transformed_at(u)
        if bool(bounded.any()):
            se = torch.tensor(ses, dtype=u.dtype, device=u.device)
            slope = bounds.derivative(u).abs()
            se_q = torch.where(se == 0, torch.zeros_like(se), se / slope)
            q_hat = bounds.internal(u)
            a, b = bounds.external(q_hat - q * se_q, u), bounds.external(q_hat + q * se_q, u)
            ends = torch.stack([torch.minimum(a, b), torch.maximum(a, b)])  # u falls with q below an upper bound only
            for i in bounded.nonzero().flatten().tolist():
                out[names[i]] = (float(ends[0, i]), float(ends[1, i]))
                kinds[names[i]] = "mapped"
            # on its bound the internal variable's standard error is unbounded (``du/dq`` -> 0): the
            # interval about the estimate, clipped to the bounds (a c >= 0 at 4e-36 with standard
            # error 0.0047 had (0, inf)); so near one, where the mapped interval reaches past
            # NEAR_BOUND_REACH times the Wald half-width and the internal variable's linearization
            # means nothing over it (k >= 1.2 at 1.20057, standard error 0.0107: (1.2, 8.4e12))
            near = set(bounds.at_bound(u, stderr=se))
            reach = torch.maximum(ends[1] - u, u - ends[0])  # in the unknown's units, whatever its scale
            wide = (reach > NEAR_BOUND_REACH * q * se) | (q * se_q > NEAR_BOUND_WIDTH)
            wide &= bounds.has_lower | bounds.has_upper
            near |= {names[i] for i in (bounded & wide).nonzero().flatten().tolist()}
            for name in sorted(near, key=names.index):
                i = names.index(name)
                lo, hi = float(bounds.lower[i]), float(bounds.upper[i])
                if bool(bounds.log[i]):  # a log scale's edge is 0
                    lo = max(lo, 0.0)
                out[name] = (max(lo, float(u[i]) - q * ses[i]), min(hi, float(u[i]) + q * ses[i]))
                kinds[name] = "clipped"
    return {name: ends if math.isfinite(s) else (nan, nan) for (name, ends), s in zip(out.items(), ses)}
