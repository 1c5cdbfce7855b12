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

**Estimation.** The sigmas are unknowns of the fit, estimated with the coefficients by maximum
likelihood (:mod:`torchql.estimated_noise`); at the optimum each group's weighted sum of squares
is its number of values (``sigma_g^2 = SSE_g / n_g``).

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

__all__ = ["NOISE_MODELS", "sigma_group_index", "estimate_sigma", "negative_log_likelihood", "run_with_noise",
           "non_finite_residuals"]

#: The noise distributions of :class:`torchql.Observations`.
NOISE_MODELS = ("normal", "lognormal")


def sigma_group_index(groups, K: int, labels: Sequence[str]) -> tuple[list[str], list[int]]:
    """``(group names, group of each of the K outputs)`` from ``Observations``' ``sigma_groups``.

    ``labels`` name the outputs (the observed state, else ``"y[k]"``) for the default grouping: one
    group per output, named by its label, the second output with a label (two sensors of one state)
    ``"label#2"``, and so on; so that experiments fitted together share a sigma per label and
    occurrence (:mod:`torchql.multi`).
    """
    if groups is None:
        names, seen = [], {}
        for label in labels:
            seen[label] = seen.get(label, 0) + 1
            name, n = label, seen[label]
            while name in names:
                name = f"{label}#{n}"
                n += 1
            names.append(name)
        return names, list(range(len(labels)))
    if isinstance(groups, str):
        if groups != "shared":
            raise ValueError(f"`sigma_groups` must be None, 'shared' or one label per output; received {groups!r}")
        return ["sigma"], [0] * K
    if not isinstance(groups, Sequence) or len(groups) != K:
        received = len(groups) if isinstance(groups, Sequence) else type(groups).__name__
        raise ValueError(f"`sigma_groups` must give one label per output (K = {K}); received {received}")
    names = list(dict.fromkeys(str(g) for g in groups))
    return names, [names.index(str(g)) for g in groups]


def non_finite_residuals(noise: str) -> str:
    """The detail of a fit's ``DIVERGED`` status when its residuals are not finite, for the noise model ``noise``."""
    if noise == "lognormal":
        return (" The residuals became non-finite: with noise='lognormal' they compare log y with the logarithm "
                "of the model's predictions, which is not defined where a prediction is zero or negative. Observe "
                "a positive quantity, start from guesses whose predictions are positive, or use noise='normal'.")
    return " The residuals became non-finite."


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
    """``run(spec)`` (the engine on the problem ``spec``, a :class:`torchql.problem.Problem`), with the
    result's noise fields set: ``noise``, ``nll``, and with ``sigma="estimate"`` the sigmas moved out
    of its unknowns (``sigma``, ``sigma_stderr``, ``sigma_names``). Returns the result."""
    result = run(spec)
    result.noise = spec.noise
    result.sigma_function = spec.sigma_callable is not None and spec.estimated_noise is None
    _set_likelihood(spec, result)
    if spec.estimated_noise is not None:
        spec.estimated_noise.split(result, spec.m)
    return result


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
