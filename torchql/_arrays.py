"""Array-likes (tensors, NumPy arrays, sequences) as floating tensors: one conversion for every
entry point, with errors that name the argument."""

from __future__ import annotations

import warnings

import numpy as np
import torch

__all__ = ["float_tensor"]


def float_tensor(value, name: str, dtype: torch.dtype | None = None, device: torch.device | str | None = None,
                 expected: str = "a tensor or array of real numbers") -> torch.Tensor:
    """Convert array-likes to a floating tensor; a clear error for anything else.

    Integers become float64 (or ``dtype``); booleans, complex values and strings are refused, naming
    ``name`` and ``expected`` (what the argument should be, e.g. its shape). A tensor that requires
    grad is read detached (its values; measurements are not differentiated through), never modified:
    callers copy before writing.
    """
    if isinstance(value, torch.Tensor):
        if value.is_meta:
            raise TypeError(f"`{name}` must be {expected} with values; received a tensor on the meta device")
        tensor = value.detach()
    else:
        tensor = _from_array_like(value, name, expected)
    if tensor.is_complex() or tensor.dtype == torch.bool:
        raise TypeError(f"`{name}` must be real-valued; received dtype {tensor.dtype}")
    if not tensor.is_floating_point():
        tensor = tensor.to(torch.float64)
    return tensor.to(dtype=dtype, device=device)


def _from_array_like(value, name: str, expected: str) -> torch.Tensor:
    """A NumPy array or (nested) sequence of numbers as a float64 tensor (bool and complex kept, to be refused)."""
    try:
        array = np.asarray(value)
    except RuntimeError:  # a sequence of tensors that require grad: torch reads their values
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            return torch.as_tensor(value).detach()
    except (TypeError, ValueError) as exc:  # ragged sequences
        raise TypeError(f"`{name}` must be {expected}; received {type(value).__name__}") from exc
    if array.dtype.kind in "bc":
        return torch.as_tensor(array)
    if array.dtype.kind in "iufO":  # numbers, also as objects (strings are refused)
        try:
            return torch.as_tensor(array.astype(np.float64))
        except (TypeError, ValueError):
            pass
    raise TypeError(f"`{name}` must be {expected}; received {type(value).__name__}")
