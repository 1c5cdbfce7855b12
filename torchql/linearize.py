"""Linearization of the augmented right-hand side: ``A_n = df/dz`` and ``B_n = f - A_n z_n``.

Every Jacobian is taken with :func:`torch.func.jacrev`; over a grid of times it is one
:func:`torch.func.vmap` call, so a whole iteration's linearization costs a single batched
evaluation of the model.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch.func import jacrev, vmap

from .model import AugmentedSystem

__all__ = ["Linearization", "linearize"]


class Linearization(NamedTuple):
    """The augmented right-hand side and its derivatives at a set of points.

    Attributes
    ----------
    f : Tensor ``(G, M)``
        ``f(t_j, z_j)``.
    jac : Tensor ``(G, M, M)``
        ``A_j = df/dz (t_j, z_j)``.
    f_t : Tensor ``(G, M)``
        ``df/dt (t_j, z_j)`` (zero for autonomous models).
    """

    f: torch.Tensor
    jac: torch.Tensor
    f_t: torch.Tensor


def _with_aux(system: AugmentedSystem):
    def g(t, z):
        out = system.f(t, z)
        return out, out

    return g


def linearize(system: AugmentedSystem, t: torch.Tensor, z: torch.Tensor) -> Linearization:
    """Linearize ``f`` at points ``(t_j, z_j)``.

    Parameters
    ----------
    system : AugmentedSystem
    t : Tensor ``(G,)``
        Times.
    z : Tensor ``(G, M)``
        Augmented states.

    Returns
    -------
    Linearization
        ``f``, ``df/dz`` and ``df/dt`` at every point, from one vmapped ``jacrev`` call.
    """
    (f_t, jac), f = vmap(jacrev(_with_aux(system), argnums=(0, 1), has_aux=True))(t, z)
    return Linearization(f=f, jac=jac, f_t=f_t)
