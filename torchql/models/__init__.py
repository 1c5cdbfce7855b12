"""Ready-to-use models: the thesis' oscillators and coasting car, a driven oscillator (a measured
input), FitzHugh–Nagumo, A -> B -> C kinetics, and stiff ones (Robertson, van der Pol, HIRES, enzyme
kinetics, which ``solver="auto"`` integrates by Rodas5P)."""

from .car import AIR_DENSITY, GRAVITY, CoastingCar
from .fitzhugh_nagumo import FitzHughNagumo
from .oscillators import DrivenOscillator, HarmonicOscillator, LinearOscillator, NonlinearOscillator
from .reactions import BranchedReactions, FirstOrderReactions
from .stiff import HIRES, MichaelisMentenEnzyme, Robertson, VanDerPol

__all__ = [
    "HarmonicOscillator", "LinearOscillator", "NonlinearOscillator", "DrivenOscillator", "CoastingCar", "AIR_DENSITY", "GRAVITY",
    "FitzHughNagumo", "FirstOrderReactions", "BranchedReactions", "Robertson", "VanDerPol", "HIRES",
    "MichaelisMentenEnzyme",
]
