"""FitzHugh–Nagumo (Ramsay et al. 2007): right-hand side by hand, and recovery from exact data."""

import pytest
import torch

import torchql
from torchql.models import FitzHughNagumo

DT = torch.float64


def test_defaults_and_state_names():
    model = FitzHughNagumo()
    assert model.state_names == ("V", "R")
    assert [name for name, _ in model.named_buffers()] == ["a", "b", "c"]
    assert (model.a.item(), model.b.item(), model.c.item()) == (0.2, 0.2, 3.0)
    assert all(buf.dtype == DT for buf in model.buffers())


def test_right_hand_side_by_hand():
    model = FitzHughNagumo(a=0.3, b=0.5, c=2.0)
    x = torch.tensor([[-1.0, 1.0], [2.0, -0.5], [0.0, 0.0]], dtype=DT)
    # V' = c (V - V^3/3 + R), R' = -(V - a + b R) / c
    expected = torch.tensor([
        [2.0 * (-1.0 + 1.0 / 3.0 + 1.0), -(-1.0 - 0.3 + 0.5) / 2.0],
        [2.0 * (2.0 - 8.0 / 3.0 - 0.5), -(2.0 - 0.3 - 0.25) / 2.0],
        [0.0, 0.3 / 2.0],
    ], dtype=DT)
    out = model(torch.tensor(0.0, dtype=DT), x)
    assert out.shape == (3, 2)
    torch.testing.assert_close(out, expected, rtol=1e-15, atol=1e-15)
    # unbatched state
    torch.testing.assert_close(model(torch.tensor(0.0, dtype=DT), x[0]), expected[0], rtol=1e-15, atol=1e-15)


@pytest.mark.slow
def test_exact_data_recovery_from_a_guess_20_percent_off():
    """Ramsay's setting (V0, R0) = (-1, 1) on [0, 20], both states at 41 times; every unknown 20% off."""
    t = torch.linspace(0.0, 20.0, 41, dtype=DT)
    x = torchql.simulate(FitzHughNagumo(), torch.tensor([-1.0, 1.0], dtype=DT), t, rtol=1e-13, atol=1e-15)
    data = torchql.Observations(t, x, observe=["V", "R"])
    result = torchql.fit(FitzHughNagumo(a=0.24, b=0.16, c=3.6), data, x0=torch.tensor([-1.2, 0.8], dtype=DT))
    assert result.success, result.message
    assert result.unknown_names == ["V(t0)", "R(t0)", "a", "b", "c"]
    truth = torch.tensor([-1.0, 1.0, 0.2, 0.2, 3.0], dtype=DT)
    # Kantorovich converges to the fixed point of its grid-stored iteration (1000 intervals, cubic
    # Hermite interpolation), which differs from the exact solution by ~1e-7 relative here
    assert ((result.estimates - truth).abs() / truth.abs()).max() < 1e-6
    torch.testing.assert_close(result.predict(t), x, rtol=0, atol=1e-6)
