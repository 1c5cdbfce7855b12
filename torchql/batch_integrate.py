"""Integration for a batch of independent samples, each on its own error control.

The samples share one time grid ``(G,)`` or each has its own, ``(S, G)``: a row of a
per-sample grid is non-decreasing, and a sample whose grid is shorter than ``G`` nodes repeats
its last node up to ``G`` (zero-length intervals, whose transfer is the identity). Every
tolerance that is spread over a grid's intervals is spread over the sample's own intervals of
positive length, so a sample's solution is the one its grid alone would give.

No sample's error is averaged with (diluted by) another's: every integrator below makes its
step decisions per sample (or per sample and grid interval), and reports failures per sample
(a boolean mask or a message), never raised for the whole batch.

* :func:`propagate_linear_batch`: the particular and homogeneous solutions of each sample's
  quasilinear system, by the Taylor-series interval transfers of :mod:`torchql.taylor` over
  ``samples x intervals`` flattened (each interval of each sample with its own substeps and
  truncation bound), composed per sample by the prefix scan.
* :func:`~torchql.dopri.dopri_batch` (re-exported here): the nonlinear (augmented) model by
  Dormand–Prince 5(4), every sample with its own time, step size and accept/reject decision.
* :func:`~torchql.grid_solve.solve_on_grid_batch` (in its own module): the nonlinear model by
  multiple shooting from a guess, Newton converging per sample.
* :func:`integrate_each`: one sample at a time by torchdiffeq, the last resort (as
  :func:`torchql.fit` uses it).

Each sample's coefficients are its trailing components of the augmented state ``z = (x, p)``,
so one vmapped right-hand side serves every sample.
"""

from __future__ import annotations

import torch

from .dopri import dopri_batch
from .integrate import CountedField, IntegrationError, interval_tolerances, solve
from .grid import interval_counts, last_nodes
from .model import AugmentedSystem
from .taylor import series_transfers
from .transfer import _Coefficients, interval_coefficients, prefix_products

__all__ = ["propagate_linear_batch", "interval_coefficients", "dopri_batch", "integrate_each"]


def propagate_linear_batch(t: torch.Tensor, z: torch.Tensor, z_dot: torch.Tensor, lin, w0: torch.Tensor, *,
                           rtol: float, atol: float, max_substeps: int = 1024, propagator=None,
                           coefficients: _Coefficients | None = None) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Particular and homogeneous solutions of ``S`` samples' quasilinear systems on the grid ``t``.

    Parameters
    ----------
    t : Tensor ``(G,)`` or ``(S, G)``
        The grid, shared by the samples, or each sample's own (padded at the end by repeating
        its last node).
    z, z_dot : Tensor ``(S, G, M)``
        Each sample's reference and its slopes at the nodes.
    lin : Linearization
        ``f (S, G, M)``, ``jac (S, G, M, M)``, ``f_dot``, ``jac_dot`` along each reference.
    w0 : Tensor ``(S, M, 1 + m)``
        Initial columns (particular first).
    rtol, atol : float
        Tolerances of a whole propagation, as :func:`torchql.superposition.propagate_linear`
        (each interval gets them divided by the square root of the number of intervals: ``G - 1``
        on a shared grid, the sample's intervals of positive length on per-sample grids).
    max_substeps : int
        Most substeps on one interval (see :func:`torchql.taylor.series_transfers`).
    propagator : LinearPropagator, optional
        Whose batched :meth:`~torchql.propagators.LinearPropagator.series` integrates the
        intervals (default: the Taylor series).
    coefficients : _Coefficients, optional
        The intervals' coefficients, if already built (:func:`torchql.transfer.interval_coefficients`
        of these arguments, in the propagator's degree).

    Returns
    -------
    W : Tensor ``(S, G, M, 1 + m)``
        The columns at every node (NaN for failed samples).
    failed : bool Tensor ``(S,)``
        Samples with an interval that could not meet the tolerance or became non-finite.
    n_evals : int
        Series terms computed, one interval-substep's term counting one.
    """
    S, G, M = z.shape
    cols = w0.shape[-1]
    if G == 1:
        return w0.unsqueeze(1).clone(), torch.zeros(S, dtype=torch.bool, device=z.device), 0
    N = G - 1
    if coefficients is None:
        coefficients = interval_coefficients(t, z, z_dot, lin, 3 if propagator is None else propagator.hermite_degree)
    series = _taylor_series if propagator is None else propagator.series
    if t.dim() == 1:
        rtol_j, atol_j = interval_tolerances(rtol, atol, N, z.dtype)
        Y, failed, points = series(coefficients, rtol=rtol_j, atol=atol_j, max_substeps=max_substeps)
    else:
        Y, failed, points = _series_per_sample(coefficients, interval_counts(t), rtol, atol, max_substeps, series)
    order = coefficients.order
    failed = failed.reshape(S, N).any(dim=1)
    a, P = Y.shape[0], Y.shape[1]
    Yb = Y.reshape(a, P, S, N).permute(2, 0, 1, 3)  # (S, a, M+1, N)
    one = torch.zeros(S, 1, cols, dtype=w0.dtype, device=w0.device)
    one[:, 0, 0] = 1.0
    w = torch.cat([w0, one], dim=1)[:, order]  # (S, M+1, cols)
    W = w0.unsqueeze(1).repeat(1, G, 1, 1)
    if a:
        Pr = prefix_products(Yb)  # (S, a, M+1, N)
        W[:, 1:, order[:a]] = torch.einsum("sapn,spc->snac", Pr, w)
    W[failed] = float("nan")
    return W, failed, points


def _taylor_series(coefficients: _Coefficients, *, rtol: float, atol: float, max_substeps: int):
    """:func:`torchql.taylor.series_transfers` as ``(Y, failed, points)``."""
    out = series_transfers(coefficients, rtol=rtol, atol=atol, max_substeps=max_substeps)
    return out.Y, out.failed, out.points


def _series_per_sample(coefficients: _Coefficients, counts: torch.Tensor, rtol: float, atol: float,
                       max_substeps: int, series=_taylor_series) -> tuple[torch.Tensor, torch.Tensor, int]:
    """``series`` (default the Taylor series) of ``S`` samples' ``N`` intervals each, per-sample tolerances.

    ``counts (S,)``: each sample's intervals of positive length, over whose square root its
    tolerances are divided. Samples with the same count are integrated in one call (an
    interval's transfer does not depend on the intervals integrated with it). Returns
    ``Y (a, M+1, S N)``, ``failed (S N,)`` and the work done.
    """
    S = counts.shape[0]
    data = coefficients.data
    N = data.shape[-1] // S
    dtype = data.dtype
    values = counts.unique().tolist()
    if len(values) == 1:
        rtol_j, atol_j = interval_tolerances(rtol, atol, values[0], dtype)
        return series(coefficients, rtol=rtol_j, atol=atol_j, max_substeps=max_substeps)
    Y = data.new_zeros(coefficients.a, coefficients.M + 1, S * N)
    failed = torch.zeros(S * N, dtype=torch.bool, device=data.device)
    points = 0
    for value in values:
        samples = (counts == value).nonzero().flatten()
        columns = (samples.unsqueeze(1) * N + torch.arange(N, device=data.device)).flatten()
        part = _Coefficients.of(data[..., columns], coefficients.order, coefficients.a, coefficients.M,
                                coefficients.jacobian_degree, samples=samples.numel())
        rtol_j, atol_j = interval_tolerances(rtol, atol, value, dtype)
        Y_part, failed_part, work = series(part, rtol=rtol_j, atol=atol_j, max_substeps=max_substeps)
        Y[..., columns], failed[columns] = Y_part, failed_part
        points += work
    return Y, failed, points


def integrate_each(system: AugmentedSystem, z0: torch.Tensor, grid: torch.Tensor, *, solver: str, rtol: float,
                   atol: float, hit: torch.Tensor | None, max_steps: int | None = None) -> tuple[torch.Tensor, list, int]:
    """Each sample's model integrated on its own by torchdiffeq (the fallback of :func:`solve_on_grid_batch`).

    ``grid``: the shared grid ``(G,)`` or each sample's own ``(S, G)`` (padded at the end by
    repeating its last node: a sample is integrated on its grid up to its final time, and the
    padding repeats its last value). ``hit``: times the solver steps onto, shared ``(T,)`` or
    per sample ``(S, T)``.

    Returns ``traj (S, G, M)`` (NaN for failures), one error message or ``None`` per sample,
    and the right-hand-side evaluations.
    """
    S, M = z0.shape
    n = system.n
    G = grid.shape[-1]
    out = z0.new_full((S, G, M), float("nan"))
    errors: list = [None] * S
    n_evals = 0
    ends = (last_nodes(grid) + 1).tolist() if grid.dim() == 2 else [G] * S
    for s in range(S):
        model = system.model_with(z0[s, n:])
        counter = CountedField(model)
        end = ends[s]
        own = grid[s, :end] if grid.dim() == 2 else grid
        try:
            with torch.no_grad():
                x = solve(counter, z0[s, :n], own, solver=solver, rtol=rtol, atol=atol,
                          hit=hit[s] if hit is not None and hit.dim() == 2 else hit, max_steps=max_steps,
                          jumps=model.input_jumps() if hasattr(model, "input_jumps") else None)
            out[s, :end, :n] = x
            out[s, end:, :n] = x[-1]
            out[s, :, n:] = z0[s, n:]
        except IntegrationError as exc:
            errors[s] = str(exc)
        n_evals += counter.n_evals
    return out, errors, n_evals
