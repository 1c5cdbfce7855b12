"""A stiff model's solution and its sensitivities: Rodas5P's own steps, differentiated.

The shooting scheme, and every scheme's final pass, need the model's solution ``x(t)`` from the
estimates and its derivatives with respect to the unknowns: the homogeneous columns ``V(t)`` of
the model linearized about that solution, ``V' = A(t) V`` with ``A = df/dz`` of the augmented
state ``z = (x, p)``. On a grid, as the non-stiff propagators take them, a stiff ``A`` needs many
implicit substeps per interval (the intervals are placed before the solution is known, so most of
them sit where the solution is smooth but the stiffness is not). Here the columns take the steps
that ``x`` takes.

**The steps differentiated.** Rodas5P applied to the joint system ``(x, V)`` with its exact
(block lower triangular) Jacobian gives, on the ``x`` rows, the steps of ``x`` alone, and on the
``V`` rows the derivative of those steps with respect to the start (the step sizes held fixed):
the internal numerical differentiation of H. G. Bock, whose columns are the exact derivatives of
the computed solution, as a Gauss–Newton method wants them. With the ``x`` steps known, each
step's ``V`` rows are linear in the step's starting columns. So this module integrates ``x`` alone
(:func:`rodas5p_model`, the error controlled on ``x``), keeps its accepted steps, rebuilds every
step's stages and computes every step's linear map at once, batched over all the steps of all the
samples (:func:`step_sensitivities`), and composes the maps along each sample's steps. The joint
integration it replaces took a Jacobian of the model at every stage of every step, one step at a
time; here those Jacobians are one batched call.

For one step from ``(t0, x0)`` of size ``h`` with stage increments ``k_i`` and stage arguments
``u_i = x0 + sum_j a_ij k_j`` (:mod:`torchql.solvers.tableau`), the columns' increments are::

    (I / (h gamma) - A_x(t0, z0)) K_i = A(t_i, u_i) (V0 + sum_j a_ij K_j) + sum_j (C_ij / h) K_j
                                        + h d_i A_t(t0, z0) V0 + (dA/dx(t0, z0) . k_i) V0,

(``K_j`` the ``x`` rows; the coefficients' rows of ``V`` are constant), ``V1 = V0 + sum_i m_i K_i``
and the dense output between is the method's, applied to ``K``. The columns' accuracy is that of
the steps of ``x``, whose error the solver controls (the columns' own is not tested, as
CVODES without ``errconS``): a column is the exact derivative of the computed ``x``.
"""

from __future__ import annotations

import torch
from torch.func import jacrev, vmap

from ..linearize import node_jacobian
from . import tableau
from .rosenbrock import RosenbrockSolution, rodas5p_batch
from .steps import StepRecord, dense_value

__all__ = ["rodas5p_model", "rodas5p_sensitivities", "step_sensitivities", "compose_steps", "state_rows"]

#: Steps whose maps are computed in one batched call (bounds the memory of the stages' Jacobians).
STEP_CHUNK = 4096


def rodas5p_model(system, z0: torch.Tensor, grid: torch.Tensor, *, rtol: float, atol: float,
                  land: torch.Tensor | None = None, keep_steps: bool = False, stop=None, **budget
                  ) -> tuple[RosenbrockSolution, torch.Tensor]:
    """The augmented model integrated from ``z0 (S, M)`` over ``grid`` by Rodas5P, the error
    controlled on the states: ``(solution, z (S, G, M))`` (NaN where a sample failed). One sample
    is integrated with its coefficients bound in its model (no ``vmap`` over the augmented state).
    ``stop``: as :func:`~torchql.solvers.rodas5p_batch`'s, on the augmented state ``(L, G, M)``."""
    n, G = system.n, grid.shape[-1]
    if z0.shape[0] == 1:  # the states alone; the coefficients appended to them
        def augmented(rows, y):
            return torch.cat([y, z0[rows, n:].unsqueeze(1).expand(-1, G, -1)], dim=2)
        states_stop = None if stop is None else (lambda rows, y, reached: stop(rows, augmented(rows, y), reached))
        sol = rodas5p_batch(system.model_with(z0[0, n:]), z0[:, :n], grid, rtol=rtol, atol=atol, land=land,
                            vectorize=False, keep_steps=keep_steps, stop=states_stop, **budget)
        return sol, augmented(torch.zeros(1, dtype=torch.long, device=z0.device), sol.y)
    sol = rodas5p_batch(system.f, z0, grid, rtol=rtol, atol=atol, land=land, error_components=n,
                        keep_steps=keep_steps, stop=stop, **budget)
    return sol, sol.y


def rodas5p_sensitivities(system, z0: torch.Tensor, columns: torch.Tensor, grid: torch.Tensor, *, rtol: float,
                          atol: float, land: torch.Tensor | None = None, **budget
                          ) -> tuple[RosenbrockSolution, torch.Tensor, torch.Tensor]:
    """The model from ``z0 (S, M)`` and its columns from ``columns (S, M, m)`` (their values at the
    first node) over ``grid`` (``(G,)`` or ``(S, G)``): ``(solution, z (S, G, M), V (S, G, M, m))``.
    Arguments as :func:`rodas5p_model`; a failed sample's values are not meaningful."""
    sol, z = rodas5p_model(system, z0, grid, rtol=rtol, atol=atol, land=land, keep_steps=True, **budget)
    return sol, z, step_sensitivities(system, sol.steps, z0[:, system.n:], columns, grid)


def step_sensitivities(system, steps: StepRecord, p: torch.Tensor, columns: torch.Tensor,
                       grid: torch.Tensor) -> torch.Tensor:
    """The columns ``V (S, G, M, m)`` at the nodes of ``grid`` (``(G,)`` or ``(S, G)``) along the
    accepted Rodas5P ``steps`` of ``S`` samples (their states first in ``steps.y``), with
    coefficients ``p (S, P)`` and the columns' values ``columns (S, M, m)`` at the first node."""
    S = columns.shape[0]
    grid = grid.expand(S, grid.shape[-1])
    if not steps.t.shape[0]:  # no sample took a step (each failed at once): their first columns throughout
        return columns.unsqueeze(1).expand(S, grid.shape[-1], *columns.shape[1:]).clone()
    step, theta = steps.locate(grid)
    dense = torch.zeros(steps.t.shape[0], dtype=torch.bool, device=grid.device)
    dense[step[theta < 1]] = True
    change, dense_q = _step_maps(system, steps, p, dense, tableau.Tensors(columns.dtype, columns.device))
    return compose_steps(steps, change, columns, grid, (dense, dense_q))


def compose_steps(steps: StepRecord, change: torch.Tensor, columns: torch.Tensor, grid: torch.Tensor,
                  dense: tuple | None = None) -> torch.Tensor:
    """The columns ``V (S, G, M, m)`` at the nodes of ``grid (S, G)`` from each step's map of them,
    ``change (N, n, M)`` (a step takes ``V`` to ``V + [change @ V; 0]``), composed along each
    sample's ``steps`` from ``columns (S, M, m)`` at the first node. A node inside a step (not
    landed on, nor its start) takes the step's dense output, ``dense = (which steps (N,) bool, q (3, D, n, M))``
    (Rodas5P's, :func:`dense_value`); without it every node must be landed on."""
    n, S = change.shape[1], columns.shape[0]
    counts, offsets = steps.counts(S)
    step, theta = steps.locate(grid)
    landed = theta >= 1
    V_start, _ = _compose(change, columns, counts, offsets)
    V0 = V_start[step]  # (S, G, M, m)
    Vx = V0[..., :n, :] + change[step] @ V0  # at the steps' ends
    if dense is not None and dense[1].shape[1]:
        which, dense_q = dense
        q = dense_q[:, which.cumsum(0).sub(1).clamp(min=0)[step]] @ V0  # (3, S, G, n, m); unused where landed
        between = dense_value(V0[..., :n, :], Vx, q, theta[..., None, None])
        Vx = torch.where(landed[..., None, None], Vx, between)
    else:  # every node at a step's end, or at its start (the first node)
        start = theta <= 0
        if not bool((landed | start).all()):
            raise ValueError("compose_steps: a node inside a step needs the steps' dense output")
        Vx = torch.where(start[..., None, None], V0[..., :n, :], Vx)
    V = torch.cat([Vx, V0[..., n:, :]], dim=-2)
    none = counts == 0  # a sample without steps (one node, or failed at once): its first columns throughout
    return torch.where(none[:, None, None, None], columns.unsqueeze(1), V)


def _step_maps(system, steps: StepRecord, p: torch.Tensor, dense: torch.Tensor, tab: tableau.Tensors
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """Every step's change of the columns' state rows, ``V1_x - V0_x = change @ V0`` (``change
    (N, n, M)``), and the dense output's vectors ``q_r = dense_q[r] @ V0`` (``(3, D, n, M)``) of the
    ``D`` steps that ``dense (N,)`` selects, in their order (``tab``: the method's coefficients)."""
    n, M = system.n, system.M
    N = steps.t.shape[0]
    change = steps.y.new_zeros(N, n, M)
    dense_q = steps.y.new_zeros(3, int(dense.sum()), n, M)
    done = 0
    for start in range(0, N, STEP_CHUNK):
        c = slice(start, min(start + STEP_CHUNK, N))
        K = _column_increments(system, tab, steps.t[c], steps.h[c], steps.y[c, :n], steps.K[:, c, :n],
                               p[steps.sample[c]])
        change[c] = tableau.stage_sums(tab.m, K)
        chosen = dense[c]
        if bool(chosen.any()):
            q = tableau.stage_sums(tab.dense, K[:, chosen])
            dense_q[:, done:done + q.shape[1]] = q
            done += q.shape[1]
    return change, dense_q


def _column_increments(system, tab: tableau.Tensors, t, h, x0, k, p) -> torch.Tensor:
    """The stage increments ``(8, N, n, M)`` of the columns' state rows for the basis ``V0 = I``
    (``M`` columns) of ``N`` steps: ``t``, ``h (N,)``, ``x0 (N, n)``, the states' increments
    ``k (8, N, n)``, coefficients ``p (N, P)`` (see the module's description)."""
    n, M = system.n, system.M
    N = t.shape[0]
    a, C = tab.a, tab.c
    flat_k = k.reshape(tableau.STAGES, -1)
    args = torch.stack([x0] + [x0 + (a[i] @ flat_k[:i]).view(N, n) for i in range(1, tableau.STAGES)])
    times = t + tab.nodes.unsqueeze(1) * h  # (8, N)
    z = torch.cat([args, p.expand(tableau.STAGES, N, -1)], dim=-1)
    _, (A,) = node_jacobian(state_rows(system), (times.reshape(-1), z.reshape(-1, M)), (1,), n)
    A = A.view(tableau.STAGES, N, n, M)
    A_t, A_z = vmap(jacrev(_jacobian(system), argnums=(0, 1)))(t, z[0])  # (N, n, M), (N, n, M, M)
    coupling = torch.einsum("nimj,snj->snim", A_z[..., :n], k)  # (dA/dx . k_i), (8, N, n, M)
    W = -A[0, :, :, :n]
    W.diagonal(dim1=-2, dim2=-1).add_((1.0 / (tableau.GAMMA * h)).unsqueeze(-1))
    LU, pivots, _ = torch.linalg.lu_factor_ex(W)
    hc = h.view(N, 1, 1)
    h_At = hc * A_t
    Kc = A.new_empty(tableau.STAGES, N, n, M)
    flat = Kc.view(tableau.STAGES, -1)
    for i in range(tableau.STAGES):
        rhs = A[i] + coupling[i]
        if i:
            rhs = rhs + A[i, :, :, :n] @ (a[i] @ flat[:i]).view(N, n, M) + (C[i] @ flat[:i]).view(N, n, M) / hc
        if tableau.D[i]:
            rhs = rhs + tableau.D[i] * h_At
        Kc[i] = torch.linalg.lu_solve(LU, pivots, rhs)
    return Kc


def _compose(change: torch.Tensor, columns: torch.Tensor, counts: torch.Tensor, offsets: torch.Tensor
             ) -> tuple[torch.Tensor, torch.Tensor]:
    """The columns at the start of every step ``(N, M, m)`` and at each sample's end ``(S, M, m)``:
    the steps' maps applied in order along each sample's steps, from ``columns (S, M, m)``."""
    n = change.shape[1]
    V = columns.clone()
    V_start = columns.new_empty(change.shape[0], *columns.shape[1:])
    for k in range(int(counts.max()) if counts.numel() else 0):
        rows = (counts > k).nonzero().flatten()
        ids = offsets[rows] + k
        V_start[ids] = V[rows]
        V[rows, :n] += change[ids] @ V[rows]
    return V_start, V


def state_rows(system):
    """One node's state rows of the augmented right-hand side, ``(t, z (M,)) -> (n,)``."""
    n = system.n

    def rows(t, z):
        return system.rhs(t, z[:n], z[n:])
    return rows


def _jacobian(system):
    """One node's ``A = d(state rows)/dz``, ``(t, z) -> (n, M)``."""
    return jacrev(state_rows(system), argnums=1)
