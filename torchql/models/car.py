"""The coasting automobile of the thesis (eq. 4.6), in US customary units."""

from __future__ import annotations

import torch

from ..model import ODEModel

__all__ = ["CoastingCar", "AIR_DENSITY", "GRAVITY"]

#: Air density assumed by the thesis, slug/ft^3.
AIR_DENSITY = 0.00238
#: Acceleration of gravity, ft/s^2.
GRAVITY = 32.2


class CoastingCar(ODEModel):
    """``v' = -rho A_f C_D v^2 / (2 M) - mu g``: a car coasting on level ground.

    State ``v`` (ft/s). Unknown by default: ``C_D`` (aerodynamic drag coefficient, -) and
    ``mu`` (rolling friction coefficient, -). Fixed constants: ``frontal_area`` (ft^2),
    ``mass`` (slug), ``rho`` (slug/ft^3) and ``g`` (ft/s^2).
    """

    state_names = ("v",)
    constants = ("frontal_area", "mass", "rho", "g")

    def __init__(self, frontal_area: float, mass: float, C_D: float = 0.4, mu: float = 0.02,
                 rho: float = AIR_DENSITY, g: float = GRAVITY) -> None:
        super().__init__()
        for name, value in (("C_D", C_D), ("mu", mu), ("frontal_area", frontal_area), ("mass", mass),
                            ("rho", rho), ("g", g)):
            self.register_buffer(name, torch.tensor(float(value), dtype=torch.float64))

    def forward(self, t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        drag = 0.5 * self.rho * self.frontal_area * self.C_D / self.mass
        return -drag * x**2 - self.mu * self.g
