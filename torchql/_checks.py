"""Argument checks shared by the public entry points; each error names the argument."""

from __future__ import annotations

import math
import numbers

import numpy
import torch

__all__ = ["positive_number", "finite_number", "positive_int", "flag", "model_class", "model_forward", "distinct_names",
           "not_differentiable",
           "coefficients_text", "single_observations"]

#: Floating dtypes a model may compute in (half precisions cannot resolve a fit's tolerances,
#: and torch's CPU linear algebra does not implement them).
_MODEL_DTYPES = (torch.float32, torch.float64)


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


def non_negative_number(name: str, value) -> float:
    """``value`` as a float; ``ValueError`` naming ``name`` unless it is finite and >= 0."""
    if not _is_real_number(value) or not math.isfinite(float(value)) or float(value) < 0:
        raise ValueError(f"`{name}` must be a non-negative finite number; received {value!r}")
    return float(value)


def positive_int(name: str, value, minimum: int = 1) -> int:
    """``value``; ``ValueError`` naming ``name`` unless it is an integer >= ``minimum`` (bools rejected)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
        kind = {0: "a non-negative integer", 1: "a positive integer"}.get(minimum, f"an integer >= {minimum}")
        raise ValueError(f"`{name}` must be {kind}; received {value!r}")
    return int(value)


def flag(name: str, value) -> bool:
    """``value`` as a bool; ``TypeError`` naming ``name`` unless it is ``True`` or ``False``."""
    if not isinstance(value, (bool, numpy.bool_)):
        raise TypeError(f"`{name}` must be True or False; received {value!r}")
    return bool(value)


def model_class(model, fitted: bool = True) -> None:
    """``TypeError``/``ValueError`` unless ``model`` is a :class:`torchql.ODEModel` with valid
    state names and float32 or float64 coefficients (buffers and parameters); ``fitted``: its
    states' and coefficients' names apart too (a fit's arguments name both)."""
    from .model import ODEModel, coefficients, model_dtype_device, tied_coefficients

    if not isinstance(model, ODEModel):
        raise TypeError(f"`model` must be a torchql.ODEModel; received {type(model).__name__}")
    given = model.state_names
    names = () if isinstance(given, (str, bytes)) else tuple(given)  # ("xv" would read as states 'x' and 'v')
    if not names or not all(isinstance(s, str) for s in names) or len(set(names)) != len(names):
        raise ValueError(f"`model.state_names` must be a non-empty tuple of distinct strings; received {given!r}")
    tied = tied_coefficients(model) if fitted else None
    if tied:
        raise ValueError(f"`model` holds one coefficient under two names, {tied[0]!r} and {tied[1]!r} (a tensor "
                         "shared by two submodules): a fit sets it under one name only; register it once and read "
                         "it from there")
    shared = [name for name in coefficients(model) if name in names] if fitted else []
    if shared:  # (`bounds`, `guesses`, `parameters` name a state's initial value or a coefficient)
        raise ValueError(f"`model` has a state and a coefficient both named {shared[0]!r}: the names given to "
                         "`bounds`, `guesses` and `parameters` could not tell them apart; rename one")
    dtype, _ = model_dtype_device(model)
    if dtype not in _MODEL_DTYPES:
        which = [name for name, value in coefficients(model).items() if value.dtype not in _MODEL_DTYPES]
        raise TypeError(
            f"`model` computes in {dtype} (its coefficients {which[:5]} are {dtype}), which cannot resolve the "
            "integration and least-squares tolerances; convert it to float64 with `model.double()` (or float32 "
            "with `model.float()`)")


def model_forward(rhs, t0: torch.Tensor, x0: torch.Tensor, names, coefficients: dict[str, float],
                  dtype: torch.dtype, sample: str = "", finite: bool = True) -> torch.Tensor:
    """Evaluate a model's right-hand side once at the guesses; errors name `model` forward and the fix.

    ``rhs(t, x)`` is the model's forward (with the coefficient guesses ``coefficients``, named
    element-wise, in place); ``x0 (n,)`` the initial state at ``t0``. ``x`` is passed as a copy that
    requires grad, outside ``torch.no_grad``, so that an in-place update of ``x`` in the forward is
    caught here by torch's own check (a fit differentiates through the forward), and any change
    of ``x``'s values too. Then: a Tensor of ``x``'s shape and ``dtype``, finite (unless ``finite``
    is false). ``sample`` says whose guesses they are in the message, e.g. ``" of `data[3]`"``.
    Returns the derivative ``(n,)``.
    """
    n = x0.shape[0]
    x = x0.detach().clone().requires_grad_(True)
    inplace = ("`model` forward updates its input `x` in place ({}); a fit differentiates through the "
               "forward, so it must leave `x` unchanged: build a new tensor instead (e.g. `x * 2` instead of "
               "`x.mul_(2)`, `torch.stack`/`torch.cat` of the components instead of `x[..., 0] += ...`)")
    try:
        with torch.enable_grad():
            out = rhs(t0, x)
    except Exception as exc:  # noqa: BLE001 - report any failure of user code clearly
        if "in-place" in str(exc) or "inplace" in str(exc):
            raise ValueError(inplace.format(f"torch said: {exc}")) from exc
        raise ValueError(f"`model` forward(t, x) failed for x of shape ({n},): {exc}") from exc
    if not torch.equal(x.detach(), x0.detach()):
        raise ValueError(inplace.format(f"x = {x0.tolist()} became {x.detach().tolist()}"))
    if not isinstance(out, torch.Tensor):
        raise TypeError(f"`model` forward must return a Tensor; received {type(out).__name__}")
    if out.shape != (n,):
        raise ValueError(f"`model` forward must return dx/dt of the state's shape ({n},) for x of shape ({n},); "
                         f"received shape {tuple(out.shape)}")
    if out.dtype != dtype:
        raise TypeError(f"`model` forward must return dtype {dtype} (the coefficients' dtype); received {out.dtype}")
    out = out.detach()
    derivatives = non_finite_slopes(out, names) if finite else ""
    if derivatives:
        state = ", ".join(f"{name} = {value:g}" for name, value in zip(names, x0.tolist()))
        items = list(coefficients.items())
        coefs = "".join(f", {name} = {value:g}" for name, value in items[:8]) + (", ..." if len(items) > 8 else "")
        raise ValueError(
            f"`model` forward is not finite at the guesses{sample}: {derivatives} at t0 = {float(t0):g}, x0 = ({state})"
            f"{coefs}. The model must be finite at the initial state: choose a `x0` and coefficient guesses where "
            "it is defined, or guard the forward against division by zero and log/sqrt of negative values")
    return out


def non_finite_slopes(slope: torch.Tensor, names) -> str:
    """The derivatives ``slope (n,)`` that are not finite, named by state (``"dy/dt = nan"``), ``""``
    when all are."""
    return ", ".join(f"d{name}/dt = {float(v)}" for name, v in zip(names, slope) if not torch.isfinite(v))


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


def coefficients_text(model) -> str:
    """What an error about an unknown coefficient name lists: the model's float buffers, and its
    float parameters when it has any."""
    internal = getattr(model, "internal_buffers", ())
    buffers = tuple(name for name, b in model.named_buffers() if b.is_floating_point() and name not in internal)
    parameters = tuple(name for name, p in model.named_parameters() if p.is_floating_point())
    return f"the model's float buffers are {buffers}" + (f" and its float parameters {parameters}" if parameters else "")


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


def not_differentiable(exc: Exception) -> ValueError:
    """The error of a model whose forward torch.func cannot vectorize or differentiate."""
    return ValueError("`model` forward could not be differentiated with torch.func (jacrev and jvp under "
                      f"vmap): {exc}. Avoid .item(), in-place updates of inputs and Python branching on tensor "
                      "values.")
