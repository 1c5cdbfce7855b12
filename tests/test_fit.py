"""The mathematics of `fit`: recovery of known truth, quadratic convergence, exactness, agreement.

Tolerances: the data are made at rtol 1e-13 and fits integrate at the default rtol 1e-10, so
a converged fit of exact data recovers the truth to about 1e-10 relative; the bounds below
(1e-8 and 1e-6) are the ones the project promises, with margin to that floor.
"""

import math

import pytest
import torch

import torchql
from testmodels import Product
from torchql.models import HarmonicOscillator, LinearOscillator, NonlinearOscillator

DT = torch.float64
LINEAR_TRUTH = torch.tensor([0.0, 1.0, 0.1, 3.0], dtype=DT)  # y0, v0, A, B
NONLINEAR_TRUTH = torch.tensor([0.0, 1.0, 0.1, 3.0, 0.2, 4.0], dtype=DT)


def exact_data(model, x0, times, observe=("y",)):
    x = torchql.simulate(model, torch.tensor(x0, dtype=DT), times, rtol=1e-13, atol=1e-15)
    idx = [list(model.state_names).index(s) for s in observe]
    return torchql.Observations(times, x[:, idx], observe=list(observe))


def rel_error(estimates, truth):
    """Relative error, absolute where the truth is zero."""
    scale = torch.where(truth == 0, torch.ones_like(truth), truth.abs())
    return ((estimates - truth).abs() / scale).max().item()


@pytest.fixture(scope="module")
def linear_data():
    return exact_data(LinearOscillator(), [0.0, 1.0], torch.arange(14, dtype=DT) * 0.5)


@pytest.fixture(scope="module")
def linear_fits(linear_data):
    return {
        method: torchql.fit(LinearOscillator(0.5, 1.0), linear_data, x0=torch.tensor([0.5, 0.5], dtype=DT),
                            method=method)
        for method in torchql.METHODS
    }


@pytest.mark.parametrize("method", torchql.METHODS)
def test_linear_oscillator_exact_data_within_1e8_in_8_iterations(linear_fits, method):
    result = linear_fits[method]
    assert result.success, result.message
    assert result.unknown_names == ["y(t0)", "v(t0)", "A", "B"]
    # the iterate after at most 8 updates is within 1e-8 of the truth ...
    after_8 = result.history[min(8, result.iterations)]
    est8 = torch.cat([after_8.x0, after_8.params["A"].reshape(1), after_8.params["B"].reshape(1)])
    assert rel_error(est8, LINEAR_TRUTH) < 1e-8
    # ... and the converged estimate too
    assert rel_error(result.estimates, LINEAR_TRUTH) < 1e-8
    assert result.iterations <= 9
    assert result.sse < 1e-16


@pytest.mark.parametrize("damping", ["lm", None])
def test_kantorovich_converges_quadratically(linear_fits, linear_data, damping):
    """e_{k+1} <= K e_k^2 over the iterates above the noise floor, damped (default) or not and
    integrated from the guesses (the thesis; from the data it is in the quadratic range at once)."""
    result = linear_fits["kantorovich"] if damping == "lm" else torchql.fit(
        LinearOscillator(0.5, 1.0), linear_data, x0=torch.tensor([0.5, 0.5], dtype=DT), damping=None,
        initial_trajectory="integrate")
    assert result.success, result.message
    errors = []
    for rec in result.history:
        est = torch.cat([rec.x0, rec.params["A"].reshape(1), rec.params["B"].reshape(1)])
        errors.append((est - LINEAR_TRUTH).abs().max().item())
    pairs = [(a, b) for a, b in zip(errors, errors[1:]) if 1e-9 < b and a < 0.1]
    assert len(pairs) >= (2 if damping is None else 1), errors
    ratios = [b / a**2 for a, b in pairs]
    assert max(ratios) < 50, (errors, ratios)
    # and the error at least squares each time: digits double
    assert all(math.log10(b) < 1.6 * math.log10(a) for a, b in pairs), errors


def test_alpha_goes_to_zero(linear_fits):
    norms = [rec.alpha_norm for rec in linear_fits["kantorovich"].history if rec.alpha is not None]
    assert norms[-1] <= 1e-8 and norms[-1] < 1e-4 * norms[-3]


@pytest.fixture(scope="module")
def nonlinear_fits():
    data = exact_data(NonlinearOscillator(), [0.0, 1.0], torch.arange(66, dtype=DT) * 0.1)
    return {
        method: torchql.fit(NonlinearOscillator(0.5, 2.0, 0.5, 2.0), data, x0=torch.tensor([0.5, 0.5], dtype=DT),
                            method=method)
        for method in torchql.METHODS
    }


@pytest.mark.parametrize("method", torchql.METHODS)
def test_nonlinear_oscillator_exact_data_within_1e6(nonlinear_fits, method):
    result = nonlinear_fits[method]
    assert result.success, result.message
    assert rel_error(result.estimates, NONLINEAR_TRUTH) < 1e-6


def test_harmonic_table_3_2_gives_pi_squared():
    # x'' + xi x = 0, x = cos(pi t) observed at three times, from (1, 1, 1) with a data-built first trajectory
    times = torch.tensor([0.0, 0.25, 0.5], dtype=DT)
    data = torchql.Observations(times, torch.cos(math.pi * times), observe=["x"])
    result = torchql.fit(HarmonicOscillator(1.0), data, x0=torch.tensor([1.0, 1.0], dtype=DT),
                         initial_trajectory="data")
    assert result.success, result.message
    assert abs(result.params["xi"].item() - math.pi**2) < 1e-8
    assert abs(result.x0[0].item() - 1.0) < 1e-9 and abs(result.x0[1].item()) < 1e-8


@pytest.fixture(scope="module")
def rounded_linear_data():
    times = torch.arange(14, dtype=DT) * 0.5
    x = torchql.simulate(LinearOscillator(), torch.tensor([0.0, 1.0], dtype=DT), times, rtol=1e-13, atol=1e-15)
    return times, torch.round(x[:, 0] * 100) / 100  # two decimals: the optimum is off the truth


def test_both_methods_agree_at_the_least_squares_optimum(rounded_linear_data):
    times, y = rounded_linear_data
    data = torchql.Observations(times, y, observe=["y"])
    x0 = torch.tensor([0.1, 0.9], dtype=DT)
    a = torchql.fit(LinearOscillator(0.2, 2.5), data, x0=x0, method="kantorovich")
    b = torchql.fit(LinearOscillator(0.2, 2.5), data, x0=x0, method="shooting")
    assert a.success and b.success
    torch.testing.assert_close(a.estimates, b.estimates, rtol=1e-8, atol=1e-10)
    assert a.sse == pytest.approx(b.sse, rel=1e-8)
    # the optimum: the gradient of the SSE, J^T r, vanishes
    grad = a.jacobian.T @ a.residuals
    assert grad.abs().max() < 1e-8 * a.jacobian.abs().max() * a.residuals.abs().max() * len(a.residuals)


def test_exact_observations_are_met_to_1e10(rounded_linear_data):
    times, y = rounded_linear_data
    exact = torch.zeros(14, dtype=torch.bool)
    exact[[0, 5, 13]] = True
    data = torchql.Observations(times, y, observe=["y"], exact=exact)
    for method in torchql.METHODS:
        result = torchql.fit(LinearOscillator(0.2, 2.5), data, x0=torch.tensor([0.1, 0.9], dtype=DT), method=method)
        assert result.success, result.message
        assert result.exact_residual < 1e-10
        fitted = result.predict(times[exact])[:, 0]
        torch.testing.assert_close(fitted, y[exact], rtol=0, atol=1e-10)
    free = torchql.fit(LinearOscillator(0.2, 2.5), torchql.Observations(times, y, observe=["y"]),
                       x0=torch.tensor([0.1, 0.9], dtype=DT))
    assert free.sse < result.sse  # constraints cost fit quality


def test_known_initial_state_is_honoured_exactly(linear_data):
    x0 = torch.tensor([0.0, 0.7], dtype=DT)  # y0 known (and true), v0 a guess
    for method in torchql.METHODS:
        result = torchql.fit(LinearOscillator(0.3, 2.0), linear_data, x0=x0, fixed_x0=["y"], method=method)
        assert result.success, result.message
        assert result.unknown_names == ["v(t0)", "A", "B"]
        assert all(rec.x0[0].item() == 0.0 for rec in result.history)
        assert rel_error(result.estimates, LINEAR_TRUTH[1:]) < 1e-8


def test_jacobian_matches_finite_differences(rounded_linear_data):
    times, y = rounded_linear_data
    data = torchql.Observations(times, y, observe=["y"], sigma=0.01)
    result = torchql.fit(LinearOscillator(0.2, 2.5), data, x0=torch.tensor([0.1, 0.9], dtype=DT))
    u = result.estimates

    def observed(u):
        model = LinearOscillator(u[2].item(), u[3].item())
        return torchql.simulate(model, u[:2], times, rtol=1e-13, atol=1e-15)[:, 0] / 0.01

    fd = torch.zeros_like(result.jacobian)
    for i in range(4):
        h = 1e-5 * max(abs(u[i].item()), 1e-2)
        up, dn = u.clone(), u.clone()
        up[i] += h
        dn[i] -= h
        fd[:, i] = (observed(up) - observed(dn)) / (2 * h)
    torch.testing.assert_close(result.jacobian, fd, rtol=1e-6, atol=1e-6 * fd.abs().max().item())


def test_observation_operators_matrix_and_callable_agree_with_names(linear_data):
    y = linear_data.y
    x0 = torch.tensor([0.5, 0.5], dtype=DT)
    by_matrix = torchql.fit(LinearOscillator(0.5, 1.0), torchql.Observations(linear_data.t, y, observe=torch.tensor([[1.0, 0.0]], dtype=DT)), x0=x0)
    assert rel_error(by_matrix.estimates, LINEAR_TRUTH) < 1e-8
    # a nonlinear measurement h(x) = y + y^3, linearized like the right-hand side
    times = linear_data.t
    x = torchql.simulate(LinearOscillator(), torch.tensor([0.0, 1.0], dtype=DT), times, rtol=1e-13, atol=1e-15)
    h = lambda s: (s[..., 0] + s[..., 0] ** 3).unsqueeze(-1)
    data = torchql.Observations(times, h(x), observe=h)
    for method in torchql.METHODS:
        result = torchql.fit(LinearOscillator(0.2, 2.5), data, x0=torch.tensor([0.1, 0.9], dtype=DT), method=method)
        assert result.success, result.message
        assert rel_error(result.estimates, LINEAR_TRUTH) < 1e-8


def test_sigma_weights_the_residuals(rounded_linear_data):
    times, y = rounded_linear_data
    x0 = torch.tensor([0.1, 0.9], dtype=DT)
    plain = torchql.fit(LinearOscillator(0.2, 2.5), torchql.Observations(times, y, observe=["y"]), x0=x0)
    scaled = torchql.fit(LinearOscillator(0.2, 2.5), torchql.Observations(times, y, observe=["y"], sigma=0.005), x0=x0)
    torch.testing.assert_close(plain.estimates, scaled.estimates, rtol=1e-8, atol=1e-10)
    assert scaled.sse == pytest.approx(plain.sse / 0.005**2, rel=1e-6)
    # down-weighting the second half moves the optimum
    sigma = torch.ones(14, 1, dtype=DT)
    sigma[7:] = 100.0
    weighted = torchql.fit(LinearOscillator(0.2, 2.5), torchql.Observations(times, y, observe=["y"], sigma=sigma), x0=x0)
    assert (weighted.estimates - plain.estimates).abs().max() > 1e-5


def test_initial_time_before_first_observation_and_uneven_long_span():
    # decay observed late and unevenly over a long span, initial state at t0 = 0
    class Decay(torchql.ODEModel):
        state_names = ("c",)

        def __init__(self, k):
            super().__init__()
            self.register_buffer("k", torch.tensor(k, dtype=DT))

        def forward(self, t, x):
            return -self.k * x

    times = torch.tensor([50.0, 120.0, 400.0, 410.0, 1500.0, 4000.0], dtype=DT)
    y = 100.0 * torch.exp(-1e-3 * times)
    data = torchql.Observations(times, y, observe=["c"])
    for method in torchql.METHODS:
        result = torchql.fit(Decay(2e-3), data, x0=torch.tensor([80.0], dtype=DT), t0=0.0, method=method)
        assert result.success, result.message
        assert result.t0 == 0.0
        assert abs(result.x0[0].item() - 100.0) < 1e-7
        assert abs(result.params["k"].item() / 1e-3 - 1) < 1e-8


def test_matrix_coefficient_and_several_outputs_with_missing_values():
    """Any number of states and coefficients: a 3-state linear system with a (3, 3) buffer."""

    class Linear3(torchql.ODEModel):
        state_names = ("a", "b", "c")

        def __init__(self, K):
            super().__init__()
            self.register_buffer("K", torch.as_tensor(K, dtype=DT))

        def forward(self, t, x):
            return x @ self.K.T

    K_true = torch.tensor([[-0.5, 1.0, 0.0], [-1.0, -0.2, 0.3], [0.0, -0.3, -0.4]], dtype=DT)
    times = torch.linspace(0, 6, 31, dtype=DT)
    x = torchql.simulate(Linear3(K_true), torch.tensor([1.0, 0.0, -1.0], dtype=DT), times, rtol=1e-13, atol=1e-15)
    # all three states observed (with gaps): with b hidden, K would be determined only up to
    # a rescaling of b, which the next test's identifiability check reports
    y = x.clone()
    y[3, 0] = float("nan")
    y[10, 1] = float("nan")
    y[::2, 1] = float("nan")
    data = torchql.Observations(times, y, observe=["a", "b", "c"])
    guess = K_true + 0.05 * torch.tensor([[1, -1, 1], [1, 1, -1], [-1, 1, 1]], dtype=DT)
    result = torchql.fit(Linear3(guess), data, x0=torch.tensor([0.9, 0.1, -0.9], dtype=DT))
    assert result.success, result.message
    assert "K[1,2]" in result.unknown_names and len(result.unknown_names) == 12
    torch.testing.assert_close(result.params["K"], K_true, rtol=0, atol=1e-8)
    # b hidden: the scale of b is arbitrary, and the fit says so instead of returning numbers
    hidden = torchql.Observations(times, x[:, [0, 2]], observe=["a", "c"])
    result = torchql.fit(Linear3(guess), hidden, x0=torch.tensor([0.9, 0.1, -0.9], dtype=DT))
    assert result.status is torchql.Status.NOT_IDENTIFIABLE
    assert "b(t0)" in result.message


def test_product_of_parameters_is_reported_not_identifiable():
    times = torch.linspace(0, 2, 11, dtype=DT)
    data = torchql.Observations(times, torch.exp(-0.6 * times), observe=["y"])
    result = torchql.fit(Product(1.0, 1.0), data, x0=torch.tensor([1.0], dtype=DT))
    assert not result.success
    assert result.status is torchql.Status.NOT_IDENTIFIABLE
    assert "{a, b}" in result.message
    with pytest.raises(torchql.FitError, match="rank deficient"):
        torchql.fit(Product(1.0, 1.0), data, x0=torch.tensor([1.0], dtype=DT), throw=True)


def test_blow_up_is_a_failed_status_not_an_answer():
    class Riccati(torchql.ODEModel):
        state_names = ("y",)

        def __init__(self, k=1.0):
            super().__init__()
            self.register_buffer("k", torch.tensor(k, dtype=DT))

        def forward(self, t, x):
            return self.k * x**2

    times = torch.linspace(0, 3, 7, dtype=DT)
    data = torchql.Observations(times, 1.0 / (1.0 + 0.1 * times), observe=["y"])  # truth k = -0.1
    # integrated from k = 1, the model blows up (built from the data, the first reference is the
    # data's own solution, k = -0.1, and the fit converges)
    result = torchql.fit(Riccati(1.0), data, x0=torch.tensor([1.0], dtype=DT), max_steps=2000,
                         initial_trajectory="integrate")
    assert not result.success
    assert result.status in (torchql.Status.INTEGRATION_FAILED, torchql.Status.DIVERGED)
    assert "solver" in result.message or "non-finite" in result.message


@pytest.mark.parametrize("solver", ["dopri8", "rk4"])
def test_other_solvers(linear_data, solver):
    result = torchql.fit(LinearOscillator(0.2, 2.5), linear_data, x0=torch.tensor([0.1, 0.9], dtype=DT),
                         solver=solver, rtol=1e-11, atol=1e-13)
    assert result.success, result.message
    # dopri8 in torchdiffeq and the fixed-step rk4 on the default grid are less exact than dopri5
    assert rel_error(result.estimates, LINEAR_TRUTH) < 1e-6


def test_table_4_5_damped_kantorovich_reaches_the_least_squares_optimum(table_4_5_two_digit):
    """Undamped, the first step overshoots into a finite-time blow-up; damped, both methods agree."""
    guess = dict(A=0.5, B=2.0, C=0.5, D=2.0)
    x0 = torch.tensor([0.5, 0.5], dtype=DT)
    undamped = torchql.fit(NonlinearOscillator(**guess), table_4_5_two_digit, x0=x0, damping=None, max_steps=200)
    assert undamped.status is torchql.Status.INTEGRATION_FAILED
    damped = torchql.fit(NonlinearOscillator(**guess), table_4_5_two_digit, x0=x0, max_steps=200)
    shooting = torchql.fit(NonlinearOscillator(**guess), table_4_5_two_digit, x0=x0, method="shooting", max_steps=200)
    assert damped.success and shooting.success, (damped.message, shooting.message)
    assert sum(rec.rejected for rec in damped.history) > 0  # the damping did work here
    assert torch.allclose(damped.estimates, shooting.estimates, rtol=1e-7, atol=1e-8)
    assert damped.sse == pytest.approx(shooting.sse, rel=1e-9)
    assert abs(damped.params["B"].item() - 3.0) < 0.05  # not the thesis' B = .67


def test_a_reanchoring_whose_transfers_fail_raises_the_damping_instead_of_ending_the_fit(table_4_5_two_digit):
    """Re-anchoring an undamped rejection is a second try: where the transfers about the model's
    own solution fail (a fast layer inside a grid interval, on a stiff model), the sample keeps
    its iterate and its damping is raised, and the fit reaches the same optimum."""
    import sys
    from unittest import mock

    import torchql.engine as engine

    guess = dict(A=0.5, B=2.0, C=0.5, D=2.0)
    x0 = torch.tensor([0.5, 0.5], dtype=DT)
    evaluate, failed = engine.Engine._evaluate, []

    def reanchoring() -> bool:
        frame = sys._getframe(2)
        while frame is not None and frame.f_code.co_name != "_reanchor":
            frame = frame.f_back
        return frame is not None

    def failing_when_reanchored(self, *args, **kwargs):
        out = evaluate(self, *args, **kwargs)
        if reanchoring():
            out["failed"] = torch.ones_like(out["failed"])
            failed.append(True)
        return out

    with mock.patch.object(engine.Engine, "_evaluate", failing_when_reanchored):
        damped = torchql.fit(NonlinearOscillator(**guess), table_4_5_two_digit, x0=x0, max_steps=200)
    reference = torchql.fit(NonlinearOscillator(**guess), table_4_5_two_digit, x0=x0, max_steps=200)
    assert failed  # the re-anchorings were tried, and failed
    assert damped.success, damped.message
    torch.testing.assert_close(damped.estimates, reference.estimates, rtol=1e-7, atol=1e-8)
    assert damped.sse == pytest.approx(reference.sse, rel=1e-9)


def test_data_driven_first_trajectory_derives_unobserved_states(linear_data):
    """Only y is observed; y' = v gives v from the smoothed data, far better than the guess."""
    result = torchql.fit(LinearOscillator(0.5, 1.0), linear_data, x0=torch.tensor([0.5, 0.5], dtype=DT),
                         initial_trajectory="data")
    assert result.success, result.message
    assert rel_error(result.estimates, LINEAR_TRUTH) < 1e-8
    first = result.history[0]
    truth = torchql.simulate(LinearOscillator(), torch.tensor([0.0, 1.0], dtype=DT), first.trajectory_t,
                             rtol=1e-12, atol=1e-14)
    v_error = (first.trajectory[:, 1] - truth[:, 1]).square().mean().sqrt()
    guess_error = (0.5 - truth[:, 1]).square().mean().sqrt()
    # the not-a-knot spline through 14 samples (7 per period) gives v to about 1.5% of its amplitude
    assert v_error < guess_error / 20
    assert result.iterations <= 4


def test_shooting_rejects_stiff_trials_instead_of_crawling_through_them(monkeypatch):
    """2-digit oscillator data, bounded rates from A = 0.61, B = 1.14: one trial asks for A ~ 350.

    That trial's trajectory needs far more than the grid solver's step budget; it is rejected
    (the damping shortens the step) rather than integrated by the adaptive solver, which took
    more than 500,000 right-hand-side evaluations (over a minute) on the rejected trials alone.
    The adaptive solvers must run only for the first solution, from the guesses, where no
    prediction of the trajectory is at hand. (``nfev`` counts every state a right-hand side is
    evaluated at, about 24,000 per grid solve on this 1,000-interval grid, so it no longer
    tells the two apart: the test watches the solvers instead.)
    """
    import torchql.engine_evaluate as engine

    adaptive = []
    for name in ("dopri_batch", "integrate_each"):
        def spy(*args, _name=name, _real=getattr(engine, name), **kwargs):
            adaptive.append(_name)
            return _real(*args, **kwargs)
        monkeypatch.setattr(engine, name, spy)
    times = torch.arange(14, dtype=DT) * 0.5
    y = torchql.simulate(LinearOscillator(), torch.tensor([0.0, 1.0], dtype=DT), times, rtol=1e-13, atol=1e-15)[:, 0]
    data = torchql.Observations(times, torch.tensor([[float(f"{v:.1e}")] for v in y.tolist()], dtype=DT),
                                observe=["y"])
    result = torchql.fit(LinearOscillator(A=0.6138, B=1.1418), data, x0=torch.tensor([0.0, 0.86], dtype=DT),
                         method="shooting", bounds={"A": (0.0, None), "B": (0.0, None)})
    assert result.success, result.message
    assert sum(rec.rejected for rec in result.history) > 0
    assert adaptive == ["dopri_batch"]  # the first solution only (one sample as fit_many's: batched Dormand–Prince)
    assert abs(result.params["A"].item() - 0.102) < 1e-3 and abs(result.params["B"].item() - 3.0009) < 1e-3


@pytest.mark.parametrize("A, B", [(0.0153, 0.447), (1.0, 30.0), (0.01, 30.0), (1.0, 0.3)])
def test_data_driven_first_trajectory_on_sparse_two_digit_data(A, B):
    """Thesis Table 4.1's 14 samples rounded to 2 digits, y only, coefficients 10x off either way.

    Gradient matching on the spline through the samples puts the first coefficients within 5%
    of the truth, so every start converges in a few undamped steps to the least-squares
    optimum (the one shooting reaches from the truth). Straight lines between the samples gave
    piecewise-constant slopes there, first coefficients like B = 7, and 30 iterations.
    """
    times = torch.arange(14, dtype=DT) * 0.5
    y = torchql.simulate(LinearOscillator(), torch.tensor([0.0, 1.0], dtype=DT), times, rtol=1e-13, atol=1e-15)[:, :1]
    data = torchql.Observations(times, torch.tensor([[float(f"{v:.1e}")] for v in y[:, 0].tolist()], dtype=DT),
                                observe=["y"])
    x0 = torch.tensor([data.y[0, 0].item(), ((data.y[1, 0] - data.y[0, 0]) / 0.5).item()], dtype=DT)
    result = torchql.fit(LinearOscillator(A, B), data, x0=x0, initial_trajectory="data")
    optimum = torchql.fit(LinearOscillator(), data, x0=torch.tensor([0.0, 1.0], dtype=DT), method="shooting")
    assert result.success and optimum.success, (result.message, optimum.message)
    assert result.iterations <= 6
    first = result.history[0].params
    assert abs(first["A"].item() / 0.1 - 1) < 0.5 and abs(first["B"].item() / 3.0 - 1) < 0.05
    assert torch.allclose(result.estimates, optimum.estimates, rtol=1e-7, atol=1e-9)
    assert result.sse == pytest.approx(optimum.sse, rel=1e-9)


def _oscillator_in_time_units(s: float, method: str) -> torch.Tensor:
    """The noisy damped oscillation of 25 values over 6 time units, its time measured in units ``1 / s``
    of them (times ``s t``, coefficients ``A / s`` and ``B / s^2``, velocity ``v / s``): the estimates
    fitted from guesses 0.2-5x off, converted back to the first units."""
    t = torch.linspace(0, 6, 25, dtype=DT)
    noise = torch.randn(25, 1, generator=torch.Generator().manual_seed(0), dtype=DT)
    y = torchql.simulate(LinearOscillator(0.1, 3.0), torch.tensor([0.0, 1.0], dtype=DT), t)[:, :1] + 0.01 * noise
    result = torchql.fit(LinearOscillator(0.5 / s, 1.0 / s**2), torchql.Observations(s * t, y, observe=["y"]),
                         torch.tensor([0.2, 0.8 / s], dtype=DT), method=method)
    assert result.status is torchql.Status.CONVERGED, result.message
    return result.estimates * torch.tensor([1.0, s, s, s * s], dtype=DT)


@pytest.mark.parametrize("method", ["kantorovich", "shooting"])
@pytest.mark.parametrize("s", [1e-5, 1e5])
def test_a_fit_does_not_depend_on_the_time_unit(method, s):
    """The same oscillation in microseconds or in days: the interval transfers' growth bound is taken
    in states scaled to balance ``h A`` (:func:`torchql.taylor._balance`), where the raw norm of ``h A``
    (``h omega^2`` in the thousands, ``h omega`` a tenth) asked more substeps than allowed and every
    such fit ended ``INTEGRATION_FAILED`` before its first iteration. The estimates are those of the
    first units to 1e-10."""
    torch.testing.assert_close(_oscillator_in_time_units(s, method), _oscillator_in_time_units(1.0, method),
                               rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("method", torchql.METHODS)
def test_one_observation_time_at_t0_is_a_span_of_length_zero(method):
    """Both states measured once, at the first (and only) time, which is ``t0``: the initial state is
    the measurement. Shooting integrated that span of length zero into a bare IndexError."""
    data = torchql.Observations(torch.tensor([1.0], dtype=DT), torch.tensor([[[0.5, 0.1]], [[0.2, 0.3]]], dtype=DT),
                                observe=["y", "v"])
    guess = torch.tensor([0.2, 0.8], dtype=DT)
    batch = torchql.fit_many(LinearOscillator(), data, x0=guess, params=[], method=method)
    for b, expected in enumerate(([0.5, 0.1], [0.2, 0.3])):
        single = torchql.fit(LinearOscillator(), data[b], x0=guess, params=[], method=method)
        assert single.status is torchql.Status.CONVERGED and batch[b].status is torchql.Status.CONVERGED
        assert single.x0.tolist() == pytest.approx(expected, abs=1e-12)
        assert torch.equal(batch[b].x0, single.x0)


class _Forced(torchql.ODEModel):
    """``y'' + A y' + B y = cos(t - t_ref)``: a forward that reads the data's own time."""

    state_names = ("y", "v")

    def __init__(self, A=0.1, B=3.0, t_ref=0.0):
        super().__init__()
        for name, value in dict(A=A, B=B, t_ref=t_ref).items():
            self.register_buffer(name, torch.tensor(value, dtype=DT))

    def forward(self, t, x):
        y, v = x.unbind(-1)
        return torch.stack((v, -self.A * v - self.B * y + torch.cos(t - self.t_ref)), dim=-1)


def _on_a_clock(model, offset: float):
    """30 irregular times in [0, 7] s on a clock at ``offset``, noisy positions of ``model`` from (0, 1)."""
    local = torch.sort(torch.rand(30, generator=torch.Generator().manual_seed(3), dtype=DT) * 7).values
    clean = torchql.simulate(model, torch.tensor([0.0, 1.0], dtype=DT), local, t0=0.0, rtol=1e-12, atol=1e-14)
    y = clean[:, :1] + 0.01 * torch.randn(30, 1, generator=torch.Generator().manual_seed(4), dtype=DT)
    return torchql.Observations(local + offset, y, observe=["y"])


@pytest.mark.parametrize("offset", [1e3, 1.7e9])
def test_clock_times_are_fitted_in_local_time(offset):
    """The same times on a clock at ``offset`` (s): a model that does not read ``t`` is fitted in local
    time from ``t0`` and equals its fit at offset 0. At 1.7e9 its grid at the data's times resolved
    its nodes to 2.4e-7 (its intervals 0.007): 22 iterations instead of 5, and a note that the grid
    missed a smooth model. A model that reads ``t`` is given the data's time."""
    guess = torch.tensor([0.2, 0.8], dtype=DT)
    fits = [torchql.fit(LinearOscillator(A=0.5, B=1.0), _on_a_clock(LinearOscillator(A=0.1, B=3.0), at), x0=guess,
                        t0=at) for at in (0.0, offset)]
    assert [f.status for f in fits] == [torchql.Status.CONVERGED] * 2 and fits[1].message == fits[0].message
    assert fits[1].iterations == fits[0].iterations and fits[1].t0 == offset
    # (the data's times at 1.7e9 are themselves rounded to 2.4e-7 s, where the positions change by
    # about 2.4e-7: the estimates move by about that much)
    close = dict(rtol=1e-6, atol=1e-6) if offset > 1e6 else dict(rtol=1e-9, atol=0.0)
    assert torch.allclose(fits[1].estimates, fits[0].estimates, **close)
    assert torch.allclose(fits[1].predict(torch.tensor([offset + 7.5], dtype=DT)),
                          fits[0].predict(torch.tensor([7.5], dtype=DT)), rtol=1e-5, atol=1e-8)
    if offset < 1e6:  # the forcing read at the data's times: the fit at offset 0's
        forced = [torchql.fit(_Forced(0.5, 1.0, t_ref=at), _on_a_clock(_Forced(), at), x0=guess, t0=at,
                              params=["A", "B"]) for at in (0.0, offset)]
        assert forced[1].iterations == forced[0].iterations
        assert torch.allclose(forced[1].estimates, forced[0].estimates, rtol=1e-9, atol=0)


class _Daylight(torchql.ODEModel):
    """``x' = g light(t) - k x``, the light on for the first 12 h of each day: a forward that reads ``t``
    only through a comparison, which autograd does not see."""

    state_names = ("x",)

    def __init__(self, k=0.3, g=1.0):
        super().__init__()
        self.register_buffer("k", torch.tensor(k, dtype=DT))
        self.register_buffer("g", torch.tensor(g, dtype=DT))

    def forward(self, t, x):
        return self.g * (torch.remainder(t, 24.0) < 12.0).to(x.dtype) - self.k * x


def test_a_forward_that_switches_on_t_between_the_observations_keeps_the_data_times():
    """Sampled daily at 6 am, the switch's value is the same at every observation, and autograd sees no
    use of ``t``: the model was taken for one that does not read ``t`` and fitted on ``t - 6``, which
    moved the switch by 6 h (shooting: CONVERGED at g = 1.47, truth 1, its predictions 4.9 off the
    data). The midpoints between the times now see the switch, and near 0 the data's own times serve
    anyway (``torchql.local_time.CLOCK_RATIO``)."""
    t = 6.0 + 24.0 * torch.arange(0, 8, dtype=DT)
    x0 = torch.tensor([2.0], dtype=DT)
    y = torchql.simulate(_Daylight(0.05, 1.0), x0, t, solver="dopri5")
    fit = torchql.fit(_Daylight(0.1, 0.5), torchql.Observations(t, y, observe=["x"]), x0=x0, method="shooting")
    assert fit.status is torchql.Status.CONVERGED
    # (dopri5's data against the fit's solver: the same optimum to their tolerances)
    assert fit.params["g"].item() == pytest.approx(1.0, rel=1e-6)
    assert fit.params["k"].item() == pytest.approx(0.05, rel=1e-6)


def test_samples_at_their_own_clock_times_from_a_shared_t0_are_their_own_fits():
    """Two oscillators at their own times on a clock at 1.7e9 s, both from a shared ``t0``: each sample is
    fitted in its own local time, as its own fit is, and equals it."""
    data = [_on_a_clock(LinearOscillator(A=0.1, B=3.0), 1.7e9)]
    shifted = _on_a_clock(LinearOscillator(A=0.2, B=2.5), 1.7e9)
    data.append(torchql.Observations(shifted.t + 0.5, shifted.y, observe=["y"]))
    guess = torch.tensor([0.2, 0.8], dtype=DT)
    batch = torchql.fit_many(LinearOscillator(A=0.5, B=1.0), data, x0=guess, t0=1.7e9)
    for b in range(2):
        single = torchql.fit(LinearOscillator(A=0.5, B=1.0), data[b], x0=guess, t0=1.7e9)
        assert single.status is torchql.Status.CONVERGED and batch[b].status is single.status
        assert batch[b].iterations == single.iterations
        assert torch.allclose(batch[b].estimates, single.estimates, rtol=1e-8, atol=1e-12)
