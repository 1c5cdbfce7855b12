"""How far the storage grid's interpolants stray from the model between their nodes.

The linear problems read the reference ``z`` and ``h f`` between the storage grid's nodes as
Hermite interpolants (:func:`torchql.transfer.interval_coefficients`). ``grid="auto"`` counts the
intervals from the size of the solutions' derivatives at the nodes of a probe grid; a change of
the model faster than the nodes see (a steep ``tanh`` that switches between two of them) escapes
that count, and the transfers' sensitivities miss it as much: Gauss–Newton with them can stop
at a point that is not the model's optimum and see no step left to take.

This module measures the miss after the fact, at the final solution: at interior local times
(:data:`CHECK_POINTS`, the midpoint) of every interval it compares ``h f`` evaluated on the storage's
interpolant of ``z`` with the storage's interpolant of ``h f`` and with the slope of the
interpolant of ``z`` itself (its defect as a solution of the model), as the propagator reads them,
against the states' scale (what the difference moves the solution by over the interval). On a
grid that resolves the solution they differ by a small part of the interpolation error the count
allows (``sqrt(rtol)`` of the states, :data:`torchql.grid.AUTO_SAFETY`); across a switch, by a
good part of the jump times the interval. The defect counts only where the Jacobian changes
along the trajectory: a linear system whose unknowns are initial states alone is propagated
exactly whatever its stored trajectory (the interpolant of ``f = A z`` is ``A`` times that of
``z``). An unknown coefficient's column is not: its forcing ``df/dp`` reads the stored trajectory
(``-(x - A cos t)`` for a relaxation rate ``k``, affine in ``x``, whose interpolants of ``f`` and
of ``z`` agree with each other while both miss a transient of width ``1 / k`` between two nodes:
shooting's Gauss–Newton steps stopped 0.2 standard errors short of the optimum, CONVERGED_SSE).
"""

from __future__ import annotations

import math

import torch

from .transfer import interval_coefficients

__all__ = ["CHECK_POINTS", "MISS_FACTOR", "interpolation_misfit", "storage_misses"]

#: Local times inside every storage interval where the interpolants are compared with the model: the
#: midpoint, where a Hermite interpolant's error peaks (at 1/4 and 3/4 too the largest misfits of
#: tanh(50 v) and of a nonlinear oscillation were the midpoint's).
CHECK_POINTS = (0.5,)
#: A sample's storage misses its model where the misfit exceeds this many times ``sqrt(rtol)``.
#: Over the test suite's fits on automatic grids at ``rtol=1e-10`` the largest misfit was 5.8e-6
#: (0.06 of the threshold); across the switch of ``tanh(50 v)`` it is 1.9e-3 to 3e-3.
MISS_FACTOR = 10.0


#: A Jacobian whose entries stay within this fraction of its largest along the trajectory is constant.
_CONSTANT = 1e-12


def interpolation_misfit(f, t: torch.Tensor, traj: torch.Tensor, lin, degree: int, n: int,
                         coefficients=None, floor: float = 0.0) -> torch.Tensor:
    """The largest relative misfit ``(S,)`` of each sample's interpolant of ``h f`` from the model.

    Parameters
    ----------
    f : callable
        The augmented model at one node, ``f(t (), z (M,)) -> (M,)``.
    t : Tensor ``(G,)`` or ``(S, G)``
        The storage grid (per-sample grids may repeat their last node).
    traj : Tensor ``(S, G, M)``
        The reference at the nodes; ``lin`` its linearization there (fields ``(S, G, ...)``).
    degree : int
        Degree of the interpolants of ``z`` and ``h f`` (3 or 5), as the propagator stores them.
    n : int
        The model's states (the coefficients' rows are constant).
    coefficients : _Coefficients, optional
        The storage's coefficients, if already built (:func:`~torchql.transfer.interval_coefficients`
        of these arguments).
    floor : float
        The smallest scale of a state (``atol / rtol``: below it the tolerances are absolute, as
        :func:`torchql.grid.needed_intervals` sizes the automatic grid with them), in its units.

    Returns
    -------
    Tensor ``(S,)``
        ``max |h f(t_s, z(t_s)) - (h f)(t_s)| / max(max_t |z_i|, floor)`` over the check points, the intervals
        and the states ``i``: the stray of the interval's slope, in its local time, against the
        state's scale (an interval as short as a zero-order hold's step counts as little as it
        moves the solution).
    """
    S, G, M = traj.shape
    if G < 2:
        return traj.new_zeros(S)
    if coefficients is None:
        coefficients = interval_coefficients(t, traj, lin.f, lin, degree)
    order, a = coefficients.order, coefficients.a
    perm = order[:-1]
    h = (t[..., 1:] - t[..., :-1]).expand(S, G - 1).reshape(-1)  # (S N,)
    start = t[..., :-1].expand(S, G - 1).reshape(-1)
    states = [i for i in range(a) if int(perm[i]) < n]  # the active rows that are states
    if not states:
        return traj.new_zeros(S)
    rows = torch.tensor(states, device=traj.device)
    components = perm[rows]
    scale = traj[..., :n].abs().amax(dim=1).clamp(min=max(floor, torch.finfo(traj.dtype).tiny))  # (S, n)
    scale = scale[:, components].repeat_interleave(G - 1, dim=0).T  # (states, S N)
    points = torch.tensor(CHECK_POINTS, dtype=traj.dtype, device=traj.device)
    values = coefficients.values(points)  # (P, Q, S N): every check point at once
    z = torch.empty(M, *values.shape[::2], dtype=values.dtype, device=values.device)  # (M, P, S N)
    z[perm] = values[:, :M].transpose(0, 1)
    times = start + points.unsqueeze(1) * h  # (P, S N)
    slopes = torch.vmap(f)(times.reshape(-1), z.flatten(1).T).T[components].unflatten(1, times.shape)
    stored = values[:, M:].unflatten(1, (a, M + 1))[:, rows, 0].transpose(0, 1)  # h f's rows (states, P, S N)
    # the interpolant of z's own slope there, d/ds z(s) (its local time's: h z'), in stored rows (P, M, S N)
    z_slope = coefficients.values(points, rows=slice(0, M), derivative=True)
    defect = z_slope[:, rows].transpose(0, 1) - h * slopes  # the interpolant of z against the model (states, P, S N)
    # (it moves the propagation only where the Jacobian, the unknown coefficients' columns included,
    # changes along the trajectory: a linear system with only initial states unknown is propagated
    # exactly whatever its stored trajectory)
    jac = lin.jac[..., :n, :]
    changes = (jac - jac[:, :1]).abs().flatten(1).amax(dim=1) > _CONSTANT * jac.abs().flatten(1).amax(dim=1)
    defect = defect * changes.repeat_interleave(G - 1).to(defect.dtype)
    misfit = (torch.maximum((h * slopes - stored).abs(), defect.abs()) / scale.unsqueeze(1)).nan_to_num(nan=math.inf)
    worst = misfit.where(h > 0, 0.0).flatten(0, 1).amax(dim=0)
    return worst.reshape(S, G - 1).amax(dim=1)


def storage_misses(misfit: torch.Tensor, rtol: float) -> torch.Tensor:
    """Samples ``(S,)`` whose :func:`interpolation_misfit` exceeds :data:`MISS_FACTOR` times ``sqrt(rtol)``."""
    return misfit > MISS_FACTOR * math.sqrt(rtol)
