"""Leaving a saddle: a fit that ended where the data cannot separate some unknowns, although they
could be separated a step away.

A symmetric model started on its symmetry (two decays observed only as their sum, guessed with
equal rates) has, at every iterate on it, two columns of its Jacobian equal: the Gauss–Newton step
never leaves the symmetry, and the fit ends ``NOT_IDENTIFIABLE`` at the best point on it, a saddle
of the sum of squares (0.158 where the optimum off it has 0.0054). No step of the iteration can
tell it from a true non-identifiability (a product ``a b`` of which the data read only the
product), but the sum of squares can: along a true null direction it stays (or rises, the valley
curving), at a saddle it falls. :func:`off_saddle` tries steps of :data:`SADDLE_STEPS` along
each null direction (:func:`directions`), both ways; where one lowers the sum of squares by more
than :data:`SADDLE_GAIN` of it, the fit is made again from the lowest
(:func:`torchql.engine_run.run_engine`), and the better of the two fits is kept. A fit made again
that ends on another saddle (three equal rates: the first step separates one of them) is tried
again, at most once per unknown.
"""

from __future__ import annotations

import torch

from .budget import TimeBudgetExceeded, until
from .result import Status

__all__ = ["SADDLE_FLOOR", "SADDLE_GAIN", "SADDLE_PAIRS", "SADDLE_STEPS", "SADDLE_WORDS", "off_saddle", "directions"]

#: The steps along a null direction, relative to the unknowns' magnitudes at the estimates (the
#: step's norm in unknowns scaled by them). The sum of squares falls off a saddle as the step's
#: square, until the valley turns: two decays at their symmetric point 1.7 % lower a tenth of their
#: magnitude away, 0.01 % a hundredth away; three decays two of whose rates met 2.4 % lower 0.07
#: away, 26 % higher 0.2 away. So each direction is tried at three lengths.
SADDLE_STEPS = (0.3, 0.1, 0.03)
#: ... the least relative decrease of the sum of squares there that counts as leaving a saddle
#: (far above the integration's error of the sum, about ``rtol``).
SADDLE_GAIN = 1e-3
#: A fit whose sum of squares is at most this many times its integration error's square (the data
#: met to the integration's accuracy) is on no saddle: nothing lies below it that the sums resolve
#: (a FitzHugh–Nagumo fit of exact data at SSE 1e-19 spent a quarter of its time on the steps).
SADDLE_FLOOR = 100.0
#: With a null space of several dimensions (three rates met), the directions tried are its basis
#: and the normalized sums and differences of pairs of it, for at most this many basis vectors.
SADDLE_PAIRS = 4
#: What a result's message says when the fit was made again from off a saddle (as
#: :data:`torchql.data_start.START_WORDS`' entries: the first fit's end, the fit kept, the second's end).
SADDLE_WORDS = (" The fit first ended ",
                "the sum of squares fell a step along the unknowns the data could not separate there (a saddle), "
                "and this fit started from that step.",
                " A step along the unknowns the data could not separate lowered the sum of squares (a saddle); "
                "fitted again from there, the fit ended ")


def off_saddle(engine, codes: list, z0: torch.Tensor, sse: torch.Tensor) -> torch.Tensor:
    """Where to fit again the ``engine``'s samples that ended ``NOT_IDENTIFIABLE`` (``codes``) at the
    estimates ``z0 (S, M)`` with sums of squares ``sse (S,)``, whose null directions (``engine.
    null_directions``: sample -> ``(m, k)`` unit directions in the unknowns' own units) lead down:
    ``(S, M)``, the lowest of the steps of :data:`SADDLE_STEPS` along each of :func:`directions`,
    both ways, that lowers the sum of squares by more than :data:`SADDLE_GAIN` of it and stays
    inside the bounds; NaN rows elsewhere. Without null directions, with estimated sigmas or values
    marked ``exact`` (whose objectives are no plain sum of squares), or with a sum of squares within
    :data:`SADDLE_FLOOR` of the integration's resolution, nothing is tried."""
    spec = engine.spec
    out = torch.full_like(z0, float("nan"))
    rows = [r for r, code in enumerate(codes) if code is Status.NOT_IDENTIFIABLE and r in engine.null_directions]
    if not rows or spec.sigma_function is not None or spec.has_exact:
        return out
    index = torch.tensor(rows, device=z0.device)  # (a sum of squares the integration cannot resolve: no way down)
    floor = engine._integration_floor(index, engine.w[index].reshape(index.numel(), -1))
    rows = [r for r, low in zip(rows, (sse[index] <= SADDLE_FLOOR * floor).tolist()) if not low]
    if not rows:
        return out
    idx = spec.unknown_index
    typical = engine._typical(torch.tensor(rows, dtype=torch.long, device=z0.device))
    candidates, owners = [], []
    for r, usual in zip(rows, typical):
        u = z0[r, idx]
        scale = torch.where(u != 0, u.abs(), usual)  # (the estimates': the guesses may lie far away)
        for v in directions(engine.null_directions[r]):
            for length in SADDLE_STEPS:
                step = length * v / (v / scale).norm()
                for trial in (u + step, u - step):
                    if _strictly_inside(spec.bounds, trial):
                        z = z0[r].clone()
                        z[idx] = trial
                        candidates.append(z)
                        owners.append(r)
    if not candidates:
        return out
    chunk = torch.tensor(owners, device=z0.device)
    start = torch.stack(candidates)
    try:  # a check within the fit's time budget
        with until(getattr(engine, "deadline", None)):
            traj, errors = engine._nonlinear(chunk, start, loose=False)
    except TimeBudgetExceeded:
        return out
    best: dict[int, float] = {}
    value = engine._objective(chunk, traj, engine.w[chunk].reshape(chunk.numel(), -1), torch.zeros_like(start[:, 0]))
    for k, r in enumerate(owners):
        better = errors[k] is None and float(value[k]) < (1 - SADDLE_GAIN) * float(sse[r])
        if better and (r not in best or float(value[k]) < best[r]):
            out[r], best[r] = start[k], float(value[k])
    return out


def directions(null: torch.Tensor) -> list[torch.Tensor]:
    """The directions tried in the null space spanned by the columns of ``null (m, k)``: each
    column, and for ``k > 1`` the normalized sums and differences of pairs of the first
    :data:`SADDLE_PAIRS` (a basis is any rotation of the space; the way down may lie between its
    vectors)."""
    basis = list(null.T)
    out = list(basis)
    first = basis[:SADDLE_PAIRS]
    for i, a in enumerate(first):
        for b in first[i + 1:]:
            out.extend(((a + b) / 2 ** 0.5, (a - b) / 2 ** 0.5))
    return out


def _strictly_inside(bounds, u: torch.Tensor) -> bool:
    """Whether the unknowns ``u (m,)`` lie strictly inside ``bounds`` (and are positive where on a log scale)."""
    _, moved = bounds.move_inside(u)
    return not bool(moved.any() or (bounds.log & ~(u > 0)).any())
