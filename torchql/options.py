"""How a fit runs: its options, tolerances and limits, every default written once, validated once.

``fit`` and ``fit_many`` resolve their keyword arguments here, so that the same arguments give
the same numbers in both, and a default changes in one place. :class:`FitOptions` holds them as
one object that ``fit``, ``fit_many``, ``profile``, ``multistart``, ``fit_many_ray`` and
``adjoint_fit`` take as ``options=``, and every fit returns as ``result.options``.
"""

from __future__ import annotations

import functools
import inspect
import math
import numbers
from dataclasses import dataclass, fields, replace

import torch

from . import _checks
from .grid import check_grid_times
from .damping import DAMPING_MAX, DAMPING_MIN, DAMPING_START, DAMPINGS, damping_strategy
from .integrate import default_tolerances
from .schemes import METHODS, Scheme, scheme_strategy

__all__ = ["DAMPINGS", "DAMPING_START", "DAMPING_MIN", "DAMPING_MAX", "METHODS", "INITIAL_TRAJECTORIES", "Tolerances",
           "Limits", "FitOptions", "with_options", "expand_options", "accepts_options", "check_damping",
           "check_scheme", "recorded_options"]

#: How the first Kantorovich reference is made: built from the data where some state is measured
#: directly (``"auto"``, :func:`torchql.data_start.first_reference`), integrated from the guesses,
#: or built from the data.
INITIAL_TRAJECTORIES: tuple[str, ...] = ("auto", "integrate", "data")


@dataclass(frozen=True)
class Tolerances:
    """The tolerances of a fit in a given precision.

    Attributes
    ----------
    rtol, atol : float
        Integrator tolerances: ``1e-10``/``1e-12`` in float64, ``1e-6``/``1e-8`` below.
    xtol : float
        Step test: converged when the scaled update is at most ``xtol``; default
        ``max(1e-8, 100 rtol)`` in float64, ``max(1e-4, 100 rtol)`` below (no finer than the
        integration can resolve).
    ftol : float
        Sum-of-squares test: default ``max(1e-12, rtol)`` in float64, ``max(1e-6, rtol)`` below
        (a change of the SSE below the integration's relative accuracy is no change).
    rcond : float
        Relative singular-value threshold of the rank tests: default ``max(min(1e3 rtol, sqrt(rtol)),
        1e3 eps)``: a thousand times the integration's accuracy, and no more than its square root
        where that is loose (``rtol=1e-3``, scipy's default, would make it 1: every direction
        undetermined).
    """

    rtol: float
    atol: float
    xtol: float
    ftol: float
    rcond: float

    @classmethod
    def resolve(cls, dtype: torch.dtype, rtol: float | None = None, atol: float | None = None,
                xtol: float | None = None, ftol: float | None = None, rcond: float | None = None) -> "Tolerances":
        """The given tolerances, validated (positive numbers), and the defaults of ``dtype`` for the rest."""
        rtol, atol = default_tolerances(dtype, rtol, atol)
        rtol, atol = _checks.positive_number("rtol", rtol), _checks.positive_number("atol", atol)
        _below_one("rtol", rtol)
        double = dtype == torch.float64
        eps = torch.finfo(dtype).eps
        return cls(
            rtol=rtol, atol=atol,
            xtol=_checks.positive_number("xtol", xtol) if xtol is not None else max(1e-8 if double else 1e-4, 100 * rtol),
            ftol=_checks.positive_number("ftol", ftol) if ftol is not None else max(1e-12 if double else 1e-6, rtol),
            rcond=(_below_one("rcond", _checks.positive_number("rcond", rcond)) if rcond is not None
                   else max(min(1e3 * rtol, math.sqrt(rtol)), 1e3 * eps)),
        )


def _below_one(name: str, value: float) -> float:
    """``value``; ``ValueError`` naming ``name`` unless it is below 1 (a relative tolerance)."""
    if value >= 1:
        raise ValueError(f"`{name}` must be below 1 (a relative tolerance); received {value:g}")
    return value


@dataclass(frozen=True)
class Limits:
    """The budgets of a fit: ``max_iter`` updates, ``max_steps`` solver steps per grid interval
    (None: the solver's own), ``max_time`` seconds of wall-clock time (None: no budget)."""

    max_iter: int = 50
    max_steps: int | None = None
    max_time: float | None = None

    @classmethod
    def resolve(cls, max_iter: int = 50, max_steps: int | None = None, max_time: float | None = None) -> "Limits":
        """Validated limits (``max_iter >= 0``, ``max_steps >= 1``, ``max_time > 0``)."""
        return cls(
            max_iter=_checks.positive_int("max_iter", max_iter, minimum=0),
            max_steps=None if max_steps is None else _checks.positive_int("max_steps", max_steps),
            max_time=None if max_time is None else _checks.positive_number("max_time", max_time),
        )


def check_damping(damping):
    """``damping`` as given if it names a registered strategy (:data:`DAMPINGS`) or is a
    :class:`torchql.damping.Damping`, else ``ValueError`` naming the registered ones."""
    damping_strategy(damping)
    return damping


def check_scheme(method, initial_trajectory) -> tuple[Scheme, str]:
    """``(method, initial_trajectory)`` validated: ``method`` a registered scheme's name or a
    :class:`torchql.schemes.Scheme` (:func:`torchql.schemes.scheme_strategy`), returned as the
    scheme; ``initial_trajectory`` a string among :data:`INITIAL_TRAJECTORIES` (``TypeError``/
    ``ValueError`` naming the valid ones)."""
    scheme = scheme_strategy(method)
    if not isinstance(initial_trajectory, str):
        raise TypeError(f"`initial_trajectory` must be a string, one of {INITIAL_TRAJECTORIES}; received "
                        f"{type(initial_trajectory).__name__}")
    if initial_trajectory not in INITIAL_TRAJECTORIES:
        raise ValueError(f"`initial_trajectory` must be one of {INITIAL_TRAJECTORIES}; received {initial_trajectory!r}")
    return scheme, initial_trajectory


@dataclass(frozen=True)
class FitOptions:
    """How a fit runs, as one object to reuse: ``fit(model, data, options=opts)``.

    Every field is the keyword of :func:`torchql.fit` of that name, with its default (``None``:
    the default of the model's precision, see :class:`Tolerances`). Validated when made, so a
    bad value is reported where the options are written. An entry point's keyword given with
    another value than its default wins over a field left at its default; a field and a keyword
    both set to different values is an error. ``opts.replace(rtol=1e-8)`` is a changed copy.

    Attributes
    ----------
    method, solver, linear_solver, damping, initial_trajectory, grid
        The scheme, the nonlinear and linear solvers, the damping, the first reference, the grid.
    max_iter, max_time, max_steps
        The limits (:class:`Limits`).
    rtol, atol, xtol, ftol, rcond
        The tolerances (:class:`Tolerances`).
    """

    method: str = "kantorovich"
    solver: str = "auto"
    linear_solver: object = None
    damping: str | None = "lm"
    initial_trajectory: str = "auto"
    grid: object = None
    max_iter: int = 50
    max_time: float | None = None
    max_steps: int | None = None
    rtol: float | None = None
    atol: float | None = None
    xtol: float | None = None
    ftol: float | None = None
    rcond: float | None = None

    def __post_init__(self) -> None:
        from .integrate import check_solver
        from .superposition import check_linear_solver

        check_scheme(self.method, self.initial_trajectory)
        check_damping(self.damping)
        if not isinstance(self.solver, str):
            raise TypeError(f"`solver` must be a string; received {type(self.solver).__name__}")
        check_solver(self.solver, auto=True)
        if self.linear_solver is not None:
            check_linear_solver(self.linear_solver)
        Limits.resolve(self.max_iter, self.max_steps, self.max_time)
        for name in ("rtol", "atol", "xtol", "ftol", "rcond"):
            if getattr(self, name) is not None:
                _checks.positive_number(name, getattr(self, name))
        for name in ("rtol", "rcond"):  # relative: 1 or more would accept anything
            if getattr(self, name) is not None:
                _below_one(name, getattr(self, name))
        grid = self.grid
        if (isinstance(grid, str) and grid not in ("auto", "smooth")
                or not isinstance(grid, (str, numbers.Integral, torch.Tensor, type(None))) or isinstance(grid, bool)):
            raise ValueError(f'`grid` must be a number of intervals, a tensor of times, "auto" or "smooth"; '
                             f'received {grid!r}')
        if isinstance(grid, torch.Tensor):
            check_grid_times(grid)
        elif grid is not None and not isinstance(grid, str):
            _checks.positive_int("grid", grid)

    def replace(self, **changes) -> "FitOptions":
        """A copy with ``changes`` (validated)."""
        return replace(self, **changes)

    @classmethod
    def of(cls, keywords: dict) -> "FitOptions":
        """The options among a fit's ``keywords`` (others ignored)."""
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in keywords.items() if k in names})


def _same(a, b) -> bool:
    if isinstance(a, torch.Tensor) or isinstance(b, torch.Tensor):
        return isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor) and a.shape == b.shape and bool(
            torch.equal(a, b))
    if type(a) is type(b):
        return a == b
    numbers = (int, float)  # 10 and 10.0 are one value; True is no number here
    if isinstance(a, numbers) and isinstance(b, numbers) and not isinstance(a, bool) and not isinstance(b, bool):
        return a == b
    return a is b


def _set_fields(options) -> list[tuple[str, object, object]]:
    """``(name, value, default)`` of the fields of ``options`` (a :class:`FitOptions`, else
    ``TypeError``) set away from their defaults."""
    if not isinstance(options, FitOptions):
        raise TypeError(f"`options` must be a torchql.FitOptions; received {type(options).__name__}")
    return [(f.name, getattr(options, f.name), f.default) for f in fields(FitOptions)
            if not _same(getattr(options, f.name), f.default)]


def _given_twice(name: str, keyword, value) -> ValueError:
    return ValueError(f"`{name}` is given twice, {keyword!r} as a keyword and {value!r} in `options`; give it once")


def with_options(options: "FitOptions | None", given: dict, explicit: set, unlike: tuple = ()) -> dict:
    """The keyword arguments ``given`` (as an entry point received them) with ``options``' fields.

    A keyword the caller did not pass (not in ``explicit``) takes the field; a field that the entry
    point does not take (not in ``given``, or in ``unlike``: a keyword of the same name that means
    something else there) must be at its default; a field and a keyword passed with different
    values is a ``ValueError`` naming it, also where the keyword passed is its default.
    """
    out = dict(given)
    if options is None:
        return out
    for name, value, default in _set_fields(options):
        if name not in given or name in unlike:
            what = (f"this function's `{name}` is another quantity" if name in unlike
                    else f"this function takes no `{name}`")
            raise ValueError(f"`options.{name}` = {value!r} does not apply here ({what}); leave it at its "
                             f"default {default!r}")
        keyword = given[name]
        if name in explicit and not _same(keyword, value):
            raise _given_twice(name, keyword, value)
        out[name] = value
    return out


def expand_options(keywords: dict) -> dict:
    """``keywords`` of a function that passes them on to a fit (``profile``, ``multistart``), with an
    ``options`` entry (a :class:`FitOptions`) replaced by its fields set away from their defaults; a
    field also given as a keyword with another value is a ``ValueError`` naming it."""
    keywords = dict(keywords)
    options = keywords.pop("options", None)
    if options is None:
        return keywords
    for name, value, _ in _set_fields(options):
        if name in keywords and not _same(keywords[name], value):
            raise _given_twice(name, keywords[name], value)
        keywords[name] = value
    return keywords


def accepts_options(function=None, *, unlike: tuple = ()):
    """Decorate a fitting function whose keywords include some of :class:`FitOptions`' fields and
    ``options=None``: a call with ``options`` runs it with those keywords resolved by
    :func:`with_options` (the keywords the call passed against the options' fields). ``unlike``:
    the function's keywords named as a field but meaning something else (``adjoint_fit``'s
    ``max_steps`` counts optimizer steps, the field solver steps): such a field set is an error."""
    if function is None:
        return lambda wrapped: accepts_options(wrapped, unlike=unlike)
    signature = inspect.signature(function)
    names = [f.name for f in fields(FitOptions) if f.name in signature.parameters and f.name not in unlike]

    @functools.wraps(function)
    def call(*args, options: "FitOptions | None" = None, **kwargs):
        if options is None:
            return function(*args, **kwargs)
        bound = signature.bind(*args, **kwargs)
        explicit = {name for name in names if name in bound.arguments}
        bound.apply_defaults()
        given = {name: bound.arguments[name] for name in names}
        bound.arguments.update(with_options(options, given, explicit, unlike))
        return function(*bound.args, **bound.kwargs)
    return call


def recorded_options(*, params, fixed_x0, bounds, scale=None, **options) -> dict:
    """A fit's options as ``result.fit_kwargs`` keeps them for a re-fit (``profile``,
    ``multistart``): copies of the lists, dicts and tensor (``x0``, when given) the user passed,
    the other options as given."""
    record = dict(params=None if params is None else list(params),
                  fixed_x0=None if fixed_x0 is None else list(fixed_x0),
                  bounds=None if bounds is None else dict(bounds), scale=None if scale is None else dict(scale),
                  **options)
    if record.get("x0") is not None:
        record["x0"] = torch.as_tensor(record["x0"]).detach().clone()
    return record
