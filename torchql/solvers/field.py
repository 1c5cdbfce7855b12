"""A right-hand side as an implicit solver needs it: values and Jacobians of ``S`` samples at once."""

from __future__ import annotations

from collections.abc import Callable

import torch

from ..linearize import node_jacobian

__all__ = ["BatchedField", "JacobianError"]


class JacobianError(RuntimeError):
    """``torch.func.jacrev`` could not differentiate the right-hand side (it is not written in
    torch operations that ``torch.func`` can transform: in-place updates of its inputs, NumPy,
    Python control flow on tensor values under ``vmap``)."""


class BatchedField:
    """``f(t, y)`` of one sample, evaluated and differentiated for ``S`` samples at once.

    Parameters
    ----------
    f : callable ``(t, y) -> dy/dt``
        One sample's right-hand side: ``t`` a 0-d tensor, ``y`` of shape ``(M,)``, returns ``(M,)``.
    vectorize : bool
        ``True``: samples are mapped by :func:`torch.vmap` (any ``S``). ``False``: ``f`` is called
        on the single sample directly (``S`` must be 1), which spares ``vmap``'s overhead and
        allows Python control flow on tensor values in ``f``.

    Attributes
    ----------
    n_f, n_jac : int
        Points at which ``f`` and its Jacobian were evaluated (a call on ``S`` samples counts ``S``).
    """

    def __init__(self, f: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], vectorize: bool = True) -> None:
        self._f = torch.vmap(f) if vectorize else (lambda t, y: f(t[0], y[0]).unsqueeze(0))

        def derivatives(t, y):
            value, (ft, J) = node_jacobian(f, (t, y), (0, 1), y.shape[1], vectorize=vectorize, replicate=True)
            return (ft, J), value
        self._derivatives = derivatives
        self.n_f = 0
        self.n_jac = 0

    def __call__(self, t: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """``f`` at times ``t (S,)`` and states ``y (S, M)``: ``(S, M)``."""
        self.n_f += y.shape[0]
        return self._f(t, y)

    def linearize(self, t: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``f (S, M)``, its Jacobian ``df/dy (S, M, M)`` and time derivative ``df/dt (S, M)`` at ``t (S,)``, ``y (S, M)``."""
        try:
            (ft, J), value = self._derivatives(t, y)
        except Exception as exc:  # functorch reports untransformable code by many exception types
            raise JacobianError(
                "the implicit solver needs the Jacobian of the right-hand side from torch.func.jacrev, which "
                f"failed: {exc}. Write the model's forward with out-of-place torch operations, or use an "
                "explicit solver") from exc
        self.n_f += y.shape[0]
        self.n_jac += y.shape[0]
        # each sample's own memory: jacrev under vmap may return expanded (shared) rows, which the
        # solver's per-sample updates would write through
        return value.contiguous(), J.contiguous(), ft.contiguous()
