"""Every grid interval's transfer at once: the intervals' coefficients, the step-doubling
integrators' refinement, RK4 transfers, and their composition.

Over the interval ``[t_j, t_{j+1}]`` the quasilinear system ``w' = A(t) w + B(t)`` maps
``w(t_j)`` to ``w(t_{j+1}) = Phi_j w(t_j) + c_j``. On the augmented state ``[w; 1]`` that affine
map is one matrix ``T_j = [[Phi_j, c_j], [0, 1]]`` of size ``(M+1, M+1)``, the value at ``s = 1``
of ``dT/ds = X_j(s) T``, ``T(0) = I``, with ``X_j = [[h_j A_j, h_j B_j], [0, 0]]`` in the local
time ``s`` in ``[0, 1]``.

Classical RK4 applied to a linear system is a matrix polynomial in the coefficients at the
start, middle and end of a step, so its propagator is formed directly (three matrix products a
step). Each interval is integrated with ``n`` and with ``2n`` equal steps (``n = 1`` first); the
two share their coefficient evaluations. Their difference over 15 estimates the error of the
finer one (RK4 is of order 4); the transfer returned is the Richardson extrapolation
``fine + (fine - coarse) / 15`` (order 5), as an embedded pair propagates its higher-order
solution. Intervals whose estimate exceeds the tolerance are integrated again with more steps
(as many as the estimate predicts, a power of two), only those, until all pass or the step
cap is reached.

Every propagator reads the intervals' coefficients from one builder, :func:`interval_coefficients`
(the reference ``z``, ``h f`` and ``h A`` as power-basis polynomials in ``s``, for one reference or
the intervals of many samples side by side), and the step-doubling ones (RK4 here, Radau IIA in
:mod:`torchql.propagators.exponential`) share one refinement, :func:`step_doubling`.

The transfers are composed by a parallel prefix scan (Hillis–Steele doubling):
``ceil(log2(G - 1))`` batched matrix products instead of a loop over the nodes.

Only the rows of the components that change are integrated (coefficients have null equations)
and the interval index is the last, contiguous dimension of every array, so that each
elementwise operation runs over all intervals at once; the small matrix products are written
as broadcast products over the inner index (batched GEMM on 2x2 to 8x8 matrices costs far more
per entry).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from .budget import check_time
from .integrate import IntegrationError
from .linearize import Linearization, SecondLinearization
from .trajectory import IntervalSystem

__all__ = ["Transfers", "DoubledTransfers", "interval_coefficients", "interval_transfers", "rk4_series", "step_doubling",
           "prefix_products", "compose_transfers"]

#: Largest number of interval-steps integrated in one batch (bounds the memory of refinement).
_CHUNK = 1 << 13
#: Safety factor on the predicted number of steps.
_SAFETY = 2.0


class Transfers(NamedTuple):
    """The transfers ``T_j`` of ``N`` intervals, stored by the rows that change.

    Components whose equations are null on every interval (the coefficients, ``p' = 0``) keep
    unit rows in every ``T_j``; only the ``a`` others ("active") are stored and integrated.
    Rows and columns are ordered as ``order``: active components, then the constant ones, then
    the augmented ``1``; in that order ``T_j = [[Y_j], [0 | I]]``.

    Attributes
    ----------
    Y : Tensor ``(a, M+1, N)``
        The active rows of every ``T_j``, columns in ``order``, the interval index last.
    order : Tensor ``(M+1,)`` of int
        Components in stored order.
    """

    Y: torch.Tensor
    order: torch.Tensor

    @property
    def active(self) -> int:
        """Number ``a`` of integrated components."""
        return self.Y.shape[0]

    def full(self) -> torch.Tensor:
        """``T (N, M+1, M+1) = [[Phi_j, c_j], [0, 1]]`` in the original order."""
        a, P, N = self.Y.shape
        T_perm = torch.eye(P, dtype=self.Y.dtype, device=self.Y.device).repeat(N, 1, 1)
        T_perm[:, :a] = self.Y.permute(2, 0, 1)
        T = torch.empty_like(T_perm)
        T[:, self.order.unsqueeze(-1), self.order] = T_perm
        return T

    @classmethod
    def from_full(cls, T: torch.Tensor) -> "Transfers":
        """All ``M`` rows of ``T (N, M+1, M+1)`` as active, in the original order."""
        M = T.shape[-1] - 1
        return cls(T[:, :M].permute(1, 2, 0).contiguous(), torch.arange(M + 1, device=T.device))


def _after(Y2: torch.Tensor, Y1: torch.Tensor) -> torch.Tensor:
    """Active rows of ``T2 @ T1`` from those of ``T2`` and ``T1``, both ``(..., a, M+1, N)``."""
    a = Y2.shape[-3]
    if a == 0:
        return Y2.clone()
    out = Y2[..., :, 0:1, :] * Y1[..., 0:1, :, :]
    for j in range(1, a):
        out += Y2[..., :, j:j + 1, :] * Y1[..., j:j + 1, :, :]
    out[..., a:, :] += Y2[..., a:, :]
    return out


def interval_transfers(system: IntervalSystem, *, rtol: float, atol: float,
                       max_substeps: int = 1024) -> tuple[Transfers, int]:
    """Transfers ``T_j`` of all grid intervals, each within the tolerance.

    The error test is the one of an adaptive solver with max-norm, entry by entry on the rows
    of ``[Phi_j | c_j]``: ``|fine - coarse| / 15 <= atol + rtol * max(|T(0)|, |fine|)``.

    Parameters
    ----------
    system : IntervalSystem
        The coefficients of every interval (``N = G - 1`` intervals, state dimension ``M``).
    rtol, atol : float
        Tolerances of one interval's transfer.
    max_substeps : int
        Most RK4 steps spent on one interval (a power of two, at least 2).

    Returns
    -------
    transfers : Transfers
        ``T_j = [[Phi_j, c_j], [0, 1]]`` of the ``N`` intervals.
    n_evals : int
        Batched coefficient evaluations: one evaluates ``A_j(s)`` and ``B_j(s)`` at one local
        time ``s`` on every interval being integrated (5 for the first pass over all intervals,
        ``4n + 1`` for each refinement with ``2n`` steps on the intervals that need it).

    Raises
    ------
    IntegrationError
        When an interval still fails the tolerance with ``max_substeps`` steps, or a transfer is
        not finite.
    """
    coefficients = _Coefficients(system)
    out = rk4_series(coefficients, rtol=rtol, atol=atol, max_substeps=max_substeps)
    capped = out.failed & (out.substeps >= max_substeps)
    if bool(capped.any()):
        index = capped.nonzero().flatten()
        _fail(system, index, out.substeps[index], out.ratio, rtol, atol, max_substeps)
    if bool(out.failed.any()):
        raise IntegrationError("the transfer of a grid interval became non-finite (NaN or inf)")
    return Transfers(out.Y, coefficients.order), out.n_evals


class DoubledTransfers(NamedTuple):
    """The transfers of ``N`` intervals of ``a`` active components by a step-doubling integrator
    (:func:`step_doubling`: RK4 here, Radau IIA in :mod:`torchql.propagators.exponential`).

    Attributes
    ----------
    Y : Tensor ``(a, M+1, N)``
        The transfers' active rows (see :class:`Transfers`).
    failed : bool Tensor ``(N,)``
        Intervals past the tolerance with ``max_substeps`` steps, or not finite.
    substeps : long Tensor ``(N,)``
        Steps of the returned (finer) result on each interval.
    ratio : Tensor ``(N,)``
        Each interval's error estimate over its tolerance (``<= 1`` where it passed).
    n_evals : int
        Batched coefficient evaluations: one evaluates the coefficients at one local time on
        every interval being integrated.
    """

    Y: torch.Tensor
    failed: torch.Tensor
    substeps: torch.Tensor
    ratio: torch.Tensor
    n_evals: int


def step_doubling(pair, intervals: int, device: torch.device, *, max_substeps: int, order: int,
                  max_doublings: int | None = None, inf_ratio: float | None = None) -> DoubledTransfers:
    """Every interval's transfer within its tolerance by step doubling, failures marked per
    interval (never raised): the refinement of the step-doubling propagators.

    ``pair(index, n)`` integrates the intervals ``index`` (None: all ``intervals``) with ``n`` and
    ``2 n`` steps: ``(Y (a, M+1, I), ratio (I,), evaluations)``, the finer (or extrapolated) result
    and its error estimate over the tolerance. Each interval starts with 1 and 2 steps; one whose
    ratio exceeds 1 is integrated again, with the steps its ratio predicts for a method of
    ``order`` (a power of two, at least double, at most ``2 ** max_doublings`` times as many), until
    it passes or would need more than ``max_substeps`` (a power of two, at least 2). An infinite
    (or NaN) ratio predicts as ``inf_ratio`` (default ``16 ** order``) or 16 would.
    """
    check_max_substeps(max_substeps)
    most = max_substeps.bit_length() if max_doublings is None else max_doublings
    Y, ratio, n_evals = pair(None, 1)
    steps = torch.full((intervals,), 2, dtype=torch.long, device=device)  # fine steps per interval
    failed = torch.zeros(intervals, dtype=torch.bool, device=device)
    while True:
        check_time()
        bad = ~(ratio <= 1.0) & ~failed  # NaN fails too
        capped = bad & (steps >= max_substeps)
        failed |= capped
        bad &= ~capped
        if not bool(bad.any()):
            break
        index = bad.nonzero().squeeze(-1)
        current = steps[index]
        # error ~ steps^-order: predict the steps needed; a huge finite ratio would overflow 2**factor
        r = ratio[index].nan_to_num(nan=16.0, posinf=16.0 ** order if inf_ratio is None else inf_ratio).clamp(min=1.0)
        factor = torch.ceil(torch.log2((_SAFETY * r) ** (1 / order))).clamp(1, most).to(torch.long)
        wanted = torch.minimum(current * 2**factor, torch.full_like(current, max_substeps))
        for n_fine in wanted.unique().tolist():
            group = index[wanted == n_fine]
            Y_g, ratio_g, evals = pair(group, n_fine // 2)
            Y[..., group], ratio[group], steps[group] = Y_g, ratio_g, n_fine
            n_evals += evals
    failed |= ~torch.isfinite(Y).flatten(0, 1).all(dim=0)
    return DoubledTransfers(Y, failed, steps, ratio, n_evals)


def check_max_substeps(max_substeps: int) -> None:
    """``ValueError`` unless ``max_substeps`` is a power of two, at least 2."""
    if max_substeps < 2 or max_substeps & (max_substeps - 1):
        raise ValueError(f"`max_substeps` must be a power of two, at least 2; received {max_substeps}")


def in_chunks(pair, coefficients: "_Coefficients", index: torch.Tensor | None, per_chunk: int, *args):
    """``pair(coefficients, index, *args)`` over the intervals ``index`` (None: all) in chunks of
    at most ``per_chunk`` (bounding the memory of a pass): ``(Y, ratio, evaluations)``, or None
    where they fit in one (the caller then integrates them at once)."""
    count = coefficients.intervals if index is None else index.numel()
    if count <= per_chunk:
        return None
    if index is None:
        index = torch.arange(count, device=coefficients.data.device)
    parts = []
    for k in range(0, count, per_chunk):
        check_time()  # (a chunk of matrix exponentials may take a tenth of a second)
        parts.append(pair(coefficients, index[k:k + per_chunk], *args))
    return torch.cat([p[0] for p in parts], dim=-1), torch.cat([p[1] for p in parts]), parts[0][2]


def rk4_series(coefficients: "_Coefficients", *, rtol: float, atol: float,
               max_substeps: int = 1024) -> DoubledTransfers:
    """Transfers of all intervals of ``coefficients`` by RK4 with step doubling (:func:`step_doubling`,
    order 4), failures marked per interval: the integrator of :func:`interval_transfers`, for one
    reference or the intervals of many samples side by side (``linear_solver="rk4_doubling"``)."""
    return step_doubling(lambda index, n: _rk4_pair(coefficients, index, n, rtol, atol), coefficients.intervals,
                         coefficients.data.device, max_substeps=max_substeps, order=4, inf_ratio=16.0 ** 8)


def hermite_to_power(data: torch.Tensor) -> torch.Tensor:
    """Cubic Hermite data to power-basis coefficients, in place: ``data (4, ...)`` is returned.

    In: the values and scaled slopes at the start (``data[0]``, ``data[1]``), then at the end
    (``data[2]``, ``data[3]``). Out: ``c_0 .. c_3`` of ``sum_k c_k s^k`` on ``s`` in ``[0, 1]``:
    ``c_0 = v_0``, ``c_1 = d_0``, ``c_2 = 3 (v_1 - v_0) - 2 d_0 - d_1``,
    ``c_3 = 2 (v_0 - v_1) + d_0 + d_1``.
    """
    rise = data[2] - data[0]
    data[3].add_(data[1]).add_(rise, alpha=-2.0)  # c_3
    torch.sub(rise, data[1], out=data[2])
    data[2].sub_(data[3])  # c_2 = rise - d_0 - c_3
    return data


def raise_to_quintic(power: torch.Tensor, second_start: torch.Tensor, second_end: torch.Tensor) -> torch.Tensor:
    """Cubic Hermite power-basis coefficients made the quintic Hermite ones, in place: ``power (6, ...)``
    holds ``c_0 .. c_3`` of :func:`hermite_to_power` (``c_4``, ``c_5`` ignored) and is returned.

    The quintic also takes the scaled second derivatives ``second_start``, ``second_end`` at
    ``s = 0`` and ``1``. It is the cubic plus ``s^2 (1 - s)^2 (alpha + beta s)``, which leaves the
    values and slopes at both ends as they are and adds ``2 alpha`` and ``2 (alpha + beta)`` to the
    second derivatives ``2 c_2`` and ``2 c_2 + 6 c_3``.
    """
    alpha = second_start / 2 - power[2]
    beta = second_end / 2 - power[2] - 3 * power[3] - alpha
    power[2] += alpha
    power[3] += beta - 2 * alpha
    power[4] = alpha - 2 * beta
    power[5] = beta
    return power


def interval_coefficients(t: torch.Tensor, z: torch.Tensor, z_dot: torch.Tensor, lin, degree: int = 3
                          ) -> _Coefficients:
    """The interval coefficients of ``S`` samples, as :class:`torchql.transfer._Coefficients` holds them.

    ``t``: the shared grid ``(G,)`` or per-sample grids ``(S, G)``. ``degree``: that of the
    interpolants of ``z`` and ``h f``, 3 (cubic Hermite) or 5 (quintic, see
    :func:`_quintic_rows`); ``h A`` is cubic, or quintic where ``degree`` is 5 and ``lin`` is a
    :class:`~torchql.linearize.SecondLinearization` (:func:`_quintic_jacobian_rows`).

    Built from the node values directly (the intervals' arrays of
    :class:`torchql.trajectory.IntervalSystem` are never formed): interval ``s (G-1) + j`` is
    sample ``s``'s interval ``j``. Per interval and Hermite node: the reference values and
    scaled slopes of every component, then for each active component (a nonzero row of ``f``
    or ``A`` somewhere) its row ``h [f | A]`` and scaled slope ``h^2 [f' | A']``.
    """
    S, G, M = z.shape
    # a component moves where its row of f or A (or of their slopes) is nonzero somewhere; NaN
    # counts as moving (a sum of magnitudes with a NaN is NaN, and NaN != 0). Summed over the
    # nodes as (nodes, entries) arrays: reductions over a leading axis with small trailing ones
    # are several times slower
    def magnitude(x: torch.Tensor) -> torch.Tensor:
        return x.reshape(S * G, -1).abs().sum(dim=0).reshape(M, -1).sum(dim=1)  # (M,)

    size = torch.stack([magnitude(lin.f), magnitude(lin.f_dot), magnitude(lin.jac), magnitude(lin.jac_dot)])
    moving = (size != 0).any(dim=0)  # (M,)
    index = torch.arange(M, device=z.device)
    order = torch.cat([index[moving], index[~moving], torch.tensor([M], device=z.device)])
    perm = order[:-1]
    a = int(moving.sum())
    Q = M + a * (M + 1)

    def rows_of(x: torch.Tensor, both: bool) -> torch.Tensor:
        """``x[..., act]`` (and ``[..., perm]`` on the last axis too if ``both``); slices when the moving
        components come first, as the states do before the constant coefficients."""
        if ordered:
            return x[..., :a, :] if both else x[..., :a]
        x = x[..., perm[:a], :] if both else x[..., perm[:a]]
        return x[..., perm] if both else x

    ordered = bool((perm == index).all())
    # node values and slopes, component-major: (Q, S, G)
    values, slopes = z.new_empty(Q, S, G), z.new_empty(Q, S, G)
    values[:M] = (z if ordered else z[..., perm]).permute(2, 0, 1)
    slopes[:M] = (z_dot if ordered else z_dot[..., perm]).permute(2, 0, 1)
    rows = values[M:].unflatten(0, (a, M + 1))
    rows[:, 0], rows[:, 1:] = rows_of(lin.f, False).permute(2, 0, 1), rows_of(lin.jac, True).permute(2, 3, 0, 1)
    rows = slopes[M:].unflatten(0, (a, M + 1))
    rows[:, 0] = rows_of(lin.f_dot, False).permute(2, 0, 1)
    rows[:, 1:] = rows_of(lin.jac_dot, True).permute(2, 3, 0, 1)
    # per interval: values at the start, scaled slopes there, then the same at the end; the rows of
    # f and A scaled by h (values) and h^2 (slopes), those of z by 1 and h
    h = (t[..., 1:] - t[..., :-1]).reshape(1, -1, G - 1)  # (1, 1 or S, G - 1)
    value_scale = torch.cat([torch.ones_like(h).expand(M, -1, -1), h.expand(Q - M, -1, -1)])
    slope_scale = torch.cat([h.expand(M, -1, -1), (h * h).expand(Q - M, -1, -1)])
    if degree not in (3, 5):
        raise ValueError(f"`degree` must be 3 or 5; received {degree}")
    data = z.new_empty(degree + 1, Q, S, G - 1)  # one allocation: the quintic's rows are filled in place
    start, end = slice(0, G - 1), slice(1, G)
    blocks = ((values, start, value_scale), (slopes, start, slope_scale), (values, end, value_scale),
              (slopes, end, slope_scale))
    for b, (source, side, scale) in enumerate(blocks):
        torch.mul(source[..., side], scale, out=data[b])
    data = data.reshape(degree + 1, Q, S * (G - 1))
    hermite_to_power(data[:4])
    jacobian_degree = 3
    if degree == 5:
        _quintic_rows(data, h, z_dot, lin, perm, a)
        if isinstance(lin, SecondLinearization):
            _quintic_jacobian_rows(data, h, lin.jac_ddot, perm, a, S)
            jacobian_degree = 5
    return _Coefficients.of(data, order, a, M, jacobian_degree, samples=S)


def _quintic_rows(out: torch.Tensor, h: torch.Tensor, z_dot: torch.Tensor, lin, perm: torch.Tensor, a: int) -> None:
    """The coefficients ``out (6, Q, S N)``, cubic in ``out[:4]``, completed in place: the rows of
    the active components' ``z`` and ``h f`` become quintic Hermite interpolants
    (:func:`~torchql.transfer.raise_to_quintic`); the other rows (``h A``'s, and ``z``'s constant
    components) keep degree 3, zero above.

    The second derivatives along the reference are ``z'' = f'`` (the reference's own second
    derivative wherever it solves the model: at a converged iterate) and ``f'' = A' z' + A f'``,
    exact where ``f`` has no explicit time dependence; a sample's component whose ``f'`` is not
    ``A z'`` to rounding at some node keeps its cubic ``h f`` row. ``perm``: the components in
    stored order, the ``a`` active ones first; ``h (1, 1 or S, N)``.
    """
    M = perm.numel()
    S, G = z_dot.shape[:2]
    out[4:].zero_()
    if a == 0:
        return
    act = perm[:a]
    ordered = bool((act == torch.arange(a, device=act.device)).all())
    rows_of = (lambda x: x[..., :a, :]) if ordered else (lambda x: x[..., act, :])
    jac, f_dot = rows_of(lin.jac), lin.f_dot  # (S, G, a, M), (S, G, M)
    f_t = f_dot[..., act] - torch.einsum("sgij,sgj->sgi", jac, z_dot)  # zero without explicit time dependence
    size = torch.einsum("sgij,sgj->sgi", jac.abs(), z_dot.abs()) + f_dot[..., act].abs()
    autonomous = (f_t.abs() <= 64 * torch.finfo(f_t.dtype).eps * size).all(dim=1)  # (S, a)
    f_ddot = torch.einsum("sgij,sgj->sgi", rows_of(lin.jac_dot), z_dot) + torch.einsum("sgij,sgj->sgi", jac, f_dot)
    f_rows = slice(M, M + a * (M + 1), M + 1)
    # scaled to the local time: z's second derivatives by h^2, h f's by h^3
    for rows, second, scale in ((slice(0, a), f_dot[..., act], h * h), (f_rows, f_ddot, h ** 3)):
        second = second.permute(2, 0, 1)  # (a, S, G)
        target = out[:, rows].unflatten(-1, (S, G - 1))  # (6, a, S, N), a view
        cubic = target.clone() if rows is f_rows and not bool(autonomous.all()) else None
        raise_to_quintic(target, second[..., :-1] * scale, second[..., 1:] * scale)  # in place
        if cubic is not None:
            target.copy_(torch.where(autonomous.T.unsqueeze(-1), target, cubic))


def _quintic_jacobian_rows(out: torch.Tensor, h: torch.Tensor, jac_ddot: torch.Tensor, perm: torch.Tensor, a: int,
                           S: int) -> None:
    """The rows of ``h A`` in the coefficients ``out (6, Q, S N)`` raised to quintic Hermite
    interpolants, in place, from the second time derivatives ``jac_ddot (S, G, M, M)`` of ``A`` at
    the nodes (scaled to the local time by ``h^3``; ``perm``: the components in stored order, the
    ``a`` active ones first; ``h (1, 1 or S, N)``). Exact with explicit time dependence too: the
    linearization's ``d^2/dt^2 A`` has its time terms."""
    M = perm.numel()
    G = jac_ddot.shape[1]
    second = jac_ddot[:, :, perm[:a]][..., perm].permute(2, 3, 0, 1)  # (a, M, S, G): active rows, stored columns
    scale = h ** 3
    rows = out[:, M:].unflatten(1, (a, M + 1))[:, :, 1:]  # (6, a, M, S N), a view: the rows of h A
    raise_to_quintic(rows.unflatten(-1, (S, G - 1)), second[..., :-1] * scale, second[..., 1:] * scale)


class _Coefficients:
    """The local-time coefficients ``X_j(s)`` of every interval, active rows only, in stored order.

    The reference ``z``, ``h f`` and ``h A`` of every interval are cubic Hermite interpolants of
    their node values and scaled slopes; they are stored once as power-basis coefficients
    (``data (4, Q, N)``, degree first), so that their values at any local times are one matrix
    product and the Taylor series of :mod:`torchql.taylor` reads them directly. A component is
    active when its row of ``f`` or ``A`` (or of their slopes) is nonzero at some node.
    """

    def __init__(self, system: IntervalSystem, degree: int = 3) -> None:
        """One reference's intervals (``system.reference``), by :func:`interval_coefficients` as a
        batch of one (``degree``: 3, cubic Hermite, or 5, quintic)."""
        ref = system.reference
        second = None if degree == 3 else getattr(ref, "jac_ddot", None)
        fields = (ref.f, ref.jac, ref.f_dot, ref.jac_dot) + (() if second is None else (second,))
        lin = (Linearization if second is None else SecondLinearization)(*(v.unsqueeze(0) for v in fields))
        built = interval_coefficients(ref.t, ref.z.unsqueeze(0), ref.z_dot.unsqueeze(0), lin, degree)
        self.data, self.order, self.a, self.M = built.data, built.order, built.a, built.M
        self.jacobian_degree, self.samples = built.jacobian_degree, built.samples

    @classmethod
    def of(cls, data: torch.Tensor, order: torch.Tensor, a: int, M: int, jacobian_degree: int = 3,
           samples: int = 1) -> "_Coefficients":
        """Coefficients already in stored form: power-basis ``data (D, Q, N)``, ``order (M+1,)``,
        ``a`` active components of ``M``, the rows of ``h A`` of degree ``jacobian_degree``; the
        ``N`` intervals are ``samples`` contiguous blocks of equal length, one per sample (a sample
        with an interval that cannot be integrated fails as a whole, and the series of its other
        intervals are not summed: :func:`torchql.taylor.series_transfers`)."""
        coefficients = object.__new__(cls)
        coefficients.data, coefficients.order, coefficients.a, coefficients.M = data, order, a, M
        coefficients.jacobian_degree, coefficients.samples = jacobian_degree, samples
        return coefficients

    @property
    def intervals(self) -> int:
        return self.data.shape[-1]

    def values(self, s: torch.Tensor, index: torch.Tensor | None = None, *, rows: slice | None = None,
               derivative: bool = False) -> torch.Tensor:
        """The interpolants' values ``(K, Q, I)`` at local times ``s (K,)``, in the stored rows (the
        reference ``z``, then each active component's ``h f`` and ``h A``; ``rows``: those only), of
        the intervals ``index`` (default all): one matrix product with the powers of ``s``. With
        ``derivative``, their derivatives in local time (``h`` times the time derivative)."""
        data = self.data if index is None else self.data[..., index]
        if rows is not None:
            data = data[:, rows]
        if derivative:
            degrees = torch.arange(1, data.shape[0], dtype=data.dtype, device=data.device)
            data = data[1:] * degrees.reshape(-1, 1, 1)
        powers = [torch.ones_like(s)]
        for _ in range(data.shape[0] - 1):
            powers.append(powers[-1] * s)
        return (torch.stack(powers, dim=-1) @ data.flatten(1)).unflatten(1, data.shape[1:])

    def at(self, s: torch.Tensor, index: torch.Tensor | None) -> torch.Tensor:
        """``X (K, a, M+1, I)``: active rows of ``[[h A, h B], [0, 0]]`` at local times ``s (K,)``."""
        values = self.values(s, index)  # (K, Q, I)
        M, a = self.M, self.a
        z, fA = values[:, :M], values[:, M:].unflatten(1, (a, M + 1))  # (K, M, I), (K, a, 1 + M, I)
        b = fA[:, :, 0] - (fA[:, :, 1:] * z.unsqueeze(1)).sum(dim=2)
        return torch.cat([fA[:, :, 1:], b.unsqueeze(2)], dim=2)


def _rk4_pair(coefficients: _Coefficients, index: torch.Tensor | None, n: int, rtol: float,
              atol: float) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Extrapolated active rows ``(a, M+1, I)`` from ``n`` and ``2n`` RK4 steps, error ratios ``(I,)``, evaluations."""
    chunks = in_chunks(_rk4_pair, coefficients, index, max(1, _CHUNK // (4 * n + 1)), n, rtol, atol)
    if chunks is not None:
        return chunks
    dtype, device = coefficients.data.dtype, coefficients.data.device
    s = torch.arange(4 * n + 1, dtype=dtype, device=device) / (4 * n)
    X = coefficients.at(s, index)
    # steps scaled by their length: 2n fine steps then n coarse ones, batched together
    X0 = torch.cat([X[0:-1:2] / (2 * n), X[0:-1:4] / n])
    Xm = torch.cat([X[1::2] / (2 * n), X[2::4] / n])
    X1 = torch.cat([X[2::2] / (2 * n), X[4::4] / n])
    R = _rk4_steps(X0, Xm, X1)
    fine, coarse = _product(R[:2 * n]), _product(R[2 * n:])
    diff = (fine - coarse) / 15
    a, P = fine.shape[:2]
    eye = torch.eye(a, P, dtype=dtype, device=device).unsqueeze(-1)
    scale = atol + rtol * torch.maximum(eye, fine.abs())
    ratio = (diff.abs() / scale).flatten(0, 1).amax(dim=0) if a else fine.new_zeros(fine.shape[-1])
    return fine + diff, ratio, s.numel()


def _rk4_steps(X0: torch.Tensor, Xm: torch.Tensor, X1: torch.Tensor) -> torch.Tensor:
    """RK4 transfers ``(S, a, M+1, I)`` of unit steps of ``T' = X(s) T``, from the start, middle and end coefficients."""
    a, P = X0.shape[1:3]
    eye = torch.eye(a, P, dtype=X0.dtype, device=X0.device).unsqueeze(-1)
    K2 = _after(Xm, eye + X0 / 2)
    K3 = _after(Xm, eye + K2 / 2)
    K4 = _after(X1, eye + K3)
    return eye + (X0 + 2 * (K2 + K3) + K4) / 6


def _product(R: torch.Tensor) -> torch.Tensor:
    """Active rows of ``T[n-1] @ ... @ T[0]`` from ``R (n, a, M+1, I)``, ``n`` a power of two: ``(a, M+1, I)``."""
    while R.shape[0] > 1:
        R = _after(R[1::2], R[0::2])
    return R[0]


def _fail(system, index, steps, ratio, rtol, atol, max_substeps) -> None:
    worst = index[ratio[index].nan_to_num(nan=math.inf).argmax()]
    t_worst = float(system.t_start[worst])
    value = float(ratio[worst])
    what = "non-finite" if not math.isfinite(value) else f"{value:.3g} times the tolerance"
    raise IntegrationError(
        f"the transfer of {int((steps >= max_substeps).sum())} grid interval(s) did not meet the tolerance "
        f"(rtol={rtol:.3g}, atol={atol:.3g}) with {max_substeps} RK4 steps each (worst: the interval starting "
        f"at t = {t_worst:.6g}, error {what}); refine the grid where the solution changes fast, loosen "
        f"`rtol`/`atol`, or use `linear_solver='torchdiffeq'`")


def prefix_products(Y: torch.Tensor) -> torch.Tensor:
    """Running products ``P_j = T_j @ T_{j-1} @ ... @ T_0``, by active rows ``Y (a, M+1, N)``: ``(a, M+1, N)``.

    Hillis–Steele doubling: after the pass with offset ``d``, ``P_j`` holds the product of
    ``T_{max(0, j-2d+1)} .. T_j``; ``ceil(log2 N)`` passes of one batched product each.
    """
    P = Y
    d = 1
    N = Y.shape[-1]
    while d < N:
        P = torch.cat([P[..., :d], _after(P[..., d:], P[..., :-d])], dim=-1)
        d *= 2
    return P


def compose_transfers(transfers: Transfers, w0: torch.Tensor) -> torch.Tensor:
    """Columns ``w0 (M, 1 + m)`` carried over the grid: ``W (N + 1, M, 1 + m)`` with ``W[0] = w0``.

    Column 0 is the particular solution (it takes the forced responses ``c_j``), the others are
    homogeneous (``Phi_j`` alone), as in ``w_{j+1} = Phi_j w_j + c_j e_0^T``.
    """
    M, cols = w0.shape
    order, a = transfers.order, transfers.active
    one = torch.zeros(1, cols, dtype=w0.dtype, device=w0.device)
    one[0, 0] = 1.0
    w = torch.cat([w0, one])[order]
    P = prefix_products(transfers.Y)  # (a, M+1, N)
    W = w0.repeat(P.shape[-1] + 1, 1, 1)
    W[1:, order[:a]] = torch.tensordot(P, w, dims=([1], [0])).permute(1, 0, 2)
    return W
