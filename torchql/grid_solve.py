"""The nonlinear model integrated over a grid by multiple shooting: all intervals at once.

``x' = f(t, x)`` from ``x(t_0) = x0`` is solved on the nodes ``t_0 < ... < t_{G-1}`` as the
root of the node defects: given node values ``X_j``, every interval is integrated at once from
its own start ``X_j`` (fixed RK4 steps, vectorized over the intervals, with the variational
equations for ``S_j = d phi_j / d X_j``), and the defects ``d_j = phi_j(X_j) - X_{j+1}`` are
removed by Newton's method. Newton's correction obeys ``delta_{j+1} = S_j delta_j + d_j``,
``delta_0 = 0``: an affine recurrence, composed by the prefix scan of :mod:`torchql.transfer`.
Convergence is quadratic from a good guess (for instance the linear prediction of a
quasilinearization iterate); for a linear model one Newton step lands within the integration
error whatever the guess.
Once a correction is within ``sqrt(rtol)`` of the solution, the next steps are chord steps:
the new nodes' defects propagated by the last sensitivities, which are not evaluated again.

Each interval's integration is controlled like the interval transfers': ``n`` and ``2n`` RK4
steps, the difference over 15 as the error estimate (max-norm, tolerances divided by the square
root of the number of intervals), the Richardson extrapolation as the result, and more steps
for the intervals that fail. Only the defects need that accuracy: the sensitivities ``S_j`` are
Newton's matrices, which set how fast the corrections shrink and not where they end, and are
integrated once, by the ``n`` RK4 steps of the variational equations that met the tolerance
(the Jacobian of ``f``, from :func:`torchql.linearize.node_jacobian`, costs a few evaluations of ``f``).
"""

from __future__ import annotations

import math
from typing import Callable, NamedTuple

import torch

from .budget import check_time
from .integrate import IntegrationError, interval_tolerances
from .linearize import node_jacobian
from .model import BatchedCall
from .transfer import Transfers, compose_transfers

__all__ = ["GridSolveInfo", "IntervalBudgetError", "solve_on_grid"]

#: Safety factor on the predicted number of steps.
_SAFETY = 2.0


class IntervalBudgetError(IntegrationError):
    """An interval of the grid cannot be integrated to the tolerance within ``max_substeps`` steps.

    From node values that Newton has already matched, this usually means the solution grows
    without bound (or is too stiff for the grid); a caller that must tell a blow-up from a
    poor guess catches it apart from the other :class:`IntegrationError`.
    """


class GridSolveInfo(NamedTuple):
    """Statistics of :func:`solve_on_grid`.

    Attributes
    ----------
    newton_iterations : int
        Newton updates of the node values.
    n_evals : int
        Batched evaluations of ``f``, or of ``f`` with its Jacobian (each one at one stage of
        the intervals being integrated).
    max_defect : float
        Largest node defect ``|phi_j(X_j) - X_{j+1}|`` at the end (max-norm).
    max_substeps : int
        Most RK4 steps (of the finer of each pair) used on one interval.
    """

    newton_iterations: int
    n_evals: int
    max_defect: float
    max_substeps: int


def solve_on_grid(func: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], z0: torch.Tensor,
                  grid: torch.Tensor, *, rtol: float, atol: float, guess: torch.Tensor | None = None,
                  max_newton: int = 25, max_substeps: int = 1024) -> tuple[torch.Tensor, GridSolveInfo]:
    """Solve ``x' = func(t, x)``, ``x(grid[0]) = z0``, at the nodes of ``grid``.

    Parameters
    ----------
    func : callable ``(t, x) -> dx/dt``
        For one time (0-dim tensor) and one state ``(M,)``; called on all the intervals at once
        where it takes a batch of them, else vmapped (:class:`torchql.model.BatchedCall`), and
        differentiated with :func:`torchql.linearize.node_jacobian`.
    z0 : Tensor ``(M,)``
        Initial state.
    grid : Tensor ``(G,)``
        Strictly increasing node times.
    rtol, atol : float
        Tolerances of the whole solution (each interval gets them divided by ``sqrt(G - 1)``);
        Newton stops when its correction is below them.
    guess : Tensor ``(G, M)``, optional
        Node values to start Newton from (default: ``z0`` at every node, adequate for linear or
        mildly nonlinear models over short spans; pass a prediction otherwise).
    max_newton : int
        Most Newton iterations.
    max_substeps : int
        Most RK4 steps per interval (a power of two, at least 2).

    Returns
    -------
    traj : Tensor ``(G, M)``
        The solution at the nodes, ``traj[0] = z0``.
    info : GridSolveInfo

    Raises
    ------
    IntegrationError
        When Newton does not converge in ``max_newton`` iterations (or its correction grows
        again from the third iteration on: the guess is outside its basin), an interval cannot meet the
        tolerance with ``max_substeps`` steps, or the solution becomes non-finite.
    """
    if max_substeps < 2 or max_substeps & (max_substeps - 1):
        raise ValueError(f"`max_substeps` must be a power of two, at least 2; received {max_substeps}")
    G, M = grid.shape[0], z0.shape[0]
    X = z0.expand(G, M).clone() if guess is None else guess.detach().clone()
    X[0] = z0
    if G == 1:
        return X, GridSolveInfo(0, 0, 0.0, 0)
    intervals = G - 1
    rtol_j, atol_j = interval_tolerances(rtol, atol, intervals, z0.dtype)
    field = _Field(func)
    t0, h = grid[:-1], grid[1:] - grid[:-1]
    steps = torch.full((intervals,), 1, dtype=torch.long, device=grid.device)  # coarse steps per interval
    n_evals = 0
    previous = float("inf")  # the last correction's size
    S = None  # Newton's matrices, kept for chord steps once the corrections are small
    for iteration in range(1, max_newton + 1):
        check_time()
        phi, evals = _integrate_controlled(field, t0, h, X[:-1], steps, rtol_j, atol_j, max_substeps, grid)
        n_evals += evals
        if S is None:
            S, evals = newton_matrices(field, t0, h, X[:-1], steps)
            n_evals += evals
        defect = phi - X[1:]
        # Newton: delta_{j+1} = S_j delta_j + d_j from delta_0 = 0, by the prefix scan
        T = torch.zeros(intervals, M + 1, M + 1, dtype=z0.dtype, device=z0.device)
        T[:, :M, :M] = S
        T[:, :M, M] = defect
        T[:, M, M] = 1.0
        delta = compose_transfers(Transfers.from_full(T), torch.zeros(M, 1, dtype=z0.dtype, device=z0.device))[:, :, 0]
        if not torch.isfinite(delta).all():
            raise IntegrationError("the solution on the grid became non-finite (NaN or inf)")
        X = X + delta
        size = float(delta.abs().max())
        if iteration >= 3 and size > previous:
            raise IntegrationError(f"Newton on the node defects is not converging (correction {size:.3g} after "
                                   f"{previous:.3g}); pass a closer `guess`")
        previous = size
        if bool((delta.abs() <= 0.1 * (atol + rtol * X.abs())).all()):
            return X, GridSolveInfo(iteration, n_evals, float(defect.abs().max()), int(2 * steps.max()))
        if not bool((delta.abs() <= math.sqrt(rtol) * (atol / rtol + X.abs())).all()):
            S = None  # still far: Newton's matrices again at the new nodes
    raise IntegrationError(f"Newton on the node defects did not converge in `max_newton` = {max_newton} iterations "
                           f"(last correction {float(delta.abs().max()):.3g}); pass a closer `guess`")


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


def _integrate_controlled(field, t0, h, x0, steps, rtol, atol, max_substeps, grid):
    """``phi_j(x0_j) (N, M)`` within tolerance and the batched evaluations of ``f`` it took;
    ``steps`` (coarse) is updated in place."""
    N, M = x0.shape
    phi = x0.new_empty(N, M)
    ratio = x0.new_empty(N)
    n_evals = 0
    todo = torch.arange(N, device=x0.device)
    while todo.numel():
        for n in steps[todo].unique().tolist():
            group = todo[steps[todo] == n]
            phi[group], ratio[group], evals = rk4_pair(field, t0[group], h[group], x0[group], n, rtol, atol)
            n_evals += evals
        bad = ~(ratio[todo] <= 1.0)
        todo = todo[bad]
        if not todo.numel():
            break
        current = steps[todo]
        if bool((2 * current >= max_substeps).any()):
            worst = todo[ratio[todo].nan_to_num(nan=float("inf")).argmax()]
            raise IntervalBudgetError(
                f"the nonlinear model could not be integrated to the tolerance over the grid interval starting "
                f"at t = {float(grid[worst]):.6g} with {max_substeps} RK4 steps; refine the grid or loosen `rtol`/`atol`")
        steps[todo] = more_steps(current, ratio[todo], max_substeps)
    return phi, n_evals


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
