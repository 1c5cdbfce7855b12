"""ODE models and their augmentation with unknown coefficients (null equations).

A model is an :class:`ODEModel`: an ``nn.Module`` whose floating-point buffers are the
coefficients of the right-hand side ``dx/dt = f(t, x; p)``. The estimator never asks the user
to write the augmented system ``z = (x, p)``, ``p' = 0`` by hand: :class:`AugmentedSystem`
builds it with :func:`torch.func.functional_call`, substituting the unknown buffers by the
trailing components of ``z``.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence

import torch
from torch import nn
from torch.func import functional_call

__all__ = ["ODEModel", "AugmentedSystem", "coefficient_names"]


class ODEModel(nn.Module):
    """Base class of the ODE models that torchql fits.

    Subclasses set :attr:`state_names` (one name per state, in order), register each
    coefficient as a floating-point buffer, and implement :meth:`forward`.

    Attributes
    ----------
    state_names : tuple of str
        Names of the states, in the order of the last axis of ``x``.
    constants : tuple of str
        Buffers that are fixed physical constants (a mass, a density). They are excluded from
        the default set of unknowns of :func:`torchql.fit`, but may still be named in
        ``params=`` explicitly.

    Examples
    --------
    >>> class Decay(ODEModel):
    ...     state_names = ("y",)
    ...     def __init__(self, k=1.0):
    ...         super().__init__()
    ...         self.register_buffer("k", torch.tensor(k, dtype=torch.float64))
    ...     def forward(self, t, x):
    ...         return -self.k * x
    """

    state_names: tuple[str, ...] = ()
    constants: tuple[str, ...] = ()

    @property
    def n_states(self) -> int:
        """Number of states ``n``."""
        return len(self.state_names)

    def forward(self, t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:  # pragma: no cover
        """Right-hand side ``dx/dt``.

        Parameters
        ----------
        t : Tensor, shape ``()``
            Time.
        x : Tensor, shape ``(..., n_states)``
            State.

        Returns
        -------
        Tensor, shape ``(..., n_states)``
            Time derivative of the state.
        """
        raise NotImplementedError(f"{type(self).__name__} must implement forward(t, x)")


def model_dtype_device(model: nn.Module) -> tuple[torch.dtype, torch.device]:
    """The dtype a fit computes in (the float buffers' promoted dtype, float64 if none) and the device."""
    floats = [b for b in model.buffers() if b.is_floating_point()]
    dtype = floats[0].dtype if floats else torch.float64
    for b in floats[1:]:
        dtype = torch.promote_types(dtype, b.dtype)
    return dtype, next((b.device for b in model.buffers()), torch.device("cpu"))


def coefficient_names(model: nn.Module) -> list[str]:
    """Names of all floating-point buffers of ``model`` (its coefficients), in registration order."""
    return [name for name, buf in model.named_buffers() if buf.is_floating_point()]


def _element_names(name: str, shape: torch.Size) -> list[str]:
    """Names of the scalar elements of a buffer: ``"A"`` for a scalar, ``"W[0,1]"`` otherwise."""
    if len(shape) == 0:
        return [name]
    names = []
    for flat in range(math.prod(shape)):
        index, rem = [], flat
        for size in reversed(shape):
            index.append(rem % size)
            rem //= size
        names.append(f"{name}[{','.join(str(i) for i in reversed(index))}]")
    return names


class AugmentedSystem:
    """The model's state augmented with its unknown coefficients: ``z = (x, p)``, ``p' = 0``.

    Parameters
    ----------
    model : ODEModel
        The user's model. It is deep-copied and moved to ``dtype``/``device``; the user's
        object is never modified.
    param_names : sequence of str
        Buffers to treat as unknowns. Their elements, flattened in row-major order, are the
        trailing ``P`` components of ``z``.
    dtype, device
        Floating dtype and device of every computation.

    Attributes
    ----------
    n : int
        Number of model states.
    P : int
        Number of unknown coefficient elements.
    M : int
        Dimension of the augmented state, ``n + P``.
    component_names : list of str
        Names of the ``M`` components of ``z``: state names, then coefficient element names.
    """

    def __init__(
        self,
        model: ODEModel,
        param_names: Sequence[str],
        dtype: torch.dtype,
        device: torch.device,
    ) -> None:
        self.model = copy.deepcopy(model).to(device=device)
        buffers = dict(self.model.named_buffers())
        for name, buf in buffers.items():
            if buf.is_floating_point() and buf.dtype != dtype:
                _set_buffer(self.model, name, buf.to(dtype))
        buffers = dict(self.model.named_buffers())
        self.dtype = dtype
        self.device = device
        self.param_names = list(param_names)
        self.param_shapes = [buffers[name].shape for name in self.param_names]
        self.param_sizes = [math.prod(shape) for shape in self.param_shapes]
        self.n = len(model.state_names)
        self.P = sum(self.param_sizes)
        self.M = self.n + self.P
        self.state_names = list(model.state_names)
        self.element_names = [
            el for name, shape in zip(self.param_names, self.param_shapes) for el in _element_names(name, shape)
        ]
        self.component_names = self.state_names + self.element_names

    # ----------------------------------------------------------------------------------------
    def pack_params(self) -> torch.Tensor:
        """Current values of the unknown buffers, flattened: shape ``(P,)``."""
        buffers = dict(self.model.named_buffers())
        if not self.param_names:
            return torch.zeros(0, dtype=self.dtype, device=self.device)
        return torch.cat([buffers[name].reshape(-1) for name in self.param_names])

    def unpack_params(self, p: torch.Tensor) -> dict[str, torch.Tensor]:
        """Split a flat parameter vector ``(P,)`` into buffers of their registered shapes."""
        out, start = {}, 0
        for name, shape, size in zip(self.param_names, self.param_shapes, self.param_sizes):
            out[name] = p[start : start + size].reshape(shape)
            start += size
        return out

    def rhs(self, t: torch.Tensor, x: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        """Model right-hand side ``f(t, x; p)`` for a single state ``x`` of shape ``(n,)``."""
        return functional_call(self.model, self.unpack_params(p), (t, x))

    def f(self, t: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """Augmented right-hand side for ``z`` of shape ``(M,)``: ``(f(t, x; p), 0)``."""
        x, p = z[: self.n], z[self.n :]
        dx = self.rhs(t, x, p)
        return torch.cat([dx, torch.zeros_like(p)])

    def model_with(self, p: torch.Tensor) -> ODEModel:
        """A deep copy of the model whose unknown buffers hold ``p`` (shape ``(P,)``)."""
        fitted = copy.deepcopy(self.model)
        for name, value in self.unpack_params(p.detach()).items():
            _set_buffer(fitted, name, value.clone())
        return fitted


def _set_buffer(module: nn.Module, dotted: str, value: torch.Tensor) -> None:
    """Replace buffer ``dotted`` (``"sub.name"`` allowed) of ``module`` by ``value``."""
    *path, leaf = dotted.split(".")
    owner = module
    for part in path:
        owner = getattr(owner, part)
    owner._buffers[leaf] = value
