"""Particular and homogeneous solutions, propagated together over the grid.

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

from .integrate import interval_tolerances
from .propagators import DEFAULT_PROPAGATOR, PROPAGATORS, LinearPropagator, linear_propagator
from .trajectory import IntervalSystem, LinearizedReference
from .transfer import compose_transfers

__all__ = ["LINEAR_SOLVERS", "DEFAULT_LINEAR_SOLVER", "check_linear_solver", "initial_columns", "propagate_linear"]

#: The built-in propagators' names (:mod:`torchql.propagators`): ``"taylor"`` (each interval's
#: Taylor series, exact for its polynomial coefficients, summed to a bounded truncation error),
#: ``"rk4_doubling"`` (fixed RK4 steps with step doubling and refinement of the intervals that
#: need it), ``"torchdiffeq"`` (one adaptive torchdiffeq call over all intervals, with the
#: solver named by ``solver``), and for stiff models ``"radau"`` (Radau IIA collocation) and
#: ``"exponential"`` (the frozen coefficients' matrix exponential with a Radau correction).
LINEAR_SOLVERS: tuple[str, ...] = tuple(PROPAGATORS)
DEFAULT_LINEAR_SOLVER: str = DEFAULT_PROPAGATOR


def check_linear_solver(linear_solver: "str | LinearPropagator") -> LinearPropagator:
    """The propagator ``linear_solver`` names (or is); ``ValueError`` naming the valid choices otherwise."""
    return linear_propagator(linear_solver)


def initial_columns(z0: torch.Tensor, unknown_index: torch.Tensor) -> torch.Tensor:
    """``W(t0) = [z0, e_{i_1}, ..., e_{i_m}]``: shape ``(..., M, 1 + m)`` for ``z0 (..., M)`` (one
    sample, or a batch of them)."""
    M, m = z0.shape[-1], unknown_index.numel()
    E = torch.zeros(M, m, dtype=z0.dtype, device=z0.device)
    E[unknown_index, torch.arange(m, device=z0.device)] = 1.0
    return torch.cat([z0.unsqueeze(-1), E.expand(*z0.shape[:-1], M, m)], dim=-1)


def propagate_linear(reference: LinearizedReference, w0: torch.Tensor, *, solver: str = "dopri5", rtol: float,
                     atol: float, max_steps: int | None = None,
                     linear_solver: "str | LinearPropagator" = DEFAULT_LINEAR_SOLVER) -> tuple[torch.Tensor, int]:
    """Integrate the quasilinear system over the reference's grid.

    Every interval's transfer ``(Phi_j, c_j)`` is integrated at once, in the local time ``s``
    in ``[0, 1]``, with max-norm error control so that no interval dilutes another's error and
    tolerances divided by the square root of the number of intervals, for the accumulation of
    local errors. The transfers are then composed over the grid by a parallel prefix scan.

    Parameters
    ----------
    reference : LinearizedReference
        Grid ``(G,)`` and the linearization at its nodes.
    w0 : Tensor ``(M, 1 + m)``
        Particular (column 0) and homogeneous initial columns at the first node.
    solver : str
        The torchdiffeq method of ``linear_solver="torchdiffeq"`` (unused otherwise).
    rtol, atol : float
        Tolerances of the whole propagation.
    max_steps : int, optional
        Step budget of the torchdiffeq call (unused by ``"taylor"`` and ``"rk4_doubling"``, which
        cap the substeps per interval instead; see :func:`torchql.taylor.taylor_transfers`).
    linear_solver : str or LinearPropagator
        A registered name (:data:`LINEAR_SOLVERS`) or a propagator object: ``"taylor"`` (default) sums each interval's Taylor series
        (exact for the interpolated coefficients) to a bounded truncation error, in substeps
        where the interval is long against the dynamics; ``"rk4_doubling"`` integrates with fixed
        RK4 steps and step doubling, refining only the intervals that need it; ``"torchdiffeq"``
        with one adaptive torchdiffeq call (first step the whole interval, since the intervals
        are short against the dynamics).

    Returns
    -------
    W : Tensor ``(G, M, 1 + m)``
        Particular (column 0) and homogeneous solutions at every grid node.
    n_evals : int
        Evaluations of the interval system's coefficients, each one at one local time on all
        intervals being integrated at once (for ``"taylor"`` one series term of all intervals of
        a batch; for ``"torchdiffeq"`` one call of the batched
        :class:`~torchql.trajectory.IntervalSystem`).

    Raises
    ------
    IntegrationError
        When a transfer cannot be integrated to the tolerance or becomes non-finite.
    """
    propagator = linear_propagator(linear_solver)
    G = reference.t.shape[0]
    if G == 1:
        return w0.unsqueeze(0), 0
    system = IntervalSystem(reference)
    rtol_j, atol_j = interval_tolerances(rtol, atol, G - 1, w0.dtype)
    transfers, n_evals = propagator.transfers(system, rtol=rtol_j, atol=atol_j, solver=solver, max_steps=max_steps)
    return compose_transfers(transfers, w0), n_evals
