"""The final statuses (torchql.engine_diagnosis): a stalled fit at the model's optimum, as far as the
integration resolves it, is converged."""

import pytest
import torch

import torchql
from torchql.models import HarmonicOscillator

DT = torch.float64


def test_a_stalled_fit_whose_model_step_promises_less_than_the_integration_resolves_is_converged():
    """A harmonic oscillator (xi = 9) fitted from xi = 3 integrated, x(0) unknown: its sum of squares has
    local minima every few units of xi, with large residuals; there the undamped steps overshoot,
    the damped ones creep, and the iteration stalls (27 iterations, at xi = 2.69). At the estimates
    the Gauss-Newton step on the model promises to lower the sum of squares (41) by about 1e-8, of
    the order of its integration error: CONVERGED_SSE, where it was STALLED. It is a local minimum:
    the model's own sum of squares is higher a step of 1e-2 of its scale away in each unknown, either
    side, by more than ten times the integration's error."""
    t = torch.linspace(0, 20, 81, dtype=DT)
    y = torchql.simulate(HarmonicOscillator(9.0), torch.tensor([1.0, 0.0], dtype=DT), t)[:, 0]
    y = y + 0.05 * torch.randn(81, generator=torch.Generator().manual_seed(11), dtype=DT)
    data = torchql.Observations(t, y[:, None], observe=["x"])
    result = torchql.fit(HarmonicOscillator(3.0), data, torch.tensor([0.5, 0.5], dtype=DT), initial_trajectory="integrate")
    assert result.status is torchql.Status.CONVERGED_SSE, result.message
    assert "stalled" in result.message and "below what the integration's error lets it resolve" in result.message
    assert result.covariance is not None and bool(torch.isfinite(result.covariance).all())
    x0, xi = result.x0, float(result.params["xi"])
    for k in range(3):
        for sign in (-1.0, 1.0):
            shifted = torch.cat([x0, torch.tensor([xi], dtype=DT)])
            shifted[k] += sign * 1e-2 * max(abs(float(shifted[k])), 0.1)
            there = torchql.fit(HarmonicOscillator(float(shifted[2])), data, shifted[:2], max_iter=0)
            assert there.sse > result.sse + 1e-7, (k, sign, there.sse - result.sse)  # (its error: 8e-9)
    assert result.sse == pytest.approx(40.985794, rel=1e-6)


def test_an_undamped_fit_from_a_guess_whose_model_blows_up_is_diverged_not_unidentifiable():
    """``damping=None`` from ``a = -80`` (``y' = 80 y``): 50 undamped iterations end at a sum of squares
    of 3.8e72, x(0) = 2e19, with data of order 1. The Jacobian there is rank deficient, and the
    typical magnitudes, taken from the blown-up first trajectory, made every step look small: the
    fit was called NOT_IDENTIFIABLE, which ``profile`` accepts as a fit."""
    from testmodels import Lag

    x0 = torch.tensor([1.0, 0.3], dtype=DT)
    t = torch.linspace(0.0, 3.0, 20, dtype=DT)
    x = torchql.simulate(Lag(3.0, 1.0), x0, t, rtol=1e-11, atol=1e-13)
    y = x + 0.01 * torch.randn(x.shape, generator=torch.Generator().manual_seed(5), dtype=DT)
    data = torchql.Observations(t, y, observe=["x", "y"], sigma=0.01)
    result = torchql.fit(Lag(1.0, -80.0), data, x0, damping=None, initial_trajectory="integrate")
    assert result.status is torchql.Status.DIVERGED, result.message
    assert "misses the data by orders of magnitude" in result.message


def test_log_normal_data_near_one_are_not_compared_with_a_model_predicting_zero():
    """With ``noise="lognormal"`` the residuals are of logarithms, which for data near 1 are near 0:
    a logistic fit cut short by ``max_iter=1``, within 3.5 % of every value, was called DIVERGED,
    "1.96e3 times the data's own". It is MAX_ITER, as the same fit with normal noise is."""
    class Logistic(torchql.ODEModel):
        state_names = ("y",)

        def __init__(self, r=1.0, K=1.0):
            super().__init__()
            self.register_buffer("r", torch.tensor(r, dtype=DT))
            self.register_buffer("K", torch.tensor(K, dtype=DT))

        def forward(self, t, x):
            return self.r * x * (1 - x / self.K)

    t = torch.linspace(0, 10, 30, dtype=DT)
    y = torchql.simulate(Logistic(0.8, 1.0), torch.tensor([0.998], dtype=DT), t)
    y = y * torch.exp(1e-4 * torch.randn(y.shape, generator=torch.Generator().manual_seed(0), dtype=DT))
    for noise in ("lognormal", "normal"):
        data = torchql.Observations(t, y, observe=["y"], noise=noise)
        result = torchql.fit(Logistic(0.3, 1.3), data, torch.tensor([0.99], dtype=DT), max_iter=1)
        assert result.status is torchql.Status.MAX_ITER, (noise, result.message)


@pytest.mark.parametrize("options", [{"method": "shooting"},
                                     {"initial_trajectory": "integrate", "damping": None}])
def test_a_fit_whose_model_amplifies_rounding_beyond_the_data_is_diverged(options):
    """A decaying oscillation (A = 0.2, B = 2) from guesses A = -5, B = -50, whose model grows as
    e^(10 t) over the data's 6.5 time units: the fit ends with its initial state on the decaying mode
    e^(-5 t), "converged" at a sum of squares (1.86) that its own ``predict`` misses by 1e22, and its
    column-scaled Jacobian is of rank 1. It was called NOT_IDENTIFIABLE, telling the user to fix
    unknowns the data determine well (from A = 0.3, B = 2.5 the fit converges to SSE 8.4e-4). A
    change of the unknowns in their last digits moves a fitted value by 2.5e11, the data being of
    order 0.36: DIVERGED, saying so, in fit and fit_many alike."""
    from torchql.models import LinearOscillator

    t = torch.arange(14, dtype=DT) * 0.5
    x0 = torch.tensor([0.0, 1.0], dtype=DT)
    y = torchql.simulate(LinearOscillator(0.2, 2.0), x0, t)[:, :1]
    y = y + 0.01 * torch.randn(y.shape, generator=torch.Generator().manual_seed(5), dtype=DT)
    data = torchql.Observations(t, y, observe=["y"])
    result = torchql.fit(LinearOscillator(-5.0, -50.0), data, x0, **options)
    assert result.status is torchql.Status.DIVERGED, result.message
    assert "changes a weighted fitted value by up to" in result.message
    assert "more than the data's own root mean square (0.363)" in result.message
    batch = torchql.fit_many(LinearOscillator(-5.0, -50.0), torchql.Observations(t, torch.stack([y, y]), observe=["y"]),
                             x0, **options)
    assert [s.name for s in batch.status] == ["DIVERGED", "DIVERGED"]
    good = torchql.fit(LinearOscillator(0.3, 2.5), data, x0, **options)
    assert good.success, good.message
    assert abs(float(good.params["B"]) - 2.0) < 0.05 and "last digits" not in good.message


def test_a_step_that_promises_no_decrease_is_not_said_to_promise_a_negative_one():
    """A bounded shooting fit's message read "promises a decrease of the sum of squares by -0.28"."""
    from torchql.engine_diagnosis import _promise

    assert "promises no decrease" in _promise(-0.28, 1e-8) and "-0.28" not in _promise(-0.28, 1e-8)
    assert "by 3e-09, below what the integration's error lets it resolve (1e-08)" in _promise(3e-9, 1e-8)
