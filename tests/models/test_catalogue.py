"""Every catalogue model is recovered from exact data by both methods."""

import math

import pytest
import torch

import torchql
from torchql.models import CoastingCar, HarmonicOscillator, LinearOscillator, NonlinearOscillator

DT = torch.float64


def _case(name):
    """(truth model, true x0, guess model, guess x0, observation times, observed states, tolerance)."""
    if name == "harmonic":
        return (HarmonicOscillator(math.pi**2), [1.0, 0.0], HarmonicOscillator(7.0), [0.9, 0.3],
                torch.linspace(0, 2, 21, dtype=DT), ["x"], 1e-8)
    if name == "linear":
        return (LinearOscillator(0.1, 3.0), [0.0, 1.0], LinearOscillator(0.3, 2.5), [0.1, 0.8],
                torch.arange(14, dtype=DT) * 0.5, ["y"], 1e-8)
    if name == "nonlinear":
        return (NonlinearOscillator(0.1, 3.0, 0.2, 4.0), [0.0, 1.0], NonlinearOscillator(0.2, 2.5, 0.3, 3.5),
                [0.1, 0.8], torch.arange(27, dtype=DT) * 0.25, ["y"], 1e-6)
    if name == "car":
        return (CoastingCar(17.3, 80.43, C_D=0.45, mu=0.018), [117.0], CoastingCar(17.3, 80.43), [110.0],
                torch.arange(9, dtype=DT) * 5.0, ["v"], 1e-8)
    raise KeyError(name)


def _unknowns(model, x0):
    buffers = dict(model.named_buffers())
    names = [n for n in buffers if n not in model.constants]
    return torch.cat([torch.tensor(x0, dtype=DT), torch.stack([buffers[n] for n in names])])


@pytest.mark.parametrize("method", torchql.METHODS)
@pytest.mark.parametrize("name", ["harmonic", "linear", "nonlinear", "car"])
def test_exact_data_recovery(name, method):
    truth, x0_true, guess, x0_guess, times, observe, tol = _case(name)
    states = torchql.simulate(truth, torch.tensor(x0_true, dtype=DT), times, rtol=1e-13, atol=1e-15)
    cols = [truth.state_names.index(s) for s in observe]
    data = torchql.Observations(times, states[:, cols], observe=observe)
    result = torchql.fit(guess, data, x0=torch.tensor(x0_guess, dtype=DT), method=method)
    assert result.success, result.message
    expected = _unknowns(truth, x0_true)
    scale = torch.where(expected == 0, torch.ones_like(expected), expected.abs())
    assert ((result.estimates - expected).abs() / scale).max() < tol
    # the fitted model reproduces the data
    torch.testing.assert_close(result.predict(times)[:, cols], states[:, cols], rtol=1e-7, atol=1e-9)


def test_car_constants_are_not_estimated_by_default():
    car = CoastingCar(17.3, 80.43)
    assert set(car.constants) == {"frontal_area", "mass", "rho", "g"}
    assert car.rho.item() == 0.00238 and car.g.item() == 32.2
    v = torch.tensor([117.3, 104.9, 95.3, 87.3, 79.2, 71.9, 65.7, 59.8, 54.0], dtype=DT)
    result = torchql.fit(car, torchql.Observations(torch.arange(9, dtype=DT) * 5, v, observe=["v"]), max_iter=1)
    assert result.unknown_names == ["v(t0)", "C_D", "mu"]
    assert result.params["mass"].item() == 80.43
