"""Every grid interval's transfer at once, from the Taylor series of its solution.

Between two grid nodes the reference ``z``, ``h f`` and ``h A`` are Hermite interpolants,
polynomials in the local time ``s`` in ``[0, 1]``: cubic (the default propagator), or, for ``z``
and ``h f``, quintic (:mod:`torchql.propagators.quintic`); so is the forcing ``h B = h f - h A z``
(of degree 6, or 8). The interval's transfer ``T(s) = [[Phi(s), c(s)], [0, 1]]`` solves
``T' = X(s) T``, ``T(0) = I``, with ``X = [[h A, h B], [0, 0]]`` a polynomial, so its Taylor coefficients
follow exactly from the recurrence

    ``(k + 1) T_{k+1} = sum_i X_i T_{k-i}``,

no coefficient is ever evaluated at a point, and the series converges for every ``s`` (the
solution is entire). Only the rows of the components that change (the "active" ones) are
stored; ``T_k`` for ``k >= 1`` is zero elsewhere, so a product ``X_i T_j`` needs only the
active-by-active block ``A_aa`` of ``h A``.

**Truncation, bounded rather than estimated.** ``X_k`` is zero past the forcing's degree ``d`` (6
or 8), and ``h A`` is cubic, so once ``T_1 .. T_K`` (``K > d``) are summed, the remainder
``R(s) = sum_{k>K} T_k s^k`` solves ``R' = A_aa R + g`` with ``R(0) = 0``, where ``g`` is the part of
degree ``K .. K+3`` of ``A_aa`` times the terms summed, known from the last four of them. With
``rho = sum_i ||A_aa,i||_inf`` (a bound on ``||h A_aa(s)||`` over the interval), Gronwall's
inequality bounds ``||R(1)||`` column by column (:func:`_tail_weights`). The series is summed
until that bound is within the tolerance of every entry, interval by interval: each interval keeps
the sum at its own first passing test, so the result does not depend on which intervals are summed
together. The one error left is rounding.

**Substeps.** An interval with ``rho > RHO_MAX`` is split into ``n`` equal substeps (a power of
two, ``rho / n <= RHO_MAX``): the series' terms then decrease from the start, so rounding does
not grow by cancellation (at most by ``e^RHO_MAX``), and the substeps' transfers are composed by
products. Each substep gets ``1 / n`` of the interval's tolerance. The polynomial coefficients of
a substep are those of the interval shifted and scaled exactly (one square matrix per substep
acting on the interval's power-basis coefficients).

Compared with the RK4 step doubling of :mod:`torchql.transfer` (which evaluates the
coefficients at ``4 n + 1`` points and forms ``3 n`` step propagators per interval), a smooth
interval (``rho`` of a few hundredths) costs 8 or 9 terms, each a handful of elementwise
products over all intervals at once, and its error is bounded.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import torch

from .budget import check_time
from .integrate import IntegrationError
from .trajectory import IntervalSystem
from .transfer import Transfers, _Coefficients, _product

__all__ = ["RHO_MAX", "SeriesTransfers", "series_transfers", "taylor_transfers"]

#: Largest ``||h A||`` bound of one substep: larger intervals are split into substeps.
RHO_MAX = 1.0
#: Most series terms on one substep (with ``rho <= RHO_MAX`` about 20 reach double precision).
_MAX_TERMS = 48
#: Most interval-substeps integrated in one batch (larger batches cost fewer Python dispatches,
#: smaller ones stay in cache; 2^14 was the fastest of 2^11 .. 2^17 on 10^5 intervals).
_CHUNK = 1 << 14
#: Degree of the interpolant of ``h A`` (cubic Hermite) in local time.
_HERMITE_DEGREE = 3


class SeriesTransfers(NamedTuple):
    """Active rows of every interval's transfer, and how they were obtained.

    Attributes
    ----------
    Y : Tensor ``(a, M+1, N)``
        Active rows of ``T_j``, columns in the stored order (see :class:`torchql.transfer.Transfers`).
    failed : bool Tensor ``(N,)``
        Intervals whose series did not meet the tolerance within ``max_substeps`` substeps, or
        that are not finite.
    substeps : Tensor ``(N,)`` of int
        Substeps used on each interval.
    passes : int
        Series terms computed, each one a pass over all the interval-substeps of a batch.
    points : int
        Series terms computed, counted per interval-substep.
    """

    Y: torch.Tensor
    failed: torch.Tensor
    substeps: torch.Tensor
    passes: int
    points: int


def _forcing_degree(degree: int, jacobian_degree: int = _HERMITE_DEGREE) -> int:
    """Degree of the forcing ``h B = h f - h A z`` when ``z`` and ``h f`` have ``degree`` and ``h A``
    has ``jacobian_degree``; the terms up to it are summed before the truncation bound is first
    tested (it holds from the first term without forcing on; testing costs about as much as a term)."""
    return degree + jacobian_degree


def _substep_matrices(n: int, dtype: torch.dtype, device: torch.device, degree: int = 3) -> torch.Tensor:
    """``W (n, D, D)``, ``D = degree + 1``: ``W[m, k, j]`` is the coefficient of ``sigma^j`` of ``s^k``
    at ``s = (m + sigma) / n``.

    So a polynomial ``sum_k c_k s^k`` is ``sum_j (sum_k c_k W[m, k, j]) sigma^j`` on substep ``m``.
    """
    return _shift_table(n, degree).to(dtype=dtype, device=device, copy=True)  # (the cached table stays as built)


@functools.lru_cache(maxsize=64)
def _shift_table(n: int, degree: int) -> torch.Tensor:
    """:func:`_substep_matrices` in float64 on the CPU, built once per ``(n, degree)``: a loop of
    ``n (degree + 1)^2`` Python steps, which at 1,024 substeps had cost more than the series they
    shift (4.5 of 13.5 s of an SIR fit whose rejected trials needed that many)."""
    shift = torch.zeros(n, degree + 1, degree + 1, dtype=torch.float64)
    for m in range(n):
        for k in range(degree + 1):
            for j in range(k + 1):
                shift[m, k, j] = math.comb(k, j) * (m / n) ** (k - j) * (1.0 / n) ** j
    return shift


def _monomials(data: torch.Tensor, M: int, n: int) -> torch.Tensor:
    """Power-basis coefficients ``(D, Q, n I)`` of the ``n`` substeps of every interval, substep-major.

    ``data (D, Q, I)``: the intervals' power-basis coefficients (:class:`torchql.transfer._Coefficients`),
    returned as they are for one substep. For more, each substep's are those of the interval
    shifted and scaled exactly, and the rows of ``h f`` and ``h A`` (all but the first ``M``) are
    divided by ``n``, the substep's length.
    """
    if n == 1:
        return data
    D, Q, I = data.shape
    W = _substep_matrices(n, data.dtype, data.device, D - 1)  # (n, D, D)
    mono = (W.permute(0, 2, 1).reshape(D * n, D) @ data.reshape(D, Q * I)).reshape(n, D, Q, I)
    out = mono.permute(1, 2, 0, 3).reshape(D, Q, n * I)
    out[:, M:] /= n
    return out


def _active_block(mono: torch.Tensor, a: int, M: int, jacobian_degree: int) -> torch.Tensor:
    """``|A_aa,k| (d + 1, a, a, J)``: the active-by-active block of ``h A``'s power-basis coefficients
    ``k = 0 .. d`` (``d = jacobian_degree``), entry by entry in absolute value."""
    return mono[:jacobian_degree + 1, M:].unflatten(1, (a, M + 1))[:, :, 1:1 + a].abs()


def _norms(mono: torch.Tensor, a: int, M: int, jacobian_degree: int = _HERMITE_DEGREE,
           scale: torch.Tensor | None = None) -> torch.Tensor:
    """``||A_aa,k||_inf (d + 1, J)`` per interval-substep, from power-basis coefficients ``(D, Q, J)``
    (``h A``'s degrees above ``d = jacobian_degree`` are zero), in the norm of the states scaled by
    ``scale (a, J)`` (:func:`_balance`; default none): ``||S^-1 A_aa,k S||_inf``, ``S = diag(scale)``.

    Their sum ``rho`` bounds ``||h A_aa(s)||`` on the substep in that norm.
    """
    A_aa = _active_block(mono, a, M, jacobian_degree)
    if scale is not None:
        A_aa = A_aa * (scale.unsqueeze(0) / scale.unsqueeze(1))
    return A_aa[:, 0, 0] if a == 1 else A_aa.sum(dim=2).amax(dim=1)


def _balance(mono: torch.Tensor, a: int, M: int, jacobian_degree: int = _HERMITE_DEGREE,
             sweeps: int = 4) -> torch.Tensor:
    """Scales ``(a, J)`` of the active states, powers of two, that balance ``sum_k |A_aa,k|`` per
    interval (Osborne's iteration, as LAPACK's ``gebal``: each state's off-diagonal row and
    column sums made alike).

    The bound ``rho`` of :func:`_norms` is that of one norm; a diagonal similarity leaves the
    series' sums as they are but not the norm, which for states of very different magnitudes
    (an oscillator in microseconds: ``h A = [[0, h], [-h omega^2, ..]]`` with ``h omega^2`` in the
    thousands where ``h omega`` is a tenth) overstates the growth by orders of magnitude, and
    with it the substeps and the truncation bound. Powers of two scale without rounding.
    """
    A = _active_block(mono, a, M, jacobian_degree).sum(dim=0)  # (a, a, J)
    A = A * (1 - torch.eye(a, dtype=A.dtype, device=A.device)).unsqueeze(-1)  # the diagonal is invariant
    scale = torch.ones(a, A.shape[-1], dtype=A.dtype, device=A.device)
    for _ in range(sweeps):
        for i in range(a):
            rows, columns = A[i].sum(dim=0), A[:, i].sum(dim=0)
            ok = (rows > 0) & (columns > 0) & torch.isfinite(rows) & torch.isfinite(columns)
            f = torch.where(ok, torch.exp2(torch.round(0.5 * torch.log2(rows / columns))), torch.ones_like(rows))
            f = torch.where(torch.isfinite(f), f, torch.ones_like(f))
            scale[i] = scale[i] * f
            A[i] = A[i] / f
            A[:, i] = A[:, i] * f
    return scale


def _series(mono: torch.Tensor, a: int, M: int, n: int, rtol: float, atol: float, r: torch.Tensor | None = None,
            jacobian_degree: int = _HERMITE_DEGREE, scale: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Transfers ``(a, M+1, J)`` of substeps from their power-basis coefficients ``(D, Q, J)``
    (``z`` and ``h f`` of degree ``D - 1``, ``h A`` of degree ``jacobian_degree``: 3 or 5).

    ``r (d + 1, J)``: the norms ``||A_aa,i||_inf`` of the coefficients, if already at hand (:func:`_norms`),
    in the norm of the states scaled by ``scale (a, J)`` (:func:`_balance`; default unscaled), in
    which the truncation bound is then taken, entry by entry scaled back.

    Returns the active rows, the ratio of the truncation bound to the tolerance ``(J,)`` (the
    substep's share ``1 / n`` of it) and the number of terms summed.
    """
    P = M + 1
    degree = mono.shape[0] - 1
    dA = jacobian_degree
    forcing_degree = _forcing_degree(degree, dA)
    z = mono[:, :M]  # (D, M, J)
    fA = mono[:, M:].unflatten(1, (a, P))  # (D, a, P, J): column 0 = h f, then h A
    F, A = fA[:, :, 0], fA[:, :, 1:]
    A_aa = A[:, :, :a]
    # the forcing h B = h f - h A z, a polynomial of degree forcing_degree
    B = F.new_zeros(forcing_degree + 1, a, F.shape[-1])
    B[:degree + 1] = F
    for i in range(dA + 1):
        B[i:i + degree + 1] -= (A[i].unsqueeze(0) * z.unsqueeze(1)).sum(dim=2)
    if r is None:
        r = _norms(mono, a, M, dA, scale)
    rows_scale = None if scale is None else scale.unsqueeze(1)  # (a, 1, J)
    growth = r.sum(dim=0).exp()  # e^rho, rho = sum_i ||A_aa,i|| >= ||A_aa(s)|| on the substep
    eye = torch.eye(a, P, dtype=mono.dtype, device=mono.device).unsqueeze(-1)
    # the views a term's products read, taken once (a term is a few dozen small kernels: on a
    # single fit's intervals their dispatch, not the arithmetic, is its cost): A_aa's columns
    # (a, 1, J) by degree, and each recent term's rows (1, P, J), with its column norms (P, J)
    columns = [[A_aa[i, :, c].unsqueeze(1) for c in range(a)] for i in range(dA + 1)]
    first = torch.cat([A[0], B[0].unsqueeze(1)], dim=1)  # T_1
    recent = [_rows(first)]  # the last dA + 1 terms' rows and norms, newest last
    T = eye + first
    result = result_ratio = passed = None
    k = 1  # terms T_1 .. T_k summed
    while True:
        check_time()  # a term costs O(a) products: a long sum must not outlast the fit's budget
        new = columns[0][0] * recent[-1][0][0]  # the products A_i T_{k-i}
        for i in range(min(dA + 1, k)):
            previous, column = recent[-1 - i][0], columns[i]  # T_{k-i}
            for c in range(1 if i == 0 else 0, a):
                new.addcmul_(column[c], previous[c])
        if k <= dA:
            new[:, :M] += A[k]
        if k <= forcing_degree:
            new[:, M] += B[k]
        new /= k + 1
        T += new
        k += 1
        testing = k > forcing_degree + 1  # (< _MAX_TERMS: the cap below always follows a test)
        recent = recent[-dA:] + [_rows(new, norms=k > forcing_degree + 1 - dA, scale=rows_scale)]
        if testing:
            norms = torch.stack([term[1] for term in recent])  # (dA+1, P, J): ||T_{k-dA}||, .., ||T_k|| by column
            weights = _tail_weights(k, r)  # (dA+1, J) in the same order
            tail = (weights.unsqueeze(1) * norms).sum(dim=0) * growth  # (P, J)
            if rows_scale is None:
                share = (atol + rtol * torch.maximum(eye, T.abs())).amin(dim=0) / n  # (P, J)
                ratio = (tail / share).amax(dim=0)
            else:  # the bound of entry (i, c) is scale_i times column c's in the scaled norm
                share = (atol + rtol * torch.maximum(eye, T.abs())) / n  # (a, P, J)
                ratio = (tail * rows_scale / share).amax(dim=(0, 1))
            ratio = ratio.nan_to_num(nan=math.inf)
            # each interval keeps the sum at its own first passing test, so that the result does
            # not depend on which intervals are summed together
            if result is None:
                result, result_ratio, passed = T.clone(), ratio, ratio <= 1
            else:
                take = ~passed
                result = torch.where(take, T, result)
                result_ratio = torch.where(take, ratio, result_ratio)
                passed = passed | (ratio <= 1)
            if k >= _MAX_TERMS or bool(passed.all()):
                return result, result_ratio, k


def _rows(term: torch.Tensor, norms: bool = False,
          scale: torch.Tensor | None = None) -> tuple[list[torch.Tensor], torch.Tensor | None]:
    """A series term ``(a, P, J)``'s rows as the products read them (``(1, P, J)`` each) and, if
    ``norms``, its column norms ``||T_k||_inf (P, J)`` that the truncation bound weighs (of the
    rows divided by ``scale (a, 1, J)``, if given)."""
    rows = [term[c].unsqueeze(0) for c in range(term.shape[0])]
    if not norms:
        return rows, None
    size = term.abs() if scale is None else term.abs() / scale
    return rows, size[0] if term.shape[0] == 1 else size.amax(dim=0)


def _tail_weights(K: int, r: torch.Tensor) -> torch.Tensor:
    """Weights ``(D + 1, J)`` of the last ``D + 1`` terms ``T_{K-D}, .., T_K`` in the bound of the
    series' tail, for ``h A`` of degree ``D`` (``r (D + 1, J)``, 3 or 5).

    The remainder ``R = sum_{k>K} T_k s^k`` solves ``R' = A_aa R + g`` with ``R(0) = 0``, where
    ``g`` collects the degrees ``K .. K+D`` of ``A_aa (sum_{k<=K} T_k s^k)``:
    ``g_{K+j} = sum_{i>=j} A_i T_{K+j-i}`` (``K`` above the forcing's degree: the forcing and
    the constant columns are matched by the terms summed). Gronwall's inequality with
    ``||A_aa(s)|| <= rho`` gives ``||R(1)|| <= e^rho sum_j ||g_{K+j}|| / (K+j+1)``, column by column,
    so ``T_{K-d}`` weighs ``sum_{j<=D-d} ||A_{j+d}|| / (K+j+1)``.
    """
    return _tail_matrix(K, r.dtype, r.device, r.shape[0] - 1) @ r


@functools.lru_cache(maxsize=256)
def _tail_matrix(K: int, dtype: torch.dtype, device: torch.device, dA: int = _HERMITE_DEGREE) -> torch.Tensor:
    """``C (dA + 1, dA + 1)``: the weights of :func:`_tail_weights` are ``C @ r`` (``h A`` of degree ``dA``)."""
    C = torch.zeros(dA + 1, dA + 1, dtype=torch.float64)
    for d in range(dA + 1):
        for j in range(dA + 1 - d):
            C[dA - d, j + d] = 1.0 / (K + j + 1)
    return C.to(dtype=dtype, device=device)


def series_transfers(coefficients: _Coefficients, *, rtol: float, atol: float,
                     max_substeps: int = 1024) -> SeriesTransfers:
    """Transfers of all intervals within the tolerance, failures marked per interval (never raised).

    A sample (``coefficients.samples`` contiguous blocks of intervals) with an interval that would
    need more than ``max_substeps`` fails: its other intervals' series that need substeps are then
    not summed (their ``Y`` is left zero), the work that a sample's failed trial step would waste.

    The error test is the one of an adaptive solver with max-norm, entry by entry on the rows
    of ``[Phi_j | c_j]``: truncation bound ``<= atol + rtol * max(|T(0)|, |T(1)|)``.

    Parameters
    ----------
    coefficients : _Coefficients
        Power-basis coefficients of the ``N`` intervals (see :class:`torchql.transfer._Coefficients`).
    rtol, atol : float
        Tolerances of one interval's transfer.
    max_substeps : int
        Most substeps on one interval (a power of two); an interval that needs more fails.
    """
    if max_substeps < 1 or max_substeps & (max_substeps - 1):
        raise ValueError(f"`max_substeps` must be a power of two; received {max_substeps}")
    data, a, M = coefficients.data, coefficients.a, coefficients.M
    degree = coefficients.jacobian_degree  # of h A
    N = data.shape[-1]
    device = data.device
    Y = data.new_zeros(a, M + 1, N)
    substeps = torch.ones(N, dtype=torch.long, device=device)
    if a == 0 or N == 0:
        return SeriesTransfers(Y, torch.zeros(N, dtype=torch.bool, device=device), substeps, 0, 0)
    pending = torch.zeros(N, dtype=torch.bool, device=device)
    counts = [0, 0]  # passes, points
    scales = None  # (a, N): the states' scales of the intervals balanced (:func:`_balance`), once there are any

    def integrate(mono: torch.Tensor, part, n: int, r: torch.Tensor | None = None) -> None:
        """Sum the series of the intervals ``part`` in ``n`` substeps (``mono``: their coefficients)."""
        scale = None if scales is None else scales[:, part].repeat(1, n)
        T, ratio, terms = _series(mono, a, M, n, rtol, atol, r, degree, scale)
        counts[0] += terms
        counts[1] += terms * mono.shape[-1]
        width = T.shape[-1] // n
        Y[..., part] = T if n == 1 else _product(T.unflatten(-1, (n, width)).permute(2, 0, 1, 3))
        met = ratio.unflatten(0, (n, width)).amax(dim=0) <= 1.0
        if not bool(met.all()):  # only a non-finite interval or one past the term cap
            pending[part] = ~met
            substeps[part] = torch.where(met, substeps[part], 2 * n)

    # one pass over chunks of contiguous intervals (cache-sized): coefficients, substeps, and the
    # series of every interval that needs no substeps, the common case
    for start in range(0, N, _CHUNK):
        part = slice(start, start + _CHUNK)
        mono = data[..., part]  # one substep: the interval's own coefficients
        r = _norms(mono, a, M, degree)
        rho = r.sum(dim=0)
        wide = rho > RHO_MAX
        if a > 1 and bool(wide.any()):  # in the balanced norm, where that is smaller
            scale = _balance(mono, a, M, degree)
            balanced = _norms(mono, a, M, degree, scale)
            better = wide & (balanced.sum(dim=0) < rho)
            if bool(better.any()):
                if scales is None:
                    scales = data.new_ones(a, N)
                scales[:, part] = torch.where(better, scale, scales[:, part])
                r = torch.where(better, balanced, r)
                rho = r.sum(dim=0)
        wanted = torch.ceil(torch.log2((rho / RHO_MAX).clamp(min=1.0))).nan_to_num(nan=62.0, posinf=62.0)
        substeps[part] = 2 ** wanted.clamp(max=62).to(torch.long)
        single = substeps[part] == 1
        if bool(single.all()):
            integrate(mono, part, 1, r)
            continue
        index = single.nonzero().flatten()
        if index.numel():
            integrate(mono[..., index], index + start, 1, r[:, index])
        pending[part] = ~single
    # the rest, by number of substeps
    while bool(pending.any()):
        check_time()
        n = int(substeps[pending].min())
        if n > max_substeps:
            break
        _skip_failed_samples(pending, substeps > max_substeps, coefficients.samples)
        group = (pending & (substeps == n)).nonzero().flatten()
        pending[group] = False
        per_chunk = max(1, _CHUNK // n)
        for start in range(0, group.numel(), per_chunk):
            part = group[start:start + per_chunk]
            integrate(_monomials(data[..., part], M, n), part, n)
    failed = pending | ~torch.isfinite(Y).flatten(0, 1).all(dim=0)
    return SeriesTransfers(Y, failed, substeps, counts[0], counts[1])


def _skip_failed_samples(pending: torch.Tensor, beyond: torch.Tensor, samples: int) -> None:
    """Leave out of ``pending (N,)`` (in place) the intervals of every sample (``samples``
    contiguous blocks) that has an interval ``beyond`` the substeps allowed: that sample's
    transfer fails whatever the others give (its intervals ``beyond`` stay pending: failed)."""
    doomed = (pending & beyond).unflatten(0, (samples, -1)).any(dim=1, keepdim=True)
    if bool(doomed.any()):
        pending.unflatten(0, (samples, -1)).logical_and_(~doomed | beyond.unflatten(0, (samples, -1)))


def taylor_transfers(system: IntervalSystem, *, rtol: float, atol: float, max_substeps: int = 1024,
                     coefficients: _Coefficients | None = None) -> tuple[Transfers, int]:
    """Transfers ``T_j`` of all grid intervals of ``system``, each within the tolerance, by their Taylor series.

    ``coefficients``: the intervals' interpolants (default the cubic Hermite ones of ``system``).
    Returns the transfers and the series terms computed (one term of all the intervals of a
    batch counts one). Raises :class:`~torchql.integrate.IntegrationError` when an interval
    needs more than ``max_substeps`` substeps or its transfer is not finite.
    """
    coefficients = _Coefficients(system) if coefficients is None else coefficients
    out = series_transfers(coefficients, rtol=rtol, atol=atol, max_substeps=max_substeps)
    if bool(out.failed.any()):
        bad = out.failed.nonzero().flatten()
        worst = int(bad[0])
        finite = bool(torch.isfinite(coefficients.data[..., worst]).all()) and bool(torch.isfinite(out.Y[..., worst]).all())
        what = ("needs more than {} substeps (||h A|| too large for the grid)".format(max_substeps) if finite
                else "is not finite (NaN or inf)")
        raise IntegrationError(
            f"the transfer of {bad.numel()} grid interval(s) {what}; first at the interval starting at "
            f"t = {float(system.t_start[worst]):.6g}; refine the grid where the solution changes fast, or use "
            f"`linear_solver='torchdiffeq'`")
    return Transfers(out.Y, coefficients.order), out.passes
