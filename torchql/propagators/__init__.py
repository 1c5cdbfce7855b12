"""Linear propagators: how the quasilinear system's interval transfers are integrated.

A propagator turns the :class:`~torchql.trajectory.IntervalSystem` of a reference (every grid
interval's ``W' = A(t) W + [B(t), 0]`` in local time ``s`` in ``[0, 1]``) into the intervals'
transfers ``T_j`` (:class:`~torchql.transfer.Transfers`), each within the per-interval tolerance;
:func:`torchql.superposition.propagate_linear` composes them over the grid. ``fit``'s
``linear_solver=`` takes a registered name or a :class:`LinearPropagator` object; adding one is
one module here with a subclass, registered by :func:`register_propagator`.

Registered: ``"taylor"`` (default, :mod:`.taylor`), ``"rk4_doubling"`` (:mod:`.rk4`),
``"torchdiffeq"`` (:mod:`.torchdiffeq`), ``"exponential"`` (:mod:`.exponential`: the matrix
exponential of frozen coefficients corrected by Radau IIA collocation, exact for constant
coefficients and stable for stiff ``A``), ``"radau"`` (the same module: Radau IIA collocation of
the whole transfer, for every stiffness; what ``solver="auto"`` takes for a stiff model),
``"rodas5p"`` (the same module: ``"radau"``, but where the reference is the model's own solution
its sensitivities are integrated with it by Rodas5P, on its adaptive steps) and ``"taylor_quintic"``
(:mod:`.quintic`: ``"taylor"``'s series over quintic interpolants of the reference and ``h f``).
"""

from __future__ import annotations

from ..registry import Registry
from ._base import LinearPropagator
from .exponential import ExponentialRadau, RadauCollocation, SensitivityRodas
from .quintic import TaylorQuintic
from .rk4 import RK4Doubling
from .taylor import TaylorSeries
from .torchdiffeq import Torchdiffeq

__all__ = ["LinearPropagator", "TaylorSeries", "TaylorQuintic", "RK4Doubling", "Torchdiffeq", "ExponentialRadau", "RadauCollocation",
           "SensitivityRodas",
           "PROPAGATORS", "DEFAULT_PROPAGATOR",
           "register_propagator", "linear_propagator"]

_REGISTRY = Registry(LinearPropagator, "torchql.propagators.LinearPropagator", "`propagator`")
#: The registered propagators by name.
PROPAGATORS: dict[str, LinearPropagator] = _REGISTRY.entries
#: The name of the default propagator.
DEFAULT_PROPAGATOR = "taylor"


def register_propagator(propagator: LinearPropagator) -> LinearPropagator:
    """Register ``propagator`` under its ``name``, so that ``linear_solver=name`` selects it."""
    if isinstance(propagator, LinearPropagator) and (not isinstance(propagator.name, str) or not propagator.name):
        raise ValueError(f"a propagator needs a non-empty string `name`; received {propagator.name!r}")
    return _REGISTRY.register(propagator)


def linear_propagator(value: "str | LinearPropagator", arg: str = "linear_solver") -> LinearPropagator:
    """The propagator that ``value`` names, or ``value`` itself when it is one.

    Raises ``ValueError`` listing the registered names for an unknown name, ``TypeError`` for
    anything that is neither a name nor a :class:`LinearPropagator`.
    """
    found = _REGISTRY.find(value)
    if found is not None:
        return found
    if isinstance(value, str):
        raise ValueError(f"`{arg}` must be one of {_REGISTRY.names} or a {_REGISTRY.public_name}; "
                         f"received {value!r}")
    raise TypeError(f"`{arg}` must be a string, one of {_REGISTRY.names}, or a {_REGISTRY.public_name}; "
                    f"received {type(value).__name__}")


for _propagator in (TaylorSeries(), RK4Doubling(), Torchdiffeq(), ExponentialRadau(), RadauCollocation(),
                    SensitivityRodas(), TaylorQuintic()):
    register_propagator(_propagator)
