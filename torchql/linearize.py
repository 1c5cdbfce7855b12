"""Linearization of the augmented right-hand side: ``A_n = df/dz`` and ``B_n = f - A_n z_n``.

Over a grid of times the linearization is one :func:`torch.func.vmap` call: a whole iteration's
linearization costs a single batched evaluation of the model's derivatives. The same call
carries a forward-mode tangent along the trajectory (:func:`torch.func.jvp`), which gives the
time derivatives of ``f`` and of ``A`` at the nodes for the cubic Hermite interpolation between
them. ``d/dt A`` is the Jacobian of that tangent ``f_t + A z'`` in ``z`` (``z'`` held fixed).

Two orders of differentiation give the same values (to rounding), at different costs:

* **reverse over forward** (:func:`torch.func.jacrev` of the tangent): torch runs each model
  operation as one kernel; the backward pass costs about ``2 M`` vector products per node.
  The faster on small grids: on 50 to 1,000 nodes of 3- to 6-component models it takes 0.4 to
  0.6 of the time of the other order.
* **forward over forward** (:func:`torch.func.jvp` of :func:`torch.func.jacfwd`): nested
  forward mode makes torch run each elementwise model operation through a Python reference
  implementation (about 0.1 ms each, whatever the grid size), but the arithmetic is ``M``
  forward passes per node. The faster on large grids (batches of samples): 0.31 to 0.35 of the
  time of the other order on ``10^5`` nodes.

:func:`linearize` takes reverse over forward while ``nodes * M**2`` is at most
:data:`REVERSE_WORK_LIMIT`, forward over forward above.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch.func import jacfwd, jacrev, jvp, vmap

from .model import AugmentedSystem

__all__ = ["Linearization", "linearize", "REVERSE_WORK_LIMIT"]

#: Largest ``nodes * M**2`` linearized in reverse over forward mode (see the module docstring).
#: Measured crossovers: 7e4 to 1.5e5 on 3- to 6-component nonlinear models, below 6.4e4 on a
#: 16-component linear one (few operations, so little Python-kernel overhead to save).
REVERSE_WORK_LIMIT = 16_384


class Linearization(NamedTuple):
    """The augmented right-hand side and its derivatives along a trajectory, at its nodes.

    Attributes
    ----------
    f : Tensor ``(G, M)``
        ``f(t_j, z_j)``.
    jac : Tensor ``(G, M, M)``
        ``A_j = df/dz (t_j, z_j)``.
    f_dot : Tensor ``(G, M)``
        ``d/dt f(t, z(t))`` at the nodes: ``A_j z'_j + df/dt``.
    jac_dot : Tensor ``(G, M, M)``
        ``d/dt A(t, z(t))`` at the nodes.
    """

    f: torch.Tensor
    jac: torch.Tensor
    f_dot: torch.Tensor
    jac_dot: torch.Tensor


def linearize(system: AugmentedSystem, t: torch.Tensor, z: torch.Tensor,
              z_dot: torch.Tensor | None = None, order: str | None = None) -> Linearization:
    """Linearize ``f`` along a trajectory given at nodes ``(t_j, z_j)`` with slopes ``z'_j``.

    Parameters
    ----------
    system : AugmentedSystem
    t : Tensor ``(G,)``
        Times.
    z : Tensor ``(G, M)``
        Augmented states.
    z_dot : Tensor ``(G, M)``, optional
        Slopes of the trajectory; default ``f(t_j, z_j)`` (a solution of the model).
    order : {"reverse", "forward"}, optional
        ``"reverse"`` (reverse over forward) or ``"forward"`` (forward over forward); default by
        :data:`REVERSE_WORK_LIMIT`, among ``system.linearization_orders``, the orders torch.func
        can take on the model as far as known: reverse mode (which :class:`~torchql.problem.Problem`
        checks) stands in where forward mode fails (a model's operation without a forward-mode
        derivative), and forward mode is not tried again. Both give the same values to rounding.

    Returns
    -------
    Linearization
    """
    if z_dot is None:
        z_dot = vmap(system.f)(t, z)

    if order is None:
        order = "reverse" if t.shape[0] * system.M**2 <= REVERSE_WORK_LIMIT else "forward"
        if order not in system.linearization_orders:
            order = "reverse"
        if order == "forward":
            try:
                return _linearize(order, system.f, t, z, z_dot)
            except Exception:  # noqa: BLE001 -- the model's forward does not take nested forward mode
                system.linearization_orders = ("reverse",)
                order = "reverse"
    return _linearize(order, system.f, t, z, z_dot)


def _linearize(order: str, f, t, z, z_dot) -> Linearization:
    """The linearization in ``order`` (``"reverse"`` or ``"forward"``), vmapped over the nodes."""
    if order == "reverse":
        value, jac, value_dot, jac_dot = vmap(_reverse_over_forward(f))(t, z, z_dot)
    else:
        (value, jac), (value_dot, jac_dot) = vmap(_forward_over_forward(f))(t, z, z_dot)
    return Linearization(f=value, jac=jac, f_dot=value_dot, jac_dot=jac_dot)


def _reverse_over_forward(f):
    """``(t, z, z') -> (f, A, f_t + A z', d/dt A)`` at one node: ``jacrev`` of the tangent."""

    def node(ti, zi, zdi):
        def value_and_tangent(zz):
            both = jvp(f, (ti, zz), (torch.ones_like(ti), zdi))
            return both, both

        (jac, jac_dot), (value, value_dot) = jacrev(value_and_tangent, has_aux=True)(zi)
        return value, jac, value_dot, jac_dot

    return node


def _forward_over_forward(f):
    """``(t, z, z') -> ((f, A), (f_t + A z', d/dt A))`` at one node: ``jvp`` of ``jacfwd``."""

    def value_and_jacobian(ti, zi):
        return f(ti, zi), jacfwd(f, argnums=1)(ti, zi)

    def node(ti, zi, zdi):
        return jvp(value_and_jacobian, (ti, zi), (torch.ones_like(ti), zdi))

    return node
