"""Covariance, standard errors and Wald intervals of the estimates."""

import math

import numpy as np
import pytest
import torch

import torchql
from testmodels import Decay, Product
from torchql.models import CoastingCar
from torchql.uncertainty import normal_quantile, student_t_quantile

DT = torch.float64


SUNBEAM = torch.tensor([117.3, 104.9, 95.3, 87.3, 79.2, 71.9, 65.7, 59.8, 54.0], dtype=DT)
CAR_TIMES = torch.arange(9, dtype=DT) * 5.0


def test_stderr_matches_a_finite_difference_jacobian_covariance():
    result = torchql.fit(CoastingCar(17.3, 80.43), torchql.Observations(CAR_TIMES, SUNBEAM, observe=["v"]))
    assert result.success
    u = result.estimates

    def velocity(u):
        car = CoastingCar(17.3, 80.43, C_D=u[1].item(), mu=u[2].item())
        return torchql.simulate(car, u[:1], CAR_TIMES, rtol=1e-13, atol=1e-13)[:, 0]

    J = torch.zeros(9, 3, dtype=DT)
    for i in range(3):
        h = 1e-6 * abs(u[i].item())
        up, dn = u.clone(), u.clone()
        up[i] += h
        dn[i] -= h
        J[:, i] = (velocity(up) - velocity(dn)) / (2 * h)
    r = SUNBEAM - velocity(u)
    s2 = float(r @ r) / (9 - 3)
    expected = s2 * torch.linalg.inv(J.T @ J)
    torch.testing.assert_close(result.covariance, expected, rtol=1e-4, atol=0)
    assert result.dof == 6
    assert result.residual_variance == pytest.approx(s2, rel=1e-6)
    se = result.stderr
    assert list(se) == ["v(t0)", "C_D", "mu"]
    assert se["C_D"] == pytest.approx(math.sqrt(expected[1, 1]), rel=1e-4)
    corr = result.correlation
    torch.testing.assert_close(torch.diagonal(corr), torch.ones(3, dtype=DT))
    assert corr[1, 2] < -0.9  # drag and rolling friction trade off against each other


def test_wald_intervals_use_student_t_with_estimated_variance_and_normal_with_known_sigma():
    data = torchql.Observations(CAR_TIMES, SUNBEAM, observe=["v"])
    result = torchql.fit(CoastingCar(17.3, 80.43), data)
    lo, hi = result.confidence_intervals(0.95)["C_D"]
    q = student_t_quantile(0.975, 6)
    assert (hi - lo) / 2 == pytest.approx(q * result.stderr["C_D"], rel=1e-12)
    known = torchql.fit(CoastingCar(17.3, 80.43), torchql.Observations(CAR_TIMES, SUNBEAM, observe=["v"], sigma=0.4))
    assert known.sigma_known and known.residual_variance == 1.0
    lo, hi = known.confidence_intervals(0.9)["mu"]
    assert (hi - lo) / 2 == pytest.approx(normal_quantile(0.95) * known.stderr["mu"], rel=1e-12)
    with pytest.raises(ValueError, match="`level`"):
        result.confidence_intervals(95)


def test_quantiles_match_scipy():
    stats = pytest.importorskip("scipy.stats")
    for p in (0.5, 0.9, 0.975, 0.995, 1e-6):
        assert normal_quantile(p) == pytest.approx(stats.norm.ppf(p), rel=1e-12, abs=1e-12)
        for dof in (1, 3, 7.5, 40, 1000):
            assert student_t_quantile(p, dof) == pytest.approx(stats.t.ppf(p, dof), rel=1e-9, abs=1e-12)


def test_exact_values_leave_no_variance_along_their_constraint():
    times = torch.linspace(0, 3, 12, dtype=DT)
    y = 2 * torch.exp(-0.7 * times) + 0.02 * torch.sin(7 * times)
    exact = torch.zeros(12, dtype=torch.bool)
    exact[0] = True  # y(0) met exactly: y(t0) is then known, with zero variance
    result = torchql.fit(Decay(1.0), torchql.Observations(times, y, observe=["y"], exact=exact),
                         x0=torch.tensor([1.5], dtype=DT))
    assert result.success and result.dof == 12 - 2
    assert result.stderr["y(t0)"] < 1e-12 * result.stderr["k"] + 1e-14
    assert result.stderr["k"] > 0


def test_not_identifiable_has_no_error_bars():
    times = torch.linspace(0, 2, 11, dtype=DT)
    result = torchql.fit(Product(), torchql.Observations(times, torch.exp(-0.6 * times), observe=["y"]),
                         x0=torch.tensor([1.0], dtype=DT))
    assert result.status is torchql.Status.NOT_IDENTIFIABLE
    se = result.stderr
    # only the product a b is determined: a and b get no error bars; y(t0) keeps its own
    assert math.isnan(se["a"]) and math.isnan(se["b"])
    assert se["y(t0)"] >= 0 and not math.isnan(se["y(t0)"])
    assert torch.isnan(result.covariance[1:, :]).all() and torch.isnan(result.covariance[:, 1:]).all()


@pytest.mark.slow
def test_stderr_and_wald_coverage_over_repeated_noisy_datasets():
    """Gaussian noise, 200 seeded datasets: the stderr predicts the spread of the estimates and the
    95% Wald intervals cover the truth 90-99% of the time (binomial sd at 200 draws: 1.5%)."""
    truth = {"y(t0)": 2.0, "k": 0.7}
    times = torch.linspace(0, 3, 16, dtype=DT)
    clean = 2.0 * torch.exp(-0.7 * times)
    gen = torch.Generator().manual_seed(12345)
    estimates, stderrs, covered = [], [], {name: 0 for name in truth}
    n = 200
    for _ in range(n):
        y = clean + 0.05 * torch.randn(16, generator=gen, dtype=DT)
        result = torchql.fit(Decay(1.0), torchql.Observations(times, y, observe=["y"]),
                             x0=torch.tensor([1.5], dtype=DT), grid=100)
        assert result.success
        estimates.append(result.estimates.numpy())
        stderrs.append([result.stderr[name] for name in truth])
        for name, (lo, hi) in result.confidence_intervals(0.95).items():
            covered[name] += lo <= truth[name] <= hi
    estimates, stderrs = np.array(estimates), np.array(stderrs)
    spread = estimates.std(axis=0, ddof=1)
    mean_se = np.sqrt((stderrs**2).mean(axis=0))
    # the sample sd of 200 draws is within about 3 * 5% of the true sd
    assert np.all(np.abs(spread / mean_se - 1) < 0.15), (spread, mean_se)
    for name, count in covered.items():
        assert 0.90 <= count / n <= 0.99, (name, count)
