"""Rodas5P for a batch of independent samples, each on its own error control.

Why a Rosenbrock method. Stiff models (fast chemistry, relaxation oscillations, enzyme binding)
make every explicit solver crawl at the step size that its stability region allows, however
smooth the solution. An implicit solver takes steps at the size the accuracy needs. Of the two
standard families of order 5,

* Radau IIA (scipy's ``Radau``, Hairer's RADAU5) solves a nonlinear system per step by simplified
  Newton: a variable number of iterations with its own convergence tests, a Jacobian kept across
  steps and refactorised on heuristics, two LU factorisations (one complex) per step. Per sample,
  every one of these decisions differs, which batches badly;
* a Rosenbrock method replaces the Newton iteration by a fixed sequence of linear solves with one
  matrix ``I / (h gamma) - J``: one Jacobian, one LU factorisation and a fixed number of
  right-hand-side evaluations per step, the same operations for every sample, which batches as
  well as an explicit Runge–Kutta step. It needs the exact Jacobian (for its order), which
  ``torch.func.jacrev`` gives.

Rodas5P (Steinebach 2023, see :mod:`torchql.solvers.tableau`) is the Rosenbrock method of choice
at tight tolerances: order 5 with an embedded order-4 estimate, L-stable and stiffly accurate
(its solution is its last stage, so it damps the fast components fully, as Radau IIA does), an
order-4 dense output, and a design that keeps its order on stiff and on differential–algebraic
problems better than the older Rodas4/Rodas5. It is the default stiff solver of Julia's
DifferentialEquations.jl for tolerances below ``1e-6``.

The loop is :func:`torchql.batch_integrate.dopri_batch`'s: every sample has its own time, step
size and accept/reject decision, no sample's error is averaged with another's, a round advances
every unfinished sample by one trial step and evaluates only those. Step sizes follow the
standard controller with Gustafsson's prediction (as Hairer's RODAS and RADAU5), which keeps the
step sequence smooth where stiff components are being damped.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

from ..budget import check_time
from . import tableau
from .field import BatchedField
from .output import OutputGrid
from .steps import StepRecord, dense_value

__all__ = ["RosenbrockSolution", "rodas5p_batch", "precision_note", "SUCCESS", "NON_FINITE", "STEP_UNDERFLOW",
           "MAX_STEPS", "STOPPED"]

#: Per-sample status codes of :class:`RosenbrockSolution`.
SUCCESS, NON_FINITE, STEP_UNDERFLOW, MAX_STEPS, STOPPED = 0, 1, 2, 3, 4

_SAFETY = 0.9
_MIN_FACTOR, _MAX_FACTOR = 0.2, 6.0
#: Exponent of the step-size controller: the embedded estimate's error is ``O(h^5)``.
_EXPONENT = 1.0 / 5.0
#: ... and where the dense output's error dominates: ``O(h^4)`` on stiff components.
_DENSE_EXPONENT = 1.0 / 4.0


@dataclass
class RosenbrockSolution:
    """What :func:`rodas5p_batch` returns.

    Attributes
    ----------
    y : Tensor ``(S, G, M)``
        The solutions at the grid nodes (NaN for the samples that failed).
    status : long Tensor ``(S,)``
        ``SUCCESS`` (0), ``NON_FINITE`` (1), ``STEP_UNDERFLOW`` (2), ``MAX_STEPS`` (3) or
        ``STOPPED`` (4: the caller's ``stop`` test ended it at a node).
    t : Tensor ``(S,)``
        The time each sample reached (its final time where it succeeded).
    n_accepted, n_rejected : long Tensor ``(S,)``
        Each sample's accepted and rejected steps.
    n_f, n_jac : int
        Points at which the right-hand side and its Jacobian were evaluated (a batched call on
        ``A`` samples counts ``A``; a Jacobian evaluation also gives one value of ``f``, counted
        in ``n_f``).
    max_steps : int
        The step budget the solution ran under (for the messages).
    steps : StepRecord or None
        Every accepted step, where asked for (``keep_steps``).
    interval_steps : int or None
        The budget of trial steps between two nodes it ran under (for the messages).
    """

    y: torch.Tensor
    status: torch.Tensor
    t: torch.Tensor
    n_accepted: torch.Tensor
    n_rejected: torch.Tensor
    n_f: int
    n_jac: int
    max_steps: int
    steps: "StepRecord | None" = None
    interval_steps: int | None = None

    @property
    def ok(self) -> torch.Tensor:
        """Samples that reached their final time, ``(S,)`` bool."""
        return self.status == SUCCESS

    def message(self, sample: int = 0) -> str | None:
        """Why sample ``sample`` failed, with what to try; ``None`` if it succeeded."""
        code, t = int(self.status[sample]), float(self.t[sample])
        if code == NON_FINITE:
            return (f"the solution became non-finite (NaN or inf) at t = {t:.6g} and no smaller step "
                    "avoided it: the model may blow up there, or its coefficients be unphysical")
        if code == STEP_UNDERFLOW:
            return (f"step size underflow at t = {t:.6g}: the error test could not be met with any "
                    "representable step (a singularity, a discontinuity, or tolerances below roundoff)"
                    + precision_note(t, self.t.dtype))
        if code == MAX_STEPS and int(self.n_accepted[sample] + self.n_rejected[sample]) < self.max_steps:
            return (f"max_steps = {self.interval_steps} steps between two grid nodes ran out at t = {t:.6g}: raise "
                    "`max_steps`, loosen `rtol`/`atol`, or check that the model is not far stiffer than expected")
        if code == MAX_STEPS:
            return (f"the step budget (max_steps={self.max_steps}) was spent at t = {t:.6g}: raise "
                    "`max_steps`, loosen `rtol`/`atol`, or check that the model is not far stiffer than expected")
        if code == STOPPED:
            return f"stopped at t = {t:.6g} by the caller's test on the values so far"
        return None


def precision_note(t: float, dtype: torch.dtype) -> str:
    """For a step-size underflow at time ``t`` in a precision below float64: the shortest step taken
    there (``10 eps |t|``) and that float64 takes shorter ones. Van der Pol (mu = 1000) in float32
    stops at its first jump near t = 807, where no step is shorter than 1e-3; '' in float64."""
    if dtype == torch.float64 or not dtype.is_floating_point:
        return ""
    name = str(dtype).removeprefix("torch.")
    return (f"; in {name} no step near t = {t:.6g} is shorter than 10 eps |t| = "
            f"{10 * torch.finfo(dtype).eps * abs(t):.2g}: the model in float64 (model.double(), float64 data) "
            "takes shorter ones")


def _stages(field: BatchedField, tab: tableau.Tensors, t, h, y, f0, J, ft) -> tuple[torch.Tensor, torch.Tensor, tuple]:
    """One Rodas5P step of every sample: the new states ``(A, M)``, the stage increments ``(8, A, M)``
    and the LU factorisation of ``I / (h gamma) - J``.

    ``t (A,)``, ``h (A,)`` (positive), ``y (A, M)``, and at ``(t, y)``: ``f0 (A, M)``, the Jacobian
    ``J (A, M, M)`` and the time derivative ``ft (A, M)``.
    """
    A, M = y.shape
    hc = h.unsqueeze(-1)
    inv_h = hc.reciprocal()
    W = -J
    W.diagonal(dim1=-2, dim2=-1).add_(inv_h, alpha=1.0 / tableau.GAMMA)
    LU, pivots, _ = torch.linalg.lu_factor_ex(W)
    K = y.new_empty(tableau.STAGES, A, M)
    flat = K.view(tableau.STAGES, A * M)  # combinations of the increments as one matrix product each
    times, hft = t + tab.nodes.unsqueeze(-1) * h, hc * ft
    arg = y
    for i in range(tableau.STAGES):
        if i == 0:
            rhs = torch.add(f0, hft, alpha=tableau.D[0])
        else:
            if i <= 5:  # the stage's argument and its right-hand side's increments in one product
                sums = (tab.ac[i] @ flat[:i]).view(2, A, M)
                arg, increments = y + sums[0], sums[1]
            else:  # the stiffly accurate stages run on at t + h
                arg, increments = arg + K[i - 1], (tab.c[i] @ flat[:i]).view(A, M)
            rhs = torch.addcmul(field(times[i], arg), inv_h, increments)
            if tableau.D[i]:
                rhs = rhs.add_(hft, alpha=tableau.D[i])
        K[i] = torch.linalg.lu_solve(LU, pivots, rhs.unsqueeze(-1)).squeeze(-1)
    return arg + K[-1], K, (LU, pivots)


def _dense_error(field: BatchedField, tab: tableau.Tensors, t, h, y, y_new, K, lu) -> torch.Tensor:
    """An estimate ``(A, M)`` of the dense output's error at the step's midpoint, from its defect.

    The dense output is of order 4 on smooth (non-stiff) components but of lower order on stiff
    ones, where the step size is far beyond their time scale and the step's own error estimate
    is tiny (e.g. the Prothero–Robinson problem ``y' = lambda (y - phi(t)) + phi'(t)`` with
    ``h lambda = -1e5``). The defect ``delta = p'(t_mid) - f(t_mid, p(t_mid))`` of the
    interpolant ``p`` maps to its error as ``(I / (h gamma) - J)^{-1} delta``: close to
    ``delta / |lambda|`` on stiff components (where it matches the true error closely) and to
    ``h gamma delta`` on smooth ones (within a small factor of the true error, which the step's
    own estimate bounds there).
    """
    q = tableau.stage_sums(tab.dense, K)
    mid = dense_value(y, y_new, q, 0.5)
    slope = (y_new - y + 0.25 * (q[1] + q[2])) / h.unsqueeze(-1)
    defect = slope - field(t + 0.5 * h, mid)
    return torch.linalg.lu_solve(lu[0], lu[1], defect.unsqueeze(-1)).squeeze(-1)


def _error_ratio(err, y, y_new, rtol, atol, norm) -> torch.Tensor:
    """The local error over its tolerance, ``(A,)`` (accept where ``<= 1``)."""
    scaled = err / (atol + rtol * torch.maximum(y.abs(), y_new.abs()))
    if norm is None:
        return scaled.square().mean(dim=1).sqrt()
    return norm(scaled)


def _initial_step(field: BatchedField, t, y, f0, span, n, rtol, atol) -> torch.Tensor:
    """Hairer's starting step size (Solving ODEs I, II.4) per sample, at most ``span``: ``(S,)``."""
    scale = atol + rtol * y[:, :n].abs()
    d0 = (y[:, :n] / scale).square().mean(dim=1).sqrt()
    d1 = (f0[:, :n] / scale).square().mean(dim=1).sqrt()
    h0 = torch.where((d0 > 1e-5) & (d1 > 1e-5), 0.01 * d0 / d1.clamp(min=1e-300), torch.full_like(d0, 1e-6))
    h0 = torch.minimum(h0, span)
    f1 = field(t + h0, y + h0.unsqueeze(-1) * f0)
    d2 = ((f1 - f0)[:, :n] / scale).square().mean(dim=1).sqrt() / h0
    big = torch.maximum(d1, d2)
    h1 = torch.where(big > 1e-15, (0.01 / big.clamp(min=1e-300)) ** _EXPONENT, (h0 * 1e-3).clamp(min=1e-6))
    return torch.minimum(torch.minimum(100 * h0, h1), span).clamp(min=torch.finfo(y.dtype).tiny)


class _Samples:
    """Every sample's running state: time, state, step size, the linearization at the current
    point (kept across rejected steps, which restart from the same point) and the controller's memory."""

    def __init__(self, field: BatchedField, y0: torch.Tensor, t0: torch.Tensor) -> None:
        S = y0.shape[0]
        self.t, self.y = t0.clone(), y0.clone()
        self.f0, self.J, self.ft = field.linearize(self.t, self.y)
        self.fresh = torch.ones(S, dtype=torch.bool, device=y0.device)
        self.h = torch.empty_like(self.t)
        self.h_prev = torch.zeros_like(self.t)  # last accepted step (0: none yet)
        self.err_prev = torch.ones_like(self.t)
        self.rejected = torch.zeros(S, dtype=torch.bool, device=y0.device)  # the last trial was rejected
        self.n_accepted = torch.zeros(S, dtype=torch.long, device=y0.device)
        self.n_rejected = torch.zeros_like(self.n_accepted)

    NAMES = ("t", "y", "f0", "J", "ft", "fresh", "h", "h_prev", "err_prev", "rejected", "n_accepted", "n_rejected")

    def take(self, rows: torch.Tensor | None) -> dict:
        """The state of samples ``rows`` (``None``: all, without copies)."""
        return {k: getattr(self, k) if rows is None else getattr(self, k)[rows] for k in self.NAMES}

    def put(self, rows: torch.Tensor | None, state: dict) -> None:
        for k in self.NAMES:
            if rows is None:
                setattr(self, k, state[k])
            else:
                getattr(self, k)[rows] = state[k]


def _controller(ratio, accept, he, st, exponent) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Next step size ``(A,)`` after a trial step ``he`` with error ratio ``ratio``, and the
    controller's memory (last accepted step and error) updated for the accepted samples.

    ``exponent``: ``1 / (order + 1)`` of the error that the ratio measures (a float, or ``(A,)``).
    """
    r = ratio.nan_to_num(nan=1e10, posinf=1e10).clamp(min=1e-10)
    growth = (_SAFETY * r ** -exponent).clamp(_MIN_FACTOR, _MAX_FACTOR)
    # Gustafsson's predictive controller (as Hairer's RODAS): the error's trend over the last two accepted steps
    predicted = _SAFETY * (he / st["h_prev"].clamp(min=1e-300)) * (st["err_prev"] / r.square()) ** exponent
    predicted = predicted.nan_to_num(nan=_MAX_FACTOR, posinf=_MAX_FACTOR).clamp(_MIN_FACTOR, _MAX_FACTOR)
    growth = torch.where(accept & (st["h_prev"] > 0), torch.minimum(growth, predicted), growth)
    # no growth right after a rejection, nor while rejecting
    growth = torch.where(~accept | st["rejected"], growth.clamp(max=1.0), growth)
    h_prev = torch.where(accept, he, st["h_prev"])
    err_prev = torch.where(accept, r.clamp(min=1e-2), st["err_prev"])
    return he * growth, h_prev, err_prev


def _round(field: BatchedField, tab: tableau.Tensors, grid: OutputGrid, samples: _Samples, active: torch.Tensor,
           n: int, rtol: float, atol: float, norm, steps: list | None
           ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """One trial step of every sample in ``active``: the accepted mask, the next step sizes,
    whether the trial's values were finite and whether the step landed on a node, each ``(A,)``;
    the accepted steps appended to ``steps`` (unless None) as
    :meth:`~torchql.solvers.steps.StepRecord.join` takes them."""
    rows = None if active.numel() == samples.t.shape[0] else active
    st = samples.take(rows)
    t, y, h = st["t"], st["y"], st["h"]
    stale = ~st["fresh"]
    if bool(stale.any()):  # the linearization at the points reached by the last accepted steps
        if bool(stale.all()):
            st["f0"], st["J"], st["ft"] = field.linearize(t, y)
        else:
            where = stale.nonzero().flatten()
            f0, J, ft = field.linearize(t[where], y[where])
            st["f0"], st["J"], st["ft"] = st["f0"].clone(), st["J"].clone(), st["ft"].clone()
            st["f0"][where], st["J"][where], st["ft"][where] = f0, J, ft
    target = grid.target(rows)
    gap = target - t
    clipped = h >= gap
    empty = clipped & (gap <= 0)  # a zero-length interval: its end value is its start value
    he = torch.where(clipped & ~empty, gap, (t + h) - t)  # the step the clock takes (as dopri_batch's)
    y_new, K, lu = _stages(field, tab, t, he, y, st["f0"], st["J"], st["ft"])
    ratio = _error_ratio(K[-1][:, :n], y[:, :n], y_new[:, :n], rtol, atol, norm)
    exponent = _EXPONENT
    t_new = torch.where(clipped, target, t + he)
    if grid.dense:  # steps that pass a node to interpolate: the dense output's error is controlled too
        passes = grid.passes(rows, t_new)
        if bool(passes.any()):
            i = passes.nonzero().flatten()
            err = _dense_error(field, tab, t[i], he[i], y[i], y_new[i], K[:, i], (lu[0][i], lu[1][i]))
            dense_ratio = _error_ratio(err[:, :n], y[i, :n], y_new[i, :n], rtol, atol, norm)
            dense_ratio = dense_ratio.nan_to_num(nan=float("inf"))
            ratio, exponent = ratio.clone(), torch.full_like(ratio, _EXPONENT)
            exponent[i[dense_ratio > ratio[i]]] = _DENSE_EXPONENT  # (in the ratio's dtype, not the default one)
            ratio[i] = torch.maximum(ratio[i], dense_ratio)
    y_new = torch.where(empty.unsqueeze(-1), y, y_new)
    ratio = torch.where(empty, torch.zeros_like(ratio), ratio)
    finite = torch.isfinite(y_new).all(dim=1) & torch.isfinite(ratio)
    accept = finite & (ratio <= 1.0)
    h_next, st["h_prev"], st["err_prev"] = _controller(ratio, accept, he, st, exponent)
    h_next = torch.where(empty, h, torch.where(accept & clipped, torch.maximum(h_next, h), h_next))
    take = accept.unsqueeze(-1)
    st["y"], st["t"] = torch.where(take, y_new, y), torch.where(accept, t_new, t)
    st["fresh"], st["rejected"], st["h"] = ~accept, ~accept, h_next
    st["n_accepted"], st["n_rejected"] = st["n_accepted"] + accept, st["n_rejected"] + ~accept
    samples.put(rows, st)
    glob = active
    if steps is not None:
        kept = (accept & ~empty).nonzero().flatten()
        steps.append((glob[kept], t[kept], he[kept], t_new[kept], y[kept], K[:, kept]))
    if grid.dense and bool(accept.any()):  # nodes passed inside accepted steps: filled from the steps at the end
        local = accept.nonzero().flatten()
        grid.skip_passed(glob[local], t_new[local])
    landed = accept & clipped
    if bool(landed.any()):
        grid.land(glob[landed], y_new[landed])
    return accept, h_next, finite, landed


def rodas5p_batch(f: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], y0: torch.Tensor, grid: torch.Tensor, *,
                  rtol: float, atol: float, max_steps: int = 100_000, land: torch.Tensor | None = None,
                  error_components: int | None = None, norm: Callable | None = None,
                  first_step: float | None = None, vectorize: bool = True, keep_steps: bool = False,
                  stop: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
                  interval_steps: int | None = None) -> RosenbrockSolution:
    """``y' = f(t, y)`` from ``y0 (S, M)`` over ``grid`` by Rodas5P, each sample on its own steps.

    Parameters
    ----------
    f : callable ``(t, y) -> dy/dt``, or a :class:`~torchql.solvers.field.BatchedField`
        One sample's right-hand side (``t`` 0-d, ``y (M,)`` -> ``(M,)``), written in torch
        operations that ``torch.func.jacrev`` (and, with ``vectorize``, ``torch.vmap``) can
        transform: an augmented system's ``system.f`` (coefficients as trailing components of
        ``y``, whose zero rows make them constants) or a model's ``forward``. A field given
        already (with its own Jacobian) is used as it is, and ``vectorize`` is its own.
    y0 : Tensor ``(S, M)``
        Initial states at each sample's first node; float32 or float64, on any device.
    grid : Tensor ``(G,)`` or ``(S, G)``
        Output times: shared, or each sample's own (rows non-decreasing, padded at the end by
        repeating the last node). Integration runs forward, from ``grid[..., 0]``.
    rtol, atol : float
        Tolerances of the local error, per component ``atol + rtol * max(|y|, |y_new|)``,
        measured in the RMS norm of each sample's first ``error_components`` components.
    max_steps : int
        Budget of trial steps (accepted and rejected) of each sample.
    interval_steps : int, optional
        Budget of trial steps of a sample between two nodes (a fit's ``max_steps``, which
        torchdiffeq counts per output time); a sample that spends it ends ``MAX_STEPS``.
    land : bool Tensor ``(G,)`` or ``(S, G)``, optional
        Nodes the steps land on exactly (default: every node; each sample's last node always).
        The others are filled by the order-4 dense output of the step that passes them, whose
        error is of the order of the controlled local error.
    error_components : int, optional
        How many leading components enter the error norm (default all): ``system.n`` for an
        augmented system, whose trailing coefficients never change.
    norm : callable, optional
        ``(A, M') -> (A,)``: the norm of each sample's scaled error (default RMS).
    first_step : float, optional
        The first trial step (default: Hairer's estimate per sample).
    vectorize : bool
        ``False`` calls ``f`` on the one sample (``S = 1``) without ``torch.vmap``.
    keep_steps : bool
        Return every accepted step (:class:`StepRecord`), e.g. to differentiate them.
    stop : callable, optional
        ``stop(rows (L,), y (L, G, M), reached (L,)) -> bool (L,)``, asked after the samples
        ``rows`` landed on a node, with their values at the nodes so far (NaN at nodes not yet
        reached or filled by the dense output, and at every node from ``reached`` on): the
        samples it says end there, ``STOPPED`` (e.g. a trial whose sum of squares over the data
        passed already exceeds the one it must beat). It is asked at each sample's last node
        too, where its answer is moot (the sample has finished), so that it sees every solution
        that finishes whole.

    Returns
    -------
    RosenbrockSolution
        ``y (S, G, M)`` (NaN where a sample failed), per-sample status, step counts and the
        evaluation counts. Failures are reported per sample, never raised.
    """
    y0, grid = _checked(y0, grid, rtol, atol, max_steps, land, error_components, vectorize, stop)
    if interval_steps is not None and (not isinstance(interval_steps, int) or interval_steps < 1):
        raise ValueError(f"`interval_steps` must be a positive integer or None; received {interval_steps!r}")
    S, M = y0.shape
    n = M if error_components is None else error_components
    field = f if isinstance(f, BatchedField) else BatchedField(f, vectorize=vectorize)
    out = OutputGrid(grid, land, y0)
    status = torch.where(torch.isfinite(y0).all(dim=1), SUCCESS, NON_FINITE)
    t0 = grid[:, 0] if grid.dim() == 2 else grid[0].expand(S)
    if grid.shape[-1] == 1:
        return RosenbrockSolution(out.result(status == SUCCESS), status, t0.clone(), *[torch.zeros_like(status)] * 2,
                                  0, 0, max_steps, StepRecord.join([], y0) if keep_steps else None, interval_steps)
    samples = _Samples(field, y0, t0)
    span = grid[..., -1] - grid[..., 0]
    if first_step is None:
        samples.h = _initial_step(field, samples.t, samples.y, samples.f0, span.expand(S), n, rtol, atol)
    else:
        samples.h = torch.full_like(samples.t, float(first_step))
    tab = tableau.Tensors(y0.dtype, y0.device)
    steps = [] if keep_steps or out.dense else None
    run = _one_sample if S == 1 else _batched
    run(field, tab, out, samples, status, n, rtol, atol, norm, (max_steps, interval_steps), stop, steps)
    record = None if steps is None else StepRecord.join(steps, y0)
    if out.dense:
        out.fill_between(record, tab)
    return RosenbrockSolution(out.result(status == SUCCESS), status, samples.t, samples.n_accepted,
                              samples.n_rejected, field.n_f, field.n_jac, max_steps, record if keep_steps else None,
                              interval_steps)


def _batched(field, tab, out: OutputGrid, samples: _Samples, status, n, rtol, atol, norm, budgets, stop, steps
             ) -> None:
    """:func:`rodas5p_batch`'s loop: rounds of one trial step of every unfinished sample until
    each has finished or failed; ``samples``, ``status`` (``(S,)``, in place), ``out`` and ``steps`` updated.
    ``budgets``: ``(max_steps, interval_steps)``."""
    max_steps, interval_steps = budgets
    tiny, eps = torch.finfo(samples.y.dtype).tiny, torch.finfo(samples.y.dtype).eps
    active = ((status == SUCCESS) & out.unfinished()).nonzero().flatten()
    since = torch.zeros_like(out.node)  # trial steps since each sample's last node
    while active.numel():
        check_time()
        before = out.node[active].clone()
        accept, h_next, finite, landed = _round(field, tab, out, samples, active, n, rtol, atol, norm, steps)
        finished = ~out.unfinished()[active]
        ta = samples.t[active]
        underflow = (h_next <= 10 * eps * ta.abs()) | (h_next <= tiny)
        spent = samples.n_accepted[active] + samples.n_rejected[active] >= max_steps
        if interval_steps is not None:
            since[active] = torch.where(out.node[active] > before, 0, since[active] + 1)
            spent |= since[active] >= interval_steps
        code = torch.where(spent, MAX_STEPS, torch.where(underflow, STEP_UNDERFLOW, SUCCESS))
        # a sample that keeps failing on non-finite values ends as such, not as an underflow
        code = torch.where((code == STEP_UNDERFLOW) & ~finite, NON_FINITE, code)
        code = torch.where(finished, SUCCESS, code)
        if stop is not None:
            code = _stopped(stop, out, active, landed & (code == SUCCESS), finished, code)
        status[active] = code
        active = active[(code == SUCCESS) & ~finished]


def _one_sample(field, tab, out: OutputGrid, samples: _Samples, status, n, rtol, atol, norm, budgets, stop, steps
                ) -> None:
    """:func:`_batched` for one sample (``S = 1``), step for step the same (to the bit), its step
    control in Python numbers: a batched round's bookkeeping (masks, gathers and scatters over the
    active samples) costs more than the step's own arithmetic where the system is small."""
    if int(status[0]) != SUCCESS:
        return
    max_steps, interval_steps = budgets
    since = 0  # trial steps since the last node
    tiny, eps = torch.finfo(samples.y.dtype).tiny, torch.finfo(samples.y.dtype).eps
    times, landing, nxt = out._times.tolist(), out._landing.tolist(), out._next.tolist()
    G, end = out.G, out.G if out.end is None else int(out.end[0])
    node, first = int(out.node[0]), samples.t.new_zeros(1, dtype=torch.long)
    t, h, y, (f0, J, ft) = float(samples.t[0]), float(samples.h[0]), samples.y, (samples.f0, samples.J, samples.ft)
    h_prev, err_prev, fresh, rejected, accepted, failed, code = 0.0, 1.0, True, False, 0, 0, SUCCESS
    while node < end:
        check_time()
        node_before = node
        tt = samples.t.new_tensor([t])
        if not fresh:
            f0, J, ft = field.linearize(tt, y)
        target = times[nxt[node]]
        gap = target - t
        clipped = h >= gap
        empty = clipped and gap <= 0
        he = gap if clipped and not empty else (t + h) - t  # the step the clock takes (as dopri_batch's)
        ht = samples.t.new_tensor([he])
        y_new, K, lu = _stages(field, tab, tt, ht, y, f0, J, ft)
        ratio = float(_error_ratio(K[-1][:, :n], y[:, :n], y_new[:, :n], rtol, atol, norm))
        exponent = _EXPONENT
        t_new = target if clipped else t + he
        at = min(node, G - 1)
        if out.dense and times[at] < t_new and not landing[at]:  # the dense output's error too
            err = _dense_error(field, tab, tt, ht, y, y_new, K, lu)
            dense = float(_error_ratio(err[:, :n], y[:, :n], y_new[:, :n], rtol, atol, norm))
            dense = math.inf if math.isnan(dense) else dense
            exponent = _DENSE_EXPONENT if dense > ratio else _EXPONENT
            ratio = ratio if math.isnan(ratio) else max(ratio, dense)
        if empty:
            y_new, ratio = y, 0.0
        finite = math.isfinite(ratio) and bool(torch.isfinite(y_new).all())
        accept = finite and ratio <= 1.0
        h_next, h_prev, err_prev = _scalar_controller(ratio, accept, he, h_prev, err_prev, rejected, exponent)
        h_next = h if empty else (max(h_next, h) if accept and clipped else h_next)
        if steps is not None and accept and not empty:
            steps.append((first, tt, ht, samples.t.new_tensor([t_new]), y, K))
        if accept:
            y, t, f0, J, ft = y_new, t_new, None, None, None
            if out.dense:  # nodes passed inside the step: filled from the steps at the end
                node = max(node, min(bisect.bisect_left(times, t_new, hi=G), nxt[at]))
                out.node[0] = node
            if clipped:
                out.land(first, y_new)
                node += 1
        fresh = rejected = not accept
        h = h_next
        accepted, failed = accepted + accept, failed + (not accept)
        since = 0 if node > node_before else since + 1
        code = SUCCESS
        if accepted + failed >= max_steps or interval_steps is not None and since >= interval_steps:
            code = MAX_STEPS
        elif h_next <= 10 * eps * abs(t) or h_next <= tiny:
            code = STEP_UNDERFLOW if finite else NON_FINITE
        if node >= end:
            code = SUCCESS
        if stop is not None and accept and clipped and code == SUCCESS and bool(stop(first, out.out[first], out.node)[0]):
            code = SUCCESS if node >= end else STOPPED
        if code != SUCCESS:
            break
    status[0] = code
    samples.t[0], samples.y = t, y
    samples.n_accepted[0], samples.n_rejected[0] = accepted, failed


def _scalar_controller(ratio: float, accept: bool, he: float, h_prev: float, err_prev: float, rejected: bool,
                       exponent: float) -> tuple[float, float, float]:
    """:func:`_controller` of one sample in Python numbers: ``(next step, h_prev, err_prev)``."""
    r = max(1e10 if math.isnan(ratio) or ratio == math.inf else ratio, 1e-10)
    growth = min(max(_SAFETY * r ** -exponent, _MIN_FACTOR), _MAX_FACTOR)
    predicted = _SAFETY * (he / max(h_prev, 1e-300)) * (err_prev / (r * r)) ** exponent
    predicted = _MAX_FACTOR if math.isnan(predicted) or predicted == math.inf else predicted
    if accept and h_prev > 0:
        growth = min(growth, min(max(predicted, _MIN_FACTOR), _MAX_FACTOR))
    if not accept or rejected:
        growth = min(growth, 1.0)
    if accept:
        h_prev, err_prev = he, max(r, 1e-2)
    return he * growth, h_prev, err_prev


def _stopped(stop, out: OutputGrid, active, asked, finished, code) -> torch.Tensor:
    """``code`` with ``STOPPED`` where ``stop`` ends the samples ``active[asked]`` that have not ``finished``."""
    if not bool(asked.any()):
        return code
    rows = active[asked]
    ended = torch.zeros_like(asked)
    ended[asked] = stop(rows, out.out[rows], out.node[rows])
    return torch.where(ended & ~finished, STOPPED, code)


def _checked(y0, grid, rtol, atol, max_steps, land, error_components, vectorize, stop):
    """:func:`rodas5p_batch`'s arguments validated (``ValueError``/``TypeError`` naming the argument)."""
    if not isinstance(y0, torch.Tensor) or not y0.is_floating_point() or y0.dim() != 2 or 0 in y0.shape:
        got = f"shape {tuple(y0.shape)}, dtype {y0.dtype}" if isinstance(y0, torch.Tensor) else type(y0).__name__
        raise TypeError(f"`y0` must be a floating-point tensor of shape (S, M), S, M >= 1; received {got}")
    S, M = y0.shape
    if not isinstance(grid, torch.Tensor) or grid.dim() not in (1, 2) or grid.shape[-1] == 0:
        got = f"shape {tuple(grid.shape)}" if isinstance(grid, torch.Tensor) else type(grid).__name__
        raise ValueError(f"`grid` must be a tensor of shape (G,) or (S, G) with G >= 1; received {got}")
    if grid.dim() == 2 and grid.shape[0] != S:
        raise ValueError(f"`grid` of shape (S, G) must have S = {S} rows (those of `y0`); received {grid.shape[0]}")
    if grid.dtype != y0.dtype or grid.device != y0.device:
        raise TypeError(f"`grid` must have `y0`'s dtype and device ({y0.dtype}, {y0.device}); "
                        f"received {grid.dtype}, {grid.device}")
    if not bool(torch.isfinite(grid).all()) or not bool((grid[..., 1:] >= grid[..., :-1]).all()):
        raise ValueError("`grid` must be finite and non-decreasing along its last axis")
    for name, value in (("rtol", rtol), ("atol", atol)):
        if not isinstance(value, (int, float)) or not value > 0 or value == float("inf"):
            raise ValueError(f"`{name}` must be a positive finite number; received {value!r}")
    if not isinstance(max_steps, int) or max_steps < 1:
        raise ValueError(f"`max_steps` must be a positive integer; received {max_steps!r}")
    if land is not None and (land.dtype != torch.bool or land.shape not in ((grid.shape[-1],), (S, grid.shape[-1]))):
        raise ValueError(f"`land` must be a bool tensor of shape (G,) or (S, G) = ({S}, {grid.shape[-1]}); "
                         f"received {land.dtype}, shape {tuple(land.shape)}")
    if error_components is not None and not (isinstance(error_components, int) and 1 <= error_components <= M):
        raise ValueError(f"`error_components` must be an integer in [1, {M}]; received {error_components!r}")
    if not vectorize and S != 1:
        raise ValueError(f"`vectorize=False` needs a single sample (S = 1); received S = {S}")
    if stop is not None and not callable(stop):
        raise TypeError(f"`stop` must be a callable (rows, y, reached) -> bool tensor, or None; received "
                        f"{type(stop).__name__}")
    return y0, grid
