"""Noise models: Gaussian with known or estimated standard deviations, and log-normal.

A dataset's noise is ``Observations(..., noise=..., sigma=..., sigma_groups=...)``:

* ``noise="normal"`` (default): ``y = h(x) + e``, ``e ~ N(0, sigma^2)``;
* ``noise="lognormal"``: ``log y = log h(x) + e`` (positive values, multiplicative errors, as
  concentrations have); the fit then works on ``log y`` and ``log h(x)``, and ``sigma`` is the
  standard deviation of ``log y``.

``sigma`` is known (a value, as before), or ``"estimate"``: one standard deviation per group of
outputs, estimated with the unknowns by maximum likelihood. ``sigma_groups`` gives each output's
group: ``None`` (default) one group per output, ``"shared"`` one for all, or a label per output
(outputs with the same label share their sigma; with several experiments, the same label, or
the same observed state by default, is one sigma for all experiments).

**Estimation.** For fixed coefficients the likelihood's maximum over a group's sigma is
``sigma_g^2 = SSE_g / n_g`` (the group's sum of squared residuals over its number of values), and
the gradient of the profile negative log-likelihood ``sum_g n_g / 2 log SSE_g`` in the unknowns
is that of the sum of squares weighted by ``1 / sigma_g^2``. So the maximum-likelihood estimates
are the fixed point of: fit the weighted least squares, set each ``sigma_g`` from its residuals,
repeat (:func:`run_with_noise`, warm-started each round from the last estimates) until the sigmas
settle to :data:`SIGMA_RTOL`. At the fixed point the weighted sum of squares is the number of
values, and the covariance of the unknowns is ``(J^T W J)^-1`` with those weights (the sigmas
are asymptotically independent of the unknowns for Gaussian noise).

**Likelihood.** Every fit reports the negative log-likelihood of its data at the estimates
(:func:`negative_log_likelihood`): ``sum_i log sigma_i + n/2 log(2 pi) + SSE_w / 2`` over the
least-squares values, plus ``sum_i log y_i`` for log-normal noise (the density of ``y``, not of
``log y``). Without ``sigma`` the residual variance is the maximum-likelihood ``SSE / n``. AIC and
BIC follow from it, counting the estimated sigmas as unknowns.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from .status import Status

__all__ = ["NOISE_MODELS", "SIGMA_RTOL", "MAX_SIGMA_ROUNDS", "sigma_group_index", "estimate_sigma",
           "negative_log_likelihood", "run_with_noise"]

#: The noise distributions of :class:`torchql.Observations`.
NOISE_MODELS = ("normal", "lognormal")
#: The estimated sigmas have settled when no one changes by more than this, relative.
SIGMA_RTOL = 1e-9
#: Most rounds of estimating the sigmas and re-fitting.
MAX_SIGMA_ROUNDS = 50


def sigma_group_index(groups, K: int, labels: Sequence[str]) -> tuple[list[str], list[int]]:
    """``(group names, group of each of the K outputs)`` from ``Observations``' ``sigma_groups``.

    ``labels`` name the outputs (the observed state, else ``"y[k]"``) for the default grouping.
    """
    if groups is None:
        names = list(dict.fromkeys(labels))
        return names, [names.index(label) for label in labels]
    if isinstance(groups, str):
        if groups != "shared":
            raise ValueError(f"`sigma_groups` must be None, 'shared' or one label per output; received {groups!r}")
        return ["sigma"], [0] * K
    if not isinstance(groups, Sequence) or len(groups) != K:
        received = len(groups) if isinstance(groups, Sequence) else type(groups).__name__
        raise ValueError(f"`sigma_groups` must give one label per output (K = {K}); received {received}")
    names = list(dict.fromkeys(str(g) for g in groups))
    return names, [names.index(str(g)) for g in groups]


def estimate_sigma(residual: torch.Tensor, counted: torch.Tensor, group: torch.Tensor, n_groups: int) -> torch.Tensor:
    """Maximum-likelihood sigmas ``(B, G)``: ``sqrt(SSE_g / n_g)`` of the unweighted ``residual
    (B, T, K)`` over the ``counted`` values, ``group (K,)`` each output's group (NaN for a group
    without values)."""
    r2 = torch.where(counted, residual, torch.zeros_like(residual)) ** 2
    one_hot = torch.nn.functional.one_hot(group, n_groups).to(residual.dtype)  # (K, G)
    sse = torch.einsum("btk,kg->bg", r2, one_hot)
    count = torch.einsum("btk,kg->bg", counted.to(residual.dtype), one_hot)
    return torch.where(count > 0, (sse / count.clamp(min=1)).sqrt(), torch.full_like(sse, float("nan")))


def negative_log_likelihood(sse_weighted: torch.Tensor, log_sigma_sum: torch.Tensor, n: torch.Tensor,
                            log_y_sum: torch.Tensor | float = 0.0) -> torch.Tensor:
    """``sum log sigma_i + n/2 log(2 pi) + SSE_w / 2 (+ sum log y_i)``, per sample ``(B,)``."""
    return log_sigma_sum + 0.5 * n * math.log(2 * math.pi) + 0.5 * sse_weighted + log_y_sum


def run_with_noise(spec, run):
    """``run(spec)`` (the engine on the problem ``spec``, a :class:`torchql.problem.Problem`), and
    with estimated sigmas the rounds of :mod:`torchql.noise` until they settle. Sets the result's
    ``nll``, ``sigma`` and ``sigma_names``; returns it."""
    result = run(spec)
    if spec.sigma_estimated:
        first, rounds = result, 1
        total = result.iterations.clone()
        while rounds < MAX_SIGMA_ROUNDS:
            sigma = _sigma_of(spec, result)
            used = spec.sigma_per_group  # those of `result`'s weights
            if used is not None and bool(((sigma - used).abs() <= SIGMA_RTOL * used.abs()).all()):
                break
            if any(status is Status.MAX_TIME for status in result.status):
                break  # out of time: the last round's estimates, at its sigmas
            spec.set_sigma(sigma)
            spec.warm_start(result.estimates)
            result = run(spec)
            total += result.iterations
            rounds += 1
        result.iterations = total
        result.start_params, result.start_x0, result.sse_start = first.start_params, first.start_x0, first.sse_start
        if spec.sigma_per_group is None:  # out of time in the first, unweighted, round: no estimate
            result.sigma = torch.full((spec.B, len(spec.sigma_names)), float("nan"), dtype=spec.dtype,
                                      device=spec.device)
        else:
            result.sigma = spec.sigma_per_group.clone()
        result.sigma_names = list(spec.sigma_names)
    result.noise = spec.noise
    result.sigma_function = spec.sigma_function is not None
    _set_likelihood(spec, result)
    return result


def _sigma_of(spec, result) -> torch.Tensor:
    """The sigmas ``(B, G)`` of ``result``'s residuals (unweighted) over its least-squares values."""
    B, T, K = spec.y.shape
    residual = result.residuals.reshape(B, T, K) / spec.weights.clamp(min=torch.finfo(spec.dtype).tiny)
    counted = spec.mask & ~spec.exact
    sigma = estimate_sigma(residual, counted, spec.sigma_group, len(spec.sigma_names))
    floor = 1e3 * torch.finfo(spec.dtype).eps * spec.y.abs().amax(dim=(1, 2)).clamp(min=1.0).unsqueeze(-1)
    # a group fitted exactly keeps a sigma at the data's rounding (the likelihood has no maximum there)
    return torch.where(torch.isfinite(sigma), torch.maximum(sigma, floor), torch.ones_like(sigma))


def _set_likelihood(spec, result) -> None:
    """``result.nll (B,)``: the negative log-likelihood at the estimates (see :mod:`torchql.noise`)."""
    counted = (spec.mask & ~spec.exact).reshape(spec.B, -1)
    n = counted.sum(dim=1).to(spec.dtype)
    log_y = spec.log_y_sum
    if spec.sigma_known or spec.sigma_estimated:
        w = spec.weights_at(result.estimates).reshape(spec.B, -1)
        log_sigma = torch.where(counted, -torch.log(w.clamp(min=torch.finfo(spec.dtype).tiny)),
                                torch.zeros_like(w)).sum(dim=1)
        result.nll = negative_log_likelihood(result.sse, log_sigma, n, log_y)
    else:  # the residual variance at its maximum-likelihood value SSE / n
        variance = result.sse / n.clamp(min=1)
        result.nll = negative_log_likelihood(n, 0.5 * n * torch.log(variance), n, log_y)
