"""The bounded least-squares update: which bounded unknowns a step holds, and which it lets go.

The update is solved for the bounds' internal variables ``q`` (:class:`torchql.bounds.Bounds`);
an unknown that the solution pushes onto its bound, or whose internal step is capped, is held at
that move while the others are re-solved. Held on the strength of the first, unconstrained solve
alone, an unknown can be held wrongly: the others' free moves may be what pushed it outward. At
an unknown one rounding inside its bound, its column (``du/dq``, about ``1e-16``) makes the
bound a false stationary point, and the iteration converges on it although the data pull the
unknown inside (a Lotka–Volterra rate held at its upper bound with the sum of squares 42 %
above the bounded optimum). As in an active-set method, an unknown held on its bound whose
descent direction at the re-solved step points inside (the multiplier of its bound has the
wrong sign) is released and the others are re-solved with it free, until none is.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from .bounds import Bounds

__all__ = ["bounded_update"]

#: ``solve(rows, C, d, w) -> (alpha (R, m), infeasible (R,), nu (R,))``: the damped least squares of
#: the samples at positions ``rows`` of the batch (columns ``C (R, L, m)``, misfits ``d (R, L)``,
#: weights ``w (R, L)``).
Solve = Callable[[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor], tuple]


def bounded_update(bounds: Bounds, solve: Solve, C: torch.Tensor, d: torch.Tensor, w: torch.Tensor,
                   u: torch.Tensor):
    """The update of unknowns ``u (S, m)`` under ``bounds`` for columns ``C (S, L, m)`` (of ``u``),
    misfits ``d (S, L)`` and weights ``w (S, L)``.

    The unknowns that a solution pushes onto their bound (or toward it by a capped step) are held
    there and the others re-solved; those held whose descent direction then points inside are let
    go; until neither changes. Last, unknowns whose free step leaves a bound by more than the
    largest internal move are held at that capped move, and the others re-solved once.

    Returns ``(alpha, capped, infeasible, nu)``: the change of ``u`` ``(S, m)`` (strictly inside the
    bounds), the unknowns whose internal step was capped ``(S, m)``, the samples whose exact values
    cannot be met ``(S,)`` and their exact rows' largest multiplier ``(S,)`` (of the first solve).
    """
    S, m = u.shape
    Cq = bounds.internal_columns(C, u)
    alpha_q, infeasible, nu = solve(torch.arange(S, device=u.device), Cq, d, w)
    alpha, pinned, capped = _mapped(bounds, u, alpha_q)
    held = torch.zeros_like(pinned)
    rows = (pinned.any(dim=1) & ~infeasible).nonzero().flatten()
    for _ in range(2 * m + 1):  # every round holds or lets go at least one unknown
        if not rows.numel():
            break
        held[rows] |= pinned[rows]
        rest, pinned[rows], cap, stuck = _resolve(bounds, solve, Cq, C, d, w, u, alpha, held, rows)
        infeasible[rows] |= stuck
        alpha[rows] = torch.where(held[rows], alpha[rows], rest)
        capped[rows] = torch.where(held[rows], capped[rows], cap)
        release = (held[rows] & ~pinned[rows].any(dim=1, keepdim=True)
                   & _pulled_inside(bounds, C[rows], d[rows], w[rows], u[rows], alpha[rows]))
        held[rows] &= ~release
        rows = rows[(pinned[rows].any(dim=1) | release.any(dim=1)) & ~infeasible[rows]]
    leaving = capped & ~held & bounds.away(u, alpha)  # held at their capped move, the others re-solved once
    rows = (leaving.any(dim=1) & ~infeasible).nonzero().flatten()
    if rows.numel():
        held |= leaving
        rest, _, _, stuck = _resolve(bounds, solve, Cq, C, d, w, u, alpha, held, rows)
        infeasible[rows] |= stuck
        alpha[rows] = torch.where(held[rows], alpha[rows], rest)
    return alpha, capped, infeasible, nu


def _mapped(bounds: Bounds, u: torch.Tensor, alpha_q: torch.Tensor):
    """The change of ``u (R, m)`` by internal steps ``alpha_q (R, m)`` (capped, strictly inside);
    the unknowns it pins (pushed onto their bound, or toward it by a capped step); the capped ones."""
    change, blocked = bounds.step(u, alpha_q)
    capped = bounds._capped(alpha_q, u)
    return change, blocked & ~(capped & bounds.away(u, change)), capped


def _resolve(bounds, solve, Cq, C, d, w, u, alpha, held, rows):
    """The samples ``rows`` re-solved with their unknowns ``held (S, m)`` at their moves ``alpha (S,
    m)``: ``(rest, pinned, capped, stuck)``, the others' changes ``(R, m)``, which of them it pins
    and caps (as :func:`_mapped`), and the samples whose exact values cannot be met ``(R,)``."""
    hold = held[rows]
    move = alpha[rows].masked_fill(~hold, 0.0)
    rhs = d[rows] - (C[rows] @ move.unsqueeze(-1)).squeeze(-1)
    rest_q, stuck, _ = solve(rows, Cq[rows].masked_fill(hold.unsqueeze(1), 0.0), rhs, w[rows])
    rest, pinned, capped = _mapped(bounds, u[rows], rest_q.masked_fill(hold, 0.0))
    return rest, pinned & ~hold, capped & ~hold, stuck


def _pulled_inside(bounds: Bounds, C, d, w, u, alpha) -> torch.Tensor:
    """Bool ``(R, m)``: the unknowns whose descent direction of the linear problem's weighted sum of
    squares ``|w (C alpha - d)|^2`` at the step ``alpha`` points away from their nearer bound."""
    left = (C @ alpha.unsqueeze(-1)).squeeze(-1) - d
    gradient = torch.einsum("rlm,rl->rm", C, w.square() * left)
    return bounds.away(u, -gradient)
