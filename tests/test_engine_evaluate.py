"""The engine's evaluation of an iterate: its linear problem's rows (torchql.engine_evaluate)."""

import pytest
import torch

import torchql

DT = torch.float64


class _TwoCompartments(torchql.ODEModel):
    """``x1' = -(k1 + k12) x1``, ``x2' = k12 x1 - k2 x2``."""

    state_names = ("x1", "x2")

    def __init__(self, k1: float, k2: float, k12: float) -> None:
        super().__init__()
        for name, value in (("k1", k1), ("k2", k2), ("k12", k12)):
            self.register_buffer(name, torch.tensor(value, dtype=DT))

    def forward(self, t, x):
        x1, x2 = x.unbind(-1)
        return torch.stack((-(self.k1 + self.k12) * x1, self.k12 * x1 - self.k2 * x2), dim=-1)


@pytest.mark.parametrize("method", ["kantorovich", "shooting"])
def test_an_unknown_read_only_through_a_cancellation_is_left_until_the_data_read_it(method):
    """Only the sum ``y = x1 + x2`` is observed (1 % noise), from guesses with ``k1 = k2``: there
    ``y' = -k1 y`` whatever ``k12``, whose column is the integration's error (1.6e-10 of the others').
    Scaled to unit norm it read as a direction of its own, the step along it was 6e8 times its
    scale, and the fit ended at the guesses (MAX_ITER after 20 of 50 iterations, advising a finer
    grid or shooting). Now ``k12`` waits while ``k1`` and ``k2`` move apart, and the fit reaches
    the optimum that a guess off the symmetry reaches (truth 0.5, 0.2, 0.3)."""
    t = torch.linspace(0, 10, 21, dtype=DT)
    Q = torch.tensor([[1.0, 1.0]], dtype=DT)
    noise = 0.01 * torch.randn(21, 1, generator=torch.Generator().manual_seed(0), dtype=DT)
    y = torchql.simulate(_TwoCompartments(0.5, 0.2, 0.3), torch.tensor([2.0, 0.5], dtype=DT), t) @ Q.T + noise
    data = torchql.Observations(t, y, observe=Q)
    fits = [torchql.fit(_TwoCompartments(*guess), data, x0=torch.tensor([1.0, 0.5], dtype=DT), fixed_x0=["x2"],
                        method=method) for guess in ((0.3, 0.3, 0.1), (0.6, 0.25, 0.2))]
    assert all(r.success for r in fits), [r.message for r in fits]
    torch.testing.assert_close(fits[0].estimates, fits[1].estimates, rtol=1e-6, atol=0.0)
    assert fits[0].sse == pytest.approx(fits[1].sse, rel=1e-9)
    assert fits[0].params["k1"] == pytest.approx(0.5, rel=0.05) and fits[0].params["k12"] == pytest.approx(0.3, rel=0.1)
