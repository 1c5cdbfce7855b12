"""Measurements of a model's states at discrete times, and the operators that observe them."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Union

import numpy as np
import torch
from torch.func import jacrev, vmap

__all__ = ["Observations", "ObservationOperator"]

ObserveSpec = Union[Sequence[str], torch.Tensor, np.ndarray, Callable[[torch.Tensor], torch.Tensor]]


def _as_float_tensor(value, name: str, dtype: torch.dtype | None = None) -> torch.Tensor:
    """Convert array-likes to a floating tensor; a clear error for anything else."""
    if isinstance(value, torch.Tensor):
        tensor = value
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


class Observations:
    """Measured values of (functions of) the states at discrete times.

    Parameters
    ----------
    t : Tensor or array, shape ``(T,)``
        Observation times, finite and strictly increasing (same unit as the model's time).
    y : Tensor or array, shape ``(T, K)`` or ``(T,)`` when ``K == 1``
        Measured values. ``NaN`` marks a missing value, which is skipped; ``inf`` is rejected.
    observe : sequence of str, Tensor of shape ``(K, n_states)``, or callable
        What each of the ``K`` columns of ``y`` measures: state names; a matrix ``Q`` so that
        ``y = Q x``; or a differentiable function ``h(x) -> (..., K)`` of the state
        ``x (..., n_states)``, linearized like the right-hand side.
    sigma : float, Tensor of shape ``(K,)`` or ``(T, K)``, optional
        Standard deviation of each value (same unit as ``y``). Residuals are divided by it.
        Default 1 for every value. With ``K == 1``, shape ``(T,)`` is accepted too.
    exact : bool Tensor of shape ``(T,)`` or ``(T, K)``, optional
        Values to be met exactly (equality-constrained least squares) rather than in the
        least-squares sense. A ``(T,)`` mask marks every value at those times.

    Attributes
    ----------
    t : Tensor ``(T,)``; y : Tensor ``(T, K)``; sigma : Tensor ``(T, K)``; exact : bool Tensor ``(T, K)``
    observe : the ``observe`` argument as given.
    sigma_given : bool
        Whether ``sigma`` was given (then it is taken as the known standard deviation of the
        values; otherwise the residual variance is estimated from the fit).
    """

    def __init__(
        self,
        t,
        y,
        observe: ObserveSpec,
        sigma=None,
        exact=None,
    ) -> None:
        t = _as_float_tensor(t, "t")
        if t.dim() != 1:
            raise ValueError(f"`t` must be one-dimensional, shape (T,); received shape {tuple(t.shape)}")
        if t.numel() == 0:
            raise ValueError("`t` must contain at least one observation time; received an empty tensor")
        if not torch.isfinite(t).all():
            raise ValueError("`t` must be finite; received NaN or inf times")
        if t.numel() > 1 and not bool((t[1:] > t[:-1]).all()):
            bad = int(torch.nonzero(t[1:] <= t[:-1])[0, 0])
            raise ValueError(
                "`t` must be strictly increasing (no duplicates); received "
                f"t[{bad}] = {t[bad].item():g} followed by t[{bad + 1}] = {t[bad + 1].item():g}"
            )
        y = _as_float_tensor(y, "y")
        if y.dim() == 1:
            y = y.unsqueeze(-1)
        if y.dim() != 2 or y.shape[0] != t.shape[0]:
            raise ValueError(
                f"`y` must have shape (T, K) = ({t.shape[0]}, K) to match `t`; received shape {tuple(y.shape)}"
            )
        if torch.isinf(y).any():
            raise ValueError("`y` must not contain inf; mark missing values with NaN instead")
        if torch.isnan(y).all():
            raise ValueError("`y` holds no value: every entry is NaN")
        T, K = y.shape
        self.t = t.clone()
        self.y = y.to(t.dtype) if y.dtype != t.dtype else y.clone()
        self.observe = observe
        self._check_observe_spec(observe, K)

        if sigma is None:
            sig = torch.ones(T, K, dtype=self.y.dtype)
        else:
            sig = _as_float_tensor(sigma, "sigma", self.y.dtype)
            if sig.dim() == 0:
                sig = sig.expand(T, K)
            elif K == 1 and sig.shape == (T,):
                sig = sig.unsqueeze(-1)
            elif sig.shape == (K,):
                sig = sig.unsqueeze(0).expand(T, K)
            elif sig.shape != (T, K):
                raise ValueError(
                    f"`sigma` must be a scalar, shape (K,) = ({K},) or shape (T, K) = ({T}, {K}); "
                    f"received shape {tuple(sig.shape)}"
                )
            if not torch.isfinite(sig).all() or (sig <= 0).any():
                raise ValueError("`sigma` must be finite and strictly positive; received a value <= 0, NaN or inf")
        self.sigma = sig.clone()
        self.sigma_given = sigma is not None

        if exact is None:
            ex = torch.zeros(T, K, dtype=torch.bool)
        else:
            try:
                ex = torch.as_tensor(exact)
            except (TypeError, ValueError, RuntimeError) as exc:
                raise TypeError(
                    f"`exact` must be a boolean mask of shape (T,) or (T, K); received {type(exact).__name__}") from exc
            if ex.dtype != torch.bool:
                raise TypeError(f"`exact` must be a boolean mask; received dtype {ex.dtype}")
            if ex.shape == (T,):
                ex = ex.unsqueeze(-1).expand(T, K)
            elif ex.shape != (T, K):
                raise ValueError(
                    f"`exact` must have shape (T,) = ({T},) or (T, K) = ({T}, {K}); received shape {tuple(ex.shape)}"
                )
        self.exact = ex.clone()

    @staticmethod
    def _check_observe_spec(observe, K: int) -> None:
        if callable(observe) and not isinstance(observe, (torch.Tensor, np.ndarray)):
            return
        if isinstance(observe, str):
            raise TypeError(f"`observe` must be a sequence of state names, not a single string; use [{observe!r}]")
        if isinstance(observe, (torch.Tensor, np.ndarray)):
            shape = tuple(observe.shape)
            if len(shape) != 2 or shape[0] != K:
                raise ValueError(f"`observe` matrix must have shape (K, n_states) with K = {K}; received shape {shape}")
            return
        if isinstance(observe, Sequence):
            if not all(isinstance(name, str) for name in observe):
                raise TypeError("`observe` as a sequence must hold state names (str)")
            if len(observe) != K:
                raise ValueError(
                    f"`observe` names {len(observe)} states but `y` has K = {K} columns; give one name per column"
                )
            return
        raise TypeError(
            "`observe` must be a sequence of state names, a (K, n_states) matrix or a callable h(x); "
            f"received {type(observe).__name__}"
        )

    @property
    def n_times(self) -> int:
        """Number of observation times ``T``."""
        return self.t.shape[0]

    @property
    def n_outputs(self) -> int:
        """Number of observed quantities ``K``."""
        return self.y.shape[1]

    @property
    def mask(self) -> torch.Tensor:
        """Bool ``(T, K)``: values that are present (not NaN)."""
        return ~torch.isnan(self.y)

    def __repr__(self) -> str:
        return f"Observations(T={self.n_times}, K={self.n_outputs}, t=[{self.t[0].item():g}, {self.t[-1].item():g}])"


class ObservationOperator:
    """``h(x)``: what the data measure, with its Jacobian ``dh/dx``, for a given model.

    Parameters
    ----------
    observe : sequence of str, Tensor ``(K, n)`` or callable
        As in :class:`Observations`.
    state_names : sequence of str
        The model's state names.
    K : int
        Number of observed quantities.
    dtype, device
        Of the computation.
    """

    def __init__(self, observe, state_names: Sequence[str], K: int, dtype: torch.dtype, device: torch.device):
        n = len(state_names)
        self.n, self.K = n, K
        self.function: Callable[[torch.Tensor], torch.Tensor] | None = None
        self.matrix: torch.Tensor | None = None
        if isinstance(observe, (torch.Tensor, np.ndarray)):
            Q = _as_float_tensor(observe, "observe", dtype).to(device)
            if Q.shape != (K, n):
                raise ValueError(
                    f"`observe` matrix must have shape (K, n_states) = ({K}, {n}); received shape {tuple(Q.shape)}"
                )
            if not torch.isfinite(Q).all():
                raise ValueError("`observe` matrix must be finite")
            self.matrix = Q
        elif callable(observe):
            self.function = observe
        else:
            Q = torch.zeros(K, n, dtype=dtype, device=device)
            for k, name in enumerate(observe):
                if name not in state_names:
                    raise ValueError(f"`observe` names unknown state {name!r}; the model's states are {tuple(state_names)}")
                Q[k, list(state_names).index(name)] = 1.0
            self.matrix = Q

    @property
    def observed_states(self) -> list[int | None]:
        """For each output, the index of the single state it reads directly, else ``None``."""
        if self.matrix is None:
            return [None] * self.K
        out = []
        for row in self.matrix:
            nz = torch.nonzero(row).flatten()
            out.append(int(nz[0]) if nz.numel() == 1 and row[nz[0]] == 1 else None)
        return out

    def check(self, x: torch.Tensor) -> None:
        """Validate a callable operator on one state ``x (n,)``: output shape ``(K,)``, same dtype."""
        if self.function is None:
            return
        try:
            out = self.function(x)
        except Exception as exc:  # noqa: BLE001 - report any failure of user code clearly
            raise ValueError(f"`observe` callable failed on a state of shape ({self.n},): {exc}") from exc
        if not isinstance(out, torch.Tensor) or out.shape != (self.K,):
            shape = tuple(out.shape) if isinstance(out, torch.Tensor) else type(out).__name__
            raise ValueError(f"`observe` callable must return shape (K,) = ({self.K},) for x of shape ({self.n},); received {shape}")
        if out.dtype != x.dtype:
            raise TypeError(f"`observe` callable must return dtype {x.dtype}; received {out.dtype}")

    def value_and_jacobian(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``h(x)`` and ``dh/dx`` for states ``x (T, n)``: shapes ``(T, K)`` and ``(T, K, n)``."""
        if self.matrix is not None:
            return x @ self.matrix.T, self.matrix.expand(x.shape[0], self.K, self.n)

        def h(xi):
            out = self.function(xi)
            return out, out

        jac, val = vmap(jacrev(h, has_aux=True))(x)
        return val, jac
