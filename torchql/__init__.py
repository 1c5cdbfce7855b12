"""torchql: system identification by quasilinearization, in PyTorch."""

from . import baselines, damping, models, propagators, schemes
from .batch import fit_many
from .batch_result import BatchFitError, BatchFitResult
from .fit import METHODS, fit
from .compare import Comparison, compare
from .inputs import Inputs
from .parameters import Parameter
from .integrate import SOLVER_NAMES, IntegrationError, simulate
from .model import ODEModel
from .multistart import MultiStartResult, multistart
from .newton import NewtonResult, newton_raphson
from .observations import Observations
from .options import FitOptions
from .profile import ProfileResult, profile
from .ray_backend import fit_many_ray  # imports Ray only when called (the extra torchql[ray])
from .result import FitError, FitResult, IterationRecord, Status
from .superposition import LINEAR_SOLVERS

__version__ = "0.1.0"

__all__ = [
    "ODEModel",
    "Observations",
    "Inputs",
    "Parameter",
    "compare",
    "Comparison",
    "fit",
    "FitOptions",
    "fit_many",
    "fit_many_ray",
    "BatchFitResult",
    "profile",
    "multistart",
    "MultiStartResult",
    "ProfileResult",
    "FitResult",
    "FitError",
    "BatchFitError",
    "IterationRecord",
    "Status",
    "METHODS",
    "SOLVER_NAMES",
    "LINEAR_SOLVERS",
    "IntegrationError",
    "simulate",
    "newton_raphson",
    "NewtonResult",
    "models",
    "baselines",
    "propagators",
    "damping",
    "schemes",
]
