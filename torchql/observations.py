"""Measurements of a model's states at discrete times, and the operators that observe them."""

from __future__ import annotations

import inspect
import operator
from collections.abc import Callable, Iterator, Sequence
from typing import Union

import numpy as np
import torch
from torch.func import jacrev, vmap

from ._arrays import float_tensor
from .inputs import Inputs
from .noise import NOISE_MODELS, sigma_group_index
from .observation_checks import BATCH_DIMS, check_shapes, check_times, exact_mask, fits

__all__ = ["Observations", "ObservationOperator", "LogObservation", "takes_params"]

ObserveSpec = Union[Sequence[str], torch.Tensor, np.ndarray, Callable[[torch.Tensor], torch.Tensor]]


class Observations:
    """Measured values of (functions of) the states at discrete times: one dataset, or a batch.

    One dataset has values ``y (T, K)``. A batch of ``B`` independent datasets (for
    :func:`torchql.fit_many`) has values ``y (B, T, K)`` and the same ``observe``
    specification; its samples share the times ``t (T,)`` or each has its own, ``t (B, T)``
    (the same number ``T`` of times). A batch is validated once, vectorized: ``obs[b]`` is
    sample ``b`` as a one-dataset ``Observations`` (with its own times) and ``obs[i:j]`` the
    batch of samples ``i .. j - 1`` (both copies: editing them leaves the batch as it is),
    ``len(obs)`` is ``B``, and iterating gives the samples in order.

    Parameters
    ----------
    t : Tensor or array, shape ``(T,)``, or ``(B, T)`` for a batch
        Observation times, finite and strictly increasing (same unit as the model's time). Every
        tensor argument is copied (detached when it requires grad; the caller's is left as it is). A
        batch's samples share ``t (T,)``, or row ``b`` of ``t (B, T)`` holds sample ``b``'s own
        times (each row finite and strictly increasing).
    y : Tensor or array, shape ``(T, K)``, ``(T,)`` when ``K == 1``, or ``(B, T, K)`` for a batch
        Measured values. ``NaN`` marks a missing value, which is skipped (each sample of a batch
        has its own missing values, and at least one value); ``inf`` is rejected.
    observe : sequence of str, Tensor of shape ``(K, n_states)``, or callable
        What each of the ``K`` columns of ``y`` measures: state names; a matrix ``Q`` so that
        ``y = Q x``; or a differentiable function ``h(x) -> (..., K)`` of the state
        ``x (..., n_states)``, linearized like the right-hand side (with one output, ``K == 1``, it
        may return a scalar); or ``h(x, p)``, which also reads
        the model's coefficients ``p`` by name (``p["scale"] * x[1] + p["offset"]``): observation
        parameters are coefficients of the model (buffers its ``forward`` need not use), estimated
        with the rest. The same for every sample.
    sigma : float, Tensor, "estimate" or callable, optional
        Standard deviation of each value (same unit as ``y``; of ``log y`` with
        ``noise="lognormal"``). Residuals are divided by it. ``"estimate"``: unknown, one per group
        of outputs (``sigma_groups``), estimated with the unknowns by maximum likelihood
        (:mod:`torchql.noise`). A callable ``sigma(p) -> (K,)``: each output's standard deviation
        as a differentiable function of the model's coefficients ``p`` by name (noise parameters,
        or a scale that also scales ``h(x, p)``), estimated with the rest by maximum likelihood
        (:mod:`torchql.sigma_function`). Default: 1 for every value, the residual variance estimated
        from the fit. One dataset: a scalar, shape ``(K,)`` or ``(T, K)``, and with
        ``K == 1`` shape ``(T,)`` too. A batch: those shapes (shared by the samples) or any
        shape that broadcasts to ``(B, T, K)``, such as ``(B, 1, K)`` or ``(B, T, K)``.
    exact : bool Tensor, optional
        Values to be met exactly (equality-constrained least squares) rather than in the
        least-squares sense. One dataset: shape ``(T, K)``, or ``(T,)`` marking every present value
        at those times. A batch: those shapes (shared) or any shape that broadcasts to ``(B, T, K)``.
        A value marked must be present (not NaN), and a time marked must hold one.
    noise : {"normal", "lognormal"}
        The values' noise: additive Gaussian (default), or log-normal (``log y`` Gaussian about
        ``log h(x)``; every present value must be positive).
    sigma_groups : None, "shared" or sequence of ``K`` labels
        With ``sigma="estimate"``: one sigma per output (default; named by the state it observes,
        a second sensor of one state ``"y#2"``), one for all, or one per label.
    inputs : Inputs, or for a batch a sequence of ``B`` Inputs, optional
        The experiment's measured inputs ``u(t)`` (:class:`torchql.Inputs`), for a model with
        ``input_names``; their samples must cover the data's times. A batch takes one
        ``Inputs`` shared by its samples or one per sample (``obs[b].inputs`` is sample ``b``'s).

    Attributes
    ----------
    t : Tensor ``(T,)``, or ``(B, T)`` for a batch with per-sample times
    y, sigma : Tensor ``(T, K)``, or ``(B, T, K)`` for a batch (``y``'s dtype is ``t``'s)
    exact : bool Tensor of ``y``'s shape
    observe : the ``observe`` argument as given (a matrix copied).
    sigma_given : bool
        Whether ``sigma`` was given (then it is taken as the known standard deviation of the
        values; otherwise the residual variance is estimated from the fit).
    inputs : Inputs, tuple of Inputs (a batch's, one per sample) or None
    noise : str
    sigma_estimated : bool
        Whether ``sigma`` is to be estimated (``sigma="estimate"``); ``sigma`` is then 1.
    sigma_groups : the ``sigma_groups`` argument as given.
    sigma_function : callable or None
        ``sigma(p)`` when ``sigma`` was given as a function of the coefficients (``sigma`` is then 1).
    """

    def __init__(
        self,
        t,
        y,
        observe: ObserveSpec,
        sigma=None,
        exact=None,
        inputs: "Inputs | Sequence[Inputs] | None" = None,
        noise: str = "normal",
        sigma_groups=None,
    ) -> None:
        t = float_tensor(t, "t")
        y = float_tensor(y, "y")
        if y.dim() == 1:
            y = y.unsqueeze(-1)
        check_shapes(t, y)
        batched = y.dim() == BATCH_DIMS
        T = t.shape[-1]
        check_times(t)
        infinite = torch.isinf(y)
        if infinite.any():
            where = f" (y[{int(infinite.flatten(1).any(dim=1).nonzero()[0, 0])}] does)" if batched else ""
            raise ValueError(f"`y` must not contain inf{where}; mark missing values with NaN instead")
        if batched:
            empty = torch.isnan(y).flatten(1).all(dim=1).nonzero().flatten().tolist()
            if empty:
                alike = f" (samples {empty[:10]} alike)" if len(empty) > 1 else ""
                raise ValueError(f"`y[{empty[0]}]` holds no value: every entry of that sample is NaN{alike}; "
                                 "remove it from the batch")
        elif torch.isnan(y).all():
            raise ValueError("`y` holds no value: every entry is NaN")
        K = y.shape[-1]
        shape = tuple(y.shape)
        self.t = t.clone()
        self.y = y.to(t.dtype) if y.dtype != t.dtype else y.clone()
        # a matrix is copied, as t and y are: scaling it afterwards must not change these data
        observe = observe.detach().clone() if isinstance(observe, torch.Tensor) else observe
        self.observe = observe
        self._check_observe_spec(observe, K)

        if not isinstance(noise, str) or noise not in NOISE_MODELS:
            raise ValueError(f"`noise` must be one of {list(NOISE_MODELS)}; received {noise!r}")
        if noise == "lognormal" and bool((self.y[~torch.isnan(self.y)] <= 0).any()):
            raise ValueError("`y` must be positive with noise='lognormal' (its logarithm is fitted); received a value "
                             "<= 0: mark it missing (NaN) or use noise='normal'")
        self.noise = noise
        self._set_sigma(sigma, sigma_groups, shape, batched)

        self.exact = exact_mask(exact, shape, self.y)
        self.inputs = _check_inputs(inputs, shape[0] if batched else None)

    def _set_sigma(self, sigma, sigma_groups, shape: tuple, batched: bool) -> None:
        """``sigma``, ``sigma_given``, ``sigma_estimated``, ``sigma_groups`` and ``sigma_function`` from
        the arguments, validated (values of shape ``shape``)."""
        T, K = shape[-2], shape[-1]
        self.sigma_function = None
        if callable(sigma) and not isinstance(sigma, (torch.Tensor, np.ndarray)):
            self.sigma_function, sigma = sigma, 1.0
        self.sigma_estimated = isinstance(sigma, str)
        if self.sigma_estimated and sigma != "estimate":
            raise ValueError("`sigma` must be a number, a tensor or 'estimate' (or a function sigma(p) of the "
                             f"coefficients); received {sigma!r}")
        if sigma_groups is not None and not self.sigma_estimated:
            raise ValueError("`sigma_groups` applies only with sigma='estimate'")
        self.sigma_groups = sigma_groups
        if self.sigma_estimated:
            sigma_group_index(sigma_groups, K, [f"y[{k}]" for k in range(K)])  # validated here
            sigma = None
        if sigma is None:
            sig = torch.ones(shape, dtype=self.y.dtype)
        else:
            sig = float_tensor(sigma, "sigma", self.y.dtype)
            per_time = ((T,),) if K == 1 else ()  # one output: (T,) is (T, 1)
            if not fits(tuple(sig.shape), shape, ((), (K,), (T, K)) + per_time):
                raise ValueError(
                    f"`sigma` must be a scalar, shape (K,) = ({K},) or shape (T, K) = ({T}, {K})"
                    + (f", or broadcast to (B, T, K) = {shape}" if batched else "")
                    + f"; received shape {tuple(sig.shape)}"
                )
            if per_time and sig.shape == per_time[0]:
                sig = sig.unsqueeze(-1)
            if not torch.isfinite(sig).all() or (sig <= 0).any():
                raise ValueError("`sigma` must be finite and strictly positive; received a value <= 0, NaN or inf")
        self.sigma = sig.expand(shape).clone(memory_format=torch.contiguous_format)
        self.sigma_given = sigma is not None

    def sigma_at(self, coefficients: dict) -> torch.Tensor:
        """The values' standard deviations, shape of :attr:`sigma`, with a ``sigma(p)`` function at
        the model's ``coefficients`` (by name), else :attr:`sigma` itself."""
        if self.sigma_function is None:
            return self.sigma
        return self.sigma * self.sigma_function(coefficients).to(device=self.sigma.device, dtype=self.sigma.dtype)

    @classmethod
    def _validated(cls, t: torch.Tensor, y: torch.Tensor, observe, sigma: torch.Tensor, exact: torch.Tensor,
                   sigma_given: bool, inputs=None) -> "Observations":
        """An instance from tensors already validated (a sample or slice of a batch): no checks, no copies."""
        obs = cls.__new__(cls)
        obs.t, obs.y, obs.observe, obs.sigma, obs.exact, obs.sigma_given = t, y, observe, sigma, exact, sigma_given
        obs.inputs = inputs
        obs.noise, obs.sigma_estimated, obs.sigma_groups, obs.sigma_function = "normal", False, None, None
        return obs

    def _same_noise(self, source: "Observations") -> "Observations":
        """This instance with ``source``'s noise model (for samples and slices of a batch)."""
        self.noise, self.sigma_estimated, self.sigma_groups = source.noise, source.sigma_estimated, source.sigma_groups
        self.sigma_function = source.sigma_function
        return self

    def inputs_of(self, b: int) -> Inputs | None:
        """Sample ``b``'s inputs (a batch's shared ones, or its own), or ``None``."""
        return self.inputs[b] if isinstance(self.inputs, tuple) else self.inputs

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
        """Number of observation times ``T`` (of each sample)."""
        return self.t.shape[-1]

    @property
    def per_sample_times(self) -> bool:
        """Whether each sample of a batch has its own times, ``t (B, T)`` (``False``: shared ``t (T,)``)."""
        return self.t.dim() == 2

    @property
    def n_outputs(self) -> int:
        """Number of observed quantities ``K``."""
        return self.y.shape[-1]

    @property
    def batch_size(self) -> int | None:
        """Number of datasets ``B`` of a batch (values ``(B, T, K)``); ``None`` for one dataset."""
        return self.y.shape[0] if self.y.dim() == BATCH_DIMS else None

    @property
    def mask(self) -> torch.Tensor:
        """Bool of ``y``'s shape, ``(T, K)`` or ``(B, T, K)``: values that are present (not NaN)."""
        return ~torch.isnan(self.y)

    def _require_batch(self, operation: str) -> int:
        B = self.batch_size
        if B is None:
            raise TypeError(f"{operation} applies to a batch of datasets (values (B, T, K)); this Observations "
                            f"holds one dataset, values of shape {tuple(self.y.shape)}")
        return B

    def __len__(self) -> int:
        """``B``, the number of datasets of a batch (``TypeError`` for one dataset)."""
        return self._require_batch("len()")

    def __bool__(self) -> bool:
        return True  # every Observations holds at least one value (not a container that can be empty)

    def __getitem__(self, index: int | slice) -> "Observations":
        """Sample ``index`` of a batch as one dataset, or a slice of samples as a batch (copies)."""
        B = self._require_batch("indexing")
        if isinstance(index, slice):
            rows = torch.tensor(range(B)[index], dtype=torch.long)  # any step, negative too
            if rows.numel() == 0:
                raise IndexError(f"the slice {index} selects no sample of a batch of {B}")
        else:
            if isinstance(index, bool):
                raise TypeError("a sample index must be an int or a slice; received bool")
            try:
                i = operator.index(index)
            except TypeError as exc:
                raise TypeError(f"a sample index must be an int or a slice; received {type(index).__name__}") from exc
            if not -B <= i < B:
                raise IndexError(f"sample index {i} is out of range for a batch of {B}")
            rows = i % B
        t = self.t[rows].clone() if self.per_sample_times else self.t.clone()
        if isinstance(self.inputs, tuple):
            inputs = tuple(self.inputs[r] for r in rows.tolist()) if isinstance(index, slice) else self.inputs[rows]
        else:
            inputs = self.inputs
        return Observations._validated(t, self.y[rows].clone(), self.observe, self.sigma[rows].clone(),
                                       self.exact[rows].clone(), self.sigma_given, inputs)._same_noise(self)

    def __iter__(self) -> Iterator["Observations"]:
        """The samples of a batch in order, each one dataset (``TypeError`` for one dataset)."""
        B = self._require_batch("iteration")
        return (self[b] for b in range(B))

    def __repr__(self) -> str:
        batch = "" if self.batch_size is None else f"B={self.batch_size}, "
        if self.per_sample_times:  # the span of all samples' times
            times = f"t per sample in [{self.t[:, 0].min().item():g}, {self.t[:, -1].max().item():g}]"
        else:
            times = f"t=[{self.t[0].item():g}, {self.t[-1].item():g}]"
        names = self.inputs.names if isinstance(self.inputs, Inputs) else (
            self.inputs[0].names if self.inputs else None)
        inputs = f", inputs={list(names)}" if names else ""
        return f"Observations({batch}T={self.n_times}, K={self.n_outputs}, {times}{inputs})"


def _check_inputs(inputs, B: int | None) -> Inputs | tuple[Inputs, ...] | None:
    """``inputs`` validated: ``None``, one :class:`Inputs`, or for a batch of ``B`` one per sample."""
    if inputs is None or isinstance(inputs, Inputs):
        return inputs
    if B is not None and isinstance(inputs, Sequence) and not isinstance(inputs, str):
        items = tuple(inputs)
        if len(items) != B:
            raise ValueError(f"`inputs` must be one torchql.Inputs (shared) or one per sample ({B}); received {len(items)}")
        for b, item in enumerate(items):
            if not isinstance(item, Inputs):
                raise TypeError(f"`inputs[{b}]` must be a torchql.Inputs; received {type(item).__name__}")
        if all(item.same_as(items[0]) for item in items[1:]):
            return items[0]
        return items
    expected = "a torchql.Inputs" + (f" or a sequence of {B} of them (one per sample)" if B is not None else "")
    raise TypeError(f"`inputs` must be {expected}; received {type(inputs).__name__}")


class ObserveCallableError(ValueError):
    """A user's ``observe`` callable failed; the message names the state's shape (and the experiment)."""


def _one_output(observe):
    """``observe`` for one output (``K == 1``): a scalar it returns (``p["s"] * x[1]``) becomes shape ``(1,)``."""
    def h(*args):
        out = observe(*args)
        return out.unsqueeze(0) if isinstance(out, torch.Tensor) and out.dim() == 0 else out
    return h


def takes_params(observe) -> bool:
    """Whether a callable ``observe`` is ``h(x, p)``, taking the coefficients as well as the state (two
    positional parameters, or a ``takes_params`` attribute saying so)."""
    flag = getattr(observe, "takes_params", None)
    if flag is not None:
        return bool(flag)
    try:
        signature = inspect.signature(observe)
    except (TypeError, ValueError):
        return False
    kinds = (inspect.Parameter.POSITIONAL_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
    positional = [p for p in signature.parameters.values() if p.kind in kinds]
    return len(positional) >= 2


class ObservationOperator:
    """``h(x)`` or ``h(x, p)``: what the data measure, with its Jacobian, for a given model.

    A callable of two arguments, ``h(x, p)``, also reads the coefficients ``p`` (a dict of the
    model's coefficients by name: scales, offsets and other observation parameters, which are
    coefficients of the model that its ``forward`` need not use). Its Jacobian is then taken with
    respect to the whole augmented state ``z = (x, p)`` (:meth:`bind` gives the layout), so the
    coefficients that only the observation reads are estimated like any other.

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
        self.n, self.K, self.state_names = n, K, list(state_names)
        self.function: Callable[..., torch.Tensor] | None = None
        self.matrix: torch.Tensor | None = None
        self.takes_params = False
        self.system = None
        #: The size of the states :meth:`value_and_jacobian` takes: ``n``, or ``M`` for ``h(x, p)``
        #: bound to a system (the augmented state).
        self.width = n
        if isinstance(observe, (torch.Tensor, np.ndarray)):
            Q = float_tensor(observe, "observe", dtype).to(device)
            if Q.shape != (K, n):
                raise ValueError(
                    f"`observe` matrix must have shape (K, n_states) = ({K}, {n}); received shape {tuple(Q.shape)}"
                )
            if not torch.isfinite(Q).all():
                raise ValueError("`observe` matrix must be finite")
            self.matrix = Q
        elif callable(observe):
            self.takes_params = takes_params(observe)
            self.function = _one_output(observe) if K == 1 else observe
        else:
            Q = torch.zeros(K, n, dtype=dtype, device=device)
            for k, name in enumerate(observe):
                if name not in state_names:
                    raise ValueError(f"`observe` names unknown state {name!r}; the model's states are {tuple(state_names)}")
                Q[k, list(state_names).index(name)] = 1.0
            self.matrix = Q

    def bind(self, system) -> "ObservationOperator":
        """Read the coefficients of ``h(x, p)`` from augmented states of ``system`` (an
        :class:`torchql.model.AugmentedSystem`): its unknowns from ``z``, the others from its model;
        :attr:`width` becomes the augmented state's size ``M``."""
        self.system = system
        if self.takes_params:
            self.width = system.M
        return self

    def _params(self, z: torch.Tensor) -> dict[str, torch.Tensor]:
        return self.system.coefficient_values(z)

    def labels(self) -> list[str]:
        """A label per output: the state it reads directly, else ``"y[k]"``."""
        return [self.state_names[i] if i is not None else f"y[{k}]" for k, i in enumerate(self.observed_states)]

    def measured_states(self, y: torch.Tensor) -> tuple[torch.Tensor, list[int | None]]:
        """The data ``y (..., T, K)`` as values of the states the outputs read directly, and for each
        output that state's index (``None``: an output that is no state itself); here ``y`` as it is."""
        return y, self.observed_states

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

    def check(self, x: torch.Tensor, params: dict | None = None) -> None:
        """Validate a callable operator on one state ``x (n,)`` (and the coefficients ``params`` for
        ``h(x, p)``): output shape ``(K,)``, same dtype, differentiable by ``torch.func``."""
        if self.function is None:
            return
        try:
            out = self.function(x, params) if self.takes_params else self.function(x)
        except ObserveCallableError:
            raise
        except Exception as exc:  # noqa: BLE001 - report any failure of user code clearly
            raise ObserveCallableError(f"`observe` callable failed on a state of shape ({self.n},): "
                             f"{type(exc).__name__}: {exc}") from exc
        if not isinstance(out, torch.Tensor) or out.shape != (self.K,):
            shape = tuple(out.shape) if isinstance(out, torch.Tensor) else type(out).__name__
            one = " (or a scalar)" if self.K == 1 else ""
            raise ValueError(f"`observe` callable must return shape (K,) = ({self.K},){one} for x of shape ({self.n},); "
                             f"received {shape}")
        if out.dtype != x.dtype:
            raise TypeError(f"`observe` callable must return dtype {x.dtype}; received {out.dtype}")
        call = (lambda xi: self.function(xi, params)) if self.takes_params else self.function
        try:  # as the fit takes it: dh/dx by jacrev under vmap
            vmap(jacrev(call))(x.unsqueeze(0))
        except Warning:  # a warning turned error (-W error) is the warning's
            raise
        except Exception as exc:  # noqa: BLE001 - report any failure of user code clearly
            raise ObserveCallableError(
                f"`observe` callable cannot be differentiated by torch.func on a state of shape ({self.n},) (the fit "
                f"takes dh/dx by jacrev under vmap): {type(exc).__name__}: {exc}. Write it with torch operations on x: "
                "no NumPy, .item() or float() of x") from exc

    def values(self, x: torch.Tensor, params: dict | None = None) -> torch.Tensor:
        """``h(x)`` for states ``x (T, n)`` (``h(x, params)`` with the coefficients by name): ``(T, K)``."""
        if self.matrix is not None:
            return x @ self.matrix.T
        if self.takes_params:
            return vmap(lambda xi: self.function(xi, params))(x)
        return vmap(self.function)(x)

    def value_and_jacobian(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``h(x)`` and ``dh/dx`` for states ``x (T, n)``: shapes ``(T, K)`` and ``(T, K, n)``.

        For ``h(x, p)`` (bound to a system), ``x`` is the augmented state ``z (T, M)`` and the
        Jacobian ``dh/dz`` has shape ``(T, K, M)``."""
        if self.matrix is not None:
            return x @ self.matrix.T, self.matrix.expand(x.shape[0], self.K, self.n)

        if self.takes_params:
            def h(zi):
                out = self.function(zi[:self.n], self._params(zi))
                return out, out
        else:
            def h(xi):
                out = self.function(xi)
                return out, out

        jac, val = vmap(jacrev(h, has_aux=True))(x)
        return val, jac


class LogObservation:
    """``log h(x)``: the observation operator of log-normal data (fitted on ``log y``)."""

    def __init__(self, operator: ObservationOperator) -> None:
        self.inner, self.n, self.K = operator, operator.n, operator.K
        self.matrix, self.function, self.takes_params = None, operator.function, operator.takes_params

    @property
    def width(self) -> int:
        """The size of the states :meth:`value_and_jacobian` takes (the inner operator's)."""
        return self.inner.width

    @property
    def observed_states(self) -> list[None]:
        """No output is a state itself (it is the logarithm of one)."""
        return [None] * self.K

    def measured_states(self, y: torch.Tensor) -> tuple[torch.Tensor, list[int | None]]:
        """The log data ``y (..., T, K)`` as values of the states the inner operator reads directly:
        ``exp(y)``, with its indices (as :meth:`ObservationOperator.measured_states`)."""
        return torch.exp(y), self.inner.observed_states

    def check(self, x: torch.Tensor, params: dict | None = None) -> None:
        self.inner.check(x, params)

    def values(self, x: torch.Tensor, params: dict | None = None) -> torch.Tensor:
        """``log h``: ``(T, K)``."""
        return torch.log(self.inner.values(x, params))

    def value_and_jacobian(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``log h(x) (T, K)`` and its Jacobian ``(T, K, n)``."""
        h, H = self.inner.value_and_jacobian(x)
        return torch.log(h), H / h.unsqueeze(-1)
