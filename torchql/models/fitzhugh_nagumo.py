"""The FitzHugh–Nagumo model of a spiking neuron (Ramsay, Hooker, Campbell and Cao 2007)."""

from __future__ import annotations

import torch

from ..model import ODEModel

__all__ = ["FitzHughNagumo"]


class FitzHughNagumo(ODEModel):
    """``V' = c (V - V^3/3 + R)``, ``R' = -(V - a + b R) / c``.

    States ``(V, R)``: the membrane voltage and the recovery variable (dimensionless). Coefficients
    ``a``, ``b`` (dimensionless) and ``c`` (the time-scale ratio); the defaults ``a = b = 0.2``,
    ``c = 3`` are the benchmark of J. O. Ramsay, G. Hooker, D. Campbell and J. Cao, "Parameter
    estimation for differential equations: a generalized smoothing approach", J. R. Statist.
    Soc. B 69 (2007), usually started from ``(V, R) = (-1, 1)`` and observed over ``0 <= t <= 20``.
    """

    state_names = ("V", "R")

    def __init__(self, a: float = 0.2, b: float = 0.2, c: float = 3.0) -> None:
        super().__init__()
        for name, value in (("a", a), ("b", b), ("c", c)):
            self.register_buffer(name, torch.tensor(float(value), dtype=torch.float64))

    def forward(self, t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        V, R = x.unbind(-1)
        return torch.stack((self.c * (V - V**3 / 3 + R), -(V - self.a + self.b * R) / self.c), dim=-1)
