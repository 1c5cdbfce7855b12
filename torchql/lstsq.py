"""The alpha update: weighted least squares with exactly-met rows, by orthogonal factorizations.

Solves ``min || W (C alpha - d) ||`` over the least-squares rows subject to
``C_e alpha = d_e`` on the exact rows (equality-constrained least squares, null-space method):

1. Columns are scaled to unit norm (the problem's conditioning then does not depend on the
   units of the unknowns).
2. ``C_e^T = Q R`` (QR); ``alpha = Q_1 R^{-T} d_e + Q_2 beta`` satisfies the exact rows for
   every ``beta``.
3. ``beta`` minimizes the remaining weighted residual, by SVD (rank revealing, never the
   normal equations).

Singular values below ``rcond`` times the largest are treated as zero: the update is then the
minimum-norm one and the problem is reported rank deficient.

Levenberg–Marquardt damping ``lambda`` (relative to the largest singular value squared) solves
``min ||A beta - b||^2 + lambda S_0^2 ||beta||^2`` in the column-scaled unknowns by filter factors
on the same SVD: ``beta = V diag(S / (S^2 + lambda S_0^2)) U^T b``. ``lambda = 0`` is the plain
Gauss–Newton (Kantorovich) update; a large ``lambda`` shortens the step and turns it toward the
scaled steepest descent.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

__all__ = ["LstsqSolution", "ExactRowsError", "solve_update", "solve_update_batch", "relative_spectrum",
           "exact_multipliers"]


class ExactRowsError(ValueError):
    """The exactly-met observations are linearly dependent or contradict each other."""


class LstsqSolution(NamedTuple):
    """Result of :func:`solve_update`.

    Attributes
    ----------
    alpha : Tensor ``(m,)``
        The update of the unknowns.
    singular_values : Tensor ``(r,)``
        Singular values of the column-scaled weighted least-squares matrix (after eliminating
        the exact rows), in decreasing order.
    rank_deficient : bool
        Whether some singular value fell below ``rcond`` times the largest.
    null_vectors : Tensor ``(m, k)``
        Unit directions (in the unknowns' own units) that the data cannot determine.
    multipliers : Tensor ``(e,)``
        The Lagrange multipliers ``nu`` of the ``e`` exact rows (in their order; empty without):
        ``2 A^T (A alpha - b) + E^T nu = 0`` for the weighted rows ``A, b`` and the weighted exact
        rows ``E``, so ``|nu_i|`` is the rate at which the least-squares part's optimum changes
        per unit of exact row ``i``'s weighted misfit (see :func:`exact_multipliers`).
    """

    alpha: torch.Tensor
    singular_values: torch.Tensor
    rank_deficient: bool
    null_vectors: torch.Tensor
    multipliers: torch.Tensor | None = None


def solve_update(C: torch.Tensor, d: torch.Tensor, weights: torch.Tensor, exact: torch.Tensor,
                 rcond: float, damping: float = 0.0) -> LstsqSolution:
    """Solve for ``alpha``.

    Parameters
    ----------
    C : Tensor ``(L, m)``
        Sensitivities of the observations to the unknowns (unweighted).
    d : Tensor ``(L,)``
        Residuals ``data - prediction`` (unweighted).
    weights : Tensor ``(L,)``
        ``1 / sigma`` per row.
    exact : bool Tensor ``(L,)``
        Rows to satisfy exactly.
    rcond : float
        Relative singular-value threshold for rank decisions.
    damping : float
        Levenberg–Marquardt parameter ``lambda`` relative to the largest singular value squared
        (``>= 0``). The step toward the exact rows is shortened by ``1 / (1 + lambda)``, as the
        damping shortens the best-determined direction of the data (an exact row is a row of
        unbounded weight, whose relative squared singular value tends to one); the data's part is
        damped as usual. ``lambda = 0`` meets the exact rows; every damped step meets the fraction
        ``1 / (1 + lambda)`` of their misfit, so that a large damping shortens the whole step.

    Returns
    -------
    LstsqSolution
    """
    m = C.shape[1]
    Cw = C * weights.unsqueeze(-1)
    dw = d * weights
    scale = torch.linalg.vector_norm(Cw, dim=0)
    zero_cols = scale == 0
    scale = torch.where(zero_cols, torch.ones_like(scale), scale)
    Cs = Cw / scale
    alpha_s = torch.zeros(m, dtype=C.dtype, device=C.device)

    A, b = Cs[~exact], dw[~exact]
    A0, b0, R1, Q1, P = A, b, None, None, None
    basis = torch.eye(m, dtype=C.dtype, device=C.device)
    E = Cs[:0]
    if bool(exact.any()):
        E, e, P = _independent_exact_rows(Cs[exact], dw[exact], dw, rcond)
    if E.shape[0]:
        Q, R = torch.linalg.qr(E.T, mode="complete")
        k = E.shape[0]
        R1 = R[:k, :k]
        y1 = torch.linalg.solve_triangular(R1.T, e.unsqueeze(-1), upper=False).squeeze(-1)
        Q1 = Q[:, :k]
        alpha_s = Q1 @ y1 / (1.0 + damping)
        basis = Q[:, k:]
        b = b - A @ alpha_s
        A = A @ basis

    if A.shape[1] == 0 or A.shape[0] == 0:
        sv = torch.zeros(0, dtype=C.dtype, device=C.device)
        deficient = A.shape[1] > 0
        null = basis / scale.unsqueeze(-1) if deficient else torch.zeros(m, 0, dtype=C.dtype, device=C.device)
        return LstsqSolution(alpha_s / scale, sv, deficient or bool(zero_cols.any()), _normalize(null),
                             _per_row(exact_multipliers(A0, b0, alpha_s, Q1, R1), P))
    U, S, Vh = torch.linalg.svd(A, full_matrices=True)
    r = S.shape[0]
    keep = S > rcond * S[0] if r else S > 0
    safe = torch.where(keep, S, torch.ones_like(S))
    if damping > 0 and r:
        safe = safe + damping * S[0] ** 2 / safe
    coeff = torch.where(keep, (U[:, :r].T @ b) / safe, torch.zeros_like(S))
    beta = Vh[:r].T @ coeff
    alpha_s = alpha_s + basis @ beta
    deficient = bool((~keep).any()) or A.shape[0] < A.shape[1] or bool(zero_cols.any())
    dropped = torch.cat([Vh[:r][~keep], Vh[r:]], dim=0).T  # (cols of A, k)
    null = basis @ dropped / scale.unsqueeze(-1)
    return LstsqSolution(alpha_s / scale, S, deficient, _normalize(null),
                         _per_row(exact_multipliers(A0, b0, alpha_s, Q1, R1), P))


def _independent_exact_rows(E: torch.Tensor, e: torch.Tensor, dw: torch.Tensor, rcond: float
                            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Exact rows ``E (k, m)`` (scaled) with values ``e (k,)`` as independent constraints ``P^T E
    (r, m)``, ``P^T e (r,)`` meeting the same values: ``E`` itself (``P`` None, the identity) where
    its rows are independent; where they are dependent but consistent (``e`` in ``E``'s range to
    ``sqrt(eps)`` of the largest weighted value ``dw``: an exact value on an initial state held
    fixed at it, whose row is zero, or one value marked twice), the combinations of its rows along
    its ``r`` principal directions, ``P (k, r)`` (multipliers ``nu`` of the combinations are ``P nu``
    of the rows). Raises :class:`ExactRowsError` where they contradict each other."""
    k, m = E.shape
    if k <= m:
        diag = torch.diagonal(torch.linalg.qr(E.T, mode="r")[1]).abs()
        if not bool((diag <= rcond * max(diag.max().item(), 1.0)).any()):
            return E, e, None
    U, S, _ = torch.linalg.svd(E, full_matrices=False)
    r = int((S > rcond * max(S.max().item() if S.numel() else 0.0, 1.0)).sum())
    misfit = torch.linalg.vector_norm(e - U[:, :r] @ (U[:, :r].T @ e))
    scale = max(float(dw.abs().max()) if dw.numel() else 0.0, torch.finfo(E.dtype).tiny)
    if r > m or float(misfit) > math.sqrt(torch.finfo(E.dtype).eps) * scale:
        raise ExactRowsError(
            "the observations marked `exact` are linearly dependent or contradictory at the current "
            "iterate: they cannot all be met exactly; mark fewer values exact"
        )
    P = U[:, :r]
    return P.T @ E, P.T @ e, P


def _per_row(nu: torch.Tensor, P: torch.Tensor | None) -> torch.Tensor:
    """The multipliers ``(k,)`` of the ``k`` exact rows from ``nu (r,)`` of their independent
    combinations (:func:`_independent_exact_rows`' ``P (k, r)``; None: the rows themselves). With
    no combination left (``r = 0``), ``P @ nu`` is zero."""
    return nu if P is None else P @ nu


def exact_multipliers(A: torch.Tensor, b: torch.Tensor, alpha: torch.Tensor, Q1: torch.Tensor | None,
                      R1: torch.Tensor | None) -> torch.Tensor:
    """The multipliers ``nu (e,)`` of exact rows ``E`` with ``E^T = Q1 R1`` (``Q1 (m, e)``, ``R1 (e,
    e)``; None: no exact rows, ``nu`` empty) at the step ``alpha (m,)`` of the rows ``A (L, m)``,
    ``b (L,)``: ``nu = -2 R1^{-1} Q1^T A^T (A alpha - b)``, the least-squares solution of the
    stationarity condition ``2 A^T (A alpha - b) + E^T nu = 0`` (exact for the undamped step).
    Column scaling of ``A`` and ``E`` alike leaves ``nu`` unchanged: it is per unit of the exact
    rows' (weighted) values."""
    if Q1 is None:
        return alpha.new_zeros(0)
    g = A.T @ (A @ alpha - b)
    return -2 * torch.linalg.solve_triangular(R1, (Q1.T @ g).unsqueeze(-1), upper=True).squeeze(-1)


def _normalize(vectors: torch.Tensor) -> torch.Tensor:
    if vectors.shape[1] == 0:
        return vectors
    return vectors / torch.linalg.vector_norm(vectors, dim=0, keepdim=True).clamp_min(torch.finfo(vectors.dtype).tiny)


def solve_update_batch(C, d, w, rcond: float, damping):
    """Batched weighted least squares by SVD with Levenberg–Marquardt filter factors.

    ``C (S, R, m)``, ``d (S, R)``, weights ``w (S, R)`` (0 for missing values), ``damping (S,)``
    relative to the largest squared singular value (or ``None``). Returns ``alpha (S, m)``,
    ``deficient (S,)`` (a singular value below ``rcond`` times the largest, or a zero column)
    and the singular values ``(S, m)``. Samples with non-finite rows get NaN.
    """
    A, dw, scale, finite, zero_cols = _scaled_problem(C, d, w)
    U, Sv, Vh = torch.linalg.svd(A, full_matrices=False)
    keep = Sv > rcond * Sv[:, :1]
    safe = torch.where(keep, Sv, torch.ones_like(Sv))
    if damping is not None:
        safe = safe + damping.unsqueeze(-1) * Sv[:, :1] ** 2 / safe
    coeff = torch.where(keep, (U.transpose(1, 2) @ dw.unsqueeze(-1)).squeeze(-1) / safe, torch.zeros_like(Sv))
    alpha = (Vh.transpose(1, 2) @ coeff.unsqueeze(-1)).squeeze(-1) / scale
    alpha = torch.where(finite.unsqueeze(-1), alpha, torch.full_like(alpha, float("nan")))
    deficient = (~keep).any(dim=1) | zero_cols.any(dim=1)
    return alpha, deficient, Sv


def _scaled_problem(C, d, w):
    """The weighted least-squares problems of :func:`solve_update_batch` with unit columns: ``A (S,
    R, m)``, ``dw (S, R)``, the column norms ``(S, m)`` (1 for a zero column), which samples are
    finite ``(S,)`` (the others zeroed) and the zero columns ``(S, m)``."""
    Cw = C * w.unsqueeze(-1)
    dw = d * w
    finite = torch.isfinite(Cw).flatten(1).all(dim=1) & torch.isfinite(dw).all(dim=1)
    Cw = torch.where(finite.reshape(-1, 1, 1), Cw, torch.zeros_like(Cw))
    dw = torch.where(finite.reshape(-1, 1), dw, torch.zeros_like(dw))
    scale = torch.linalg.vector_norm(Cw, dim=1)
    zero_cols = scale == 0
    scale = torch.where(zero_cols, torch.ones_like(scale), scale)
    return Cw / scale.unsqueeze(1), dw, scale, finite, zero_cols


def relative_spectrum(C: torch.Tensor, w: torch.Tensor, rcond: float) -> torch.Tensor:
    """``(s_i / s_max)^2``, ``(S, m)``, of the matrices :func:`solve_update_batch` damps (``C (S, R,
    m)`` weighted by ``w (S, R)``, unit columns): the damping ``lambda`` scales direction ``i`` of
    the step by ``r_i / (r_i + lambda)``. NaN for the directions it drops (below ``rcond``)."""
    A = _scaled_problem(C, torch.zeros_like(w), w)[0]
    Sv = torch.linalg.svdvals(A)
    r = (Sv / Sv[:, :1].clamp(min=torch.finfo(Sv.dtype).tiny)) ** 2
    return torch.where(Sv > rcond * Sv[:, :1], r, torch.full_like(r, float("nan")))
