"""The nonlinear model integrated over a grid by multiple shooting: all intervals of all samples at once.

``x' = f(t, x)`` from ``x(t_0) = x0`` is solved on the nodes ``t_0 < ... < t_{G-1}`` as the
root of the node defects: given node values ``X_j``, every interval is integrated at once from
its own start ``X_j`` (fixed RK4 steps, vectorized over the intervals of every sample, with the
variational equations for ``S_j = d phi_j / d X_j``), and the defects ``d_j = phi_j(X_j) - X_{j+1}``
are removed by Newton's method. Newton's correction obeys ``delta_{j+1} = S_j delta_j + d_j``,
``delta_0 = 0``: an affine recurrence, composed per sample by the prefix scan of
:mod:`torchql.transfer`. Convergence is quadratic from a good guess (for instance the linear
prediction of a quasilinearization iterate); for a linear model one Newton step lands within the
integration error whatever the guess. Once a sample's correction is within ``sqrt(rtol)`` of its
solution, its next steps are chord steps: the new nodes' defects propagated by the last
sensitivities, which are not evaluated again.

Each interval's integration is controlled like the interval transfers': ``n`` and ``2n`` RK4
steps, the difference over 15 as the error estimate (max-norm, tolerances divided by the square
root of the sample's number of intervals), the Richardson extrapolation as the result, and more
steps for the intervals that fail. Only the defects need that accuracy: the sensitivities ``S_j``
are Newton's matrices, which set how fast the corrections shrink and not where they end, and are
integrated once, by the ``n`` RK4 steps of the variational equations that met the tolerance
(the Jacobian of ``f``, from :func:`torchql.linearize.node_jacobian`, costs a few evaluations of ``f``).

Every decision is the sample's own (its steps, its convergence, its failure), so a sample's
solution is the one it gets alone: :func:`torchql.fit` and each sample of :func:`torchql.fit_many`
solve alike.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from .budget import check_time
from .grid import interval_counts
from .integrate import interval_tolerances
from .linearize import node_jacobian
from .model import AugmentedSystem, BatchedCall
from .transfer import check_max_substeps, prefix_products

__all__ = ["GridSolution", "solve_on_grid_batch"]

#: Safety factor on the predicted number of steps.
_SAFETY = 2.0


class GridSolution(NamedTuple):
    """What :func:`solve_on_grid_batch` returns for ``S`` samples on ``G`` nodes of ``M`` components.

    Attributes
    ----------
    traj : Tensor ``(S, G, M)``
        The solutions at the nodes (NaN where ``ok`` is false).
    ok : bool Tensor ``(S,)``
        Samples whose Newton iteration converged with every interval within tolerance.
    n_evals : int
        Evaluations of ``f`` (points of the batched calls).
    over_budget : bool Tensor ``(S,)``
        Samples with an interval that needed more than ``max_substeps`` RK4 steps (a blow-up,
        or a stretch too stiff for RK4), as against a Newton iteration that did not converge.
    newton_iterations : long Tensor ``(S,)``
        Newton updates of each sample's node values.
    """

    traj: torch.Tensor
    ok: torch.Tensor
    n_evals: int
    over_budget: torch.Tensor
    newton_iterations: torch.Tensor


def solve_on_grid_batch(system: AugmentedSystem, z0: torch.Tensor, grid: torch.Tensor, *, rtol: float, atol: float,
                        guess: torch.Tensor | None = None, max_newton: int = 25, max_substeps: int = 1024
                        ) -> GridSolution:
    """The augmented model ``z' = f(t, z)`` from ``z0 (S, M)`` at the nodes of ``grid``, by multiple shooting.

    Each sample's coefficients are its trailing components of ``z``, so one right-hand side
    serves every sample (one sample's model takes its coefficients bound, and the states alone).
    Intervals of all samples are integrated at once, each with its own step count and error
    test; Newton's correction is composed per sample by the prefix scan, and a sample leaves the
    work when its correction falls below the tolerance, or when it fails.

    Parameters
    ----------
    system : AugmentedSystem
    z0 : Tensor ``(S, M)``
    grid : Tensor ``(G,)`` or ``(S, G)``
        The shared grid, or each sample's own (padded at the end by repeating its last node).
    rtol, atol : float
        Tolerances of one sample's whole solution (per interval divided by the square root of
        its number of intervals: ``G - 1``, or those of positive length of its own grid); Newton
        stops when its correction is below them.
    guess : Tensor ``(S, G, M)``, optional
        Node values to start Newton from (default ``z0`` at every node, adequate for linear or
        mildly nonlinear models over short spans; pass a prediction otherwise).
    max_newton : int
        Most Newton iterations.
    max_substeps : int
        Most RK4 steps per interval (a power of two, at least 2).

    Returns
    -------
    GridSolution
        A sample fails (``ok`` false) when an interval cannot meet the tolerance with
        ``max_substeps`` steps (``over_budget``), its solution becomes non-finite, its Newton
        correction grows again from the third iteration on (the guess is outside Newton's
        basin), or Newton does not converge in ``max_newton`` iterations.
    """
    check_max_substeps(max_substeps)
    S, M = z0.shape
    G = grid.shape[-1]
    X = z0.unsqueeze(1).expand(S, G, M).clone() if guess is None else guess.detach().clone()
    X[:, 0] = z0
    ok = torch.zeros(S, dtype=torch.bool, device=z0.device)
    over_budget = torch.zeros(S, dtype=torch.bool, device=z0.device)
    iterations = torch.zeros(S, dtype=torch.long, device=z0.device)
    if G == 1:
        return GridSolution(X, ~ok, 0, over_budget, iterations)
    N = G - 1
    per_sample = grid.dim() == 2
    if per_sample:  # each sample's tolerances over its own intervals: (S, 1) per interval below
        tolerances = [interval_tolerances(rtol, atol, c, z0.dtype) for c in interval_counts(grid).tolist()]
        rtol_j, atol_j = (torch.tensor(v, dtype=z0.dtype, device=z0.device).unsqueeze(-1) for v in zip(*tolerances))
    else:
        rtol_j, atol_j = interval_tolerances(rtol, atol, N, z0.dtype)
    n = system.n  # the coefficients are constant on every interval: Newton moves the states only
    X[:, 1:, n:] = z0[:, n:].unsqueeze(1)  # and they are the samples' own at every node, whatever the guess
    # the states are integrated; the coefficients, constant, ride along only where they differ
    # between the samples (one sample's are bound in a copy of its model: a model written for a
    # batch of states then takes every interval in one call, and vmap's cost per call, most of a
    # small model's evaluation, goes)
    field, width = (_Field(system.model_with(z0[0, n:]), n), n) if S == 1 else (_Field(system.f, n), M)
    active = torch.arange(S, device=z0.device)
    steps = torch.ones(S, N, dtype=torch.long, device=z0.device)
    t0, h = grid[..., :-1], grid[..., 1:] - grid[..., :-1]
    n_evals = 0
    matrices = z0.new_empty(S, N, n, n)  # Newton's, per sample; kept for chord steps once its corrections are small
    stale = torch.ones(S, dtype=torch.bool, device=z0.device)
    previous = z0.new_full((S,), math.inf)  # each sample's last correction (max-norm)
    for iteration in range(1, max_newton + 1):
        if not active.numel():
            break
        check_time()
        A = active.numel()
        Xa = X[active]
        st = steps[active].reshape(-1)
        if per_sample:
            ta, hs = t0[active].reshape(-1), h[active].reshape(-1)
            rt, at = rtol_j[active].repeat_interleave(N, dim=0), atol_j[active].repeat_interleave(N, dim=0)
        else:
            ta, hs, rt, at = t0.repeat(A), h.repeat(A), rtol_j, atol_j
        owner = torch.arange(A, device=z0.device).repeat_interleave(N)
        x0 = Xa[:, :-1, :width].reshape(-1, width)
        phi, failed, evals = _integrate_each(field, ta, hs, x0, st, rt, at, max_substeps, owner)
        steps[active] = st.reshape(A, N)
        n_evals += evals
        failed = failed.reshape(A, N).any(dim=1)
        over_budget[active[failed]] = True
        renewed = stale[active] & ~failed  # a failed sample leaves the work: no matrices for it
        renew = renewed.repeat_interleave(N)
        if bool(renew.any()):
            fresh, _ = newton_matrices(field, ta[renew], hs[renew], x0[renew], st[renew])
            matrices[active[renewed]] = fresh.reshape(-1, N, n, n)
            n_evals += 4 * int(st[renew].sum())  # each interval's n steps: 4 n points with the Jacobian
        defect = phi.reshape(A, N, width)[..., :n] - Xa[:, 1:, :n]
        # delta_{j+1} = S_j delta_j + d_j, delta_0 = 0: the affine recurrence, by the prefix scan
        Y = torch.cat([matrices[active], defect.unsqueeze(-1)], dim=-1).permute(0, 2, 3, 1)  # (A, n, n+1, N)
        delta = prefix_products(Y)[:, :, n, :].transpose(1, 2)  # (A, N, n)
        finite = torch.isfinite(delta).flatten(1).all(dim=1)
        size = delta.abs().flatten(1).amax(dim=1)
        diverging = size > previous[active] if iteration >= 3 else torch.zeros_like(finite)
        previous[active] = size
        iterations[active] = iteration
        Xa = Xa.clone()
        Xa[:, 1:, :n] = Xa[:, 1:, :n] + delta
        scale = Xa[:, 1:, :n].abs()
        small = (delta.abs() <= 0.1 * (atol + rtol * scale)).flatten(1).all(dim=1)
        stale[active] = ~(delta.abs() <= math.sqrt(rtol) * (atol / rtol + scale)).flatten(1).all(dim=1)
        X[active] = Xa
        going = finite & ~failed & ~diverging
        ok[active[small & going]] = True
        active = active[~small & going]
    X[~ok] = float("nan")
    return GridSolution(X, ok, n_evals, over_budget, iterations)


def _integrate_each(field, t0, h, x0, steps, rtol, atol, max_substeps, owner):
    """``phi (N, M)`` of every interval within tolerance, ``failed (N,)`` and the evaluations of
    ``f`` (points); ``steps`` updated in place.

    ``rtol``, ``atol``: floats, or Tensors ``(N, 1)`` (each interval its own). ``owner (N,)``: each
    interval's sample; when one interval of a sample exceeds ``max_substeps``, the sample's other
    intervals stop too (all failed: the sample has failed).
    """
    N, M = x0.shape
    phi = x0.new_empty(N, M)
    ratio = x0.new_empty(N)
    failed = torch.zeros(N, dtype=torch.bool, device=x0.device)
    n_evals = 0
    todo = torch.arange(N, device=x0.device)
    while todo.numel():
        check_time()
        for n in steps[todo].unique().tolist():
            group = todo[steps[todo] == n]
            rt = rtol[group] if isinstance(rtol, torch.Tensor) else rtol
            at = atol[group] if isinstance(atol, torch.Tensor) else atol
            phi[group], ratio[group], evals = rk4_pair(field, t0[group], h[group], x0[group], n, rt, at)
            n_evals += evals * group.numel()
        todo = todo[~(ratio[todo] <= 1.0)]
        if not todo.numel():
            break
        current = steps[todo]
        capped = 2 * current >= max_substeps
        failed[todo[capped]] = True
        if bool(capped.any()):
            dead = torch.isin(owner[todo], owner[todo[capped]])
            failed[todo[dead]] = True
            capped = capped | dead
        todo, current = todo[~capped], current[~capped]
        steps[todo] = more_steps(current, ratio[todo], max_substeps)
    return phi, failed, n_evals


class _Field:
    """``f`` and its Jacobian, vmapped over a batch of times and states (:meth:`values`: ``f`` alone).

    ``n``: the Jacobian's size, that of the first ``n`` components of ``f`` in the first ``n`` of
    the state (default all): an augmented state's coefficients are constant along every
    interval, so Newton's correction never moves them, and only the states' block is needed.
    """

    def __init__(self, func, n: int | None = None) -> None:
        self.func = func
        self.n = n
        #: ``f`` over a batch of times and states: by one call where ``func`` takes the batch, else
        #: vmapped (:class:`torchql.model.BatchedCall`)
        self.values = BatchedCall(func)

    def __call__(self, t: torch.Tensor, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        rows = x.shape[1] if self.n is None else self.n
        value, (jac,) = node_jacobian(self.func, (t, x), (1,), rows, batched=self.values)
        return value, jac[:, :, :rows]


def more_steps(current: torch.Tensor, ratio: torch.Tensor, max_substeps: int) -> torch.Tensor:
    """The next coarse step counts of intervals that took ``current`` steps with error ratios
    ``ratio`` above 1: RK4's error falls as the fourth power of the step, with :data:`_SAFETY`."""
    r = ratio.nan_to_num(nan=16.0, posinf=16.0 ** 8).clamp(min=1.0)
    # a huge finite ratio asks for 2**factor beyond int64 (negative steps); max_substeps binds anyway
    factor = torch.ceil(torch.log2((_SAFETY * r) ** 0.25)).clamp(1, max_substeps.bit_length()).to(torch.long)
    return torch.minimum(current * 2**factor, torch.full_like(current, max_substeps // 2))


def newton_matrices(field, t0, h, x0, steps) -> tuple[torch.Tensor, int]:
    """``S_j = d phi_j / d x0_j (N, K, K)`` (``K``: the field's ``n``, else ``M``) by ``steps[j]``
    RK4 steps of the variational equations (the coarse count that met the tolerance), and the
    batched evaluations of ``f`` with its Jacobian it took."""
    N, M = x0.shape
    size = M if field.n is None else field.n
    S = x0.new_empty(N, size, size)
    n_evals = 0
    for n in steps.unique().tolist():
        group = (steps == n).nonzero().flatten()
        _, S[group] = _rk4(field, t0[group], h[group], x0[group], n)
        n_evals += 4 * n
    return S, n_evals


def rk4_pair(field, t0, h, x0, n, rtol, atol):
    """RK4 with ``n`` and ``2n`` steps from ``x0 (I, M)`` (their first stage shared): the
    extrapolated end states ``(I, M)``, error ratios ``(I,)`` and batched evaluations of ``f``."""
    first = field.values(t0, x0)
    coarse = _rk4_values(field, t0, h, x0, n, first)
    fine = _rk4_values(field, t0, h, x0, 2 * n, first)
    diff = (fine - coarse) / 15
    scale = atol + rtol * torch.maximum(x0.abs(), fine.abs())
    ratio = (diff.abs() / scale).amax(dim=-1)
    return fine + diff, ratio, 12 * n - 1


def _rk4_values(field, t0, h, x, n, first):
    """``n`` RK4 steps of the state over every interval ``(I, M)``, ``first = f(t0, x)`` given."""
    d = (h / n).unsqueeze(-1)
    for k in range(n):
        t = t0 + k * h / n
        f1 = first if k == 0 else field.values(t, x)
        f2 = field.values(t + d[:, 0] / 2, x + d / 2 * f1)
        f3 = field.values(t + d[:, 0] / 2, x + d / 2 * f2)
        f4 = field.values(t + d[:, 0], x + d * f3)
        x = x + d / 6 * (f1 + 2 * (f2 + f3) + f4)
    return x


def _rk4(field, t0, h, x, n):
    """``n`` RK4 steps of the state and its sensitivity over every interval: ``(I, M)``, ``(I, K, K)``
    (``K``: the field's ``n``, else ``M``)."""
    I, M = x.shape
    size = M if field.n is None else field.n
    d = (h / n).unsqueeze(-1)
    S = torch.eye(size, dtype=x.dtype, device=x.device).expand(I, size, size)
    dm = d.unsqueeze(-1)
    for k in range(n):
        t = t0 + k * h / n
        f1, J1 = field(t, x)
        K1 = J1 @ S
        f2, J2 = field(t + d[:, 0] / 2, x + d / 2 * f1)
        K2 = J2 @ (S + dm / 2 * K1)
        f3, J3 = field(t + d[:, 0] / 2, x + d / 2 * f2)
        K3 = J3 @ (S + dm / 2 * K2)
        f4, J4 = field(t + d[:, 0], x + d * f3)
        K4 = J4 @ (S + dm * K3)
        x = x + d / 6 * (f1 + 2 * (f2 + f3) + f4)
        S = S + dm / 6 * (K1 + 2 * (K2 + K3) + K4)
    return x, S
