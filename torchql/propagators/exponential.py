"""``linear_solver="exponential"``: stiff-stable interval transfers, exact for constant coefficients.

Over one step (local time ``sigma`` in ``[0, 1]``) the transfer solves ``T' = X(sigma) T``,
``T(0) = I``, with ``X = [[h A, h B], [0, 0]]`` (the forcing column included, so that the
particular solution is part of the same matrix). The step is split as ``T = exp(sigma E) + U``:

* ``E = X(0)``, the coefficients frozen at the start of the step: ``exp(sigma E)`` is taken by
  ``torch.linalg.matrix_exp`` (scaling and squaring), exact whatever the stiffness, including
  the forced response of a constant ``B`` (``[[e^E_A, phi_1(E_A) h B], [0, 1]]``). Frozen at the
  start rather than the midpoint, the correction's forcing vanishes at ``sigma = 0``, so the
  correction starts on its own slow manifold to leading order: its initial layer, which Radau
  IIA damps only by ``|R(h lambda)| ~ 3 / (h |lambda|)``, is then smaller by a factor ``h |lambda|``;
* the correction ``U`` solves ``U' = X U + (X - E) exp(sigma E)``, ``U(0) = 0``, integrated by
  the three-stage Radau IIA collocation (order 5, L-stable and stiffly accurate: its result is
  the last stage value at ``sigma = 1``, so a stiff component ends on its quasi-steady state at the
  end of the step, ``-A(t_end)^{-1} B(t_end)`` to leading order, not at an interior point).

Constant coefficients give ``U = 0``: the transfer is the matrix exponential, to round-off. For
time-varying stiff ``A`` the correction's forcing ``(X - E) exp(sigma E)`` is large but Radau IIA
is L-stable; its stage equations are one linear solve of size ``3 a`` per step (``a`` active
components). Why not the augmented fourth-order Magnus expansion: its commutator term
``[X_2, X_1]`` carries ``h^2 A (B_2 - B_1)`` into the forced response, which in the stiff limit
becomes an error of order ``h |lambda| h B'`` (growing with the stiffness), and any single
exponential of frozen coefficients puts the quasi-steady state at an interior point of the step.

**Error control: step doubling.** Each interval is integrated with ``n`` and with ``2n`` equal
steps (``n = 1`` first). The difference estimates the error of the finer one; it is divided by
``2^3 - 1 = 7`` rather than the ``2^5 - 1`` of the nonstiff order: in the stiff regime Radau IIA's
order drops towards its stage order 3, and a smaller divisor keeps the estimate an upper bound
there (it costs at most one extra doubling on nonstiff intervals). The test is the mixed
absolute/relative one of the other propagators, entry by entry on the active rows of
``[Phi | c]``: ``|fine - coarse| / 7 <= atol + rtol * max(|T(0)|, |fine|)``, so decayed stiff
entries (``e^{-10^6}``) are judged by ``atol``, never by their own vanishing size. The finer
result is returned (no extrapolation, which would not keep L-stability). Intervals that fail
are integrated again with the number of steps the estimate predicts (a power of two, at least
double and at most eight times as many per pass: see :data:`_MAX_DOUBLINGS`), only those, up to
``max_substeps``.

**Limitation: intermediate stiffness.** The correction's initial layer leaves an error of order
``|q'| / (h |lambda|)^2`` per step (``q`` the quasi-steady state), from the last step of an interval
only (earlier ones decay). With ``n`` steps it is ``n`` times larger, so refinement reduces it only
once ``h |lambda| / n`` is of order one: for ``h |lambda|`` near ``10^2 .. 10^4`` and tight
tolerances an interval can reach ``max_substeps`` (an ``IntegrationError``), and in that regime the
step-doubling difference, which does not shrink with the step, can underestimate the error.
From ``h |lambda| ~ 10^5`` on the layer is below double precision's reach of most tolerances and
the first pass (two steps) passes; below ``~10`` the method is in its nonstiff regime (order 5).

Only the rows of the components that change are integrated (coefficients have null equations;
see :class:`torchql.transfer.Transfers`).
"""

from __future__ import annotations

import math

import torch

from ..integrate import IntegrationError
from ..transfer import (DoubledTransfers, Transfers, _Coefficients, _product, check_max_substeps, in_chunks,
                        step_doubling)
from ._base import LinearPropagator

__all__ = ["ExponentialRadau", "RadauCollocation", "SensitivityRodas", "exponential_series", "exponential_transfers"]

_SQRT6 = math.sqrt(6.0)
#: Radau IIA (three stages) nodes and coefficient matrix.
_NODES = ((4 - _SQRT6) / 10, (4 + _SQRT6) / 10, 1.0)
_RADAU = ((88 - 7 * _SQRT6) / 360, (296 - 169 * _SQRT6) / 1800, (-2 + 3 * _SQRT6) / 225,
          (296 + 169 * _SQRT6) / 1800, (88 + 7 * _SQRT6) / 360, (-2 - 3 * _SQRT6) / 225,
          (16 - _SQRT6) / 36, (16 + _SQRT6) / 36, 1 / 9)
#: The local times of one step's evaluations: the start (the frozen coefficients), then the Radau nodes.
_STEP_TIMES = (0.0,) + _NODES
#: Divisor of the step-doubling difference: ``2^q - 1`` for the stiff order ``q = 3``.
_DIVISOR = 7.0
#: Estimated order of the finer result, for predicting the steps an interval needs.
_ORDER = 3
#: Multiple of ``eps ||h A||`` allowed for the rounding of the matrix exponential.
_ROUNDING = 8.0
#: Most doublings of an interval's steps per refinement (at most 8 times the steps): a stiff
#: interval's first difference (one step against two) is far from the asymptotic regime that the
#: prediction assumes (``h |lambda|`` of hundreds: the stiff components' initial layer), and
#: predicted from it the steps jumped to hundreds where a few tens meet the tolerance (measured
#: on van der Pol's transfers, ``mu = 700``: 19,000 steps over 1,128 intervals instead of 556,000,
#: 0.04 s instead of 0.85 s, the same accuracy).
_MAX_DOUBLINGS = 3
#: Most interval-steps integrated in one batch (bounds the memory of refinement).
_CHUNK = 1 << 14


def _step(Xm: torch.Tensor, Xc: torch.Tensor, freeze: bool = True) -> torch.Tensor:
    """Active rows ``(J, a, P)`` of one step's transfer, from the coefficients' active rows at the
    start ``Xm (J, a, P)`` (frozen) and at the Radau nodes ``Xc (3, J, a, P)`` (already scaled by the step).

    ``freeze=False``: no frozen part (``E = 0``, ``exp(sigma E) = I``), so the correction is the
    whole transfer minus ``I``: plain Radau IIA collocation of ``T' = X T``.
    """
    J, a, P = Xm.shape
    if freeze:
        E = Xm.new_zeros(J, P, P)
        E[:, :a] = Xm
        nodes = torch.tensor(_NODES, dtype=Xm.dtype, device=Xm.device).reshape(3, 1, 1, 1)
        frozen = torch.linalg.matrix_exp(nodes * E)  # exp(c_i E): (3, J, P, P)
        G = (Xc - Xm) @ frozen  # the correction's forcing at the nodes: (3, J, a, P)
    else:
        frozen = torch.eye(P, dtype=Xm.dtype, device=Xm.device).expand(3, J, P, P)
        G = Xc.clone()
    radau = torch.tensor(_RADAU, dtype=Xm.dtype, device=Xm.device).reshape(3, 3)
    # stage values Z_i = sum_j R_ij (X_j Z_j + G_j); Z_j has active rows only (U(0) = 0, and the
    # null equations' rows of X - E vanish), so X_j Z_j = X_j[:, :a] Z_j
    blocks = -radau.reshape(3, 3, 1, 1, 1) * Xc[:, :, :, :a].unsqueeze(0)  # (3, 3, J, a, a)
    blocks = blocks + torch.eye(3, dtype=Xm.dtype, device=Xm.device).reshape(3, 3, 1, 1, 1) * \
        torch.eye(a, dtype=Xm.dtype, device=Xm.device)
    L = blocks.permute(2, 0, 3, 1, 4).reshape(J, 3 * a, 3 * a)
    R = torch.einsum("ij,jkap->kiap", radau, G).reshape(J, 3 * a, P)
    # a singular stage system (h X with an eigenvalue where Radau's collocation matrix is singular)
    # gives NaN, not an exception: the step-doubling refines that interval, or marks it failed
    Z, info = torch.linalg.solve_ex(L, R)
    Z = torch.where((info != 0).reshape(J, 1, 1), torch.full_like(Z, float("nan")), Z)
    return frozen[2, :, :a] + Z[:, 2 * a:]


def _pair(coefficients: _Coefficients, index: torch.Tensor | None, n: int, rtol: float, atol: float,
          freeze: bool = True) -> tuple[torch.Tensor, torch.Tensor, int]:
    """The result of ``2 n`` steps ``(a, M+1, I)``, error ratios ``(I,)`` against ``n`` steps, evaluations."""
    chunks = in_chunks(_pair, coefficients, index, max(1, _CHUNK // (3 * n)), n, rtol, atol, freeze)
    if chunks is not None:
        return chunks
    dtype, device = coefficients.data.dtype, coefficients.data.device
    local = torch.tensor(_STEP_TIMES, dtype=dtype, device=device)
    starts = torch.cat([torch.arange(2 * n, dtype=dtype, device=device) / (2 * n),
                        torch.arange(n, dtype=dtype, device=device) / n])  # 2n fine steps, then n coarse
    widths = torch.cat([torch.full((2 * n,), 1 / (2 * n), dtype=dtype, device=device),
                        torch.full((n,), 1 / n, dtype=dtype, device=device)])
    s = (starts.unsqueeze(1) + widths.unsqueeze(1) * local).flatten()  # (3n * 4,)
    X = coefficients.at(s, index)  # (3n * 4, a, P, I)
    a, P, I = X.shape[1:]
    rho = X[:, :, :a].abs().sum(dim=2).amax(dim=(0, 1))  # ||h A||_inf over the interval: (I,)
    X = (X.unflatten(0, (3 * n, 4)) * widths.reshape(3 * n, 1, 1, 1, 1)).permute(1, 0, 4, 2, 3)  # (4, 3n, I, a, P)
    X = X.reshape(4, 3 * n * I, a, P)
    steps = _step(X[0], X[1:], freeze).reshape(3 * n, I, a, P).permute(0, 2, 3, 1)  # (3n, a, P, I)
    fine, coarse = _product(steps[:2 * n]), _product(steps[2 * n:])
    eye = torch.eye(a, P, dtype=dtype, device=device).unsqueeze(-1)
    size = torch.maximum(eye, fine.abs())
    # the matrix exponential's own rounding, eps ||h A|| relative (its normwise backward error),
    # is allowed for: no refinement reduces it
    scale = atol + (rtol + _ROUNDING * torch.finfo(dtype).eps * rho) * size
    ratio = ((fine - coarse).abs() / (_DIVISOR * scale)).flatten(0, 1).amax(dim=0)
    return fine, ratio.nan_to_num(nan=math.inf), s.numel()


def exponential_series(coefficients: _Coefficients, *, rtol: float, atol: float,
                       max_substeps: int = 1024, freeze: bool = True) -> DoubledTransfers:
    """Transfers of all intervals within the tolerance, failures marked per interval (never raised):
    :func:`~torchql.transfer.step_doubling` of order :data:`_ORDER`, at most
    :data:`_MAX_DOUBLINGS` doublings per refinement.

    Parameters
    ----------
    coefficients : _Coefficients
        Power-basis coefficients of the ``N`` intervals (see :class:`torchql.transfer._Coefficients`).
    rtol, atol : float
        Tolerances of one interval's transfer.
    max_substeps : int
        Most steps on one interval (a power of two, at least 2); an interval that needs more fails.
    freeze : bool
        ``True``: the exponential of the frozen coefficients plus the Radau IIA correction;
        ``False``: Radau IIA collocation of the whole transfer (``linear_solver="radau"``).
    """
    a, M, N = coefficients.a, coefficients.M, coefficients.intervals
    device = coefficients.data.device
    check_max_substeps(max_substeps)
    if a == 0 or N == 0:
        return DoubledTransfers(coefficients.data.new_zeros(a, M + 1, N), torch.zeros(N, dtype=torch.bool, device=device),
                                torch.full((N,), 2, dtype=torch.long, device=device),
                                coefficients.data.new_zeros(N), 0)
    return step_doubling(lambda index, n: _pair(coefficients, index, n, rtol, atol, freeze), N, device,
                         max_substeps=max_substeps, order=_ORDER, max_doublings=_MAX_DOUBLINGS)


def exponential_transfers(coefficients: _Coefficients, *, rtol: float, atol: float, max_substeps: int = 1024,
                          t_start: torch.Tensor | None = None, freeze: bool = True) -> tuple[Transfers, int]:
    """Transfers ``T_j`` of all intervals, each within the tolerance (see :func:`exponential_series`).

    Raises :class:`~torchql.integrate.IntegrationError` when an interval needs more than
    ``max_substeps`` steps or its transfer is not finite (``t_start (N,)``: the intervals' start
    times, for the message).
    """
    out = exponential_series(coefficients, rtol=rtol, atol=atol, max_substeps=max_substeps, freeze=freeze)
    if bool(out.failed.any()):
        bad = out.failed.nonzero().flatten()
        worst = int(bad[0])
        finite = bool(torch.isfinite(out.Y[..., worst]).all())
        what = (f"did not meet the tolerance (rtol={rtol:.3g}, atol={atol:.3g}) with {max_substeps} steps"
                if finite else "is not finite (NaN or inf)")
        where = "" if t_start is None else f" starting at t = {float(t_start[worst]):.6g}"
        raise IntegrationError(
            f"the transfer of {bad.numel()} grid interval(s) {what}; first: the interval{where}; refine the "
            f"grid where the coefficients change fast, or loosen `rtol`/`atol`")
    return Transfers(out.Y, coefficients.order), out.n_evals


class ExponentialRadau(LinearPropagator):
    """Every interval's transfer by the matrix exponential of its frozen coefficients, corrected
    for their variation by Radau IIA collocation, with step doubling: exact for constant
    coefficients, stable and accurate for stiff ``A`` (``h |lambda|`` up to ``10^8`` and beyond).

    ``grid_solver`` is ``False``: the grid solver integrates the nonlinear model by explicit RK4,
    which a stiff model defeats, so every nonlinear pass uses ``fit``'s ``solver``.
    """

    name = "exponential"
    grid_solver = False
    stiff_stable = True
    #: Whether the coefficients are frozen at each step's start and exponentiated.
    freeze = True

    def __init__(self, max_substeps: int = 1024) -> None:
        self.max_substeps = max_substeps

    def series(self, coefficients, *, rtol, atol, max_substeps):
        out = exponential_series(coefficients, rtol=rtol, atol=atol, max_substeps=max(2, max_substeps),
                                 freeze=self.freeze)
        return out.Y, out.failed, out.n_evals

    def transfers(self, system, *, rtol, atol, solver, max_steps):
        return exponential_transfers(_Coefficients(system), rtol=rtol, atol=atol, max_substeps=self.max_substeps,
                                     t_start=system.t_start, freeze=self.freeze)


class RadauCollocation(ExponentialRadau):
    """Every interval's transfer by three-stage Radau IIA collocation of ``T' = X T`` (order 5,
    L-stable, stiffly accurate), with the same step doubling: the stiff propagator for every
    stiffness, including the intermediate ``h |lambda| ~ 10^2 .. 10^4`` where the frozen exponential
    of ``"exponential"`` leaves an initial layer that refinement does not remove (measured:
    Robertson kinetics to ``t = 1e5`` on the stiff grid, where ``"exponential"`` fails intervals
    near ``t = 1`` at the fit's tolerance and ``"radau"`` converges). Not exact for constant
    coefficients (its stability function is the (2, 3) Pade approximant of ``exp``), so it refines
    where ``"exponential"`` passes at once; used by ``solver="auto"`` when a model is stiff."""

    name = "radau"
    freeze = False


class SensitivityRodas(RadauCollocation):
    """``linear_solver="rodas5p"``: where the reference is the model's own solution (shooting's
    iterates, every fit's final pass), its sensitivities are those of its Rodas5P steps, on the
    solution's own adaptive steps (:mod:`torchql.solvers.sensitivity`); Kantorovich's other
    references are propagated as by ``"radau"``.

    For stiff models whose fast changes fall inside grid intervals (relaxation oscillations: van
    der Pol with ``mu = 1000``, whose jumps no grid placed before the solution is known resolves)
    or whose stiffness per interval is intermediate (``h |lambda| ~ 10^2 .. 10^5``, where Radau
    transfers need many substeps: Boehm's STAT5 model), with ``method="shooting"``. Its cost is
    one Rodas5P solve of the states per reference; on Robertson kinetics (``benchmarks/stiff_fit.py``)
    Kantorovich fits take the time they take with ``"radau"``, and shooting fits 0.9 to 1.4 times
    that.
    """

    name = "rodas5p"
    with_solution = True
