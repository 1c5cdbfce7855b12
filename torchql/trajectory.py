"""The stored iterate trajectory ``z_n(t)`` on a time grid, and the quasilinear system about it.

The Kantorovich iteration linearizes about the previous iterate, which exists only as values
on a grid. Between two grid nodes it is represented by the cubic Hermite polynomial through
the node values and node slopes (fourth-order accurate, continuously differentiable). The
same interpolation gives ``f(z_n(t))`` from the node values ``f_j`` and their time
derivatives ``A_j z_n'(t_j) + df/dt``, so the quasilinear right-hand side is known everywhere
without calling the model again: one vmapped Jacobian evaluation over the grid per iteration.

Inside one grid interval every coefficient is a polynomial in time, so the interval's
transfer (its propagator ``Phi_j`` and forced response ``c_j``) is a smooth problem that a few
fixed Runge–Kutta steps (:mod:`torchql.transfer`) or any torchdiffeq solver integrate, for all
intervals at once.
"""

from __future__ import annotations

import torch

from .splines import hermite_basis

__all__ = ["LinearizedReference", "IntervalSystem", "hermite_basis", "model_defect"]

#: A superposed trajectory whose :func:`model_defect` exceeds this is too far from solving the
#: model for its linear problem's sum of squares to judge a step by (see ``fit``'s damping).
DEFECT_TRUST = 0.1


def model_defect(f: torch.Tensor, z_dot: torch.Tensor, n: int) -> torch.Tensor:
    """How far a trajectory is from solving the model, relative to its own slopes.

    ``max_{j, i} |f_i(z(t_j)) - z_i'(t_j)| / max_j |z_i'(t_j)|`` over the nodes ``j`` and the
    ``n`` states ``i``, for node values of the model's right-hand side ``f (..., G, M)`` and the
    trajectory's slopes ``z_dot (..., G, M)``: shape ``(...)``. Zero for a solution of the model;
    for a Kantorovich step it shrinks quadratically with the step, so it tells a step near the
    optimum, whose linear sum of squares predicts the model's, from one far away.
    """
    slopes = z_dot[..., :n]
    scale = slopes.abs().amax(dim=-2, keepdim=True)
    scale = torch.where(scale > 0, scale, torch.ones_like(scale))
    return ((f[..., :n] - slopes).abs() / scale).amax(dim=(-2, -1))


class LinearizedReference:
    """The reference trajectory on its grid with the linearization at every node.

    ``w' = A(t) w + B(t)`` with ``A(t) = df/dz(z_n(t))`` and ``B(t) = f(z_n(t)) - A(t) z_n(t)``,
    where ``z_n``, ``f(z_n)`` and ``A`` are cubic Hermite interpolants of their node values and
    node time derivatives.

    Parameters
    ----------
    t : Tensor ``(G,)``
        Grid times.
    z : Tensor ``(G, M)``
        Reference values ``z_n(t_j)``.
    z_dot : Tensor ``(G, M)``
        Reference slopes ``z_n'(t_j)``.
    lin : Linearization
        ``f``, ``A`` and their time derivatives at the nodes, along ``z_dot``
        (see :func:`torchql.linearize.linearize`).
    """

    def __init__(self, t, z, z_dot, lin) -> None:
        self.t = t
        self.z = z
        self.z_dot = z_dot
        self.f = lin.f
        self.jac = lin.jac
        self.f_dot = lin.f_dot
        self.jac_dot = lin.jac_dot
        self.jac_ddot = getattr(lin, "jac_ddot", None)  # a SecondLinearization's


class IntervalSystem:
    """All grid intervals' transfer problems as one system in the local time ``s`` in ``[0, 1]``.

    State ``Y (G-1, M, M+1) = [Phi | c]`` with ``Phi(0) = I``, ``c(0) = 0`` and
    ``dY/ds = h_j (A_j(s) Y + [0 | B_j(s)])``: at ``s = 1``, ``w(t_{j+1}) = Phi_j w(t_j) + c_j``
    for the particular solution and ``Phi_j`` alone for the homogeneous ones.
    """

    def __init__(self, ref: LinearizedReference) -> None:
        self.reference = ref
        self.t_start = ref.t[:-1]
        self.h = ref.t[1:] - ref.t[:-1]
        hv = self.h.unsqueeze(-1)
        hm = self.h.reshape(-1, 1, 1)
        self.z0, self.z1 = ref.z[:-1], ref.z[1:]
        self.zd0, self.zd1 = ref.z_dot[:-1] * hv, ref.z_dot[1:] * hv
        self.f0, self.f1 = ref.f[:-1], ref.f[1:]
        self.fd0, self.fd1 = ref.f_dot[:-1] * hv, ref.f_dot[1:] * hv
        self.J0, self.J1 = ref.jac[:-1], ref.jac[1:]
        self.Jd0, self.Jd1 = ref.jac_dot[:-1] * hm, ref.jac_dot[1:] * hm
        self.n_evals = 0

    def initial(self) -> torch.Tensor:
        """``[I | 0]`` for every interval: shape ``(G-1, M, M+1)``."""
        G1, M = self.z0.shape
        eye = torch.eye(M, M + 1, dtype=self.z0.dtype, device=self.z0.device)
        return eye.expand(G1, M, M + 1).clone()

    def __call__(self, s: torch.Tensor, Y: torch.Tensor) -> torch.Tensor:
        self.n_evals += 1
        b00, b10, b01, b11 = hermite_basis(s)
        z = b00 * self.z0 + b10 * self.zd0 + b01 * self.z1 + b11 * self.zd1
        f = b00 * self.f0 + b10 * self.fd0 + b01 * self.f1 + b11 * self.fd1
        A = b00 * self.J0 + b10 * self.Jd0 + b01 * self.J1 + b11 * self.Jd1
        dY = A @ Y
        forcing = f - (A @ z.unsqueeze(-1)).squeeze(-1)
        dY[:, :, -1] += forcing
        return dY * self.h.reshape(-1, 1, 1)
