"""A -> B -> C kinetics: right-hand side by hand, and recovery with badly scaled unknowns.

The rate constants (~1e-5..1e-4 1/s) are six to seven orders of magnitude below the
concentrations (~100) and the times reach 1e4 s; the fits below get no help from the user
(no rescaling of time, states or coefficients).
"""

import pytest
import torch

import torchql
from torchql.models import FirstOrderReactions

DT = torch.float64
K1, K2 = 5e-5, 2e-4
X0 = (100.0, 0.0, 0.0)


def test_defaults_and_state_names():
    model = FirstOrderReactions()
    assert model.state_names == ("A", "B", "C")
    assert (model.k1.item(), model.k2.item()) == (K1, K2)
    assert all(buf.dtype == DT for buf in model.buffers())


def test_right_hand_side_by_hand_and_mass_conservation():
    model = FirstOrderReactions(k1=1e-4, k2=3e-5)
    x = torch.tensor([[100.0, 20.0, 5.0], [0.0, 50.0, 50.0]], dtype=DT)
    expected = torch.tensor([[-1e-2, 1e-2 - 6e-4, 6e-4], [0.0, -1.5e-3, 1.5e-3]], dtype=DT)
    out = model(torch.tensor(0.0, dtype=DT), x)
    torch.testing.assert_close(out, expected, rtol=1e-15, atol=1e-18)
    torch.testing.assert_close(out.sum(-1), torch.zeros(2, dtype=DT), rtol=0, atol=1e-18)


def test_analytic_solution():
    """``simulate`` matches the closed form (Bateman) solution of A -> B -> C."""
    t = torch.linspace(0.0, 1e4, 11, dtype=DT)
    x = torchql.simulate(FirstOrderReactions(), torch.tensor(X0, dtype=DT), t, rtol=1e-12, atol=1e-12)
    A = 100.0 * torch.exp(-K1 * t)
    B = 100.0 * K1 / (K2 - K1) * (torch.exp(-K1 * t) - torch.exp(-K2 * t))
    torch.testing.assert_close(x, torch.stack((A, B, 100.0 - A - B), dim=-1), rtol=1e-9, atol=1e-9)


def _data():
    t = torch.linspace(0.0, 1e4, 21, dtype=DT)
    x = torchql.simulate(FirstOrderReactions(), torch.tensor(X0, dtype=DT), t, rtol=1e-13, atol=1e-13)
    return t, x, torchql.Observations(t, x, observe=["A", "B", "C"])


HIGH_LOW, LOW_HIGH = (10 * K1, K2 / 10), (K1 / 10, 10 * K2)
CASES = [
    pytest.param("kantorovich", "integrate", HIGH_LOW, id="kantorovich-integrate-k1_high_k2_low"),
    # undamped, this start overshoots k2 to about -6e-3 and B grows like exp(60): the damping is needed
    pytest.param("kantorovich", "integrate", LOW_HIGH, id="kantorovich-integrate-k1_low_k2_high"),
    pytest.param("kantorovich", "data", HIGH_LOW, id="kantorovich-data-k1_high_k2_low"),
    pytest.param("kantorovich", "data", LOW_HIGH, id="kantorovich-data-k1_low_k2_high"),
    pytest.param("shooting", "integrate", HIGH_LOW, id="shooting-k1_high_k2_low"),
    pytest.param("shooting", "integrate", LOW_HIGH, id="shooting-k1_low_k2_high"),
]


@pytest.mark.parametrize("method, initial_trajectory, guess", CASES)
def test_exact_data_recovery_from_rates_10x_off_without_scaling(method, initial_trajectory, guess):
    t, x, data = _data()
    kwargs = {"initial_trajectory": initial_trajectory} if method == "kantorovich" else {}
    result = torchql.fit(FirstOrderReactions(*guess), data, x0=torch.tensor([90.0, 5.0, 5.0], dtype=DT),
                         method=method, **kwargs)
    assert result.success, result.message
    assert result.unknown_names == ["A(t0)", "B(t0)", "C(t0)", "k1", "k2"]
    # rate constants to 1e-7 relative; initial concentrations to 1e-7 of their scale (100)
    assert abs(result.params["k1"].item() / K1 - 1) < 1e-7
    assert abs(result.params["k2"].item() / K2 - 1) < 1e-7
    torch.testing.assert_close(result.x0, torch.tensor(X0, dtype=DT), rtol=0, atol=1e-5)
    torch.testing.assert_close(result.predict(t), x, rtol=0, atol=1e-6)
