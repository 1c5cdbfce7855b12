"""One specification of the unknowns and known values, in the manner of lmfit's ``Parameter``.

``fit(model, data, parameters={...})`` takes, for any coefficient or state, its value, whether it
varies, its bounds and its scale in one place::

    parameters = {
        "beta": Parameter(0.5, min=0.0, scale="log"),   # an unknown rate, guess 0.5, iterated in log
        "N": Parameter(763.0, vary=False),              # a known coefficient and its value
        "S": Parameter(762.0, vary=False),              # a known initial state
        "I": Parameter(1.0, min=0.0),                   # an unknown initial state, guess 1
        "gamma": 0.2,                                   # a number: an unknown with that guess
        "R": Parameter(expr=lambda v: v["N"] - v["S"] - v["I"]),  # follows the others
    }

It is written into the keywords the fit already takes (``params``, ``fixed_x0``, ``x0``, ``bounds``,
``scale``, ``x0_expr``) and a copy of the model holding the given coefficient values, so everything else
(profiles, multistart, reports, ``result.fit_kwargs``) sees one ordinary fit. Names not in the
specification keep their defaults: the model's buffers and ``constants``, ``x0``, and the other
keywords as given. A name given both here and in ``bounds``, ``scale`` or ``x0_expr`` is an error,
not a silent choice, and so is one whose role here contradicts ``params`` (a coefficient listed
there with ``vary=False`` here) or ``fixed_x0`` (a state fixed there with ``vary=True`` here).
"""

from __future__ import annotations

import copy
import math
import numbers
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import torch

from . import _checks
from ._arrays import float_tensor
from .bounds import SCALES
from .model import _set_buffer, coefficient_names, coefficients, model_dtype_device
from .multi import replaced_everywhere

__all__ = ["Parameter", "apply_parameters"]


@dataclass(frozen=True)
class Parameter:
    """A coefficient's or initial state's value and role in a fit.

    Parameters
    ----------
    value : float or Tensor, optional
        The guess of an unknown, or the value of a known one (``vary=False``), in the model's
        units. A coefficient's value replaces its buffer's (a scalar fills a vector or matrix
        coefficient); a state's is its initial value (``x0``'s entry). Default: the buffer's
        value, or ``x0``'s entry.
    vary : bool
        Whether it is estimated (default) or held at ``value``.
    min, max : float, optional
        Bounds of an unknown (``bounds=`` of :func:`torchql.fit`); ``None``: open.
    scale : {"lin", "log", "log10"}
        The scale it is iterated on (``scale=`` of :func:`torchql.fit`); log scales need a
        positive value.
    expr : callable, optional
        For an initial state: its value as a function of the others (``x0_expr=`` of
        :func:`torchql.fit`, :mod:`torchql.initial_state`); it is then neither estimated nor fixed.
    """

    value: float | torch.Tensor | None = None
    vary: bool = True
    min: float | None = None
    max: float | None = None
    scale: str = "lin"
    expr: Callable[[dict], torch.Tensor] | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.vary, bool):
            raise TypeError(f"`Parameter.vary` must be True or False; received {self.vary!r}")
        if self.scale not in SCALES:
            raise ValueError(f"`Parameter.scale` must be one of {list(SCALES)}; received {self.scale!r}")
        if self.expr is not None and not callable(self.expr):
            raise TypeError(f"`Parameter.expr` must be callable (values by name -> scalar); received "
                            f"{type(self.expr).__name__}")
        for side in ("min", "max"):
            bound = getattr(self, side)
            if bound is not None and (isinstance(bound, bool) or not isinstance(bound, numbers.Real)):
                raise TypeError(f"`Parameter.{side}` must be a number or None; received {bound!r}")
            if bound is not None and math.isnan(bound):
                raise ValueError(f"`Parameter.{side}` must be a number (or None for no bound), not NaN")
        if (self.min is not None and self.min == math.inf) or (self.max is not None and self.max == -math.inf):
            raise ValueError(f"`Parameter.min` must be below inf and `Parameter.max` above -inf (None: no bound); "
                             f"received min={self.min!r}, max={self.max!r}")
        if self.min is not None and self.max is not None and not self.min < self.max:
            raise ValueError(f"`Parameter.min` must be below `Parameter.max`; received min={self.min!r}, "
                             f"max={self.max!r}")
        # roles that exclude each other are an error, as the keywords they stand for make them
        given = {name: getattr(self, name) for name in ("min", "max") if getattr(self, name) is not None}
        if self.scale != "lin":
            given["scale"] = self.scale
        if self.expr is not None:
            extra = dict(given, **({"value": self.value} if self.value is not None else {}),
                         **({"vary": False} if not self.vary else {}))
            if extra:
                raise ValueError(f"`Parameter.expr` makes the state follow the others: it is neither estimated nor "
                                 f"given, so {sorted(extra)} do not apply with it; received {extra}")
        elif not self.vary and given:
            raise ValueError(f"`Parameter(vary=False)` holds a known value, which takes no bounds or scale; received "
                             f"{given}")
        elif self.scale != "lin" and self.value is not None and bool((torch.as_tensor(self.value) <= 0).any()):
            raise ValueError(f"`Parameter.scale` = {self.scale!r} needs a positive value; received {self.value!r}")


def apply_parameters(model, parameters: Mapping, *, x0, params, fixed_x0, bounds, scale, x0_expr=None,
                     rows: int | None = None, conditions=None) -> dict:
    """``parameters`` written into a fit's keywords.

    Parameters
    ----------
    model : ODEModel
        Never modified: a copy holds the given coefficient values.
    parameters : dict of str to Parameter or number
        Keys: coefficient names (whole buffers) or state names (``"S"`` or ``"S(t0)"``).
    x0, params, fixed_x0, bounds, scale, x0_expr
        The fit's own keywords, as given.
    rows : int, optional
        The rows of ``x0``: ``None`` for one initial state ``(n_states,)``; ``E`` for several
        experiments or ``B`` for a batch, ``(rows, n_states)``, a state's value set in every row.
    conditions : list of dict, optional
        The experiments' conditions: a coefficient that every experiment replaces is no unknown
        by default (as with the keywords, :class:`torchql.multi.StackedModel`).

    Returns
    -------
    dict with keys ``model``, ``x0``, ``params``, ``fixed_x0``, ``bounds``, ``scale``, ``x0_expr``.
    """
    if not isinstance(parameters, Mapping):
        raise TypeError(f"`parameters` must be a dict {{name: torchql.Parameter or number}}; received "
                        f"{type(parameters).__name__}")
    states = list(model.state_names)
    coefficients = coefficient_names(model)
    dtype, device = model_dtype_device(model)
    specs = {name: _as_parameter(name, spec) for name, spec in parameters.items()}
    fitted, changed = None, params is not None
    held = tuple(model.constants) + replaced_everywhere(conditions)
    out_params = list(params) if params is not None else [c for c in coefficients if c not in held]
    fixed, per_experiment = _fixed_lists(fixed_x0)
    state_values: dict[int, float] = {}
    out_bounds = dict(bounds) if bounds is not None else {}
    out_scale = dict(scale) if scale is not None else {}
    out_expr = dict(x0_expr) if isinstance(x0_expr, Mapping) else {}
    for key, spec in specs.items():
        name = key.removesuffix("(t0)") if isinstance(key, str) and key not in coefficients else key
        if spec.expr is not None and name not in states:
            raise ValueError(f"`parameters[{key!r}]` has an `expr`, which applies to initial states; {key!r} is not a "
                             f"state of the model (its states are {tuple(states)})")
        if name in coefficients:
            if spec.value is not None:
                fitted = fitted if fitted is not None else copy.deepcopy(model)
                _set_coefficient(fitted, key, spec.value, dtype, device)
            if spec.vary and name not in out_params:
                if params is not None:
                    raise ValueError(f"`parameters[{key!r}]` varies (vary=True, the default), but `params` = "
                                     f"{list(params)} does not list {name!r}: give the unknowns in one place (add it to "
                                     "`params`, or give it vary=False)")
                out_params.append(name)
                changed = True
            if not spec.vary and name in out_params:
                if params is not None and name in params:
                    raise ValueError(f"`parameters[{key!r}]` has vary=False, but `params` lists {name!r} as an unknown: "
                                     "give it in one place")
                out_params.remove(name)
                changed = True
        elif name in states and spec.expr is not None:
            if key in out_expr or name in out_expr:
                raise ValueError(f"`parameters[{key!r}]` gives an expression that `x0_expr` gives too: give it in one "
                                 "place")
            out_expr[name] = spec.expr
            continue
        elif name in states:
            if spec.value is not None:
                state_values[states.index(name)] = _checks.finite_number(f"parameters[{key!r}].value", spec.value)
            if spec.vary and fixed_x0 is not None and any(name in own for own in fixed):
                raise ValueError(f"`parameters[{key!r}]` has vary=True, but `fixed_x0` fixes {name!r}: give it in one "
                                 "place")
            for own in fixed:
                if not spec.vary and name not in own:
                    own.append(name)
                if spec.vary and name in own:
                    own.remove(name)
        else:
            raise ValueError(f"`parameters` names {key!r}, which is neither a coefficient nor a state of the model; "
                             f"{_checks.coefficients_text(model)}, its states {tuple(states)}")
        if not spec.vary:
            continue
        if spec.min is not None or spec.max is not None:
            if key in out_bounds or name in out_bounds:
                raise ValueError(f"`parameters[{key!r}]` gives bounds that `bounds` gives too: give them in one place")
            out_bounds[name] = (spec.min, spec.max)
        if spec.scale != "lin":
            if key in out_scale or name in out_scale:
                raise ValueError(f"`parameters[{key!r}]` gives a scale that `scale` gives too: give it in one place")
            out_scale[name] = spec.scale
    return dict(model=model if fitted is None else fitted,
                x0=_with_states(x0, state_values, states, rows, dtype, device, set(out_expr)),
                params=out_params if changed else None,
                fixed_x0=fixed if per_experiment else (fixed[0] if fixed[0] or fixed_x0 is not None else None),
                bounds=out_bounds or bounds, scale=out_scale or scale, x0_expr=out_expr or x0_expr)


def _as_parameter(name, spec) -> Parameter:
    if isinstance(spec, Parameter):
        return spec
    if isinstance(spec, bool) or not isinstance(spec, (int, float, torch.Tensor)):
        raise TypeError(f"`parameters[{name!r}]` must be a torchql.Parameter or a number (the guess of an "
                        f"unknown); received {type(spec).__name__}")
    return Parameter(spec)


def _set_coefficient(model, name: str, value, dtype, device) -> None:
    """Coefficient ``name`` of ``model`` (a buffer, or an ``nn.Parameter`` kept one) set to ``value`` (a
    number fills a vector or matrix)."""
    current = coefficients(model)[name]
    tensor = float_tensor(value, f"parameters[{name!r}].value", dtype, device, expected="a number or a tensor").clone()
    if tensor.shape != current.shape:
        if tensor.dim() != 0:
            raise ValueError(f"`parameters[{name!r}].value` must be a number or of the coefficient's shape "
                             f"{tuple(current.shape)}; received shape {tuple(tensor.shape)}")
        tensor = tensor.expand(current.shape).clone()
    if not bool(torch.isfinite(tensor).all()):
        raise ValueError(f"`parameters[{name!r}].value` must be finite; received {value!r}")
    _set_buffer(model, name, tensor)


def _fixed_lists(fixed_x0) -> tuple[list[list[str]], bool]:
    """``fixed_x0`` as editable lists (one, or one per experiment) and whether it is per experiment."""
    if fixed_x0 is None:
        return [[]], False
    if isinstance(fixed_x0, str):
        raise TypeError(f"`fixed_x0` must be a sequence of state names, not a string; use [{fixed_x0!r}]")
    items = list(fixed_x0)
    if items and all(isinstance(item, (list, tuple)) for item in items):
        return [list(item) for item in items], True
    return [items], False


def _with_states(x0, values: dict[int, float], states: list[str], rows: int | None, dtype, device,
                 expressed: set[str]):
    """``x0`` with the states' given values set (in every row); ``x0`` itself is not modified.
    Without ``x0`` every state needs a value, but those given by expressions (``expressed``)."""
    if not values:
        return x0
    n = len(states)
    if x0 is None:
        missing = [states[i] for i in range(n) if i not in values and states[i] not in expressed]
        if missing:
            raise ValueError(f"`parameters` gives the initial values of {[states[i] for i in sorted(values)]} but not "
                             f"of {missing}, and `x0` is not given: give every state's value, in `parameters` or "
                             "`x0`")
        base = torch.zeros(n if rows is None else (rows, n), dtype=dtype, device=device)
    else:
        base = float_tensor(x0, "x0", dtype, device).clone()
    for i, v in values.items():
        base[..., i] = v
    return base
