"""What is written by hand for each PEtab problem: its model, initial state, observables and noise.

A :class:`ProblemSpec` holds the parts of a PEtab problem that are formulas: the right-hand side (an
:class:`torchql.ODEModel` class), the initial state as a function of the model symbols, and for every
observable the observation function and the noise (standard deviation) function. The tables (conditions,
parameters, measurements) are read from the problem's JSON by :mod:`.problem`.

Conventions of the formula functions (all tensors float64):

* ``states``: a mapping ``state name -> Tensor (R,)``, the simulated states at the ``R`` measurement rows
  of one condition and one observable;
* ``symbols``: a mapping ``name -> Tensor ()``, the values of the model symbols in that condition and of
  every PEtab parameter (linear scale);
* ``placeholders``: a tuple of ``Tensor (R,)``, the row-wise values of ``observableParameter{i}`` (for an
  observable function) or ``noiseParameter{i}`` (for a noise function), ``i = 1, 2, ...``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import torch

import torchql

__all__ = ["ProblemSpec", "RowFunction", "InitialState"]

#: ``(states, symbols, placeholders) -> Tensor (R,)``: an observable or a noise formula.
RowFunction = Callable[[Mapping[str, torch.Tensor], Mapping[str, torch.Tensor], Sequence[torch.Tensor]], torch.Tensor]
#: ``symbols -> Tensor (n_states,)``: the initial state at ``t = 0``.
InitialState = Callable[[Mapping[str, torch.Tensor]], torch.Tensor]


@dataclass(frozen=True)
class ProblemSpec:
    """The hand-written formulas of one PEtab problem and the integrator settings it needs.

    Attributes
    ----------
    name : str
        The PEtab problem's name, which is also its JSON file's stem.
    model : type of torchql.ODEModel
        The right-hand side. Its constructor takes every model symbol that the right-hand side uses,
        by name, and registers each as a float64 buffer of that name.
    initial_state : InitialState
        ``x(0)`` from the model symbols of a condition.
    observables, noise : dict of str to RowFunction
        Per observable id: the observation formula ``y`` and the noise formula ``sigma``.
    unused_symbols : tuple of str
        Model symbols of the SBML model that no formula uses (compartments of size 1 holding every
        species: their volume cancels).
    solver, rtol, atol
        Settings of :func:`torchql.simulate` that reproduce the reference likelihood to well within
        1e-3 (measured in ``tests/experiments/test_petab.py``).
    """

    name: str
    model: type[torchql.ODEModel]
    initial_state: InitialState
    observables: dict[str, RowFunction]
    noise: dict[str, RowFunction]
    unused_symbols: tuple[str, ...] = ()
    solver: str = "dopri5"
    rtol: float = 1e-8
    atol: float = 1e-10
