"""The profile's own objective (torchql/profile_objective.py): a fit of one unknown is profiled by
integrating the model at each value, which must give the fit's objective at the estimate, on every
noise model; and the rounding of a float32 likelihood is not taken for a lower optimum."""

from __future__ import annotations

import math
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


def test_a_value_marked_exact_fixes_the_one_unknown_of_a_profile():
    """``y' = -k y`` from a known ``y(0) = 2``, its value at t = 0.2 marked exact: that value fixes k.
    The profile of this one unknown integrates the model at each k and left the exact value out:
    a closed interval (0.679, 0.957) about values the fit excludes, and a warning that the fit was
    not at its optimum. As the profile of a fit with more unknowns (whose re-fits cannot meet the
    exact value), its interval is now the estimate itself; an exact value that does not depend on
    k (the known initial state) leaves the profile as it was."""
    g = torch.Generator().manual_seed(8)
    t = torch.linspace(0.2, 4, 20, dtype=torch.float64)
    y = (2.0 * torch.exp(-0.8 * t) + 0.03 * torch.randn(20, generator=g, dtype=torch.float64)).unsqueeze(-1)
    exact = torch.zeros(20, 1, dtype=torch.bool)
    exact[0] = True
    fixing = torchql.fit(Decay(), torchql.Observations(t, y, observe=["y"], sigma=0.03, exact=exact),
                         x0=torch.tensor([2.0], dtype=torch.float64), fixed_x0=["y"], t0=0.0)
    assert fixing.params["k"].item() == pytest.approx(-math.log(y[0, 0].item() / 2.0) / 0.2, rel=1e-9)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        profile = torchql.profile(fixing, "k")
    assert profile.interval == (profile.estimate, profile.estimate) and "lower SSE" not in profile.message
    # the known initial state marked exact as well: it does not depend on k, which the data determine
    t0_data = torchql.Observations(torch.cat([torch.zeros(1, dtype=torch.float64), t]),
                                   torch.cat([torch.full((1, 1), 2.0, dtype=torch.float64), y]), observe=["y"],
                                   sigma=0.03, exact=torch.arange(21).unsqueeze(-1) == 0)
    free = torchql.fit(Decay(), t0_data, x0=torch.tensor([2.0], dtype=torch.float64), fixed_x0=["y"])
    low, high = torchql.profile(free, "k").interval
    assert low < free.params["k"].item() - 0.01 and high > free.params["k"].item() + 0.01
