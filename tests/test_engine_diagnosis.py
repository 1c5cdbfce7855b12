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
