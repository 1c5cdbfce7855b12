"""Kantorovich's storage grid: the times at which an iterate trajectory is stored.

One builder serves :func:`torchql.fit` and :func:`torchql.fit_many` (each sample's grid is the one
``fit`` builds for that dataset alone). The grid holds ``t0``, every observation time, and
``intervals`` uniform intervals (default :data:`DEFAULT_INTERVALS`) or the user's extra times.

The default, ``grid="auto"``, chooses each sample's uniform intervals from its first reference
(:func:`auto_counts`): the first reference is built on :data:`AUTO_PROBE` intervals, and the fit
goes on with the fewest of :data:`AUTO_COUNTS` whose cubic Hermite interpolation of that trajectory
stays within :data:`AUTO_SAFETY` times the tolerance, taken from the probe's nodes
(:func:`coarse_index`) where they divide it, built anew where the trajectory needs more.

A stiff model's solution has fast transients (Robertson kinetics: a boundary layer of width
``1e-4`` on a span of ``1e5``) that uniform nodes cannot represent: with ``stiff=True``
:data:`NODES_PER_DECADE` geometrically spaced nodes per decade are added from
``t0 + EARLIEST * span`` to the end (:func:`geometric_nodes`), so every interval is short against
the time since ``t0``; ``grid="auto"`` then chooses the uniform intervals besides them
(:meth:`torchql.engine_grid.AutoGrid._stiff_counts`).
"""

from __future__ import annotations

import math

import torch

__all__ = ["make_grid", "make_grids", "check_grid_times", "interval_counts", "last_nodes", "refine",
           "needed_intervals", "auto_counts", "uniform_nodes", "nearest_nodes", "geometric_nodes", "coarse_index",
           "smooth_intervals", "AUTO_PROBE", "AUTO_COUNTS", "AUTO_SAFETY", "DEFAULT_INTERVALS", "MIN_INTERVALS",
           "NODES_PER_DECADE", "EARLIEST", "SMOOTH_SAFETY", "SMOOTH_SAMPLES", "SMOOTH_RTOL"]

#: Uniform intervals of the default grid.
DEFAULT_INTERVALS = 1000
#: Fewest uniform intervals of a grid chosen from the trajectory (``grid="smooth"``).
MIN_INTERVALS = 20
#: ``grid="smooth"``: the cubic Hermite interpolation error allowed between nodes, as a fraction
#: of the tolerance ``atol + rtol |x|`` (a sixteenth: each halving of the intervals gains 16).
SMOOTH_SAFETY = 1 / 16
#: ``grid="smooth"``: uniform intervals at which the guesses' trajectories are sampled (the
#: fourth derivative is estimated by third differences of the slopes at this spacing).
SMOOTH_SAMPLES = 125
#: ``grid="smooth"``: the guesses' trajectories are integrated at this relative tolerance (or the
#: fit's, if looser): the fourth derivative is needed to a few percent, not to the fit's tolerance
#: (on cars and oscillators 1e-6 to 1e-10 gave the same counts within one interval).
SMOOTH_RTOL = 1e-8
#: ``grid="auto"``: uniform intervals of the probe grid on which the first reference is built. The
#: probe is where the data start matches the model's slopes at every node, so its size is most of
#: the start's cost; 100 nodes still sample an oscillation of ten periods ten times a period (the
#: largest slopes and rates, from which the count is taken, within 5 %). On 1,000 cars and 1,000
#: oscillators (``benchmarks/batch.py``'s) 200 intervals took 17 % and 6 % longer, with the same
#: counts for the cars and 5 % more samples at 200 for the oscillators.
AUTO_PROBE = 100
#: ``grid="auto"``: the uniform interval counts it chooses from; those dividing :data:`AUTO_PROBE`
#: take the probe's nodes (the first reference is not built again).
AUTO_COUNTS = (20, 25, 40, 50, 100, 200, 250, 500, 1000)
#: ``grid="auto"``: the cubic Hermite interpolation error allowed between nodes, relative to the
#: states' magnitudes (``atol`` scaled alike): this fraction of ``sqrt(rtol)``. A storage grid's error
#: enters a Kantorovich fixed point to first order, and the final pass's Gauss–Newton steps on the
#: model itself take it out (:mod:`torchql.engine_final`), to the second order in it where the data
#: are exact, and through the Jacobian's own error (a fraction of the estimates' standard errors)
#: where they are noisy; so the grid need only be as fine as ``sqrt(rtol)``, where the fixed default
#: asked ``rtol`` (4 to 18 times fewer intervals).
AUTO_SAFETY = 1 / 16
#: Geometric nodes per decade of ``t - t0`` added for stiff models.
NODES_PER_DECADE = 10
#: The earliest geometric node, as a fraction of the span after ``t0``. On Robertson kinetics to
#: ``t = 1e5`` (boundary layer of width ``~1e-4``, sigma 1 % of each value) ``1e-9`` left one interval
#: ``[0, 1e-4]`` over the layer, and the Kantorovich fixed point 8e-5 (relative) from the optimum
#: (SSE 91.4166 against 91.4153, whatever the nodes per decade); ``1e-13`` puts it within 3e-7 of
#: the SSE (91.41535), and ``1e-16`` changes nothing more.
EARLIEST = 1e-13


def check_grid_times(grid: torch.Tensor) -> None:
    """A ``grid`` of extra times: a one-dimensional tensor of finite real times."""
    if grid.dim() != 1 or grid.is_complex() or grid.dtype == torch.bool:
        raise ValueError(f"`grid` given as times must be a one-dimensional tensor of real times; received shape "
                         f"{tuple(grid.shape)}, dtype {grid.dtype}")
    if not bool(torch.isfinite(grid).all()):
        raise ValueError("`grid` times must be finite; received NaN or inf")


def make_grid(grid, t0: torch.Tensor, t_obs: torch.Tensor, *, stiff: bool = False,
              breakpoints: torch.Tensor | None = None) -> torch.Tensor:
    """The storage grid ``(G,)``: sorted, distinct, from ``t0`` to the last observation time.

    Parameters
    ----------
    grid : int, Tensor or None
        Number of uniform intervals (default :data:`DEFAULT_INTERVALS`), or extra times (those
        strictly between ``t0`` and the last observation are kept, with the default intervals).
    t0 : Tensor ``()``
        Initial time.
    t_obs : Tensor ``(T,)``
        Observation times, increasing, none before ``t0``.
    stiff : bool
        Add geometrically spaced early nodes (see the module's description).
    breakpoints : Tensor ``(N,)``, optional
        Times where the right-hand side is not smooth (a measured input's
        :attr:`~torchql.inputs.Inputs.nodes`), made nodes.
    """
    dtype, device = t_obs.dtype, t_obs.device
    t_end = t_obs[-1]
    span = float(t_end - t0)
    extra = torch.zeros(0, dtype=dtype, device=device)
    intervals = DEFAULT_INTERVALS
    if isinstance(grid, torch.Tensor):
        check_grid_times(grid)
        extra = grid.detach().to(dtype=dtype, device=device)
        extra = extra[(extra > t0) & (extra < t_end)]
    elif grid is not None:
        if isinstance(grid, bool) or not isinstance(grid, int) or grid < 1:
            raise ValueError(f"`grid` must be a positive number of intervals or a tensor of times; received {grid!r}")
        intervals = int(grid)
    if span <= 0:
        return t0.reshape(1)
    uniform = torch.linspace(float(t0), float(t_end), intervals + 1, dtype=dtype, device=device)
    if stiff:
        uniform = torch.cat([uniform, geometric_nodes(t0.reshape(1), t_end.reshape(1))[0]])
    fixed = torch.cat([t0.reshape(1), t_obs])
    # drop free nodes that nearly coincide with a fixed node (tiny intervals help nothing)
    gap = torch.cdist(uniform.unsqueeze(-1), fixed.unsqueeze(-1)).min(dim=1).values
    uniform = uniform[gap > 1e-6 * (uniform - t0).clamp(min=0).clamp(max=span / intervals)]
    if breakpoints is not None:
        nodes = breakpoints.to(dtype=dtype, device=device)
        extra = torch.cat([extra, nodes[(nodes > t0) & (nodes < t_end)]])
    return torch.unique(torch.cat([fixed, uniform, extra]))


def make_grids(grid, t0: torch.Tensor, t_obs: torch.Tensor, stiff: bool = False,
               breakpoints: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Each sample's own grid, as :func:`torchql.fit` builds it for that dataset alone.

    ``t0``: shared ``()`` or per sample ``(B,)``; ``t_obs (B, T)``. Returns the grids ``(B, G)``,
    each padded at the end by repeating its last node up to the longest one's ``G`` nodes
    (zero-length intervals), and each grid's own number of nodes ``(B,)``. Samples with the
    same ``t0`` and times share one construction.
    """
    B = t_obs.shape[0]
    starts = t0.expand(B) if t0.dim() == 0 else t0
    keys, inverse = torch.unique(torch.cat([starts.unsqueeze(1), t_obs], dim=1), dim=0, return_inverse=True)
    grids = [make_grid(grid, key[0], key[1:], stiff=stiff, breakpoints=breakpoints) for key in keys]
    sizes = torch.tensor([g.numel() for g in grids], dtype=torch.long, device=t_obs.device)
    G = int(sizes.max())
    padded = torch.stack([torch.cat([g, g[-1:].expand(G - g.numel())]) for g in grids])
    return padded[inverse], sizes[inverse]


def interval_counts(grid: torch.Tensor) -> torch.Tensor:
    """Intervals of positive length of each sample's grid ``(S, G)``: ``(S,)`` (padding excluded)."""
    return (grid[:, 1:] > grid[:, :-1]).sum(dim=1)


def last_nodes(grid: torch.Tensor) -> torch.Tensor:
    """Index of the first node at each sample's final time, ``(S,)``, of grids ``(S, G)`` (its padding follows)."""
    return (grid < grid[:, -1:]).sum(dim=1)


def smooth_intervals(times: torch.Tensor, x: torch.Tensor, slopes: torch.Tensor, rtol: float, atol: float) -> int:
    """The fewest uniform intervals whose cubic Hermite interpolation of trajectories meets the tolerance.

    ``times (G,)`` or per sample ``(S, G)``, uniform from ``t0`` to the end; ``x, slopes (S, G, n)``
    the trajectories and their slopes there. Over an interval of width ``h`` the interpolation error is at most
    ``h^4 / 384`` times the largest fourth derivative of ``x``, the third derivative of the
    slopes, estimated by third differences at a spacing of about ``1 / SMOOTH_SAMPLES`` of the span
    (every node of :data:`SMOOTH_SAMPLES` intervals; every eighth of 1000). Each component's error must
    stay below :data:`SMOOTH_SAFETY` times ``atol + rtol max |x|``; the count is the largest any
    sample needs, between :data:`MIN_INTERVALS` and :data:`DEFAULT_INTERVALS` (the default where
    a trajectory is not finite).
    """
    S = x.shape[0]
    times = times.expand(S, times.shape[-1])
    every = max(1, (times.shape[-1] - 1) // SMOOTH_SAMPLES)
    if slopes[:, ::every].shape[1] < 4 or not bool((times[:, -1] > times[:, 0]).all()):
        return DEFAULT_INTERVALS
    f, H = slopes[:, ::every], (times[:, every] - times[:, 0]).reshape(S, 1, 1)
    fourth = (f[:, 3:] - 3 * f[:, 2:-1] + 3 * f[:, 1:-2] - f[:, :-3]) / H**3  # third differences of the slopes
    needed = needed_intervals(fourth, x, SMOOTH_SAFETY * rtol, SMOOTH_SAFETY * atol, times[:, -1] - times[:, 0])
    if not bool(torch.isfinite(needed).all()):
        return DEFAULT_INTERVALS
    return min(DEFAULT_INTERVALS, max(MIN_INTERVALS, math.ceil(float(needed.max()))))


#: The largest error of Hermite interpolation over an interval of width ``h``, by degree: ``h^(d+1)``
#: times the derivative of order ``d + 1`` divided by this (cubic: ``4! 2^4``; quintic: ``6! 2^6``).
HERMITE_ERROR_DIVISOR = {3: 384.0, 5: 46080.0}


def needed_intervals(derivative: torch.Tensor, x: torch.Tensor, rtol: float, atol: float,
                     span: torch.Tensor, degree: int = 3) -> torch.Tensor:
    """Uniform intervals ``(S,)`` (real-valued; inf where not finite) that a Hermite interpolation of
    degree ``degree`` (3, cubic, or 5, quintic) of trajectories needs to stay within ``atol + rtol
    max |x|`` per component.

    ``derivative (S, P, n)``: the trajectories' derivatives of order ``degree + 1`` (the fourth for
    cubic interpolation) at nodes spread over the span; ``x (S, G, n)``: their values (the scale of
    the tolerance); ``span (S,)``: the length to cover. Over an interval of width ``h`` the error
    is at most ``h^(degree+1)`` times the largest such derivative over
    :data:`HERMITE_ERROR_DIVISOR` (``h^4 / 384`` for cubic interpolation).
    """
    tol = atol + rtol * x.abs().amax(dim=1)
    size = derivative.abs().amax(dim=1).clamp(min=torch.finfo(x.dtype).tiny)
    width = (HERMITE_ERROR_DIVISOR[degree] * tol / size) ** (1.0 / (degree + 1))
    needed = span / width.amin(dim=1)
    return torch.where(torch.isfinite(needed), needed, torch.full_like(needed, math.inf))


def auto_counts(needed: torch.Tensor) -> torch.Tensor:
    """The fewest of :data:`AUTO_COUNTS` at least ``needed (S,)``: ``(S,)`` long (the most where none is)."""
    counts = torch.tensor(AUTO_COUNTS, dtype=needed.dtype, device=needed.device)
    index = torch.searchsorted(counts, needed.contiguous()).clamp(max=len(AUTO_COUNTS) - 1)
    return counts.to(torch.long)[index]


def geometric_nodes(t0: torch.Tensor, t_end: torch.Tensor) -> torch.Tensor:
    """The geometric nodes of a stiff model's grid, ``(S, K)``, from ``t0 + EARLIEST * span`` on
    (:data:`NODES_PER_DECADE` per decade; the end excluded), for ``t0``, ``t_end (S,)``."""
    decades = round(-math.log10(EARLIEST))
    ratios = torch.logspace(-float(decades), 0.0, decades * NODES_PER_DECADE + 1, dtype=t0.dtype, device=t0.device)
    return t0.unsqueeze(1) + (t_end - t0).unsqueeze(1) * ratios[:-1]


def uniform_nodes(grid: torch.Tensor, t0: torch.Tensor, t_end: torch.Tensor, intervals: int) -> torch.Tensor:
    """For each sample, the index of the node of ``grid`` (``(G,)`` or ``(S, G)``, sorted) nearest to each
    of the ``intervals + 1`` uniform times from ``t0 (S,)`` to ``t_end (S,)``: ``(S, intervals + 1)``.

    On a grid built with that many uniform intervals (:func:`make_grid`) these are its uniform
    nodes, or the observation times that replaced them (within ``1e-6`` of an interval).
    """
    u = torch.linspace(0.0, 1.0, intervals + 1, dtype=grid.dtype, device=grid.device)
    return nearest_nodes(grid, t0.unsqueeze(1) + (t_end - t0).unsqueeze(1) * u)


def nearest_nodes(grid: torch.Tensor, times: torch.Tensor) -> torch.Tensor:
    """For each sample, the index of the node of ``grid`` (``(G,)`` or ``(S, G)``, sorted) nearest
    to each of its ``times (S, K)``: ``(S, K)``."""
    S = times.shape[0]
    sorted_grid = grid.expand(S, grid.shape[-1]).contiguous()
    right = torch.searchsorted(sorted_grid, times.contiguous()).clamp(max=grid.shape[-1] - 1)
    left = (right - 1).clamp(min=0)
    closer_left = (times - sorted_grid.gather(1, left)).abs() < (sorted_grid.gather(1, right) - times).abs()
    return torch.where(closer_left, left, right)


def coarse_index(keep: torch.Tensor) -> torch.Tensor:
    """The kept nodes of each sample, in order, ``(S, G')`` (``G'`` the most any sample keeps),
    padded by repeating each sample's last kept node: the gather index of its coarser grid from
    ``keep (S, G)``, a bool mask holding each sample's first node."""
    S, G = keep.shape
    order = torch.sort((~keep).to(torch.int8), dim=1, stable=True).indices  # kept nodes first, in order
    kept = keep.sum(dim=1)
    width = int(kept.max())
    column = torch.arange(width, device=keep.device).expand(S, width)
    last = (kept - 1).unsqueeze(1)
    return order[:, :width].gather(1, torch.minimum(column, last))


def refine(grid: torch.Tensor, values: torch.Tensor, slopes: torch.Tensor,
           k: int, second: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Every interval of ``grid`` split into ``k`` equal sub-intervals, with values there.

    ``grid``: ``(G,)`` shared or ``(S, G)`` per sample; ``values, slopes (S, G, M)`` at its nodes,
    and optionally their second derivatives ``second (S, G, M)``. Returns the finer grid,
    ``((G - 1) k + 1,)`` or ``(S, (G - 1) k + 1)`` (node ``j`` of ``grid`` is its node ``j k``), and
    the cubic Hermite interpolants of ``values`` there ``(S, (G - 1) k + 1, M)``, or with ``second``
    the quintic ones (the cubic plus ``s^2 (1 - s)^2 (alpha + beta s)``, which matches the second
    derivatives at both ends: :func:`torchql.transfer.raise_to_quintic`).
    """
    if k == 1:
        return grid, values
    s = torch.arange(k, dtype=grid.dtype, device=grid.device) / k  # (k,)
    h = grid[..., 1:] - grid[..., :-1]  # (..., N)
    fine = (grid[..., :-1, None] + h[..., None] * s).flatten(-2)
    fine = torch.cat([fine, grid[..., -1:]], dim=-1)
    s2, s3 = s * s, s * s * s
    basis = [2 * s3 - 3 * s2 + 1, s3 - 2 * s2 + s, 3 * s2 - 2 * s3, s3 - s2]  # each (k,)
    hh = (h if grid.dim() == 2 else h.expand(values.shape[0], -1)).unsqueeze(-1).unsqueeze(-1)  # (S, N, 1, 1)
    y0, y1 = values[:, :-1, None], values[:, 1:, None]  # (S, N, 1, M)
    f0, f1 = hh * slopes[:, :-1, None], hh * slopes[:, 1:, None]
    b = [c.reshape(1, 1, k, 1) for c in basis]
    inner = b[0] * y0 + b[1] * f0 + b[2] * y1 + b[3] * f1  # (S, N, k, M)
    if second is not None:
        c2 = 3 * (y1 - y0) - 2 * f0 - f1  # the cubic's power-basis coefficients of s^2 and s^3
        c3 = 2 * (y0 - y1) + f0 + f1
        alpha = hh * hh * second[:, :-1, None] / 2 - c2
        beta = hh * hh * second[:, 1:, None] / 2 - c2 - 3 * c3 - alpha
        bump = (s2 * (1 - s) ** 2).reshape(1, 1, k, 1)
        inner = inner + bump * (alpha + beta * s.reshape(1, 1, k, 1))
    return fine, torch.cat([inner.flatten(1, 2), values[:, -1:]], dim=1)
