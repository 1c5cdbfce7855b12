"""Argument checks shared by the public entry points; each error names the argument."""

from __future__ import annotations

import math
import numbers

import torch

__all__ = ["positive_number", "finite_number", "positive_int", "model_class", "distinct_names",
           "single_observations"]


def _is_real_number(value) -> bool:
    if isinstance(value, bool):
        return False
    if isinstance(value, torch.Tensor):
        return value.numel() == 1 and not value.dtype.is_complex and value.dtype != torch.bool
    return isinstance(value, numbers.Real)


def finite_number(name: str, value) -> float:
    """``value`` as a float; ``ValueError`` naming ``name`` unless it is a finite real number."""
    if not _is_real_number(value) or not math.isfinite(float(value)):
        raise ValueError(f"`{name}` must be a finite number; received {value!r}")
    return float(value)


def positive_number(name: str, value) -> float:
    """``value`` as a float; ``ValueError`` naming ``name`` unless it is finite and > 0."""
    if not _is_real_number(value) or not math.isfinite(float(value)) or float(value) <= 0:
        raise ValueError(f"`{name}` must be a positive finite number; received {value!r}")
    return float(value)


def positive_int(name: str, value, minimum: int = 1) -> int:
    """``value``; ``ValueError`` naming ``name`` unless it is an integer >= ``minimum`` (bools rejected)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
        kind = {0: "a non-negative integer", 1: "a positive integer"}.get(minimum, f"an integer >= {minimum}")
        raise ValueError(f"`{name}` must be {kind}; received {value!r}")
    return int(value)


def model_class(model) -> None:
    """``TypeError`` unless ``model`` is a :class:`torchql.ODEModel` with valid state names."""
    from .model import ODEModel

    if not isinstance(model, ODEModel):
        raise TypeError(f"`model` must be a torchql.ODEModel; received {type(model).__name__}")
    names = tuple(model.state_names)
    if not names or not all(isinstance(s, str) for s in names) or len(set(names)) != len(names):
        raise ValueError(f"`model.state_names` must be a non-empty tuple of distinct strings; received {names!r}")


def distinct_names(name: str, value, allowed, kind: str, allowed_text: str) -> list[str]:
    """``value`` as a list of distinct names from ``allowed``; errors name the argument ``name``.

    ``kind`` is what one name denotes (``"buffer"``, ``"state"``); ``allowed_text`` completes
    the error for an unknown name, e.g. ``"the model's states are ['y', 'v']"``.
    """
    if isinstance(value, str):
        raise TypeError(f"`{name}` must be a sequence of {kind} names, not a string; use [{value!r}]")
    try:
        names = list(value)
    except TypeError as exc:
        raise TypeError(f"`{name}` must be a sequence of {kind} names; received {type(value).__name__}") from exc
    for item in names:
        if item not in allowed:
            raise ValueError(f"`{name}` names unknown {kind} {item!r}; {allowed_text}")
    if len(set(names)) != len(names):
        raise ValueError(f"`{name}` lists a {kind} twice: {names!r}")
    return names


def single_observations(name: str, data) -> None:
    """``ValueError`` naming ``name`` when ``data`` holds a batch of datasets.

    ``data`` is what :func:`torchql.fit` received: an :class:`~torchql.Observations` or a list
    of them (experiments sharing coefficients). A batched one (values ``(B, T, K)``) is a set of
    independent datasets, which :func:`torchql.fit_many` fits; anything else passes unchanged
    (its type is the caller's to check).
    """
    from .observations import Observations

    items = list(enumerate(data)) if isinstance(data, (list, tuple)) else [(None, data)]
    for i, item in items:
        if isinstance(item, Observations) and item.batch_size is not None:
            arg = name if i is None else f"{name}[{i}]"
            raise ValueError(
                f"`{arg}` holds a batch of {item.batch_size} independent datasets (values of shape (B, T, K) = "
                f"{tuple(item.y.shape)}), but torchql.fit fits one dataset, values (T, K): fit the batch with "
                f"torchql.fit_many(model, {arg}, x0, ...), or one sample with `{arg}[b]`")
