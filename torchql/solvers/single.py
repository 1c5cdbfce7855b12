"""One trajectory by Rodas5P, with :func:`torchql.integrate.solve`'s conventions.

Any state shape (flattened into one vector, whose Jacobian is dense), output times increasing or
decreasing (backward in time by the reflection ``s = -t``), steps landing on the ``hit`` times
among the outputs and the other outputs from the dense output.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from .rosenbrock import RosenbrockSolution, rodas5p_batch

__all__ = ["rodas5p_solve", "MAX_COMPONENTS"]

#: Largest state the single-trajectory solver accepts: its Jacobian is dense (``N x N`` entries).
MAX_COMPONENTS = 4096


def rodas5p_solve(func: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], y0: torch.Tensor, t: torch.Tensor, *,
                  rtol: float, atol: float, hit: torch.Tensor | None = None, max_steps: int | None = None,
                  norm: Callable[[torch.Tensor], torch.Tensor] | None = None, first_step: float | None = None
                  ) -> tuple[torch.Tensor, RosenbrockSolution]:
    """``y' = func(t, y)`` from ``y0`` at ``t[0]``, the states at the times ``t``.

    Parameters
    ----------
    func : callable ``(t, y) -> dy/dt``
        ``t`` 0-d, ``y`` of ``y0``'s shape; differentiable by ``torch.func.jacrev``.
    y0 : Tensor, any shape ``(*shape)`` of at most :data:`MAX_COMPONENTS` elements
    t : Tensor ``(G,)``
        Strictly monotonic output times, increasing or decreasing.
    rtol, atol : float
        Tolerances of the local error (RMS norm over the elements).
    hit : Tensor, optional
        Output times that the steps land on exactly; the others (but the last) are interpolated.
        Default: only the last.
    max_steps : int, optional
        Budget of trial steps (default 100,000).
    norm : callable, optional
        Norm of the scaled error, a tensor of ``y0``'s shape -> 0-d (default RMS).
    first_step : float, optional
        Magnitude of the first trial step.

    Returns
    -------
    y : Tensor ``(G, *shape)``
        NaN where the solution failed.
    solution : RosenbrockSolution
        The status (``solution.ok[0]``, ``solution.message(0)``) and the counts.
    """
    shape = y0.shape
    N = y0.numel()
    if N > MAX_COMPONENTS:
        raise ValueError(f"`y0` has {N} elements; the implicit solver factorises a dense {N} x {N} matrix per "
                         f"step and accepts at most {MAX_COMPONENTS}: use an explicit solver for this system")
    backward = t.numel() > 1 and bool(t[-1] < t[0])
    sign = -1.0 if backward else 1.0

    if not backward and y0.dim() == 1:
        flat = func
    else:
        def flat(s: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
            return sign * func(sign * s, y.reshape(shape)).reshape(-1)

    grid = sign * t
    land = None
    if hit is not None:
        land = torch.isin(t, hit.to(dtype=t.dtype, device=t.device))
    else:
        land = torch.zeros(t.shape, dtype=torch.bool, device=t.device)
    scaled_norm = None if norm is None else (lambda e: norm(e[0].reshape(shape)).reshape(1))
    solution = rodas5p_batch(flat, y0.reshape(1, N), grid, rtol=rtol, atol=atol,
                             max_steps=100_000 if max_steps is None else max_steps, land=land, norm=scaled_norm,
                             first_step=first_step, vectorize=False)
    solution.t = sign * solution.t
    return solution.y[0].reshape(t.shape[0], *shape), solution
