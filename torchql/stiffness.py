"""``solver="auto"``: is a model stiff on the data's time span? Decided before the first integration.

An explicit solver's step is bounded by stability where the model has a fast decaying mode
(an eigenvalue of ``df/dx`` with a large negative real part) while the solution itself changes
slowly: the number of steps grows like ``max(-Re lambda) * span``. This module measures that
product along a trajectory that needs no integration, the data themselves: at every observation
time the directly observed states take their measured values and the others their guesses
``x0`` (the coefficients at their guesses), and ``df/dx`` is taken there by ``torch.func.jacrev``.
Robertson kinetics, whose Jacobian at ``(1, 0, 0)`` is mild (``0.04``), shows its ``-2 k2 y2 ~ -2e3``
as soon as a measured ``y2 ~ 4e-5`` enters it: ``2e3 * 1e5 = 2e8``.

A model is stiff when the product exceeds :data:`STIFF_RATIO` (``1e4``: an explicit solver then needs at
least about ``3e3`` steps for stability alone, more than an accurate solution of a non-stiff
problem over a few dozen characteristic times). Oscillations (imaginary eigenvalues) do not count.
"""

from __future__ import annotations

import torch
from torch.func import jacrev, vmap

from .solvers import STIFF_SOLVERS

__all__ = ["STIFF_RATIO", "AUTO", "STIFF_SOLVER", "EXPLICIT_SOLVER", "STIFF_LINEAR_SOLVER", "stiffness_ratio",
           "states_from_data", "choose_solver", "linear_solver_for", "stiff_along"]

#: ``max(-Re lambda) * span`` above which ``solver="auto"`` takes the stiff path.
STIFF_RATIO = 1e4
#: The name that asks for the choice.
AUTO = "auto"
#: What ``"auto"`` takes for a stiff model, and for any other: Hairer's eighth-order DOP853, whose
#: steps at a fit's tight tolerances (``rtol=1e-10``) are several times longer than dopri5's (1,000
#: thesis oscillators: the final pass's batched integration 0.35 s with dopri5, 0.1 s with it).
STIFF_SOLVER, EXPLICIT_SOLVER = "rodas5p", "dop853"
#: The linear propagator a stiff solver gets when none is given.
STIFF_LINEAR_SOLVER = "radau"


def states_from_data(y: torch.Tensor, observed: list, x0: torch.Tensor) -> torch.Tensor:
    """States at the observation times for the test: measured where a state is observed directly.

    ``y (..., T, K)`` data (NaN where missing), ``observed`` the state each output reads directly
    (``None`` otherwise), ``x0 (..., n)`` guesses. Returns ``(..., T, n)``.
    """
    x = x0.unsqueeze(-2).expand(*y.shape[:-1], x0.shape[-1]).clone()
    for k, i in enumerate(observed):
        if i is not None:
            column = y[..., k]
            x[..., i] = torch.where(torch.isnan(column), x[..., i], column)
    return x


def stiffness_ratio(system, t: torch.Tensor, x: torch.Tensor, p: torch.Tensor, span: torch.Tensor) -> torch.Tensor:
    """``max over t of max(-Re eig(df/dx)) * span`` for each sample.

    Parameters
    ----------
    system : AugmentedSystem
    t : Tensor ``(T,)`` or ``(S, T)``
        Times of the states.
    x : Tensor ``(S, T, n)``
        States (e.g. :func:`states_from_data`).
    p : Tensor ``(S, P)``
        Coefficients (the unknowns at their guesses).
    span : Tensor ``()`` or ``(S,)``
        Length of each sample's time span.

    Returns
    -------
    Tensor ``(S,)``: 0 where the Jacobian is not finite (the choice then stays explicit).
    """
    S, T, n = x.shape
    times = t.expand(S, T) if t.dim() == 1 else t
    z = torch.cat([x, p.unsqueeze(1).expand(S, T, p.shape[-1])], dim=-1).reshape(S * T, -1)
    with torch.no_grad():
        jac = vmap(jacrev(system.f, argnums=1))(times.reshape(-1), z)[:, :n, :n]
        finite = torch.isfinite(jac).flatten(1).all(dim=1)
        jac = torch.where(finite.reshape(-1, 1, 1), jac, torch.zeros_like(jac))
        decay = (-torch.linalg.eigvals(jac).real).clamp(min=0).amax(dim=-1).reshape(S, T)
    return decay.amax(dim=1) * span.to(decay.dtype).abs()


def stiff_along(jac: torch.Tensor, n: int, span: torch.Tensor) -> torch.Tensor:
    """Whether each sample's model is stiff along a trajectory, by the test of :func:`choose_solver`:
    its fastest decay rate times ``span (S,)`` above :data:`STIFF_RATIO`, at the nodes where the
    Jacobians ``jac (S, G, N, N)`` are given (``N >= n``: the first ``n`` rows and columns, the
    states', count). Bool ``(S,)``; False where they are not finite.

    The engine asks it at the observation times of every accepted iterate of a fit on ``"auto"``'s
    explicit solver, as :func:`choose_solver` asks along the data: a
    fitted relaxation rate of 1e4 from a guess of 1 (``tests/test_engine_run.py``) is stiff at the
    iterates though not at the guesses, and at the fit's tolerance DOP853's steps there are held at
    ``h |lambda|`` of 1.3 to 3.5, below its stiffness test's bound. The eigenvalues are computed
    only at the nodes whose Gershgorin bound on the decay rates (the largest ``-a_ii + sum_{j != i}
    |a_ij|`` over the rows) reaches the ratio: at none for a model that is not stiff."""
    A = jac[..., :n, :n]
    S = A.shape[0]
    rate = span.to(A.dtype).abs().reshape(S, 1)
    with torch.no_grad():
        rows = A.abs().sum(dim=-1)  # each row's sum bounds its Gershgorin bound: most models end here
        if float(rows.amax()) * float(rate.amax()) <= STIFF_RATIO:
            return torch.zeros(S, dtype=torch.bool, device=A.device)
        bound = (rows - A.diagonal(dim1=-2, dim2=-1).abs() - A.diagonal(dim1=-2, dim2=-1)).amax(dim=-1)
        nodes = (bound * rate > STIFF_RATIO) & torch.isfinite(A).flatten(2).all(dim=-1)  # (S, G)
        stiff = torch.zeros(S, dtype=torch.bool, device=A.device)
        if bool(nodes.any()):
            sample, node = nodes.nonzero(as_tuple=True)
            decay = (-torch.linalg.eigvals(A[sample, node]).real).amax(dim=-1)
            stiff[sample[decay * rate[sample, 0] > STIFF_RATIO]] = True
    return stiff


def choose_solver(solver: str, system, t: torch.Tensor, y: torch.Tensor, observed: list, x0: torch.Tensor,
                  p: torch.Tensor, span: torch.Tensor, explicit: str | None = None
                  ) -> tuple[str, torch.Tensor | None]:
    """``solver`` itself, or for :data:`AUTO` the solver the data call for: :data:`STIFF_SOLVER` when
    some sample's :func:`stiffness_ratio` along its data exceeds :data:`STIFF_RATIO`, else
    ``explicit`` (default :data:`EXPLICIT_SOLVER`); with the samples found stiff, bool ``(S,)``
    (None for a ``solver`` given). ``y (S, T, K)`` (NaN where missing), ``x0 (S, n)`` and ``p (S,
    P)`` guesses, ``t`` and ``span`` as :func:`stiffness_ratio` takes them."""
    if solver != AUTO:
        return solver, None
    stiff = stiffness_ratio(system, t, states_from_data(y, observed, x0), p, span) > STIFF_RATIO
    return (STIFF_SOLVER if bool(stiff.any()) else explicit or EXPLICIT_SOLVER), stiff


def linear_solver_for(solver: str, linear_solver, default: str):
    """The ``linear_solver`` given, or when it is ``None``: :data:`STIFF_LINEAR_SOLVER` for a stiff
    ``solver``, else ``default``."""
    if linear_solver is not None:
        return linear_solver
    return STIFF_LINEAR_SOLVER if solver in STIFF_SOLVERS else default
