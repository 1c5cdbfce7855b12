"""The oscillators of the thesis (eq. 3.23 and eqs. 4.1/4.2), and a forced one with a measured input."""

from __future__ import annotations

import torch

from ..model import ODEModel

__all__ = ["HarmonicOscillator", "LinearOscillator", "NonlinearOscillator", "DrivenOscillator"]


def _scalar(value: float) -> torch.Tensor:
    return torch.tensor(float(value), dtype=torch.float64)


class HarmonicOscillator(ODEModel):
    """``x'' + xi x = 0`` (thesis eq. 3.23): states ``(x, u = x')``, coefficient ``xi`` (1/s^2)."""

    state_names = ("x", "u")

    def __init__(self, xi: float = 1.0) -> None:
        super().__init__()
        self.register_buffer("xi", _scalar(xi))

    def forward(self, t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        pos, vel = x.unbind(-1)
        return torch.stack((vel, -self.xi * pos), dim=-1)


class LinearOscillator(ODEModel):
    """``y'' + A y' + B y = 0`` (thesis eq. 4.2): states ``(y, v = y')``; ``A`` (1/s), ``B`` (1/s^2)."""

    state_names = ("y", "v")

    def __init__(self, A: float = 0.1, B: float = 3.0) -> None:
        super().__init__()
        self.register_buffer("A", _scalar(A))
        self.register_buffer("B", _scalar(B))

    def forward(self, t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        y, v = x.unbind(-1)
        return torch.stack((v, -self.A * v - self.B * y), dim=-1)


class NonlinearOscillator(ODEModel):
    """``y'' + A y' + B y + C y'^3 + D y^3 = 0`` (thesis eq. 4.1): states ``(y, v = y')``."""

    state_names = ("y", "v")

    def __init__(self, A: float = 0.1, B: float = 3.0, C: float = 0.2, D: float = 4.0) -> None:
        super().__init__()
        for name, value in (("A", A), ("B", B), ("C", C), ("D", D)):
            self.register_buffer(name, _scalar(value))

    def forward(self, t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        y, v = x.unbind(-1)
        return torch.stack((v, -self.A * v - self.B * y - self.C * v**3 - self.D * y**3), dim=-1)


class DrivenOscillator(ODEModel):
    """``y'' + c y' + k y = u(t)``, a mass-spring-damper per unit mass driven by a measured force.

    States ``(y, v = y')``; coefficients ``c`` (1/s) and ``k`` (1/s^2); input ``u`` (force per
    unit mass, the unit of ``y`` per s^2), given with the data as a :class:`torchql.Inputs`.
    """

    state_names = ("y", "v")
    input_names = ("u",)

    def __init__(self, c: float = 0.5, k: float = 2.0) -> None:
        super().__init__()
        self.register_buffer("c", _scalar(c))
        self.register_buffer("k", _scalar(k))

    def forward(self, t: torch.Tensor, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        y, v = x.unbind(-1)
        return torch.stack((v, u[..., 0] - self.c * v - self.k * y), dim=-1)
