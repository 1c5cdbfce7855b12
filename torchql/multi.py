"""Several experiments that share the model's coefficients, fitted as one problem.

Experiment ``e`` has its own observation times, initial time ``t0_e`` and initial state; all
share the coefficients. Each is mapped onto the normalized time ``tau = (t - t0_e) / T_e`` in
``[0, 1]`` (``T_e`` its span), and the experiments' states are stacked into one model

    dX_e/dtau = T_e f(t0_e + T_e tau, X_e; p),    e = 1..E,

with the coefficients ``p`` its buffers. The stacked problem is an ordinary single-experiment
fit: one grid, one linearization per iteration, one least-squares update for every
experiment's initial state and the shared coefficients together, and one covariance.
"""

from __future__ import annotations

import copy
from typing import NamedTuple

import torch
from torch import nn
from torch.func import functional_call

from . import _checks
from ._arrays import float_tensor
from .initial_state import ReadValues, check_expressions
from .model import ODEModel, _set_buffer, coefficients, model_dtype_device
from .noise import sigma_group_index
from .observations import ObservationOperator, ObserveCallableError, Observations

__all__ = ["StackedModel", "StackedExperiments", "stack_experiments", "experiment_result", "stack_observations",
           "experiment_state_name", "check_conditions", "with_condition", "replaced_everywhere"]


def experiment_state_name(name: str, e: int) -> str:
    """Name of state ``name`` of experiment ``e`` in the stacked model: ``"name[e]"``."""
    return f"{name}[{e}]"


def condition_values(values: dict, condition: dict | None) -> dict:
    """``values`` (coefficients by name) as one experiment sees them: its ``condition`` applied, each
    entry a tensor or another coefficient's name (see :func:`check_conditions`). A new dict."""
    own = dict(values)
    for key, value in (condition or {}).items():
        own[key] = values[value] if isinstance(value, str) else value
    return own


def experiment_values(values: dict, conditions: list | None, e: int) -> dict:
    """``values`` as experiment ``e`` sees them, its entry of ``conditions`` (if any) applied."""
    return condition_values(values, conditions[e] if conditions else None)


def experiment_expressions(expressions: dict, names: list[str], E: int, conditions: list | None) -> dict | None:
    """``x0_expr`` of several experiments for the stacked model: each state's expression in every
    experiment, seeing that experiment's initial states by their own names and its coefficient
    values (its ``conditions`` applied)."""
    if not expressions:
        return None

    def own(fn, e: int):
        def expression(values: dict) -> torch.Tensor:
            mine = {k: v for k, v in values.items() if "[" not in k or k.rsplit("[", 1)[0] not in names}
            mine = experiment_values(mine, conditions, e)
            mine.update({s: dict.__getitem__(values, experiment_state_name(s, e)) for s in names})
            if not isinstance(values, ReadValues):
                return fn(mine)
            mine = ReadValues(mine)  # the states the experiment's expression reads, by their stacked names
            value = fn(mine)
            values.read |= {experiment_state_name(s, e) for s in mine.read if s in names}
            return value
        return expression

    return {experiment_state_name(state, e): own(fn, e) for e in range(E) for state, fn in expressions.items()}


class StackedModel(ODEModel):
    """``E`` copies of ``model`` in normalized time, sharing its buffers (the coefficients).

    Parameters
    ----------
    model : ODEModel
        The user's model (not modified; a copy is held).
    t0 : Tensor ``(E,)``
        Initial time of each experiment.
    span : Tensor ``(E,)``
        Time span ``T_e > 0`` of each experiment.
    inputs : list of ``E`` Inputs, optional
        Each experiment's measured inputs, in the model's ``input_names`` order (for a model with
        inputs): experiment ``e``'s copy is evaluated with its own signals at its own time.
    conditions : list of ``E`` dicts, optional
        Validated by :func:`check_conditions`: experiment ``e``'s copy takes coefficient ``k``'s
        value from ``conditions[e][k]``, a constant tensor or the name of another coefficient.
    """

    #: the stacking's own buffers (each experiment's initial time and span), none of the user's
    #: coefficients: no argument names them, and errors do not list them
    internal_buffers = ("_t0", "_span")

    def __init__(self, model: ODEModel, t0: torch.Tensor, span: torch.Tensor, inputs: list | None = None,
                 conditions: list | None = None) -> None:
        super().__init__()
        tensors = list(model.named_buffers()) + list(model.named_parameters())  # parameters held as buffers
        names = [name for name, _ in tensors]
        nested = [name for name in names if "." in name]
        if nested:
            raise ValueError(
                f"several experiments need a model whose buffers are its own (not a submodule's); found {nested}")
        self.inner = _Frozen(model)
        for name, value in tensors:
            self.register_buffer(name, value.detach().clone())
        self._buffer_names = names
        self.E = int(t0.shape[0])
        self.n = len(model.state_names)
        self.state_names = [experiment_state_name(s, e) for e in range(self.E) for s in model.state_names]
        self.constants = tuple(getattr(model, "constants", ())) + self.internal_buffers
        self.register_buffer("_t0", t0.clone(), persistent=False)
        self.register_buffer("_span", span.clone(), persistent=False)
        # each experiment's signals in its local time t - t0_e, read at T_e tau (at t ~ 1e8 a held
        # input's step spanned 1e5 roundoffs of t0_e + T_e tau: see Inputs.shifted)
        self._signals = None if inputs is None else [s.shifted(float(t0[e])) for e, s in enumerate(inputs)]
        self._conditions = conditions
        # a coefficient that every experiment replaces is no unknown by default
        self.constants = self.constants + replaced_everywhere(conditions)

    def forward(self, t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        buffers = {name: getattr(self, name) for name in self._buffer_names}
        out = []
        for e in range(self.E):
            xe = x[..., e * self.n:(e + 1) * self.n]
            te = self._t0[e] + self._span[e] * t
            args = (te, xe) if self._signals is None else (te, xe, self._signals[e](self._span[e] * t))
            own = condition_values(buffers, self._conditions[e]) if self._conditions else buffers
            out.append(self._span[e] * functional_call(self.inner.model, own, args))
        return torch.cat(out, dim=-1)

    def input_nodes(self) -> torch.Tensor | None:
        """The experiments' input nodes in normalized time (``None`` without inputs)."""
        return self._normalized("nodes")

    def input_jumps(self) -> torch.Tensor | None:
        """The experiments' input jumps in normalized time (``None`` without any)."""
        return self._normalized("jumps")

    def _normalized(self, kind: str) -> torch.Tensor | None:
        pieces = [getattr(s, kind).to(self._t0) / self._span[e]  # (the signals are in local time)
                  for e, s in enumerate(self._signals or ()) if getattr(s, kind) is not None]
        return torch.cat(pieces) if pieces else None


def replaced_everywhere(conditions) -> tuple[str, ...]:
    """The coefficients that every experiment's condition replaces, sorted: no unknowns by default
    (none where ``conditions`` is not a non-empty list of dicts, whose own checks name what is wrong)."""
    if not isinstance(conditions, (list, tuple)) or not conditions or not all(isinstance(c, dict) for c in conditions):
        return ()
    return tuple(sorted(set.intersection(*(set(c) for c in conditions))))


def check_conditions(model: ODEModel, conditions, E: int) -> list[dict] | None:
    """``fit``'s ``conditions`` validated: one dict per experiment ``{coefficient: value}``, a value
    being a number (a constant of that experiment) or another coefficient's name (its value: an
    unknown, or a constant, shared by the experiments that name it). Numbers become tensors of the
    coefficient's shape, dtype and device."""
    if conditions is None:
        return None
    if not isinstance(conditions, (list, tuple)) or len(conditions) != E:
        received = f"{len(conditions)} entries" if isinstance(conditions, (list, tuple)) else type(conditions).__name__
        raise ValueError(f"`conditions` must be a list of one dict per experiment ({E}); received {received}")
    available = coefficients(model)
    out = []
    for e, condition in enumerate(conditions):
        if condition is None:
            out.append({})
            continue
        if not isinstance(condition, dict):
            raise TypeError(f"`conditions[{e}]` must be a dict {{coefficient: number or coefficient name}}; "
                            f"received {type(condition).__name__}")
        own = {}
        for key, value in condition.items():
            if key not in available:
                raise ValueError(f"`conditions[{e}]` names unknown coefficient {key!r}; the model's are "
                                 f"{list(available)}")
            target = available[key]
            if isinstance(value, str):
                if value not in available or value == key:
                    raise ValueError(f"`conditions[{e}][{key!r}]` = {value!r} must name another coefficient of the "
                                     f"model; its coefficients are {list(available)}")
                if available[value].shape != target.shape:
                    raise ValueError(f"`conditions[{e}][{key!r}]` = {value!r} has shape {tuple(available[value].shape)}"
                                     f", {key!r} has {tuple(target.shape)}")
                own[key] = value
                continue
            tensor = float_tensor(value, f"conditions[{e}][{key!r}]", target.dtype, target.device,
                                  expected=f"a number, a tensor of shape {tuple(target.shape)} or a coefficient's "
                                           "name").clone()
            if tensor.shape != target.shape:
                tensor = tensor.expand(target.shape).clone() if tensor.dim() == 0 else tensor
            if tensor.shape != target.shape or not bool(torch.isfinite(tensor).all()):
                raise ValueError(f"`conditions[{e}][{key!r}]` must be finite, of shape {tuple(target.shape)}; "
                                 f"received {value!r}")
            own[key] = tensor
        out.append(own)
    return out


def with_condition(model: ODEModel, condition: dict | None) -> ODEModel:
    """A copy of ``model`` with one experiment's ``condition`` applied (see :func:`check_conditions`)."""
    fitted = copy.deepcopy(model)
    if condition:
        values = condition_values(coefficients(model), condition)
        for key in condition:
            _set_buffer(fitted, key, values[key].detach().clone())
    return fitted


class _Frozen(nn.Module):
    """Holds the user's model without registering its buffers under a prefix."""

    def __init__(self, model: nn.Module) -> None:
        super().__init__()
        object.__setattr__(self, "model", model)


def stack_observations(datasets: list[Observations], state_names: list[str], t0: torch.Tensor, span: torch.Tensor,
                       dtype: torch.dtype, device: torch.device, conditions: list | None = None) -> Observations:
    """The experiments' observations as one :class:`Observations` of the stacked model.

    Times become normalized times (their union); each experiment's values fill its own
    columns and are missing (NaN) at the others' times. Observation operators given as state
    names or matrices become one block-diagonal matrix; callables are applied block by block
    (``h(x, p)`` reading each experiment's own coefficient values, its ``conditions`` applied).
    """
    n = len(state_names)
    E = len(datasets)
    taus = [((d.t.to(dtype=dtype, device=device) - t0[e]) / span[e]) for e, d in enumerate(datasets)]
    tau = torch.unique(torch.cat(taus))
    K = [d.n_outputs for d in datasets]
    offsets = [sum(K[:e]) for e in range(E)]
    nan = float("nan")
    y = torch.full((tau.numel(), sum(K)), nan, dtype=dtype, device=device)
    sigma = torch.ones_like(y)
    exact = torch.zeros_like(y, dtype=torch.bool)
    for e, d in enumerate(datasets):
        rows = torch.searchsorted(tau, taus[e])
        cols = slice(offsets[e], offsets[e] + K[e])
        y[rows, cols] = d.y.to(dtype=dtype, device=device)
        sigma[rows, cols] = d.sigma.to(dtype=dtype, device=device)
        exact[rows, cols] = d.exact.to(device)
    operators = [ObservationOperator(d.observe, state_names, d.n_outputs, dtype, device) for d in datasets]
    if all(op.matrix is not None for op in operators):
        Q = torch.zeros(sum(K), E * n, dtype=dtype, device=device)
        for e, op in enumerate(operators):
            Q[offsets[e]:offsets[e] + K[e], e * n:(e + 1) * n] = op.matrix
        observe = Q
    else:
        observe = _BlockObservation([op.function for op in operators], operators, n, conditions)
    first = datasets[0]
    estimated = [d.sigma_estimated for d in datasets]
    if any(estimated) and not all(estimated):
        raise ValueError(f"sigma='estimate' must be given for every experiment or for none: the experiments "
                         f"{[e for e, x in enumerate(estimated) if x]} estimate theirs, "
                         f"{[e for e, x in enumerate(estimated) if not x]} do not (a known sigma, or none)")
    sigma_given = all(d.sigma_given for d in datasets)
    if not sigma_given and any(d.sigma_given for d in datasets):
        raise ValueError(f"`sigma` must be given for every experiment or for none (the residual variance is shared); "
                         f"it is given for experiments {[e for e, d in enumerate(datasets) if d.sigma_given]} only")
    for e, d in enumerate(datasets[1:], start=1):
        if (d.noise, d.sigma_estimated) != (first.noise, first.sigma_estimated):
            raise ValueError(f"`data[{e}]` has another noise model than `data[0]` (`noise` or sigma='estimate' "
                             "differ): the experiments of one fit share it")
    if first.sigma_estimated:
        return Observations(tau, y, observe=observe, sigma="estimate", exact=exact, noise=first.noise,
                            sigma_groups=[label for d, op in zip(datasets, operators) for label in _sigma_labels(d, op)])
    functions = [d.sigma_function for d in datasets]
    if any(f is not None for f in functions):
        if not all(f is not None for f in functions):
            raise ValueError("`sigma` must be a function sigma(p) for every experiment or for none (experiment "
                             f"{functions.index(None)} gives none); a known sigma can be a function returning "
                             "constants")
        sigma = _BlockSigma(functions, conditions)
    return Observations(tau, y, observe=observe, sigma=sigma if sigma_given else None, exact=exact, noise=first.noise)


class _BlockSigma:
    """``sigma(p) = [sigma_1(p_1), ..., sigma_E(p_E)]``: each experiment's function of its own
    coefficient values (its ``conditions`` applied)."""

    def __init__(self, functions: list, conditions: list | None) -> None:
        self.functions, self.conditions = functions, conditions

    def __call__(self, p: dict) -> torch.Tensor:
        return torch.cat([fn(experiment_values(p, self.conditions, e))
                          for e, fn in enumerate(self.functions)])


def _sigma_labels(data: Observations, operator: ObservationOperator) -> list[str]:
    """Each output's sigma group, by name, as one experiment's fit groups them: the same label, or
    the same observed state by default, is one sigma across experiments."""
    names, group = sigma_group_index(data.sigma_groups, data.n_outputs, operator.labels())
    return [names[g] for g in group]


class _BlockObservation:
    """``h(X) = [h_1(X_1), ..., h_E(X_E)]`` for the stacked state ``X``: each experiment's ``observe``
    as its operator takes it (a one-output function's scalar made shape ``(1,)``)."""

    def __init__(self, specs, operators: list[ObservationOperator], n: int, conditions: list | None = None) -> None:
        self.specs, self.operators, self.n, self.conditions = specs, operators, n, conditions
        #: ``h(X, p)`` when some experiment's observation reads the coefficients
        self.takes_params = any(op.takes_params for op in operators)

    def __call__(self, x: torch.Tensor, p: dict | None = None) -> torch.Tensor:
        out = []
        for e, (spec, op) in enumerate(zip(self.specs, self.operators)):
            xe = x[..., e * self.n:(e + 1) * self.n]
            if op.matrix is not None:
                out.append(xe @ op.matrix.T)
                continue
            try:
                out.append(spec(xe, experiment_values(p, self.conditions, e)) if op.takes_params else spec(xe))
            except Exception as exc:  # noqa: BLE001 - report any failure of user code clearly
                raise ObserveCallableError(f"`observe` callable of experiment {e} failed on a state of shape "
                                           f"{tuple(xe.shape)}: {type(exc).__name__}: {exc}") from exc
        return torch.cat(out, dim=-1)


class StackedExperiments(NamedTuple):
    """Several experiments as the stacked problem that :func:`torchql.fit` solves."""

    model: "StackedModel"  #: the experiments' states stacked, in normalized time
    data: Observations  #: their observations on the union of normalized times
    x0: torch.Tensor | None  #: the stacked initial states ``(E n,)``, or ``None`` (from the data)
    fixed_x0: list[str] | None  #: the stacked model's known initial states
    bounds: dict | None  #: ``bounds`` with a state's entry for each experiment where it is unknown
    scale: dict | None  #: ``scale`` alike
    x0_expr: dict | None  #: each state's expression in every experiment
    t0: torch.Tensor  #: the experiments' initial times ``(E,)``
    span: torch.Tensor  #: their spans ``(E,)`` (normalized time 1)
    conditions: list[dict] | None  #: the checked ``conditions``


def stack_experiments(model, datasets: list, x0, *, t0, fixed_x0, bounds, scale, x0_expr, grid,
                      conditions) -> StackedExperiments:
    """The experiments ``datasets`` of one fit (arguments as :func:`torchql.fit` takes them) as one
    stacked problem, validated; errors name the argument and the experiment."""
    _checks.model_class(model)
    if not datasets:
        raise ValueError("`data` is an empty list: give one torchql.Observations per experiment")
    for e, d in enumerate(datasets):
        if not isinstance(d, Observations):
            raise TypeError(f"`data[{e}]` must be a torchql.Observations; received {type(d).__name__}")
    E, names = len(datasets), list(model.state_names)
    n = len(names)
    dtype, device = model_dtype_device(model)
    first = torch.stack([d.t[0].to(dtype) for d in datasets]).to(device)
    last = torch.stack([d.t[-1].to(dtype) for d in datasets]).to(device)
    if t0 is None:
        t0s = first.clone()
    else:
        values = [t0] * E if not isinstance(t0, (list, tuple, torch.Tensor)) or (
            isinstance(t0, torch.Tensor) and t0.dim() == 0) else list(t0)
        if len(values) != E:
            raise ValueError(f"`t0` must be one time or one per experiment ({E}); received {len(values)}")
        t0s = torch.tensor([_checks.finite_number(f"t0[{e}]", float(v)) for e, v in enumerate(values)],
                           dtype=dtype, device=device)
        late = [e for e in range(E) if t0s[e] > first[e]]
        if late:
            raise ValueError(f"`t0` must not be later than each experiment's first observation; experiments {late} "
                             f"start at {[float(first[e]) for e in late]}, t0 = {[float(t0s[e]) for e in late]}")
    span = last - t0s
    span = torch.where(span > 0, span, torch.ones_like(span))
    if x0 is not None:
        x0_t = float_tensor(x0, "x0", dtype, device, expected=f"a tensor of shape (E, n_states) = ({E}, {n})")
        if x0_t.shape != (E, n):
            raise ValueError(f"`x0` must have shape (E, n_states) = ({E}, {n}) with {E} experiments; "
                             f"received shape {tuple(x0_t.shape)}")
        x0_flat = x0_t.reshape(-1).clone()
    elif x0_expr and set(names) <= set(x0_expr):  # every initial state an expression: nothing to give
        x0_flat = torch.zeros(E * n, dtype=dtype, device=device)
    else:
        if t0 is not None and bool((t0s != first).any()):
            raise ValueError("`x0` is required when `t0` precedes an experiment's first observation (unless "
                             "`x0_expr` gives every state)")
        x0_flat = None
    if isinstance(grid, torch.Tensor):
        raise ValueError("`grid` must be a number of intervals (per experiment) with several experiments; "
                         "received a tensor of times")
    checked = check_conditions(model, conditions, E)
    stacked = StackedModel(model, t0s, span, _experiment_inputs(model, datasets, t0s, last, dtype, device), checked)
    data = stack_observations(datasets, names, t0s, span, dtype, device, checked)
    fixed = _experiment_fixed(fixed_x0, names, E)
    return StackedExperiments(
        stacked, data, x0_flat, fixed,
        _per_experiment("bounds", bounds, "{name: (lower, upper)}", names, fixed, E),
        _per_experiment("scale", scale, "{name: 'lin' | 'log' | 'log10'}", names, fixed, E),
        experiment_expressions(check_expressions(x0_expr, names, None), names, E, checked), t0s, span, checked)


def experiment_result(result, model, st: StackedExperiments, datasets):
    """The stacked fit's ``result`` (a ``FitResult``, or a ``BatchFitResult`` of samples of several
    experiments) in the experiments' terms: the model's own coefficients only, ``x0 (..., E, n)``,
    ``experiment_t0``, the checked ``conditions`` and the experiments' ``datasets``. Returns it."""
    own = coefficients(model)
    result.params = {name: value for name, value in result.params.items() if name in own}
    result.x0 = result.x0.reshape(*result.x0.shape[:-1], st.t0.numel(), -1)
    result.experiment_t0 = [float(v) for v in st.t0]
    result.conditions = st.conditions
    result.data = datasets
    return result


def _per_experiment(argument: str, given, expected: str, names: list, fixed, E: int) -> dict | None:
    """``bounds`` or ``scale`` of several experiments for the stacked model: a state's entry applies
    to its initial value in every experiment where that is an unknown; a coefficient's as given."""
    if given is None:
        return None
    if not isinstance(given, dict):
        raise TypeError(f"`{argument}` must be a dict {expected}; received {type(given).__name__}")
    stacked = {}
    for key, value in given.items():
        state = key.removesuffix("(t0)") if isinstance(key, str) else key
        if state in names:  # the experiments where that state's initial value is an unknown
            stacked.update({experiment_state_name(state, e): value for e in range(E)
                            if experiment_state_name(state, e) not in (fixed or ())})
        else:
            stacked[key] = value
    return stacked


def _experiment_inputs(model, datasets: list, t0s: torch.Tensor, last: torch.Tensor, dtype, device) -> list | None:
    """Each experiment's inputs in the model's order, checked as one dataset's are (names, times)."""
    names = tuple(getattr(model, "input_names", ()))
    given = [d.inputs is not None for d in datasets]
    if not names and not any(given):
        return None
    if not names:
        e = given.index(True)
        raise ValueError(f"`data[{e}]` carries inputs {list(datasets[e].inputs.names)} but `model` declares none: "
                         "set its `input_names` and take them in forward(t, x, u)")
    signals = []
    for e, d in enumerate(datasets):
        if d.inputs is None:
            raise ValueError(f"`model` takes inputs {names} (its `input_names`) but `data[{e}]` carries none: give "
                             f"them as Observations(t, y, observe, inputs=torchql.Inputs(t_u, u, names={list(names)}))")
        signals.append(d.inputs.for_model(names, float(t0s[e]), float(last[e]), dtype, device,
                                          where=f"data[{e}].inputs", span="the experiment's times"))
    return signals


def _experiment_fixed(fixed_x0, names: list, E: int) -> list[str] | None:
    """``fixed_x0`` of several experiments as the stacked model's state names: state names fixed in
    every experiment, or one list of names per experiment."""
    if fixed_x0 is None:
        return None
    if isinstance(fixed_x0, str):
        raise TypeError(f"`fixed_x0` must be a sequence of state names, not a string; use [{fixed_x0!r}]")
    items = list(fixed_x0)
    per_experiment = len(items) == E and all(isinstance(item, (list, tuple)) for item in items)
    if not per_experiment and any(not isinstance(item, str) for item in items):
        raise TypeError(f"`fixed_x0` must be state names, or one list of state names per experiment ({E}); "
                        f"received {fixed_x0!r}")
    lists = items if per_experiment else [items] * E
    fixed = []
    for e, own in enumerate(lists):
        for name in own:
            if name not in names:
                where = f"`fixed_x0[{e}]`" if per_experiment else "`fixed_x0`"
                raise ValueError(f"{where} names unknown state {name!r}; the model's states are {tuple(names)}")
            fixed.append(experiment_state_name(name, e))
    return fixed
