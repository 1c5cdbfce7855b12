"""Ready-to-use models: the thesis' oscillators and coasting car."""

from .car import AIR_DENSITY, GRAVITY, CoastingCar
from .oscillators import HarmonicOscillator, LinearOscillator, NonlinearOscillator

__all__ = ["HarmonicOscillator", "LinearOscillator", "NonlinearOscillator", "CoastingCar", "AIR_DENSITY", "GRAVITY"]
