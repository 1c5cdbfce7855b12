"""Standard deviations that are functions of the unknowns: ``Observations(..., sigma=lambda p: ...)``.

The reference is independent of torchql's integrators: ``x' = -k x`` from ``x(0) = 1`` is
``exp(-k t)``, so the negative log-likelihood of two scaled outputs ``y_j = s_j x + e``,
``e ~ N(0, (s_j sig)^2)``, is a closed form, minimized here by scipy's BFGS to a gradient of 1e-12.
"""

import math

import numpy as np
import pytest
import torch
from scipy.optimize import minimize

import torchql
from torchql.baselines import adjoint_fit
from torchql.plotting import plot_fit

DT = torch.float64
NAMES = ("k", "s1", "s2", "sig")
TRUTH = dict(k=0.7, s1=2.0, s2=5.0, sig=0.05)
GUESS = dict(k=1.0, s1=1.5, s2=4.0, sig=0.1)


class Decay(torchql.ODEModel):
    """``x' = -k x`` with the observation's scalings ``s1, s2`` and noise level ``sig`` as coefficients."""

    state_names = ("x",)

    def __init__(self, k=1.0, s1=1.0, s2=1.0, sig=0.1):
        super().__init__()
        for name, value in dict(k=k, s1=s1, s2=s2, sig=sig).items():
            self.register_buffer(name, torch.tensor(float(value), dtype=DT))

    def forward(self, t, x):
        return -self.k * x


def observe(x, p):
    return torch.stack([p["s1"] * x[0], p["s2"] * x[0]])


def sigma(p):
    return torch.stack([p["s1"] * p["sig"], p["s2"] * p["sig"]])


def _data(seed=3, T=21):
    g = torch.Generator().manual_seed(seed)
    t = torch.linspace(0, 4, T, dtype=DT)
    x = torch.exp(-TRUTH["k"] * t)
    y = torch.stack([s * x + s * TRUTH["sig"] * torch.randn(T, generator=g, dtype=DT)
                     for s in (TRUTH["s1"], TRUTH["s2"])], 1)
    return t, y


def _nll(theta, t, y):
    """The closed-form negative log-likelihood at ``theta = (k, s1, s2, sig)``."""
    k, s1, s2, sig = theta
    x = np.exp(-k * t)
    out = 0.0
    for j, s in enumerate((s1, s2)):
        sd = s * sig
        out += np.sum(np.log(sd) + 0.5 * ((y[:, j] - s * x) / sd) ** 2 + 0.5 * np.log(2 * np.pi))
    return out


def _reference(t, y, fixed=None):
    """The closed form's minimizer (over the log-parameters; ``fixed`` {index: value} held)."""
    fixed = fixed or {}
    free = [i for i in range(4) if i not in fixed]

    def full(q):
        theta = np.empty(4)
        theta[free] = np.exp(q)
        for i, v in fixed.items():
            theta[i] = v
        return theta

    q0 = np.log([GUESS[NAMES[i]] for i in free])
    res = minimize(lambda q: _nll(full(q), t, y), q0, method="BFGS", options=dict(gtol=1e-12))
    return full(res.x), res.fun


def _fit(data, **options):
    return torchql.fit(Decay(**GUESS), data, x0=torch.tensor([1.0], dtype=DT), fixed_x0=["x"], **options)


@pytest.fixture(scope="module")
def problem():
    t, y = _data()
    result = _fit(torchql.Observations(t, y, observe=observe, sigma=sigma))
    return t, y, result


def test_the_fit_is_the_maximum_likelihood(problem):
    t, y, result = problem
    assert result.status is torchql.Status.CONVERGED, result.message
    assert result.sigma_function
    reference, nll = _reference(t.numpy(), y.numpy())
    estimates = np.array([float(result.params[name]) for name in NAMES])
    # BFGS on the closed form stops at a gradient of ~1e-9; the ODE is integrated to rtol 1e-8
    np.testing.assert_allclose(estimates, reference, rtol=1e-6)
    assert result.nll == pytest.approx(nll, abs=1e-6)
    assert result.nll == pytest.approx(_nll(estimates, t.numpy(), y.numpy()), abs=1e-6)


def test_a_free_noise_level_puts_the_weighted_sse_at_n(problem):
    """d NLL / d log sig = n - SSE_w: zero at the maximum, whatever the data."""
    _, _, result = problem
    assert result.sse == pytest.approx(result.n_observations, rel=1e-7)


def test_the_covariance_is_the_inverse_fisher_information(problem):
    """``I = sum (dmu/dtheta)(dmu/dtheta)^T / sigma^2 + 2 (dlog sigma/dtheta)(dlog sigma/dtheta)^T``,
    by central differences of the closed-form mean and sigma."""
    t, _, result = problem
    theta = np.array([float(result.params[name]) for name in NAMES])
    tn = t.numpy()

    def mean_and_log_sigma(th):
        k, s1, s2, sig = th
        x = np.exp(-k * tn)
        return np.concatenate([s1 * x, s2 * x]), np.concatenate([np.full_like(x, np.log(s1 * sig)),
                                                                 np.full_like(x, np.log(s2 * sig))])

    mu, log_sd = mean_and_log_sigma(theta)
    dmu, dls = np.empty((mu.size, 4)), np.empty((mu.size, 4))
    for i in range(4):
        h = 1e-6 * theta[i]
        up, down = theta.copy(), theta.copy()
        up[i] += h
        down[i] -= h
        (mu_u, ls_u), (mu_d, ls_d) = mean_and_log_sigma(up), mean_and_log_sigma(down)
        dmu[:, i], dls[:, i] = (mu_u - mu_d) / (2 * h), (ls_u - ls_d) / (2 * h)
    fisher = (dmu / np.exp(log_sd)[:, None]).T @ (dmu / np.exp(log_sd)[:, None]) + 2 * dls.T @ dls
    np.testing.assert_allclose(result.covariance.numpy(), np.linalg.inv(fisher), rtol=1e-5, atol=1e-12)


def test_the_report_and_criteria_follow_the_likelihood(problem):
    _, _, result = problem
    text = result.report()
    assert "sigma(p), a function of the unknowns" in text
    aic, bic = torchql.report.information_criteria(result)
    assert aic == pytest.approx(2 * result.nll + 2 * 4)
    assert bic == pytest.approx(2 * result.nll + math.log(result.n_observations) * 4)


def test_the_profile_is_of_the_likelihood(problem):
    """At each end of k's profile interval the closed form, minimized over the others with k held
    there, is 1.92 (chi2_1(0.95) / 2) above its minimum."""
    t, y, result = problem
    prof = torchql.profile(result, "k")
    _, nll_min = _reference(t.numpy(), y.numpy())
    for end in prof.interval:
        _, nll = _reference(t.numpy(), y.numpy(), fixed={0: end})
        assert nll - nll_min == pytest.approx(0.5 * 1.959963984540054 ** 2, abs=2e-3)


def test_fit_many_equals_fit(problem):
    t, y, result = problem
    data = [torchql.Observations(t, y, observe=observe, sigma=sigma),
            torchql.Observations(t, y * 1.01, observe=observe, sigma=sigma)]
    batch = torchql.fit_many(Decay(**GUESS), data, x0=torch.tensor([1.0], dtype=DT), fixed_x0=["x"])
    one = _fit(data[1])
    assert batch.status == [result.status, one.status]
    torch.testing.assert_close(batch.estimates, torch.stack([result.estimates, one.estimates]), rtol=1e-10, atol=0)
    assert float(batch.nll[1]) == pytest.approx(one.nll, rel=1e-10)


def test_several_experiments_point_slots_at_their_own_scalings(problem):
    """Two experiments, each reading one output through a slot ``s`` that its ``conditions`` point at
    ``s1`` or ``s2``, are the two-output problem."""
    t, y, result = problem

    class Slotted(Decay):
        constants = ("s",)

        def __init__(self, **values):
            super().__init__(**values)
            self.register_buffer("s", torch.tensor(1.0, dtype=DT))

    def one(x, p):
        return p["s"] * x[:1]

    def one_sigma(p):
        return (p["s"] * p["sig"]).reshape(1)

    data = [torchql.Observations(t, y[:, j], observe=one, sigma=one_sigma) for j in range(2)]
    multi = torchql.fit(Slotted(**GUESS), data, x0=torch.tensor([[1.0], [1.0]], dtype=DT), fixed_x0=["x"],
                        params=list(NAMES), conditions=[{"s": "s1"}, {"s": "s2"}])
    assert multi.status is torchql.Status.CONVERGED, multi.message
    for name in NAMES:
        assert float(multi.params[name]) == pytest.approx(float(result.params[name]), rel=1e-7)
    assert multi.nll == pytest.approx(result.nll, abs=1e-8)


def test_bad_sigma_functions_are_named():
    t, y = _data()

    def wrong_shape(p):
        return p["sig"].reshape(1)

    def negative(p):
        return -sigma(p)

    def float32(p):
        return sigma(p).float()

    for function, match in ((wrong_shape, r"shape \(K,\) = \(2,\)"), (negative, "positive"), (float32, "dtype")):
        with pytest.raises((ValueError, TypeError), match=match):
            _fit(torchql.Observations(t, y, observe=observe, sigma=function))
    exact = torch.zeros(21, dtype=torch.bool)
    exact[0] = True
    with pytest.raises(ValueError, match="`exact` values cannot be combined"):
        _fit(torchql.Observations(t, y, observe=observe, sigma=sigma, exact=exact))
    data = [torchql.Observations(t, y, observe=observe, sigma=sigma),
            torchql.Observations(t, y, observe=observe, sigma=lambda p: sigma(p))]
    with pytest.raises(ValueError, match="sigma\\(p\\) function object differ"):
        torchql.fit_many(Decay(**GUESS), data, x0=torch.tensor([1.0], dtype=DT), fixed_x0=["x"])
    mixed = [torchql.Observations(t, y, observe=observe, sigma=sigma),
             torchql.Observations(t, y, observe=observe, sigma=0.1)]
    with pytest.raises(ValueError, match="function sigma\\(p\\) for every experiment or for none"):
        torchql.fit(Decay(**GUESS), mixed, x0=torch.ones(2, 1, dtype=DT), fixed_x0=["x"])


def test_gradient_fitting_refuses_a_sigma_function():
    t, y = _data()
    with pytest.raises(ValueError, match="gradient fitting does not minimize"):
        adjoint_fit(Decay(**GUESS), torchql.Observations(t, y, observe=observe, sigma=sigma),
                            x0=torch.tensor([1.0], dtype=DT), fixed_x0=["x"])


def test_the_plot_draws_the_sigmas_at_the_estimates(problem):
    pytest.importorskip("matplotlib")
    import matplotlib

    matplotlib.use("Agg")
    _, _, result = problem
    fig, (ax, _) = plot_fit(result)
    bars = [c for c in ax.containers if isinstance(c, matplotlib.container.ErrorbarContainer)]
    half = bars[1].lines[2][0].get_segments()[0][:, 1]  # the second output's first bar: y +- sigma_2
    expected = float(result.params["s2"] * result.params["sig"])
    assert (half[1] - half[0]) / 2 == pytest.approx(expected, rel=1e-12)
    matplotlib.pyplot.close(fig)
