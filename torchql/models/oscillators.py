"""The oscillators of the thesis: eq. 3.23 and eqs. 4.1/4.2."""

from __future__ import annotations

import torch

from ..model import ODEModel

__all__ = ["HarmonicOscillator", "LinearOscillator", "NonlinearOscillator"]


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
