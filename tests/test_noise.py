"""Noise models: estimated sigmas (per output, shared, by group), log-normal values, the likelihood."""

import math

import pytest
import torch

import torchql
from torchql.models import LinearOscillator

DT = torch.float64
T = torch.linspace(0, 10, 41, dtype=DT)
X0 = torch.tensor([1.0, 0.0], dtype=DT)
GUESS_X0 = torch.tensor([0.5, 0.5], dtype=DT)
NOISE = torch.tensor([0.01, 0.2], dtype=DT)
STATES = torchql.simulate(LinearOscillator(0.3, 4.0), X0, T, rtol=1e-12, atol=1e-14)


def noisy(seed: int = 0) -> torch.Tensor:
    return STATES + torch.randn(STATES.shape, generator=torch.Generator().manual_seed(seed), dtype=DT) * NOISE


def fit(data, **kwargs):
    return torchql.fit(LinearOscillator(0.5, 2.0), data, x0=GUESS_X0, **kwargs)


def test_sigma_per_output_is_the_maximum_likelihood_fixed_point():
    y = noisy()
    result = fit(torchql.Observations(T, y, observe=["y", "v"], sigma="estimate"))
    assert result.success, result.message
    sigma = torch.tensor([result.sigma["y"], result.sigma["v"]], dtype=DT)
    assert ((sigma / NOISE - 1).abs() < 0.25).all(), result.sigma
    # at the fixed point each output's residuals, in units of its sigma, have mean square 1
    r = result.residuals.reshape(-1, 2)
    torch.testing.assert_close((r**2).mean(dim=0), torch.ones(2, dtype=DT), rtol=1e-7, atol=0)
    # and the estimates are the weighted least squares at those sigmas
    known = fit(torchql.Observations(T, y, observe=["y", "v"], sigma=sigma))
    torch.testing.assert_close(result.estimates, known.estimates, rtol=1e-7, atol=1e-9)
    torch.testing.assert_close(result.covariance, known.covariance, rtol=1e-5, atol=0)
    n = y.numel()
    expected = float(41 * torch.log(sigma).sum()) + 0.5 * n * math.log(2 * math.pi) + 0.5 * n
    assert result.nll == pytest.approx(expected, rel=1e-9)
    # the truth lies within the intervals, which the unweighted fit makes twice as wide or more
    plain = fit(torchql.Observations(T, y, observe=["y", "v"]))
    for name, value in (("A", 0.3), ("B", 4.0)):
        low, high = result.confidence_intervals(0.99)[name]
        assert low < value < high
        assert plain.stderr[name] > 2 * result.stderr[name]


def test_one_shared_sigma_is_least_squares():
    y = noisy(1)
    shared = fit(torchql.Observations(T, y, observe=["y", "v"], sigma="estimate", sigma_groups="shared"))
    plain = fit(torchql.Observations(T, y, observe=["y", "v"]))
    # the same optimum, each reached to the fits' convergence tolerance (xtol)
    torch.testing.assert_close(shared.estimates, plain.estimates, rtol=1e-7, atol=1e-10)
    n = y.numel()
    assert shared.sigma["sigma"] == pytest.approx(math.sqrt(plain.sse / n), rel=1e-8)
    assert shared.nll == pytest.approx(plain.nll, rel=1e-9)  # without sigma: the variance's MLE, SSE / n
    assert plain.nll == pytest.approx(0.5 * n * (math.log(2 * math.pi * plain.sse / n) + 1), rel=1e-12)


def test_groups_of_outputs_share_a_sigma():
    y = torch.cat([noisy(2), noisy(3)[:, :1]], dim=1)  # y, v, and y again
    data = torchql.Observations(T, y, observe=["y", "v", "y"], sigma="estimate", sigma_groups=["pos", "vel", "pos"])
    result = fit(data)
    assert list(result.sigma) == ["pos", "vel"]
    r = result.residuals.reshape(-1, 3)
    torch.testing.assert_close((r[:, [0, 2]] ** 2).mean(), torch.tensor(1.0, dtype=DT), rtol=1e-7, atol=0)


def test_known_sigma_likelihood():
    y = noisy(4)
    result = fit(torchql.Observations(T, y, observe=["y", "v"], sigma=NOISE))
    n = y.numel()
    expected = 41 * float(torch.log(NOISE).sum()) + 0.5 * n * math.log(2 * math.pi) + 0.5 * result.sse
    assert result.nll == pytest.approx(expected, rel=1e-12)


def test_lognormal_values_are_fitted_in_log_space():
    g = torch.Generator().manual_seed(5)
    positive = STATES[:, :1] + 2.0  # y + 2 > 0
    y = positive * torch.exp(0.05 * torch.randn(positive.shape, generator=g, dtype=DT))

    def shifted(x):
        return x[..., :1] + 2.0

    result = fit(torchql.Observations(T, y, observe=shifted, noise="lognormal", sigma=0.05))
    by_hand = fit(torchql.Observations(T, torch.log(y), observe=lambda x: torch.log(shifted(x)), sigma=0.05))
    assert result.success and result.noise == "lognormal"
    torch.testing.assert_close(result.estimates, by_hand.estimates, rtol=1e-9, atol=1e-12)
    assert result.sse == pytest.approx(by_hand.sse, rel=1e-9)
    # the likelihood of y itself: that of log y plus the change of variable
    assert result.nll == pytest.approx(by_hand.nll + float(torch.log(y).sum()), rel=1e-10)
    estimated = fit(torchql.Observations(T, y, observe=shifted, noise="lognormal", sigma="estimate"))
    assert estimated.sigma["y[0]"] == pytest.approx(0.05, rel=0.2)
    report = estimated.report()
    assert "noise              = lognormal" in report and "sigma (estimated)  = y[0]:" in report


def test_report_and_information_criteria_follow_the_likelihood():
    result = fit(torchql.Observations(T, noisy(6), observe=["y", "v"], sigma="estimate"))
    report = result.report()
    assert "sigma (estimated)  = y: " in report and f"-log likelihood    = {result.nll:.7g}" in report
    k = 4 + 2
    convention = "(2 NLL + 2 k, k: the unknowns and the estimated sigmas)"
    assert f"AIC                = {2 * result.nll + 2 * k:.7g} {convention}" in report


def test_profile_with_estimated_sigma_is_a_likelihood_profile():
    result = fit(torchql.Observations(T, noisy(7), observe=["y", "v"], sigma="estimate"))
    prof = torchql.profile(result, "A", level=0.95)
    assert prof.sse_min == pytest.approx(2 * result.nll, rel=1e-12)
    low, high = prof.interval
    wald_low, wald_high = result.confidence_intervals(0.95)["A"]
    # a nearly linear problem: the likelihood interval is close to the Wald one
    assert abs(low - wald_low) < 0.2 * (wald_high - wald_low)
    assert abs(high - wald_high) < 0.2 * (wald_high - wald_low)


def test_two_sensors_of_one_state_each_get_their_own_sigma():
    """One sigma per output by default, as documented, also where two outputs read one state (two
    sensors of ``y``, noise 0.01 and 0.2): they were pooled into one sigma (0.14), which weighted the
    good sensor as the bad one and made the coefficients' standard errors several times too large.
    Experiments fitted together share a sigma per sensor: ``y`` with ``y``, ``y#2`` with ``y#2``."""
    def sensors(seed):
        states = noisy(seed)
        second = STATES[:, :1] + torch.randn(41, 1, generator=torch.Generator().manual_seed(seed + 100), dtype=DT) * 0.2
        return torch.cat([states[:, :1], second], dim=1)
    result = fit(torchql.Observations(T, sensors(10), observe=["y", "y"], sigma="estimate"))
    assert result.success, result.message
    assert list(result.sigma) == ["y", "y#2"]
    assert result.sigma["y"] == pytest.approx(0.01, rel=0.25) and result.sigma["y#2"] == pytest.approx(0.2, rel=0.25)
    labelled = fit(torchql.Observations(T, sensors(10), observe=["y", "y"], sigma="estimate", sigma_groups=["a", "b"]))
    torch.testing.assert_close(result.estimates, labelled.estimates, rtol=0, atol=0)
    pooled = fit(torchql.Observations(T, sensors(10), observe=["y", "y"], sigma="estimate", sigma_groups="shared"))
    assert pooled.stderr["B"] > 3 * result.stderr["B"]
    both = torchql.fit(LinearOscillator(0.5, 2.0), [torchql.Observations(T, sensors(s), observe=["y", "y"],
                                                                         sigma="estimate") for s in (11, 12)],
                       x0=torch.stack([GUESS_X0, GUESS_X0]))
    assert list(both.sigma) == ["y", "y#2"]
    assert both.sigma["y"] == pytest.approx(0.01, rel=0.25) and both.sigma["y#2"] == pytest.approx(0.2, rel=0.25)


def test_fit_many_and_several_experiments_estimate_sigma_too():
    datasets = [torchql.Observations(T, noisy(s), observe=["y", "v"], sigma="estimate") for s in (8, 9)]
    batch = torchql.fit_many(LinearOscillator(0.5, 2.0), datasets, x0=GUESS_X0)
    for b, data in enumerate(datasets):
        alone = fit(data)
        torch.testing.assert_close(batch.estimates[b], alone.estimates, rtol=1e-8, atol=1e-10)
        assert batch[b].sigma == pytest.approx(alone.sigma, rel=1e-7)
        assert batch[b].nll == pytest.approx(alone.nll, rel=1e-9)
    both = torchql.fit(LinearOscillator(0.5, 2.0), datasets, x0=torch.stack([GUESS_X0, GUESS_X0]))
    assert list(both.sigma) == ["y", "v"]  # the same observable in both experiments: one sigma


@pytest.mark.parametrize("kwargs, error, match", [
    ({"noise": "poisson"}, ValueError, "`noise` must be one of \\['normal', 'lognormal'\\]"),
    ({"sigma": "guess"}, ValueError, "`sigma` must be a number, a tensor or 'estimate'"),
    ({"sigma_groups": "shared"}, ValueError, "`sigma_groups` applies only with sigma='estimate'"),
    ({"sigma": "estimate", "sigma_groups": ["a"]}, ValueError, "one label per output \\(K = 2\\); received 1"),
    ({"sigma": "estimate", "sigma_groups": "all"}, ValueError, "`sigma_groups` must be None, 'shared'"),
])
def test_bad_noise_settings_are_named(kwargs, error, match):
    with pytest.raises(error, match=match):
        torchql.Observations(T, STATES, observe=["y", "v"], **kwargs)


def test_lognormal_values_must_be_positive():
    with pytest.raises(ValueError, match="`y` must be positive with noise='lognormal'"):
        torchql.Observations(T, STATES, observe=["y", "v"], noise="lognormal")


def test_a_lognormal_fit_whose_predictions_cross_zero_says_so():
    """Positive values (``|y| + 0.5``) fitted with an oscillation that crosses zero: the logarithm of
    its predictions is not defined there. The fit stops ``DIVERGED`` saying why, where its message
    spoke only of estimates running away."""
    y = STATES.abs() + 0.5
    result = fit(torchql.Observations(T, y, observe=["y", "v"], noise="lognormal"))
    assert result.status is torchql.Status.DIVERGED
    assert "noise='lognormal'" in result.message and "prediction is zero or negative" in result.message
