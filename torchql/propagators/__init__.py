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
coefficients and stable for stiff ``A``) and ``"radau"`` (the same module: Radau IIA collocation of
the whole transfer, for every stiffness; what ``solver="auto"`` takes for a stiff model).
"""

from __future__ import annotations

from ._base import LinearPropagator
from .exponential import ExponentialRadau, RadauCollocation
from .rk4 import RK4Doubling
from .taylor import TaylorSeries
from .torchdiffeq import Torchdiffeq

__all__ = ["LinearPropagator", "TaylorSeries", "RK4Doubling", "Torchdiffeq", "ExponentialRadau", "RadauCollocation",
           "PROPAGATORS", "DEFAULT_PROPAGATOR",
           "register_propagator", "linear_propagator"]

#: The registered propagators by name.
PROPAGATORS: dict[str, LinearPropagator] = {}
#: The name of the default propagator.
DEFAULT_PROPAGATOR = "taylor"


def register_propagator(propagator: LinearPropagator) -> LinearPropagator:
    """Register ``propagator`` under its ``name``, so that ``linear_solver=name`` selects it."""
    if not isinstance(propagator, LinearPropagator):
        raise TypeError(f"`propagator` must be a torchql.propagators.LinearPropagator; "
                        f"received {type(propagator).__name__}")
    if not isinstance(propagator.name, str) or not propagator.name:
        raise ValueError(f"a propagator needs a non-empty string `name`; received {propagator.name!r}")
    PROPAGATORS[propagator.name] = propagator
    return propagator


def linear_propagator(value: "str | LinearPropagator", arg: str = "linear_solver") -> LinearPropagator:
    """The propagator that ``value`` names, or ``value`` itself when it is one.

    Raises ``ValueError`` listing the registered names for an unknown name, ``TypeError`` for
    anything that is neither a name nor a :class:`LinearPropagator`.
    """
    if isinstance(value, LinearPropagator):
        return value
    if isinstance(value, str):
        if value not in PROPAGATORS:
            raise ValueError(f"`{arg}` must be one of {tuple(PROPAGATORS)} or a torchql.propagators.LinearPropagator; "
                             f"received {value!r}")
        return PROPAGATORS[value]
    raise TypeError(f"`{arg}` must be a string, one of {tuple(PROPAGATORS)}, or a "
                    f"torchql.propagators.LinearPropagator; received {type(value).__name__}")


for _propagator in (TaylorSeries(), RK4Doubling(), Torchdiffeq(), ExponentialRadau(), RadauCollocation()):
    register_propagator(_propagator)
