"""Why an unconverged fit failed, told truthfully: not identifiable, or diverged.

A fit that ends at ``MAX_ITER`` or ``STALLED`` is examined at its final estimates:

* if its estimates ran away (some unknown grew more than :data:`RUNAWAY_FACTOR` times its
  typical magnitude, or :data:`WEAK_RUNAWAY_FACTOR` times along a direction the data barely
  determine) or its sum of squares grew more than :data:`SSE_GROWTH` times the model's own at the
  start, or exceeds :data:`SSE_GROWTH` times the data's own (that of a model predicting zero:
  the fit misses the data by orders of magnitude), it diverged (``DIVERGED``);
* otherwise, if the scaled Jacobian is rank deficient at a (near-)stationary iterate (the
  Gauss–Newton step there, of minimal norm, moves no unknown by more than
  :data:`STATIONARY_STEP` of its typical magnitude), the data do not determine the named
  unknowns (``NOT_IDENTIFIABLE``), the iteration having moved along them; rank deficient far
  from a stationary point, the status stands and the message names the unknowns;
* otherwise the status stands.

A Jacobian column whose effect is below rounding (:func:`negligible_columns`) is no information:
its unknown is treated as one with a zero column, which the data do not determine.

A fit, converged or not, whose model at its estimates amplifies a change of the unknowns in their
last digits into more than the data's own magnitude (:func:`rounding_spread`) diverged, whatever
its rank: no fitted value there is computable. (A linear oscillator from guesses whose model grows
as e^(10 t) ended with its initial state on the decaying mode: "converged", then called
NOT_IDENTIFIABLE, at a sum of squares its own ``predict`` missed by 1e22.)

A converged fit is examined too: a rank-deficient Jacobian at its estimates means the data do
not determine them (``NOT_IDENTIFIABLE``), unless the estimates ran away along that direction.
A runaway into a degenerate limit (a Michaelis–Menten ``V, Km -> inf`` with ``V / Km`` fixed,
where the model becomes ``S' = -(V / Km) S``) makes the Jacobian nearly rank deficient and the
relative steps tiny without the problem being unidentifiable at its optimum: that fit diverged.
Along a direction the data truly do not determine, the least-squares steps are of minimal
norm and the estimates stay near their guesses.

``fit``, ``fit_many`` and the gradient baselines share these rules and the wording of the
unknowns the data cannot separate.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from .status import Status

__all__ = ["RUNAWAY_FACTOR", "WEAK_RUNAWAY_FACTOR", "SSE_GROWTH", "STATIONARY_STEP", "null_detail",
           "typical_magnitudes", "negligible_columns", "rounding_spread", "ran_away", "final_status"]

#: An unknown whose magnitude exceeds this many times its typical one has run away.
RUNAWAY_FACTOR = 1e6
#: The same where the Jacobian at the estimates is rank deficient (a runaway along the directions
#: the data barely determine; a non-identifiable fit's minimal-norm steps stay far below it).
WEAK_RUNAWAY_FACTOR = 1e4
#: A final sum of squares this many times the model's own at the start, or the data's own (the
#: weighted squares of the values: a model predicting zero), is a divergence. (An undamped fit
#: from a guess whose model blows up ended at 3.8e72 with data of order 1; its rank-deficient
#: Jacobian there had it called NOT_IDENTIFIABLE.)
SSE_GROWTH = 1e3
#: An unconverged iterate is near-stationary when its Gauss–Newton step moves no unknown by more
#: than this fraction of its typical magnitude.
STATIONARY_STEP = 1e-3


def null_detail(null_vectors: torch.Tensor, unknown_names: Sequence[str]) -> str:
    """`` Unknowns the data cannot separate: {a, b}; {c}.`` from the null directions ``(m, k)``."""
    parts: list[str] = []
    for k in range(null_vectors.shape[1]):
        involved = [name for name, c in zip(unknown_names, null_vectors[:, k].tolist()) if abs(c) > 0.1]
        group = "{" + ", ".join(involved) + "}"
        if group not in parts:  # several null directions may involve the same unknowns
            parts.append(group)
    return " Unknowns the data cannot separate: " + "; ".join(parts) + "."


def typical_magnitudes(guess: torch.Tensor, first: torch.Tensor | None = None) -> torch.Tensor:
    """The unknowns' typical magnitudes ``(..., m)`` for :func:`ran_away`: the larger of the guesses
    ``guess`` and the first iterate's magnitudes ``first`` (a data-built start may put a coefficient
    near 0), 1 where both are 0."""
    typical = guess.abs() if first is None else torch.maximum(first, guess.abs())
    return torch.where(typical > 0, typical, torch.ones_like(typical))


def negligible_columns(jacobian: torch.Tensor, estimates: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """Which columns of the weighted Jacobian carry no information: bool ``(..., m)``.

    The rank tests scale each column to unit norm, which makes them blind to the units of the
    unknowns but also to a column that is numerically nothing (the sensitivities of a trajectory
    identically ~0, of order 1e-32, look like any other once scaled). Columns of different units
    are compared here in the units of their unknowns' own magnitudes: column ``j`` times
    ``|u_j| = max(|estimate_j|, scale_j)`` is the change of the weighted values when unknown ``j``
    changes by its magnitude. Column ``j`` is negligible when that change is at most
    ``max(L, m) eps`` times the largest such change of any unknown: the rounding threshold of the
    numerical rank of ``J diag(|u|)`` (that of numpy's ``matrix_rank``). That matrix then has a
    singular value below rounding (at most the column's norm), with ``e_j`` its direction up to
    rounding: no data in this precision tell ``u_j`` within its magnitude. A sensitivity that is small but real (a weak parameter, a tiny initial
    state measured in its own units) is many orders above that threshold. The residuals are no
    reference: an exact fit has none, and a fit to a trajectory at rest has them at the same 1e-32
    as its columns. A zero column is negligible; so are all columns when every one is zero.

    Parameters
    ----------
    jacobian : Tensor ``(..., L, m)``
        Weighted sensitivities of the values to the unknowns.
    estimates, scale : Tensor ``(..., m)``
        The estimates and the unknowns' typical magnitudes (:func:`typical_magnitudes`).
    """
    magnitude = torch.maximum(estimates.abs(), scale.abs())
    effect = torch.linalg.vector_norm(jacobian, dim=-2) * magnitude
    L, m = jacobian.shape[-2:]
    eps = torch.finfo(jacobian.dtype).eps
    return effect <= max(L, m) * eps * effect.amax(dim=-1, keepdim=True)


def rounding_spread(jacobian: torch.Tensor, estimates: torch.Tensor) -> torch.Tensor:
    """The largest change of a weighted value that rounding the unknowns makes: ``(...,)``, the
    largest over the rows of ``eps sum_j |J_ij| |estimate_j|``.

    Of the order of rounding times the data's magnitudes wherever the fitted values are a
    well-conditioned function of the unknowns. Above the data's own magnitude, the model at these
    estimates amplifies a change in the unknowns' last digits into more than the data hold (a
    solution that grows as e^(10 t) over 6.5 time units, kept small only by an initial state on its
    decaying mode): no computed value there means anything, and neither does a rank test.

    Parameters
    ----------
    jacobian : Tensor ``(..., L, m)``
        Weighted sensitivities of the values to the unknowns (zero rows for values not used).
    estimates : Tensor ``(..., m)``
    """
    eps = torch.finfo(jacobian.dtype).eps
    return eps * (jacobian.abs() * estimates.abs().unsqueeze(-2)).sum(dim=-1).amax(dim=-1)


def ran_away(estimates: torch.Tensor, scale: torch.Tensor, unknown_names: Sequence[str],
             factor: float = RUNAWAY_FACTOR) -> list[str]:
    """Names of the unknowns ``(m,)`` larger in magnitude than ``factor`` times ``scale (m,)``."""
    away = ~(estimates.abs() <= factor * scale)  # NaN runs away too
    return [name for name, flag in zip(unknown_names, away.tolist()) if flag]


def final_status(status: Status, *, rank_deficient: bool, null_text: str, estimates: torch.Tensor,
                 scale: torch.Tensor, unknown_names: Sequence[str], sse: float,
                 sse_start: float | None, step: torch.Tensor | None = None,
                 sse_data: float | None = None, rounding: float | None = None,
                 n_values: int | None = None) -> tuple[Status, str]:
    """The status of a fit whose iteration ended at ``status``, and the detail to add to its message.

    Parameters
    ----------
    status : Status
        How the iteration ended; converged statuses, ``MAX_ITER`` and ``STALLED`` are examined.
    rank_deficient : bool
        Whether the scaled Jacobian at the final estimates is rank deficient.
    null_text : str
        :func:`null_detail` of its null directions (used when it is).
    estimates, scale : Tensor ``(m,)``
        The final estimates and the unknowns' typical magnitudes (see :func:`ran_away`).
    unknown_names : sequence of str
    sse : float
        The model's sum of squares at the final estimates.
    sse_start : float or None
        The model's own sum of squares at the guesses, when the iteration started from it.
    step : Tensor ``(m,)``, optional
        The minimal-norm Gauss–Newton step at the final estimates (``None``: taken as stationary).
    sse_data : float, optional
        The data's own weighted sum of squares (a model predicting zero; ``None``: not compared, as
        for log-normal data, whose logarithms are near 0 for values near 1).
    rounding, n_values : float and int, optional
        :func:`rounding_spread` at the estimates, and the number of values used: a spread above the
        data's root mean square, ``sqrt(sse_data / n_values)`` (data not all zero), is a divergence
        into a model too ill-conditioned to compute (whatever the iteration's status or the
        Jacobian's rank).
    """
    examined = status.success or status in (Status.MAX_ITER, Status.STALLED)
    if not examined:
        return status, ""
    ill = None
    if rounding is not None and sse_data and n_values and rounding > math.sqrt(sse_data / n_values):
        ill = (Status.DIVERGED, f" At the final estimates, a change of the unknowns in their last digits changes a "
                                f"weighted fitted value by up to {rounding:.3g}, more than the data's own root mean "
                                f"square ({math.sqrt(sse_data / n_values):.3g}): the model amplifies rounding there "
                                f"beyond what the data hold (a fast-growing mode), so its fitted values, sum of squares "
                                f"and rank mean nothing.")
    if status.success and not rank_deficient:  # a runaway only matters to the others
        return ill or (status, "")
    factor = WEAK_RUNAWAY_FACTOR if rank_deficient else RUNAWAY_FACTOR
    runaway = ran_away(estimates, scale, unknown_names, factor)
    if runaway and (rank_deficient or not status.success):
        where = ", where the data barely determine them." + null_text if rank_deficient else "."
        ended = "" if status.success else f" before the iteration ended at {status.name}"
        return Status.DIVERGED, (f" The estimates of {runaway} ran away (more than {factor:g} times their typical "
                                 f"magnitude){ended}{where}")
    if status.success:
        return ill or ((Status.NOT_IDENTIFIABLE, null_text) if rank_deficient else (status, ""))
    if sse_start is not None and math.isfinite(sse_start) and sse > SSE_GROWTH * max(sse_start, 0.0) and sse > 0:
        return Status.DIVERGED, (f" The sum of squares grew from {sse_start:.6g} at the guesses to {sse:.6g}"
                                 f" before the iteration ended at {status.name}.")
    if sse_data is not None and sse > SSE_GROWTH * sse_data and sse > 0:
        return Status.DIVERGED, (f" The sum of squares, {sse:.6g}, is {sse / max(sse_data, 1e-300):.3g} times the "
                                 f"data's own ({sse_data:.6g}, a model predicting zero) when the iteration ended at "
                                 f"{status.name}: the fitted model misses the data by orders of magnitude.")
    if ill:
        return ill
    if rank_deficient and (step is None or bool((step.abs() <= STATIONARY_STEP * scale).all())):
        # near a stationary point: the iteration wandered along directions the data do not determine
        return Status.NOT_IDENTIFIABLE, null_text + f" The iteration did not converge ({status.name}): it moved along them."
    if rank_deficient:
        return status, (" The Jacobian at the last estimates is rank deficient, but they are not near a stationary "
                        "point (the Gauss-Newton step there is not small), so this need not hold at the optimum."
                        + null_text)
    return status, ""
