"""Implicit (stiff-stable) ODE solvers in torch, batched over independent samples.

* :func:`rodas5p_batch`: Rodas5P, an L-stable, stiffly accurate Rosenbrock method of order
  5(4) with an order-4 dense output, for ``S`` samples ``(S, M)`` at once, each with its own
  time, step size and accept/reject decision (the stiff counterpart of
  :func:`torchql.batch_integrate.dopri_batch`); failures reported per sample.
* :func:`rodas5p_solve`: one trajectory of any state shape, forward or backward in time; this
  is ``solver="rodas5p"`` of :func:`torchql.integrate.solve` and :func:`torchql.simulate`.

Why Rodas5P (and not Radau IIA): see :mod:`torchql.solvers.rosenbrock`.
"""

from .field import BatchedField, JacobianError
from .rosenbrock import (MAX_STEPS, NON_FINITE, STEP_UNDERFLOW, STOPPED, SUCCESS, RosenbrockSolution,
                         rodas5p_batch)
from .single import MAX_COMPONENTS, rodas5p_solve

#: Names of the implicit solvers, as ``solver=`` takes them.
STIFF_SOLVERS: tuple[str, ...] = ("rodas5p",)

__all__ = ["rodas5p_batch", "rodas5p_solve", "RosenbrockSolution", "BatchedField", "JacobianError",
           "STIFF_SOLVERS", "MAX_COMPONENTS", "SUCCESS", "NON_FINITE", "STEP_UNDERFLOW", "MAX_STEPS", "STOPPED"]
