"""ODE models and their augmentation with unknown coefficients (null equations).

A model is an :class:`ODEModel`: an ``nn.Module`` whose floating-point buffers (and
floating-point parameters, ``nn.Parameter``, treated alike) are the coefficients of the
right-hand side ``dx/dt = f(t, x; p)``. The estimator never asks the user to write the augmented
system ``z = (x, p)``, ``p' = 0`` by hand: :class:`AugmentedSystem` builds it with
:func:`torch.func.functional_call`, substituting the unknown coefficients by the trailing
components of ``z``.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

import torch
from torch import nn

from .budget import TimeBudgetExceeded

if TYPE_CHECKING:
    from .inputs import Inputs

__all__ = ["ODEModel", "AugmentedSystem", "coefficient_names", "coefficients", "attach_inputs"]


class ODEModel(nn.Module):
    """Base class of the ODE models that torchql fits.

    Subclasses set :attr:`state_names` (one name per state, in order), register each
    coefficient as a floating-point buffer, and implement :meth:`forward`. A coefficient
    registered as an ``nn.Parameter`` is treated like a buffer: a fit reads its value as the
    guess, never modifies it, and returns a model whose Parameter holds the estimate.
    Coefficients must be float32 or float64 (``model.double()``).

    Attributes
    ----------
    state_names : tuple of str
        Names of the states, in the order of the last axis of ``x``.
    constants : tuple of str
        Buffers that are fixed physical constants (a mass, a density). They are excluded from
        the default set of unknowns of :func:`torchql.fit`, but may still be named in
        ``params=`` explicitly.
    input_names : tuple of str
        Names of measured inputs ``u(t)`` (a force, a voltage, a dose rate), empty by default; a
        class attribute.
        A model with inputs implements ``forward(t, x, u)``; the values come from the data's
        :class:`torchql.Inputs`, interpolated at each evaluation (see :mod:`torchql.inputs`).

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
    input_names: tuple[str, ...] = ()

    def __init_subclass__(cls, **kwargs) -> None:
        """A model class with ``input_names`` is called through :func:`_call_with_inputs`; the
        others keep ``nn.Module``'s call, with nothing added to each evaluation."""
        super().__init_subclass__(**kwargs)
        if cls.input_names and "__call__" not in cls.__dict__:
            cls.__call__ = _call_with_inputs

    @property
    def inputs(self) -> "Inputs | None":
        """The input signals attached to this model (a fitted model holds its data's), or ``None``."""
        return self.__dict__.get(_INPUTS)

    def input_nodes(self) -> torch.Tensor | None:
        """Times where the right-hand side is not smooth, for a fit's grid (the attached inputs'
        :attr:`~torchql.inputs.Inputs.nodes`), or ``None``."""
        signals = self.inputs
        return None if signals is None else signals.nodes

    def input_jumps(self) -> torch.Tensor | None:
        """Times where an adaptive solver should restart (the attached inputs'
        :attr:`~torchql.inputs.Inputs.jumps`), or ``None``."""
        signals = self.inputs
        return None if signals is None else signals.jumps

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

        u : Tensor, shape ``(n_inputs,)`` (models with ``input_names`` only)
            The measured inputs at ``t``, in the order of ``input_names`` (a third argument
            ``forward(t, x, u)``; see :mod:`torchql.inputs`).

        Returns
        -------
        Tensor, shape ``(..., n_states)``
            Time derivative of the state.
        """
        raise NotImplementedError(f"{type(self).__name__} must implement forward(t, x)")


#: Where a model holds its attached input signals (a plain attribute: not a buffer, so never an
#: unknown, and deep-copied with the model).
_INPUTS = "_torchql_inputs"
#: ... and the origin of the local time in which it is evaluated (:func:`attach_inputs`)
_ORIGIN = "_torchql_time_origin"


def _call_with_inputs(self, t: torch.Tensor, x: torch.Tensor, *args, **kwargs) -> torch.Tensor:
    """``forward(t, x, u)`` with ``u`` the attached signals at ``t`` (unless given): every evaluation a
    fit or a simulation makes of a model with inputs goes through here."""
    if not args and "u" not in kwargs:
        signals = self.__dict__.get(_INPUTS)
        if signals is None:
            raise ValueError(
                f"`model` takes inputs {tuple(self.input_names)} (its `input_names`) but none were given: pass "
                "them with the data, Observations(..., inputs=torchql.Inputs(t, u, names=...)), or to "
                "torchql.simulate(..., inputs=...)")
        args = (signals(t),)
        origin = self.__dict__.get(_ORIGIN, 0.0)
        if origin:  # the solvers' time is local: the model's own t is the data's
            t = t + origin
    return nn.Module.__call__(self, t, x, *args, **kwargs)


def attach_inputs(model: nn.Module, signals: "Inputs | None", origin: float = 0.0) -> None:
    """Attach ``signals`` (already in the model's input order, dtype and device) to ``model`` (the
    library's own copy; modified in place), or detach with ``None``. ``origin``: the model is then
    evaluated in local time ``t - origin`` (``signals`` on those times, :meth:`Inputs.shifted`), its
    ``forward`` still given ``t`` itself."""
    if signals is None:
        model.__dict__.pop(_INPUTS, None)
        model.__dict__.pop(_ORIGIN, None)
    else:
        model.__dict__[_INPUTS] = signals
        model.__dict__[_ORIGIN] = origin


def coefficients(model: nn.Module) -> dict[str, torch.Tensor]:
    """The coefficients of ``model`` by (dotted) name: its floating-point buffers in registration
    order, then its floating-point parameters in registration order (the tensors themselves)."""
    out = {name: buf for name, buf in model.named_buffers() if buf.is_floating_point()}
    out.update((name, par) for name, par in model.named_parameters() if par.is_floating_point())
    return out


def model_dtype_device(model: nn.Module) -> tuple[torch.dtype, torch.device]:
    """The dtype a fit computes in (the coefficients' promoted dtype, float64 if none) and the device."""
    floats = list(coefficients(model).values())
    dtype = floats[0].dtype if floats else torch.float64
    for b in floats[1:]:
        dtype = torch.promote_types(dtype, b.dtype)
    tensors = list(model.buffers()) + list(model.parameters())
    return dtype, next((b.device for b in tensors), torch.device("cpu"))


def coefficient_names(model: nn.Module) -> list[str]:
    """Names of the coefficients of ``model``: its floating-point buffers, then its floating-point
    parameters, each in registration order (see :func:`coefficients`)."""
    return list(coefficients(model))


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
        object is never modified. In the copy, :attr:`model`, every coefficient is a plain
        buffer that requires no gradient (an ``nn.Parameter`` of the user's model included:
        :meth:`model_with` and :meth:`user_model` give it back as a Parameter).
    param_names : sequence of str
        Coefficients to treat as unknowns. Their elements, flattened in row-major order, are the
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
        #: ``{name: requires_grad}`` of the user's parameters, held as buffers in :attr:`model`
        self.parameter_flags = _parameters_to_buffers(self.model)
        for name, buf in coefficients(self.model).items():
            _set_buffer(self.model, name, buf.detach().to(dtype))
        buffers = coefficients(self.model)
        self.dtype = dtype
        self.device = device
        self.param_names = list(param_names)
        self.param_shapes = [buffers[name].shape for name in self.param_names]
        self.param_sizes = [math.prod(shape) for shape in self.param_shapes]
        self._scalar_params = all(len(shape) == 0 for shape in self.param_shapes)
        #: the submodule and buffer name of each unknown coefficient in :attr:`model` (for :meth:`rhs`)
        self._owners = [_owner(self.model, name) for name in self.param_names]
        #: the ways of differentiating of :func:`torchql.linearize.linearize` that torch can take
        #: on the model as far as known (reverse mode is checked; autograd and forward mode are
        #: dropped when they fail)
        self.linearization_orders: tuple[str, ...] = ("autograd", "reverse", "forward")
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
        buffers = coefficients(self.model)
        if not self.param_names:
            return torch.zeros(0, dtype=self.dtype, device=self.device)
        return torch.cat([buffers[name].reshape(-1) for name in self.param_names])

    def unpack_params(self, p: torch.Tensor) -> dict[str, torch.Tensor]:
        """Split a flat parameter vector ``(P,)`` into buffers of their registered shapes (a batch of
        them ``(..., P)`` into ``(..., *shape)``)."""
        if self._scalar_params:  # one view per coefficient in one call: the model's call chain is
            return dict(zip(self.param_names, p.unbind(-1)))  # most of a small model's evaluation
        lead = p.shape[:-1]
        return {name: part.reshape(lead + tuple(shape))
                for name, shape, part in zip(self.param_names, self.param_shapes, p.split(self.param_sizes, dim=-1))}

    def coefficient_values(self, z: torch.Tensor) -> dict[str, torch.Tensor]:
        """Every float coefficient by name for one augmented state ``z (M,)``: those in ``z`` from
        it, the others from :attr:`model` (what observation functions and initial-state expressions read)."""
        if not hasattr(self, "_fixed_values"):
            self._fixed_values = {name: value for name, value in self.model.named_buffers()
                                  if value.is_floating_point() and name not in self.param_names}
        values = dict(self._fixed_values)
        values.update(self.unpack_params(z[self.n:]))
        return values

    def rhs(self, t: torch.Tensor, x: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        """Model right-hand side ``f(t, x; p)`` for a single state ``x`` of shape ``(n,)`` (or a batch
        ``x (S, n)``, ``p (S, P)``, each coefficient held as ``(S, *shape)``: see :meth:`f`).

        The unknown buffers of :attr:`model` (this system's own copy of the user's model) hold
        ``p``'s values during the call and their own after it, as
        :func:`torch.func.functional_call` substitutes them, without its general machinery (tied
        tensors, parameters, strictness checks), which cost twice the forward of a small model
        under :func:`torch.vmap`, where every solver evaluates it.
        """
        owners = self._owners
        saved = []
        try:
            for (owner, leaf), value in zip(owners, self.unpack_params(p).values()):
                saved.append(owner._buffers[leaf])
                owner._buffers[leaf] = value
            return self.model(t, x)
        finally:
            for (owner, leaf), old in zip(owners, saved):
                owner._buffers[leaf] = old

    def f(self, t: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """Augmented right-hand side for ``z`` of shape ``(M,)``: ``(f(t, x; p), 0)``.

        Given a batch ``z (S, M)`` at times ``t (S,)``, one call of the model with each unknown
        coefficient held as ``(S, *shape)``: right for a model whose forward broadcasts over a
        leading axis (as :class:`ODEModel` asks of the states), which :class:`BatchedCall` checks
        before it relies on it."""
        x, p = z[..., : self.n], z[..., self.n :]
        dx = self.rhs(t, x, p)
        return torch.cat([dx, torch.zeros_like(p)], dim=-1)

    def model_with(self, p: torch.Tensor) -> ODEModel:
        """A copy of the user's model whose unknown coefficients hold ``p`` (shape ``(P,)``)."""
        return self.user_model({name: value.clone() for name, value in self.unpack_params(p.detach()).items()})

    def user_model(self, values: dict[str, torch.Tensor] | None = None) -> ODEModel:
        """A deep copy of :attr:`model` with coefficients set from ``values`` and the user's
        parameters registered as ``nn.Parameter`` again (with their ``requires_grad``)."""
        fitted = copy.deepcopy(self.model)
        for name, value in (values or {}).items():
            _set_buffer(fitted, name, value)
        for name, requires_grad in self.parameter_flags.items():
            owner, leaf = _owner(fitted, name)
            owner._parameters[leaf] = nn.Parameter(owner._buffers.pop(leaf), requires_grad=requires_grad)
        return fitted


#: Rows of the batch on which :class:`BatchedCall` compares a batched call with the vmapped one.
PROBE_ROWS = 7


class BatchedCall:
    """A function ``one(t, x)`` of one time ``()`` and state ``(M,)``, evaluated over a batch ``t (I,)``,
    ``x (I, M)``: by ``one(t, x)`` itself in one call (a model written for a batch of states, as
    :class:`ODEModel` asks, or :meth:`AugmentedSystem.f`) where that gives what :func:`torch.vmap`
    of ``one`` gives, else by the vmapped ``one``. On a small model vmap's cost per call is most
    of an evaluation's. The first call decides, comparing the two (relative ``1e-12``) at rows of
    its batch and at a random batch near them (a model that reads ``x[0]`` as a state, or a sum
    over all the states as one state's total, gives wrong values or fails on a batch); it returns
    the vmapped values. :attr:`direct` says what was decided (None: not yet).

    The check runs on :data:`PROBE_ROWS` rows made from the first call's (repeated as needed):
    cheap whatever the batch, and a batch size that no state or coefficient shape is likely to
    match, so that a model broadcasting a batch of coefficients ``(I,)`` against states ``(I, n)``
    fails it by shape instead of building an ``(I, I)`` array. A vmapped function called on one
    row (a single fit, the last sample of a batch still stepping) is called on that row."""

    def __init__(self, one) -> None:
        self.one = one
        self.vmapped = torch.vmap(one)
        self.direct: bool | None = None

    def __call__(self, t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        if self.direct is None:
            rows = torch.arange(PROBE_ROWS, device=x.device) % x.shape[0]
            tp, xp = t[rows], x[rows]
            generator = torch.Generator(device=x.device).manual_seed(0)
            near = xp + (0.1 * xp.abs() + 0.1) * torch.randn(xp.shape, generator=generator, dtype=x.dtype,
                                                              device=x.device)
            self.direct = (_gives(self.one, tp, xp, self.vmapped(tp, xp))
                           and _gives(self.one, tp, near, self.vmapped(tp, near)))
            return self.vmapped(t, x)
        if self.direct:
            return self.one(t, x)
        if x.shape[0] == 1:  # vmap over one row is the call on that row, without vmap's cost
            return self.one(t[0], x[0]).unsqueeze(0)
        return self.vmapped(t, x)


def _gives(batch, t: torch.Tensor, x: torch.Tensor, expected: torch.Tensor) -> bool:
    """Whether ``batch(t, x)`` gives ``expected`` (relative ``1e-12``; any error: no)."""
    try:
        value = batch(t, x)
    except TimeBudgetExceeded:  # the fit's time is up: not the model's answer
        raise
    except Exception:  # noqa: BLE001 - a function that cannot take the batch is vmapped
        return False
    return (isinstance(value, torch.Tensor) and value.shape == expected.shape
            and bool(torch.allclose(value, expected, rtol=1e-12, atol=0.0, equal_nan=True)))


def _owner(module: nn.Module, dotted: str) -> tuple[nn.Module, str]:
    """The submodule holding tensor ``dotted`` (``"sub.name"`` allowed), and the tensor's own name."""
    *path, leaf = dotted.split(".")
    owner = module
    for part in path:
        owner = getattr(owner, part)
    return owner, leaf


def _parameters_to_buffers(module: nn.Module) -> dict[str, bool]:
    """Re-register every parameter of ``module`` (modified in place) as a buffer holding its value,
    detached; returns ``{dotted name: requires_grad}`` of the parameters so moved."""
    flags = {}
    for name, par in list(module.named_parameters(remove_duplicate=False)):
        owner, leaf = _owner(module, name)
        if leaf not in owner._parameters:  # (a submodule registered under two names: moved already)
            continue
        del owner._parameters[leaf]
        owner._buffers[leaf] = par.detach()
        flags[name] = par.requires_grad
    return flags


def tied_coefficients(module: nn.Module) -> tuple[str, str] | None:
    """Two names of one coefficient tensor held by two different submodules of ``module`` (PyTorch's
    weight tying), or None. A fit substitutes a coefficient under one name, and a forward that reads
    the other would not see it."""
    seen: dict[int, tuple[str, nn.Module]] = {}
    for name, tensor in [*module.named_buffers(remove_duplicate=False),
                         *module.named_parameters(remove_duplicate=False)]:
        if tensor is None or not tensor.is_floating_point():
            continue
        owner = _owner(module, name)[0]
        first = seen.setdefault(id(tensor), (name, owner))
        if first[1] is not owner:
            return first[0], name
    return None


def _set_buffer(module: nn.Module, dotted: str, value: torch.Tensor) -> None:
    """Replace coefficient ``dotted`` (``"sub.name"`` allowed) of ``module`` by ``value``: a buffer
    is replaced by ``value`` itself, an ``nn.Parameter`` by a Parameter holding ``value``'s data
    (``requires_grad`` as before)."""
    owner, leaf = _owner(module, dotted)
    if leaf in owner._parameters:
        old = owner._parameters[leaf]
        owner._parameters[leaf] = nn.Parameter(value.detach(), requires_grad=old is None or old.requires_grad)
    else:
        owner._buffers[leaf] = value
