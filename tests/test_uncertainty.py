"""Covariance, standard errors and Wald intervals of the estimates."""

import math

import numpy as np
import pytest
import torch

import torchql
from testmodels import Decay, Product
from torchql.models import CoastingCar
from torchql.uncertainty import covariance, normal_quantile, student_t_quantile

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


def test_a_zero_column_takes_only_its_own_unknowns_error_bars():
    """The other columns' covariance is that of the fit without the unknown: ``s^2 (J^T J)^{-1}``
    of the two nonzero columns (``s^2 = SSE / (L - m)`` with all ``m = 3`` unknowns counted)."""
    J = torch.randn(8, 3, generator=torch.Generator().manual_seed(0), dtype=DT)
    J[:, 1] = 0.0
    cov = covariance(J, torch.zeros(8, dtype=torch.bool), sse=2.0, sigma_known=False, rcond=1e-12).matrix
    rest = J[:, [0, 2]]
    expected = 2.0 / (8 - 3) * torch.linalg.inv(rest.T @ rest)
    torch.testing.assert_close(cov[[0, 2]][:, [0, 2]], expected, rtol=1e-12, atol=0)
    assert torch.isnan(cov[1]).all() and torch.isnan(cov[:, 1]).all()


class FedDecay(torchql.ODEModel):
    """``y' = -k1 y + k2 z``, ``z' = -k3 z``: with ``z(0) = 0`` known, ``z`` stays 0 and the
    sensitivities of ``y`` to ``k2`` and ``k3`` are exactly zero."""

    state_names = ("y", "z")

    def __init__(self, k1=0.5, k2=0.3, k3=0.2):
        super().__init__()
        for name, value in dict(k1=k1, k2=k2, k3=k3).items():
            self.register_buffer(name, torch.tensor(value, dtype=DT))

    def forward(self, t, x):
        y, z = x.unbind(-1)
        return torch.stack((-self.k1 * y + self.k2 * z, -self.k3 * z), -1)


def test_unknowns_without_sensitivity_leave_the_determined_ones_their_error_bars():
    """k2 and k3 move nothing: NOT_IDENTIFIABLE, named, without error bars. y(t0) and k1 keep those
    of the fit of those two alone, up to the residual variance's degrees of freedom (L - m: 16, not
    18), in fit and in each sample of fit_many."""
    times = torch.linspace(0, 5, 20, dtype=DT)
    x0 = torch.tensor([1.0, 0.0], dtype=DT)
    y = torchql.simulate(FedDecay(1.0), x0, times)[:, :1]
    y = y + 1e-3 * torch.randn(y.shape, generator=torch.Generator().manual_seed(0), dtype=DT)
    data = torchql.Observations(times, y, observe=["y"])
    result = torchql.fit(FedDecay(), data, x0, fixed_x0=["z"])
    assert result.status is torchql.Status.NOT_IDENTIFIABLE and "{k3}; {k2}" in result.message
    alone = torchql.fit(FedDecay(), data, x0, fixed_x0=["z"], params=["k1"])
    assert alone.success and (result.dof, alone.dof) == (16, 18)
    se = result.stderr
    assert math.isnan(se["k2"]) and math.isnan(se["k3"])
    for name in ("y(t0)", "k1"):
        assert se[name] == pytest.approx(alone.stderr[name] * math.sqrt(18 / 16), rel=1e-9)
    batch = torchql.fit_many(FedDecay(), torchql.Observations(times, torch.stack([y, y]), observe=["y"]), x0,
                             fixed_x0=["z"])
    for k in range(2):
        assert batch.status[k] is torchql.Status.NOT_IDENTIFIABLE
        torch.testing.assert_close(batch.covariance[k], result.covariance, rtol=1e-9, atol=0, equal_nan=True)


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


# ------------------------------------------------------------------ failed fits, bounded unknowns
DECAY_TIMES = torch.linspace(0, 2, 9, dtype=DT)
# y' = -k y with k = 0.03 and noise of about 0.035: the data barely show the decay, and the
# symmetric Wald interval of an unbounded fit reaches below k = 0
DECAY_NOISE = torch.tensor([0.03, -0.04, 0.02, 0.05, -0.03, -0.02, 0.04, -0.05, 0.01], dtype=DT)
SLOW_DECAY = torchql.Observations(DECAY_TIMES, torch.exp(-0.03 * DECAY_TIMES) + DECAY_NOISE, observe=["y"])


def test_a_fit_stopped_early_has_no_error_bars_or_intervals():
    result = torchql.fit(Decay(30.0), SLOW_DECAY, x0=torch.tensor([5.0], dtype=DT), max_iter=1)
    assert result.status is torchql.Status.MAX_ITER and not result.success
    assert torch.isnan(result.covariance).all()
    assert all(math.isnan(v) for v in result.stderr.values())
    cis = result.confidence_intervals(0.95)
    assert list(cis) == ["y(t0)", "k"]
    assert all(math.isnan(lo) and math.isnan(hi) for lo, hi in cis.values())
    assert result.dof == 7 and math.isfinite(result.sse)  # the fit's own statistics are still reported


def _decay_fit(bounds=None, k=0.05):
    return torchql.fit(Decay(k), SLOW_DECAY, x0=torch.tensor([1.0], dtype=DT), bounds=bounds)


def test_positive_rate_interval_is_wald_in_log_k_and_stays_positive():
    free = _decay_fit()
    assert free.success and free.lower is None and free.upper is None
    k_hat, se = free.estimates[1].item(), free.stderr["k"]
    lo, hi = free.confidence_intervals(0.95)["k"]
    assert lo < 0 < k_hat < hi  # the symmetric interval of a positive rate crosses zero
    q = student_t_quantile(0.975, 7)
    assert (lo, hi) == pytest.approx((k_hat - q * se, k_hat + q * se), rel=1e-12)

    bounded = _decay_fit({"k": (0, None)})
    assert bounded.success
    torch.testing.assert_close(bounded.lower, torch.tensor([-math.inf, 0.0], dtype=DT))
    torch.testing.assert_close(bounded.upper, torch.tensor([math.inf, math.inf], dtype=DT))
    k_b, se_b = bounded.estimates[1].item(), bounded.stderr["k"]
    assert k_b == pytest.approx(k_hat, rel=1e-8)  # an interior optimum: the bound does not move it
    assert se_b == pytest.approx(se, rel=1e-6)  # the standard error stays in the user's units
    lo_b, hi_b = bounded.confidence_intervals(0.95)["k"]
    # u = exp(q): se_q = se / k, the interval exp(log k -/+ t se / k)
    half = q * se_b / k_b
    assert lo_b == pytest.approx(math.exp(math.log(k_b) - half), rel=1e-12, abs=0)
    assert hi_b == pytest.approx(math.exp(math.log(k_b) + half), rel=1e-12, abs=0)
    assert 0 < lo_b < k_b < hi_b
    assert hi_b - k_b > k_b - lo_b  # asymmetric, longer toward large rates
    # the unbounded initial state keeps its symmetric interval
    y_lo, y_hi = bounded.confidence_intervals(0.95)["y(t0)"]
    y_hat, y_se = bounded.estimates[0].item(), bounded.stderr["y(t0)"]
    assert (y_lo, y_hi) == pytest.approx((y_hat - q * y_se, y_hat + q * y_se), rel=1e-12)


def test_two_sided_bound_interval_is_wald_in_logit_and_stays_inside():
    free = _decay_fit()
    lo_free, hi_free = free.confidence_intervals(0.95)["k"]
    assert lo_free < 0 and hi_free > 0.08  # crosses both bounds below
    bounded = _decay_fit({"k": (0.0, 0.08)})
    assert bounded.success
    k_b, se_b = bounded.estimates[1].item(), bounded.stderr["k"]
    lo, hi = bounded.confidence_intervals(0.95)["k"]
    assert 0.0 < lo < k_b < hi < 0.08
    # u = 0.08 sigmoid(q): du/dq = k (0.08 - k) / 0.08
    q_hat = math.log(k_b / (0.08 - k_b))
    half = student_t_quantile(0.975, 7) * se_b * 0.08 / (k_b * (0.08 - k_b))
    sigmoid = lambda x: 1 / (1 + math.exp(-x))  # noqa: E731
    assert lo == pytest.approx(0.08 * sigmoid(q_hat - half), rel=1e-12, abs=0)
    assert hi == pytest.approx(0.08 * sigmoid(q_hat + half), rel=1e-12, abs=0)


def test_upper_bound_interval_mirrors_the_lower_one():
    bounded = _decay_fit({"k": (None, 0.06)})
    assert bounded.success
    k_b, se_b = bounded.estimates[1].item(), bounded.stderr["k"]
    lo, hi = bounded.confidence_intervals(0.9)["k"]
    half = student_t_quantile(0.95, 7) * se_b / (0.06 - k_b)  # u = 0.06 - exp(q)
    assert lo == pytest.approx(0.06 - math.exp(math.log(0.06 - k_b) + half), rel=1e-12, abs=0)
    assert hi == pytest.approx(0.06 - math.exp(math.log(0.06 - k_b) - half), rel=1e-12, abs=0)
    assert lo < k_b < hi < 0.06


def test_several_experiments_carry_the_bounds_and_bounded_intervals():
    second = torchql.Observations(DECAY_TIMES, 2 * torch.exp(-0.03 * DECAY_TIMES) - DECAY_NOISE, observe=["y"])
    result = torchql.fit(Decay(0.05), [SLOW_DECAY, second], x0=torch.tensor([[1.0], [2.0]], dtype=DT),
                         bounds={"k": (0, None), "y": (0, None)})
    assert result.success
    k = result.unknown_names.index("k")
    assert result.lower is not None and result.lower.shape == (len(result.unknown_names),)
    assert bool((result.lower == 0).all()) and bool(torch.isinf(result.upper).all())
    cis = result.confidence_intervals(0.95)
    k_hat, se = result.estimates[k].item(), result.stderr["k"]
    half = student_t_quantile(0.975, result.dof) * se / k_hat
    assert cis["k"] == pytest.approx((k_hat * math.exp(-half), k_hat * math.exp(half)), rel=1e-12)
    assert all(0 < lo < hi for lo, hi in cis.values())


@pytest.mark.parametrize("upper", [None, 1.0])
def test_an_estimate_just_inside_its_bound_gets_the_interval_about_it_clipped(upper):
    """A bound 0.05 standard errors below the estimate: the Wald half-width of ``log(k - lo)`` is 40,
    and its interval mapped back was (lo, 1e16) for a rate the data determine to 10 %. Past a
    half-width of 3 (a factor 20) the interval is the one about the estimate, clipped to the bounds,
    as on the bound itself; further inside, the mapped interval stays (the test above)."""
    free = _decay_fit()
    k_hat, se = free.estimates[1].item(), free.stderr["k"]
    q = student_t_quantile(0.975, 7)
    lo = k_hat - 0.05 * se
    near = _decay_fit({"k": (lo, upper)})
    assert near.success and near.estimates[1].item() == pytest.approx(k_hat, rel=1e-7)
    ends = near.confidence_intervals(0.95)["k"]
    assert ends[0] == lo
    assert ends[1] == pytest.approx(near.estimates[1].item() + q * near.stderr["k"], rel=1e-12)
    if upper is None:  # further inside, half-width 0.5 in log(k - lo): the mapped interval
        far = k_hat - 2 * q * se
        inside = _decay_fit({"k": (far, None)})
        a, b = inside.confidence_intervals(0.95)["k"]
        d = inside.estimates[1].item() - far
        assert a == pytest.approx(far + d * math.exp(-0.5), rel=1e-6)
        assert b == pytest.approx(far + d * math.exp(0.5), rel=1e-6)


class _Inflow(torchql.ODEModel):
    """``x' = -k x + c``: an inflow ``c`` the data barely see."""

    state_names = ("x",)

    def __init__(self, k: float = 0.7, c: float = 0.3) -> None:
        super().__init__()
        self.register_buffer("k", torch.tensor(k, dtype=DT))
        self.register_buffer("c", torch.tensor(c, dtype=DT))

    def forward(self, t, x):
        return -self.k * x + self.c


def _inflow_fit(c_true: float, seed: int, **options):
    t = torch.linspace(0, 4, 15, dtype=DT)
    x = torchql.simulate(_Inflow(1.0, c_true), torch.tensor([1.0], dtype=DT), t, rtol=1e-12, atol=1e-14)
    noise = 0.01 * torch.randn(x.shape, generator=torch.Generator().manual_seed(seed), dtype=DT)
    return torchql.fit(_Inflow(), torchql.Observations(t, x + noise, observe=["x"]), torch.tensor([1.0], dtype=DT),
                       **options)


def test_a_log_scaled_unknown_near_its_bound_or_at_zero_gets_the_interval_about_it_clipped():
    """``c >= 1e-3`` on a log scale, estimated at 0.0036 with standard error 0.0062: its internal
    variable is ``log(log c - log 1e-3)``, whose half-width of 2.3 mapped back to (0.00107, 3.2e7).
    The reach of the mapped interval is measured in ``c`` itself: the interval is that of the linear
    scale, (1e-3, 0.0171). Unbounded on a log scale at ``c = 1.8e-31`` (the data want it below 0):
    ``c -/+ q se`` had a negative lower end; a log scale's edge is 0."""
    linear = _inflow_fit(1e-3, 7, bounds={"c": (1e-3, None)})
    logged = _inflow_fit(1e-3, 7, bounds={"c": (1e-3, None)}, scale={"c": "log"})
    assert linear.success and logged.success
    lo, hi = logged.confidence_intervals(0.95)["c"]
    assert lo == 1e-3 and hi == pytest.approx(linear.confidence_intervals(0.95)["c"][1], rel=1e-6)
    assert hi < 0.02
    edge = _inflow_fit(0.0, 1, scale={"c": "log"})
    assert edge.success and edge.params["c"].item() < 1e-18  # (a tenfold approach a step toward the edge)
    lo, hi = edge.confidence_intervals(0.95)["c"]
    q = student_t_quantile(0.975, edge.dof)
    assert lo == 0.0 and hi == pytest.approx(edge.params["c"].item() + q * edge.stderr["c"], rel=1e-12)


class _Quadratic(torchql.ODEModel):
    """``x' = a + b t``: ``x = x0 + a t + b t^2 / 2``, linear in its unknowns (its covariance exact)."""

    state_names = ("x",)

    def __init__(self, a=0.5, b=0.1):
        super().__init__()
        self.register_buffer("a", torch.tensor(a, dtype=DT))
        self.register_buffer("b", torch.tensor(b, dtype=DT))

    def forward(self, t, x):
        return (self.a + self.b * t).expand(x.shape[:-1]).unsqueeze(-1) + 0 * x


def _constrained_least_squares(X, y, exact):
    """Estimates, dof and standard errors of ``y ~ X p`` with the rows ``exact`` met exactly, by the null
    space of their independent part (numpy)."""
    E = X[exact]
    rank = np.linalg.matrix_rank(E)
    p0 = np.linalg.lstsq(E, y[exact], rcond=None)[0]
    N = np.linalg.svd(E)[2][rank:].T
    A = X[~exact] @ N
    z = np.linalg.lstsq(A, y[~exact] - X[~exact] @ p0, rcond=None)[0]
    sse = float(np.sum((y[~exact] - X[~exact] @ (p0 + N @ z)) ** 2))
    dof = int((~exact).sum()) - N.shape[1]
    return p0 + N @ z, dof, np.sqrt(np.diag(sse / dof * N @ np.linalg.inv(A.T @ A) @ N.T))


def test_exact_values_that_repeat_each_other_fix_each_unknown_once():
    """A known initial state also marked exact, and one state seen by two sensors marked exact at one
    time with one value: each exact value was taken to fix one more unknown, and to remove a value
    from the dof. The standard errors collapsed (a's to 0, the two sensors' up to 76 times too
    small), the dof and AIC were one off. Their rank now counts (numpy's constrained least squares)."""
    rng = np.random.default_rng(0)
    t = np.linspace(0, 4, 12)
    y = 1.0 + 2.0 * t - 0.15 * t ** 2 + 0.05 * rng.standard_normal(t.size)
    y[0] = 1.0
    exact = np.zeros((12, 1), bool)
    exact[0] = True
    data = torchql.Observations(torch.tensor(t), torch.tensor(y).reshape(-1, 1), observe=["x"],
                                exact=torch.tensor(exact))
    fit = torchql.fit(_Quadratic(), data, x0=torch.tensor([1.0], dtype=DT), fixed_x0=["x"])
    X = np.stack([t, t ** 2 / 2], 1)
    # x0 known: the exact value fixes nothing more, and the other 11 values are a plain least squares
    estimates, dof, stderr = _constrained_least_squares(X[1:], y[1:] - 1.0, np.zeros(11, bool))
    assert fit.dof == dof == 9
    np.testing.assert_allclose(fit.estimates.numpy(), estimates, rtol=1e-10)
    np.testing.assert_allclose(list(fit.stderr.values()), stderr, rtol=1e-6)
    from torchql.report import information_criteria
    sse = float(np.sum((y[1:] - 1.0 - X[1:] @ estimates) ** 2))
    assert information_criteria(fit)[0] == pytest.approx(11 * math.log(sse / 11) + 2 * 2, rel=1e-9)

    y2 = 1.0 + 2.0 * t - 0.15 * t ** 2 + 0.05 * rng.standard_normal(t.size)
    y1 = y.copy()
    y1[0] += 0.01
    y2[5] = y1[5]
    both = np.zeros((12, 2), bool)
    both[5, :] = True
    data = torchql.Observations(torch.tensor(t), torch.tensor(np.stack([y1, y2], 1)), observe=["x", "x"],
                                exact=torch.tensor(both))
    fit = torchql.fit(_Quadratic(), data, x0=torch.tensor([0.0], dtype=DT))
    X1 = np.stack([np.ones_like(t), t, t ** 2 / 2], 1)
    estimates, dof, stderr = _constrained_least_squares(np.concatenate([X1, X1]), np.concatenate([y1, y2]),
                                                        np.concatenate([both[:, 0], both[:, 1]]))
    assert fit.dof == dof == 20
    np.testing.assert_allclose(fit.estimates.numpy(), estimates, rtol=1e-9)
    # (the sensitivities at the grid's accuracy: the standard errors to about sqrt(rtol) / 16)
    np.testing.assert_allclose(list(fit.stderr.values()), stderr, rtol=1e-6)


@pytest.mark.parametrize("span, rate", [(10.0, 0.1), (1e8, 1e-8)])
def test_exact_values_that_fix_every_unknown_in_any_units(span, rate):
    """``x' = -k x``, its first and last values marked exact: they fix ``x0`` and ``k``, so the dof is
    the other 8 values and the standard errors are 0. In seconds (``k = 1e-8``) the exact rows were
    ranked in the unknowns' own units, where ``k``'s column is 1e8 times ``x0``'s: one was counted as
    repeating the other (dof 7, standard errors 0.3 %). They are ranked with unit columns now."""
    t = torch.linspace(0, span, 10, dtype=DT)
    noise = 0.01 * torch.randn(10, 1, generator=torch.Generator().manual_seed(1), dtype=DT)
    noise[0] = noise[-1] = 0.0
    exact = torch.zeros(10, 1, dtype=torch.bool)
    exact[0] = exact[-1] = True
    data = torchql.Observations(t, (2.0 * torch.exp(-rate * t)).unsqueeze(-1) + noise, observe=["y"], exact=exact)
    fit = torchql.fit(Decay(2 * rate), data, x0=torch.tensor([1.5], dtype=DT))
    assert fit.success and fit.dof == 8 and all(v == 0.0 for v in fit.stderr.values())
