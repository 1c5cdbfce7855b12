"""The profile's objective at a point, and how finely the integration resolves it.

:func:`sse_of` evaluates, without fitting, what a fit minimizes (a weighted sum of squares, or twice
the negative log-likelihood) along the model integrated from given initial states, as
:func:`torchql.profile` does for a fit of one unknown. :func:`sse_noise` is the change of that
objective the integration's tolerances cannot resolve, below which a profile point "lower than the
fit" is the integration's error, not a better optimum.
"""

from __future__ import annotations

import math

import torch

from .model import coefficients
from .noise import estimate_sigma, negative_log_likelihood, sigma_group_index
from .observations import ObservationOperator, Observations
from .result import FitResult

__all__ = ["sse_noise", "sse_of"]


def sse_noise(result: FitResult, data, options: dict, likelihood: bool) -> float:
    """Differences of the profile's objective below this are integration error, to first order:
    ``2 sqrt(S)`` times the root of ``sum (delta_i / sigma_i)^2``, with ``delta_i = atol + rtol |y_i|``
    each value's local tolerance (relative, ``delta_i / |y_i|``, for log-normal values: an error of
    ``log h``), ``sigma_i`` the standard deviations the objective weighs it with, and ``S`` the
    weighted sum of squares in those units (as the fit's ``CONVERGED_SSE`` test takes it; the second
    order term took a float32 fit's own estimate for a lower optimum, its re-fits at one value
    differing by 7e-4). The sigmas are the data's, or the fit's estimates (``sigma="estimate"``: a
    float32 fit's own estimate was 2e-4 below its 2 NLL, with unit sigmas assumed), or, on the
    likelihood without sigmas, the maximum-likelihood ``sqrt(SSE / n)``, where ``S = n``."""
    from .integrate import default_tolerances

    rtol, atol = default_tolerances(result.x0.dtype, options.get("rtol"), options.get("atol"))
    floor, n = 0.0, 0
    parts = data if isinstance(data, (list, tuple)) else [data]  # each experiment's
    for part in parts:
        used = part.mask & ~part.exact
        y = part.y.abs().to(torch.float64)
        delta = atol + rtol * y
        if part.noise == "lognormal":
            delta = delta / y.clamp_min(torch.finfo(torch.float64).tiny)
        floor += float(((delta / _sigmas(result, part))[used] ** 2).sum())
        n += int(used.sum())
    sse = abs(result.sse)
    if likelihood and not any(part.sigma_given or part.sigma_estimated for part in parts):
        floor, sse = floor * n / max(sse, torch.finfo(torch.float64).tiny), float(n)
    return 2.0 * math.sqrt(sse * floor)


def _sigmas(result: FitResult, part: Observations) -> torch.Tensor:
    """The standard deviations ``(T, K)`` (or broadcastable) that the fit ``result`` weighed the
    values of ``part`` with: its estimates where ``sigma="estimate"``, else the data's."""
    sigma = part.sigma.to(torch.float64)
    if not part.sigma_estimated or not isinstance(result.sigma, dict):
        return sigma
    labels = ObservationOperator(part.observe, result.model.state_names, part.n_outputs, torch.float64,
                                 torch.device("cpu")).labels()
    names, group = sigma_group_index(part.sigma_groups, part.n_outputs, labels)
    fitted = [result.sigma.get(names[g], math.nan) for g in group]
    return torch.where(torch.isnan(torch.tensor(fitted, dtype=torch.float64)), sigma,
                       torch.tensor(fitted, dtype=torch.float64))


def sse_of(model, x0: torch.Tensor, t0: float, data: Observations, options: dict, likelihood: bool = False) -> float:
    """Weighted SSE over the least-squares values of ``model`` integrated from ``x0`` (no fitting);
    with ``likelihood``, twice the negative log-likelihood (sigmas at their maximum-likelihood
    values when estimated, the residual variance at its maximum ``SSE / n`` when not given, log-normal
    values in log space; see :mod:`torchql.noise`)."""
    from .integrate import IntegrationError, simulate

    dtype, device = x0.dtype, x0.device
    try:
        x = simulate(model, x0, data.t.to(dtype=dtype, device=device), t0=t0, solver=options.get("solver", "dopri5"),
                     rtol=options.get("rtol"), atol=options.get("atol"))
    except IntegrationError:
        return math.nan
    operator = ObservationOperator(data.observe, model.state_names, data.n_outputs, dtype, device)
    value = operator.values(x, coefficients(model))
    y = data.y.to(dtype=dtype, device=device)
    counted = data.mask.to(device) & ~data.exact.to(device)
    log_y = torch.zeros((), dtype=dtype, device=device)
    if data.noise == "lognormal":
        log_y = torch.log(y)[counted].sum()
        y, value = torch.log(y), torch.log(value)
    sigma = data.sigma_at(coefficients(model)).to(dtype=dtype, device=device)
    if likelihood and data.sigma_estimated:
        _, group = sigma_group_index(data.sigma_groups, data.n_outputs, operator.labels())
        group = torch.tensor(group, dtype=torch.long, device=device)
        sigma = estimate_sigma((y - value).unsqueeze(0), counted.unsqueeze(0), group, int(group.max()) + 1)[0]
        sigma = sigma[group].expand_as(y)
    r = ((y - value) / sigma)[counted]
    if not likelihood:
        return float((r ** 2).sum())
    n = torch.tensor(float(r.numel()), dtype=dtype)
    if not (data.sigma_given or data.sigma_estimated):  # the residual variance at its maximum, SSE / n, as the fit's
        return 2 * float(negative_log_likelihood(n, 0.5 * n * torch.log((r ** 2).sum() / n), n, log_y))
    return 2 * float(negative_log_likelihood((r ** 2).sum(), torch.log(sigma[counted]).sum(), n, log_y))
