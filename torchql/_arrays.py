"""Array-likes (tensors, NumPy arrays, sequences) as floating tensors: one conversion for every
entry point, with errors that name the argument."""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["float_tensor"]


def float_tensor(value, name: str, dtype: torch.dtype | None = None) -> torch.Tensor:
    """Convert array-likes to a floating tensor; a clear error for anything else.

    A tensor that requires grad is read detached (its values; measurements are not differentiated
    through), never modified: callers copy before writing.
    """
    if isinstance(value, torch.Tensor):
        tensor = value.detach()
    else:
        try:
            tensor = torch.as_tensor(np.asarray(value, dtype=np.float64))
        except (TypeError, ValueError) as exc:
            raise TypeError(
                f"`{name}` must be a tensor or array of real numbers; received {type(value).__name__}"
            ) from exc
    if tensor.is_complex() or tensor.dtype == torch.bool:
        raise TypeError(f"`{name}` must be real-valued; received dtype {tensor.dtype}")
    if not tensor.is_floating_point():
        tensor = tensor.to(torch.float64)
    return tensor if dtype is None else tensor.to(dtype)
