"""Particular and homogeneous solutions, integrated together as one torchdiffeq system.

The state integrated is ``W (M, 1 + m)``: column 0 is the particular solution, columns
``1..m`` the homogeneous solutions started from unit vectors on the ``m`` unknown components of
``z(t0)`` (known initial states get none). With unit initial vectors the superposition
coefficients ``alpha`` are directly the corrections of the unknowns, and ``alpha -> 0`` signals
convergence.

Both methods propagate ``W' = A_n(t) W + [B_n(t), 0]`` about a reference trajectory stored on
a grid: for Kantorovich the previous superposed solution, for shooting the nonlinear solution
from the current initial estimate (the homogeneous columns are then its variational
equations, the sensitivities of the trajectory to the unknowns).
"""

from __future__ import annotations

import torch

from .integrate import solve
from .trajectory import IntervalSystem, LinearizedReference

__all__ = ["initial_columns", "propagate_linear"]


def initial_columns(z0: torch.Tensor, unknown_index: torch.Tensor) -> torch.Tensor:
    """``W(t0) = [z0, e_{i_1}, ..., e_{i_m}]``: shape ``(M, 1 + m)``."""
    M = z0.shape[0]
    E = torch.zeros(M, unknown_index.numel(), dtype=z0.dtype, device=z0.device)
    E[unknown_index, torch.arange(unknown_index.numel(), device=z0.device)] = 1.0
    return torch.cat([z0.unsqueeze(-1), E], dim=1)


def propagate_linear(reference: LinearizedReference, w0: torch.Tensor, *, solver: str, rtol: float,
                     atol: float, max_steps: int | None = None) -> tuple[torch.Tensor, int]:
    """Integrate the quasilinear system over the reference's grid.

    Every interval's transfer ``(Phi_j, c_j)`` is integrated at once by one torchdiffeq call
    (local time ``s`` in ``[0, 1]``; max-norm error control so no interval dilutes another's
    error; tolerances divided by the square root of the number of intervals, for the
    accumulation of local errors; first step the whole interval, since the intervals are
    short against the dynamics); the transfers are then composed node by node.

    Returns
    -------
    W : Tensor ``(G, M, 1 + m)``
        Particular (column 0) and homogeneous solutions at every grid node.
    n_evals : int
        Evaluations of the batched interval system.
    """
    G = reference.t.shape[0]
    if G == 1:
        return w0.unsqueeze(0), 0
    system = IntervalSystem(reference)
    intervals = G - 1
    tiny = 10 * torch.finfo(w0.dtype).eps
    s = torch.tensor([0.0, 1.0], dtype=w0.dtype, device=w0.device)
    Y = solve(system, system.initial(), s, solver=solver, rtol=max(rtol / intervals**0.5, tiny),
              atol=max(atol / intervals**0.5, tiny), max_steps=max_steps, norm=_max_norm, first_step=1.0)[-1]
    M = w0.shape[0]
    Phi, c = Y[:, :, :M], Y[:, :, M]
    out = [w0]
    w = w0
    for j in range(intervals):
        w = Phi[j] @ w
        w[:, 0] += c[j]
        out.append(w)
    return torch.stack(out), system.n_evals


def _max_norm(x: torch.Tensor) -> torch.Tensor:
    return x.abs().max()
