"""A stiff model's solution and its sensitivities together, by Rodas5P on the variational system.

The shooting scheme, and every scheme's final pass, need the model's solution ``x(t)`` from the
estimates and its derivatives with respect to the unknowns: the homogeneous columns ``V(t)`` of
the model linearized about that solution, ``V' = A(t) V`` with ``A = df/dz`` of the augmented
state ``z = (x, p)``. On a grid, as the non-stiff propagators take them, a stiff ``A`` needs many
implicit substeps per interval (the intervals are placed before the solution is known, so most of
them sit where the solution is smooth but the stiffness is not). Integrated with ``x`` by the
adaptive implicit solver instead, the columns take the steps that ``x`` takes: the forward
sensitivity method of CVODES and AMICI.

The joint state of one sample is ``y = (x, Vx, p, Vp)``: the states ``(n,)``, their
sensitivities ``(n, m)`` row-major, the unknown coefficients ``(P,)`` and their (constant) rows
of the columns ``(P, m)``. Its right-hand side is ``(f, A V, 0, 0)``. Rodas5P keeps its order only
with the exact Jacobian of the joint system; it is block lower triangular::

    [[A_x,        0,          A_p,        0         ],
     [d(A V)/dx,  A_x (x) I,  d(A V)/dp,  A_p (x) I ],
     [0 ...                                         ]]

and is assembled from ``A`` and the second derivatives ``dA/dz`` (one reverse-over-reverse
pass), never by differentiating the joint function as a whole. The local error is controlled on
``x`` and on the columns, each column scaled by its unknown's magnitude (CVODES' ``pbar``), so a
column is as accurate relative to the effect of its unknown as the states are.
"""

from __future__ import annotations

import torch
from torch.func import jacrev

from .field import BatchedField

__all__ = ["SensitivityField", "joint_state", "split_joint"]


class SensitivityField(BatchedField):
    """The joint right-hand side ``(f, A V, 0, 0)`` of an augmented system and its exact Jacobian.

    Parameters
    ----------
    system : AugmentedSystem
        The model with its unknown coefficients as trailing state components (``n`` states, ``P``
        coefficients, ``rhs(t, x, p)``).
    m : int
        Number of sensitivity columns.
    vectorize : bool
        As :class:`~torchql.solvers.field.BatchedField`: map samples by ``torch.vmap`` with
        ``torch.func`` derivatives (any ``S``); ``False``: one sample, differentiated by
        ``torch.autograd`` with batched cotangents, which costs about half of ``torch.func``'s
        transforms per call (they dominate a small model's step).
    """

    def __init__(self, system, m: int, vectorize: bool = True) -> None:
        self.n_f = 0
        self.n_jac = 0
        layout = _Layout(system.n, system.P, m)
        if vectorize:
            value, derivatives = _transformed(system, layout)
            self._f, self._derivatives = torch.vmap(value), torch.vmap(derivatives)
        else:
            self._f, self._derivatives = _differentiated(system, layout)


class _Layout:
    """Where the parts of one sample's joint state ``(x, Vx, p, Vp)`` lie."""

    def __init__(self, n: int, P: int, m: int) -> None:
        self.n, self.P, self.m = n, P, m
        self.width = n + n * m + P + P * m

    def split(self, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``z (M,)`` and the columns ``V (M, m)`` of a joint state ``y (D,)``."""
        return split_joint(y, self.n, self.n + self.P, self.m)

    def joint(self, f: torch.Tensor, AV: torch.Tensor) -> torch.Tensor:
        """The joint vector ``(f, A V, 0, 0)`` from ``f (n,)`` and ``A V`` (``n m`` values)."""
        zeros = torch.zeros(self.P + self.P * self.m, dtype=f.dtype, device=f.device)
        return torch.cat([f, AV.reshape(-1), zeros])

    def jacobian(self, A: torch.Tensor, AV_z: torch.Tensor) -> torch.Tensor:
        """The joint Jacobian ``(D, D)`` from ``A (n, M)`` and ``d(A V)/dz (n m, M)`` (rows ``(i, k)``)."""
        n, P, m = self.n, self.P, self.m
        eye = torch.eye(m, dtype=A.dtype, device=A.device)
        A_x, A_p = A[:, :n], A[:, n:]
        coefficients = slice(n + n * m, n + n * m + P)
        J = A.new_zeros(self.width, self.width)
        J[:n, :n], J[:n, coefficients] = A_x, A_p
        rows = slice(n, n + n * m)
        J[rows, :n], J[rows, coefficients] = AV_z[:, :n], AV_z[:, n:]
        J[rows, n:n + n * m] = (A_x[:, None, :, None] * eye[None, :, None, :]).reshape(n * m, n * m)
        J[rows, n + n * m + P:] = (A_p[:, None, :, None] * eye[None, :, None, :]).reshape(n * m, P * m)
        return J


def _transformed(system, layout: _Layout):
    """One sample's ``value(t, y)`` and ``derivatives(t, y) -> ((ft, J), value)`` by ``torch.func``
    (reverse over reverse for the second derivatives), for ``torch.vmap``."""
    n = system.n

    def g(t, z):
        value = system.rhs(t, z[:n], z[n:])
        return value, value

    jacobian = jacrev(g, argnums=1, has_aux=True)  # (A (n, M), f (n,))

    def inner(t, z):
        A, value = jacobian(t, z)
        return (A, value), (A, value)

    second = jacrev(inner, argnums=(0, 1), has_aux=True)  # d(A, f)/d(t, z)

    def value(t, y):
        z, V = layout.split(y)
        A, f = jacobian(t, z)
        return layout.joint(f, A @ V)

    def derivatives(t, y):
        z, V = layout.split(y)
        ((A_t, A_z), (f_t, _)), (A, f) = second(t, z)
        J = layout.jacobian(A, torch.einsum("ijl,jk->ikl", A_z, V).reshape(n * layout.m, -1))
        return (layout.joint(f_t, A_t @ V), J), layout.joint(f, A @ V)

    return value, derivatives


def _differentiated(system, layout: _Layout):
    """One sample's ``f(t (1,), y (1, D))`` and ``derivatives`` as :class:`BatchedField` calls
    them, by ``torch.autograd`` with batched cotangents."""
    n, m = system.n, layout.m

    def tracked(t, y):
        z, V = layout.split(y)
        t, z = t.detach().requires_grad_(True), z.detach().requires_grad_(True)
        return t, z, V, system.rhs(t, z[:n], z[n:])

    def value(t, y):
        with torch.enable_grad():
            _, z, V, f = tracked(t[0], y[0])
            (A,) = _grad(f, (z,))
        return layout.joint(f.detach(), A @ V).unsqueeze(0)

    def derivatives(t, y):
        with torch.enable_grad():
            t, z, V, f = tracked(t[0], y[0])
            f_t, A = _grad(f, (t, z), create_graph=True)
            AV = (A @ V).reshape(-1)
            if AV.requires_grad:
                AV_t, AV_z = _grad(AV, (t, z))
            else:  # a model linear in z: no second derivatives
                AV_t, AV_z = torch.zeros_like(AV), AV.new_zeros(n * m, z.shape[0])
        J = layout.jacobian(A.detach(), AV_z)
        ft, value = layout.joint(f_t.detach(), AV_t), layout.joint(f.detach(), AV.detach())
        return (ft.unsqueeze(0), J.unsqueeze(0)), value.unsqueeze(0)

    return value, derivatives


def _grad(outputs: torch.Tensor, inputs: tuple, create_graph: bool = False) -> tuple:
    """The Jacobians ``(k, *x.shape)`` of the ``k`` ``outputs`` with respect to each of ``inputs``."""
    eye = torch.eye(outputs.shape[0], dtype=outputs.dtype, device=outputs.device)
    grads = torch.autograd.grad(outputs, inputs, eye, is_grads_batched=True, create_graph=create_graph,
                                allow_unused=True, materialize_grads=True)
    # an input the outputs do not use gets one unbatched zero: one per output
    return tuple(g if g.dim() > x.dim() else g.expand(outputs.shape[0], *x.shape) for g, x in zip(grads, inputs))


def joint_state(z0: torch.Tensor, columns: torch.Tensor, n: int) -> torch.Tensor:
    """The joint initial states ``(S, D)`` from ``z0 (S, M)`` and the columns ``(S, M, m)``."""
    S, M, m = columns.shape
    return torch.cat([z0[:, :n], columns[:, :n].reshape(S, n * m), z0[:, n:], columns[:, n:].reshape(S, (M - n) * m)],
                     dim=1)


def split_joint(y: torch.Tensor, n: int, M: int, m: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(z (..., M), V (..., M, m))`` from joint states ``y (..., D)``."""
    P = M - n
    x, Vx = y[..., :n], y[..., n:n + n * m].unflatten(-1, (n, m))
    p, Vp = y[..., n + n * m:n + n * m + P], y[..., n + n * m + P:].unflatten(-1, (P, m))
    return torch.cat([x, p], dim=-1), torch.cat([Vx, Vp], dim=-2)
