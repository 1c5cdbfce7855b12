"""First-order reaction networks: consecutive ``A -> B -> C``, and branched with ``A -> C`` too."""

from __future__ import annotations

import torch

from ..model import ODEModel

__all__ = ["FirstOrderReactions", "BranchedReactions"]


class FirstOrderReactions(ODEModel):
    """``A -> B -> C`` with first-order rate constants ``k1``, ``k2`` (1/s).

    ``A' = -k1 A``, ``B' = k1 A - k2 B``, ``C' = k2 B``. States ``(A, B, C)`` are concentrations
    (any unit, e.g. mol/m^3; ``A + B + C`` is conserved). The defaults ``k1 = 5e-5``,
    ``k2 = 2e-4`` 1/s are typical of slow liquid-phase kinetics: with concentrations near 100
    and times up to ``1e4`` s the coefficients are six to seven orders of magnitude smaller than
    the states, a scaling stress test for any fitting method.
    """

    state_names = ("A", "B", "C")

    def __init__(self, k1: float = 5e-5, k2: float = 2e-4) -> None:
        super().__init__()
        for name, value in (("k1", k1), ("k2", k2)):
            self.register_buffer(name, torch.tensor(float(value), dtype=torch.float64))

    def forward(self, t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        A, B, C = x.unbind(-1)
        r1, r2 = self.k1 * A, self.k2 * B
        return torch.stack((-r1, r1 - r2, r2), dim=-1)


class BranchedReactions(ODEModel):
    """``A -k1-> B -k2-> C`` and ``A -k3-> C``, first order, rate constants in 1/(time unit).

    ``A' = -(k1 + k3) A``, ``B' = k1 A - k2 B``, ``C' = k2 B + k3 A`` (``A + B + C`` is conserved).
    With all three states observed the three rates are identifiable; a standard test of starts on
    the bound ``k >= 0`` (published kinetics benchmarks start rates at 0).
    """

    state_names = ("A", "B", "C")

    def __init__(self, k1: float = 0.5, k2: float = 0.5, k3: float = 0.5) -> None:
        super().__init__()
        for name, value in (("k1", k1), ("k2", k2), ("k3", k3)):
            self.register_buffer(name, torch.tensor(float(value), dtype=torch.float64))

    def forward(self, t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        A, B, _ = x.unbind(-1)
        r1, r2, r3 = self.k1 * A, self.k2 * B, self.k3 * A
        return torch.stack((-r1 - r3, r1 - r2, r2 + r3), dim=-1)
