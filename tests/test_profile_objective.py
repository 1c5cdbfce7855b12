"""The profile's own objective (torchql/profile_objective.py): a fit of one unknown is profiled by
integrating the model at each value, which must give the fit's objective at the estimate, on every
noise model; and the rounding of a float32 likelihood is not taken for a lower optimum."""

from __future__ import annotations

import warnings

import pytest
import torch

import torchql

from testmodels import Decay


def _decay_values(dtype=torch.float64, **observations):
    """``y = 2 exp(-1.5 t)`` at 8 times in [0.5, 3] with 5 % multiplicative noise."""
    t = torch.linspace(0.5, 3, 8, dtype=torch.float64)
    noise = torch.randn(8, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    y = (2.0 * torch.exp(-1.5 * t) * (1 + 0.05 * noise)).unsqueeze(-1)
    return torchql.Observations(t.to(dtype), y.to(dtype), observe=["y"], **observations)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_a_lognormal_fit_without_sigma_is_profiled_on_its_own_likelihood(dtype):
    """Log-normal values without ``sigma``: the fit's 2 NLL takes the residual variance at its maximum
    ``SSE / n``. The profile of its one unknown once took sigma = 1 instead: its value at the estimate
    was 46 above the fit's, and its "interval" ran from 3.6e5 down to -3.6e5 (float32: a division by
    zero). At the estimate it now equals the fit's, and the interval ends where the likelihood ratio
    reaches its 95 % quantile."""
    data = _decay_values(dtype, noise="lognormal")
    x0 = torch.tensor([2.0], dtype=dtype)
    fit = torchql.fit(Decay(0.5, dtype=dtype), data, x0=x0, fixed_x0=["y"], t0=0.0)
    assert fit.status is torchql.Status.CONVERGED and fit.likelihood
    profile = torchql.profile(fit, "a" if "a" in fit.params else "k")
    centre = int((profile.values - profile.estimate).abs().argmin())
    rounding = 1e-8 if dtype == torch.float64 else 1e-3
    assert float(profile.sse[centre]) == pytest.approx(2 * fit.nll, abs=rounding)
    low, high = profile.interval
    assert low < profile.estimate < high and profile.closed == (True, True)
    # at each end, 2 NLL (written out here: log residuals, their variance at its maximum) is 1.96^2 above
    t, log_y = data.t.double(), data.y.double()[:, 0].log()
    n = t.numel()

    def twice_nll(k: float) -> float:
        variance = (log_y - (2.0 * torch.exp(-k * t)).log()).square().mean()
        return float(n * torch.log(2 * torch.pi * variance) + n + 2 * log_y.sum())
    for end in (low, high):
        assert twice_nll(end) - twice_nll(profile.estimate) == pytest.approx(1.959964 ** 2, abs=1e-3)


@pytest.mark.parametrize("fixed_x0", [["y"], None])
def test_a_float32_likelihood_profile_says_nothing_of_a_lower_optimum_at_its_estimate(fixed_x0):
    """``sigma="estimate"`` in float32: the profile evaluated the fit's own estimate 2e-4 (one unknown)
    or 3e-5 (two) below the fit's 2 NLL, rounding and the integration's error at float32's tolerances,
    and warned that the fit was not at the optimum. The allowance now weighs the integration's error
    by the estimated sigma (here 0.009), not by 1."""
    data = _decay_values(torch.float32, sigma="estimate")
    fit = torchql.fit(Decay(0.5, dtype=torch.float32), data, x0=torch.tensor([2.0], dtype=torch.float32),
                      fixed_x0=fixed_x0, t0=0.0)
    assert fit.status is torchql.Status.CONVERGED
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # (the note is also a warning)
        profile = torchql.profile(fit, "k")
    assert "lower SSE" not in profile.message and profile.closed == (True, True)
