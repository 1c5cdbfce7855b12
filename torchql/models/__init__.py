"""Ready-to-use models: the thesis' oscillators and coasting car, FitzHugh–Nagumo, A -> B -> C kinetics."""

from .car import AIR_DENSITY, GRAVITY, CoastingCar
from .fitzhugh_nagumo import FitzHughNagumo
from .oscillators import HarmonicOscillator, LinearOscillator, NonlinearOscillator
from .reactions import BranchedReactions, FirstOrderReactions

__all__ = [
    "HarmonicOscillator", "LinearOscillator", "NonlinearOscillator", "CoastingCar", "AIR_DENSITY", "GRAVITY",
    "FitzHughNagumo", "FirstOrderReactions", "BranchedReactions",
]
