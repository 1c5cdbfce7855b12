"""Argument checks of :class:`torchql.Observations`: the shapes of times and values, the times, and
the masks and weights given for the values."""

from __future__ import annotations

import torch

__all__ = ["BATCH_DIMS", "fits", "check_shapes", "check_times", "exact_mask"]


#: Dimensions of the values of a batch of datasets, ``(B, T, K)``.
BATCH_DIMS = 3


def fits(shape: tuple[int, ...], target: tuple[int, ...], shared: tuple[tuple[int, ...], ...]) -> bool:
    """Whether ``sigma`` or ``exact`` of ``shape`` suits values of shape ``target``.

    Accepted: one of the ``shared`` shapes (those of one dataset), or, for a batch
    ``target = (B, T, K)``, any shape that broadcasts to it.
    """
    if shape in shared:
        return True
    if len(target) != BATCH_DIMS:
        return False
    try:
        return tuple(torch.broadcast_shapes(shape, target)) == target
    except RuntimeError:
        return False


def check_shapes(t: torch.Tensor, y: torch.Tensor) -> None:
    """Shapes of the times and values: ``t (T,)`` with ``y (T, K)`` or ``(B, T, K)``, or ``t (B, T)``
    with ``y (B, T, K)``."""
    if t.dim() == 2 and y.dim() != BATCH_DIMS:
        raise ValueError("`t` must be one-dimensional, shape (T,), for one dataset; per-sample times (B, T) need "
                         f"values `y` of shape (B, T, K); received `t` of shape {tuple(t.shape)} and `y` of shape "
                         f"{tuple(y.shape)}")
    if t.dim() not in (1, 2):
        raise ValueError("`t` must be one-dimensional, shape (T,), or for a batch two-dimensional, shape (B, T) "
                         f"(each sample's own times); received shape {tuple(t.shape)}")
    T = t.shape[-1]
    if T == 0:
        raise ValueError("`t` must contain at least one observation time; received an empty tensor")
    if y.dim() not in (2, BATCH_DIMS) or y.shape[-2] != T:
        raise ValueError(
            f"`y` must have shape (T, K) = ({T}, K) to match `t`, or (B, T, K) = (B, {T}, K) for a batch of "
            f"B datasets; received shape {tuple(y.shape)}"
        )
    if y.dim() == BATCH_DIMS and y.shape[0] == 0:
        raise ValueError(f"`y` must hold at least one dataset: shape (B, T, K) with B >= 1; received shape "
                         f"{tuple(y.shape)}")
    if t.dim() == 2 and t.shape[0] != y.shape[0]:
        raise ValueError(f"`t` of shape (B, T) must give the times of each of the B = {y.shape[0]} samples of `y` "
                         f"{tuple(y.shape)}: expected shape ({y.shape[0]}, {T}) or ({T},) (shared); received shape "
                         f"{tuple(t.shape)}")


def check_times(t: torch.Tensor) -> None:
    """Times ``t (T,)`` or each row of ``t (B, T)``: finite and strictly increasing (vectorized over rows)."""
    rows = t.reshape(-1, t.shape[-1])
    per_sample = t.dim() == 2
    finite = torch.isfinite(rows).all(dim=1)
    if not bool(finite.all()):
        if not per_sample:
            raise ValueError("`t` must be finite; received NaN or inf times")
        b = int((~finite).nonzero()[0, 0])
        raise ValueError(f"`t` must be finite in every row; received NaN or inf times in row t[{b}] (the times of "
                         f"sample {b})")
    if rows.shape[1] < 2:
        return
    step = rows[:, 1:] > rows[:, :-1]
    if bool(step.all()):
        return
    b, j = (int(v) for v in (~step).nonzero()[0])
    remedy = _REPEATED if bool(rows[b, j] == rows[b, j + 1]) else _UNSORTED
    if not per_sample:
        raise ValueError(
            "`t` must be strictly increasing (no duplicates); received "
            f"t[{j}] = {t[j].item():g} followed by t[{j + 1}] = {t[j + 1].item():g}. {remedy}"
        )
    raise ValueError(
        f"`t` must be strictly increasing (no duplicates) in every row; received t[{b}, {j}] = {t[b, j].item():g} "
        f"followed by t[{b}, {j + 1}] = {t[b, j + 1].item():g} (the times of sample {b}). {remedy}"
    )


#: What to do about a repeated time: replicates are columns of one time's row.
_REPEATED = ("Replicate measurements at one time are columns of that time's row: observe the state once per "
             "replicate (observe=[\"y\", \"y\"]), with NaN where a replicate is missing.")
#: What to do about unsorted times.
_UNSORTED = "Sort the times, and the values with them (order = t.argsort(); t[order], y[order])."


def exact_mask(exact, shape: tuple[int, ...], y: torch.Tensor) -> torch.Tensor:
    """``exact`` as a boolean mask of the values' ``shape`` (``(T, K)`` or ``(B, T, K)``; ``None``:
    none), checked against the values ``y``: a value marked one by one (a ``(T, K)`` or batch
    mask) must be present, and a time marked as a whole (a ``(T,)`` mask: its present values) must
    hold one."""
    T, K = shape[-2], shape[-1]
    if exact is None:
        return torch.zeros(shape, dtype=torch.bool)
    try:
        ex = torch.as_tensor(exact)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise TypeError(f"`exact` must be a boolean mask of shape (T,) or (T, K); received "
                        f"{type(exact).__name__}") from exc
    if ex.dtype != torch.bool:
        raise TypeError(f"`exact` must be a boolean mask; received dtype {ex.dtype}")
    batched = len(shape) == BATCH_DIMS
    if not fits(tuple(ex.shape), shape, ((T,), (T, K))):
        raise ValueError(f"`exact` must have shape (T,) = ({T},) or (T, K) = ({T}, {K})"
                         + (f", or broadcast to (B, T, K) = {shape}" if batched else "")
                         + f"; received shape {tuple(ex.shape)}")
    per_time = ex.shape == (T,)
    mask = (ex.unsqueeze(-1) if per_time else ex).expand(shape).clone(memory_format=torch.contiguous_format)
    missing = torch.isnan(y)
    bad = (mask & missing).any(dim=-1) & missing.all(dim=-1) if per_time else mask & missing
    if bool(bad.any()):
        where = ", ".join(str(tuple(int(i) for i in row)) for row in bad.nonzero()[:5])
        what = "times" if per_time else "values"
        held = "hold no value (every value NaN)" if per_time else "are missing (NaN)"
        raise ValueError(f"`exact` marks {what} that {held}, at index {where}{' ...' if int(bad.sum()) > 5 else ''}"
                         ": a missing value cannot be met exactly; unmark it")
    return mask & ~missing if per_time else mask
