"""A non-stiff model's solution and its sensitivities: the explicit pair's own steps, differentiated.

Where the storage grid misses a change of the model, the final pass needs the model's solution
from the estimates together with its derivatives in the unknowns, the columns ``V(t)``
(:meth:`~torchql.engine_evaluate.Evaluation._solve_with_sensitivities`). For a stiff model
:mod:`torchql.solvers.sensitivity` differentiates Rodas5P's steps; for one that is not stiff, an
implicit solver's steps are short and its linear algebra wasted (an oscillation over 318 periods
spent 110 s there). Here the batched explicit pair (:func:`torchql.dopri.dopri_batch`, DOP853 at
the fit's tolerance) integrates the model alone, landing on every node, and keeps its accepted
steps; each step's map of the columns is its own derivative with respect to its start (the step
size held fixed), as Bock's internal numerical differentiation: for slopes
``k_i = f(t + c_i h, u_i)``, ``u_i = x + h sum_j a_ij k_j``, the columns' slopes are
``K_i = A_i (V + h sum_j a_ij K_j)`` with ``A_i = df/dz`` at ``(t + c_i h, u_i)``, and the step
maps ``V`` to ``V + h sum_i b_i K_i``. Every stage's Jacobian of every step is one batched call;
the maps are composed along each sample's steps. The columns are the exact derivatives of the
computed solution, as a Gauss–Newton method wants them.
"""

from __future__ import annotations

import torch

from .dopri import dopri_batch
from .linearize import node_jacobian
from .rk_pairs import PAIRS, combine
from .solvers.sensitivity import STEP_CHUNK, compose_steps, state_rows
from .solvers.steps import StepRecord

__all__ = ["explicit_sensitivities", "explicit_step_maps", "HELD_STEP"]


#: A step of the explicit pair is held by a decay when its size times the fastest decay rate at its
#: start (``max(-Re lambda)`` of the states' Jacobian) is at least this: at a fit's tolerance the
#: pair's accurate steps on a smooth solution stay below it (``h omega`` of about 0.3 on an oscillation
#: at rtol 1e-10), and a relaxation ``x' = -k (x - cos t)`` of ``k = 1e3`` holds them at about 1.3.
HELD_STEP = 1.0


def explicit_sensitivities(system, z0: torch.Tensor, columns: torch.Tensor, grid: torch.Tensor, *, rtol: float,
                           atol: float, method: str = "dop853", interval_steps: int | None = None,
                           held: list | None = None) -> tuple[torch.Tensor, torch.Tensor, list, int]:
    """The augmented model from ``z0 (S, M)`` over ``grid`` (``(G,)`` or ``(S, G)``) by the explicit
    pair ``method`` (landing on every node), and its columns from ``columns (S, M, m)`` (their
    values at the first node): ``(z (S, G, M), V (S, G, M, m), errors, evaluations)``, ``errors``
    one per sample, the solver's words or None (a failed sample's values are not meaningful), and
    the right-hand side's evaluations (points) of the solution. ``held``, a list if given, gets the
    fraction of each sample's steps held by a decay (:data:`HELD_STEP`; 0 for a sample without
    steps): where most are, an implicit solver's steps are not so held."""
    S = z0.shape[0]
    parts: list = []
    messages: list = []
    z, _, evals = dopri_batch(system, z0, grid, rtol=rtol, atol=atol, messages=messages, interval_steps=interval_steps,
                          method=method, steps=parts)
    pair = PAIRS[method](z0.dtype, z0.device)
    if held is not None:
        held[:] = [0.0] * S
    if not parts:  # no sample took a step: their first columns throughout
        return z, columns.unsqueeze(1).expand(S, grid.shape[-1], *columns.shape[1:]).clone(), messages, evals
    steps = StepRecord.join(parts, z0)
    maps = [explicit_step_maps(system, pair, steps, slice(k, k + STEP_CHUNK), decay=held is not None)
            for k in range(0, steps.t.shape[0], STEP_CHUNK)]
    change = torch.cat([m[0] for m in maps])
    if held is not None:
        decay = torch.cat([m[1] for m in maps])  # (N,): h max(-Re lambda) at each step's start
        counts = torch.bincount(steps.sample, minlength=S).to(z0.dtype)
        fraction = z0.new_zeros(S).index_add_(0, steps.sample, (decay >= HELD_STEP).to(z0.dtype))
        held[:] = (fraction / counts.clamp(min=1)).tolist()
    return z, compose_steps(steps, change, columns, grid.expand(S, grid.shape[-1])), messages, evals


def explicit_step_maps(system, pair, steps: StepRecord, part: slice, decay: bool = False
                       ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The state rows of the steps ``part``'s maps of the columns, ``(N, n, M)``: a step takes the
    columns ``V (M, m)`` to ``V + [change @ V; 0]`` (the coefficients' rows are constant); and, with
    ``decay``, each step's size times the fastest decay rate of the states' Jacobian at its start,
    ``(N,)`` (else None)."""
    n = system.n
    t, h, x, K = steps.t[part], steps.h[part], steps.y[part], steps.K[:, part]
    N, M = x.shape
    last = pair.evals  # the row of the solution's weights; the stages before it make the step
    hc = h.unsqueeze(-1)
    args = [x] + [torch.addcmul(x, hc, combine(pair.rows_a[i], K[:i])) for i in range(1, last)]
    times = torch.stack([t + pair.nodes[i] * h for i in range(last)])  # (L, N)
    _, (A,) = node_jacobian(state_rows(system), (times.reshape(-1), torch.stack(args).reshape(-1, M)), (1,), n)
    A = A.view(last, N, n, M)
    G = A.new_empty(last, N, n, M)  # the columns' slopes, from the identity at the step's start
    for i in range(last):
        G[i] = A[i]
        if i:
            G[i] += A[i, :, :, :n] @ (hc.unsqueeze(-1) * combine(pair.rows_a[i], G[:i]))
    change = hc.unsqueeze(-1) * combine(pair.rows_a[last], G)
    if not decay:
        return change, None
    return change, h.abs() * (-torch.linalg.eigvals(A[0, :, :, :n]).real).amax(dim=-1).clamp(min=0)
