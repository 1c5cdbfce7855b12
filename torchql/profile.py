"""Profile-likelihood confidence intervals.

The profile of an unknown ``theta`` (a scalar coefficient, or an initial state such as
``"y(t0)"``) is the least sum of squares the other unknowns can reach with ``theta`` held
fixed: ``S(theta) = min_{others} SSE``. :func:`profile` re-fits the model with ``theta`` fixed
at a sequence of values walking outwards from the estimate on each side (each fit
warm-started from its neighbour), until the profile crosses the threshold

* ``S(theta) - S_min <= s^2 F_{1,dof}(level) = s^2 t_{dof}((1 + level) / 2)^2`` when the
  residual variance ``s^2 = S_min / dof`` is estimated (``sigma`` not given);
* ``S(theta) - S_min <= chi2_1(level) = z((1 + level) / 2)^2`` when ``sigma`` is known;

and the crossing is located by root finding (Illinois regula falsi on
``sqrt(S(theta) - S_min) - sqrt(threshold - S_min)``, which is nearly linear in ``theta``).
Unlike Wald intervals, profile intervals follow the model's nonlinearity: they are
asymmetric where the sum of squares is, and open where the data do not bound the unknown.
For a model linear in its unknowns the two coincide.
"""

from __future__ import annotations

import copy
import inspect
import math
import re
import warnings
from dataclasses import dataclass, field
from typing import NamedTuple

import torch

from .initial_state import check_expressions
from .model import _set_buffer, coefficients
from .multi import experiment_state_name
from .options import expand_options
from .observations import Observations
from .profile_objective import sse_noise, sse_of
from .profile_result import ProfileResult
from .result import FitResult, Status
from .uncertainty import normal_quantile, student_t_quantile

__all__ = ["profile", "ProfileResult"]

#: fit() keyword arguments a profile re-fit inherits from the original fit.
_INHERITED = ("t0", "method", "max_iter", "solver", "rtol", "atol", "xtol", "ftol", "rcond", "grid",
              "initial_trajectory", "max_steps", "damping", "linear_solver", "conditions", "x0_expr")
#: Halvings of a step towards the last good point when a re-fit fails.
_FAIL_HALVINGS = 3
#: A search limit that is one of the fit's own bounds is approached to this fraction of the last
#: point's distance from it, not evaluated on it: the fit's iterates lie strictly inside, and a
#: model may degenerate there (``y' = -a b y`` at ``a = 0``, the data determining only ``a b``:
#: SSE 25.9 on the bound against 0.0137 all the way to it, which read as a closed end at 7e-6).
BOUND_APPROACH = 1e-6


class _Point(NamedTuple):
    value: float
    sse: float
    estimates: torch.Tensor  # (m,) in the free fit's unknown order
    model: object  # fitted model copy (warm start of the neighbours)
    x0: torch.Tensor


class _Threshold(NamedTuple):
    """Where the profile interval ends: ``sse_min + s2 * q2``."""

    likelihood: bool  # profile 2 NLL (estimated sigmas or log-normal noise) instead of the SSE
    s2: float  # residual variance (1 when sigma is known or on the likelihood)
    q2: float  # squared quantile: normal (sigma known, likelihood) or Student t (estimated)
    sse_min: float  # the free fit's SSE (or 2 NLL)

    @property
    def delta(self) -> float:
        """Allowed rise of the SSE above ``sse_min``: ``s2 * q2``."""
        return self.s2 * self.q2

    def excess(self, pt: _Point) -> float:
        """``sqrt(max(SSE - sse_min, 0)) - sqrt(delta)``: negative inside the interval, nearly linear in theta."""
        return math.sqrt(max(pt.sse - self.sse_min, 0.0)) - math.sqrt(self.delta)


def profile(
    result: FitResult,
    name: str,
    *,
    data: Observations | None = None,
    level: float = 0.95,
    bounds: tuple[float | None, float | None] | None = None,
    step: float | None = None,
    growth: float = 1.5,
    max_points: int = 12,
    xtol: float = 1e-3,
    **fit_options,
) -> ProfileResult:
    """Profile-likelihood confidence interval of one unknown of a fit.

    Parameters
    ----------
    result : FitResult
        A converged fit (``Status.NOT_IDENTIFIABLE`` is accepted too: its profile is flat
        where the data cannot separate the unknowns).
    name : str
        The unknown to profile, one of ``result.unknown_names``: a scalar coefficient
        (``"C_D"``) or an initial state (``"v(t0)"``).
    data : Observations, optional
        The data of the fit; default ``result.data`` (kept by :func:`torchql.fit`).
    level : float
        Confidence level, strictly between 0 and 1.
    bounds : (float or None, float or None), optional
        Limits of the search for ``name``'s value (e.g. ``(0, None)`` for a rate that must stay
        positive). A side that reaches its limit without crossing is reported open (``-inf`` or
        ``inf``). Default: the fit's own bounds on it (``0`` below for an unknown on a logarithmic
        scale), else none; a side open up to one of those ends at it, the end of the unknown's range
        (still not ``closed``).
    step : float, optional
        Scale of the first step out from the estimate, in the unknown's units. Default: its
        standard error (or 10% of its magnitude when that is not available); the first step is
        ``step`` times half the threshold's quantile (about one standard error).
    growth : float
        Each further step is ``growth`` times the previous one.
    max_points : int
        Maximum number of steps out on each side before it is declared open.
    xtol : float
        The interval's ends are located to ``xtol * step``. (Not the re-fits' own convergence
        tolerance, :func:`torchql.fit`'s ``xtol``, which this name takes from ``fit_options``: that
        one is set by ``options=torchql.FitOptions(xtol=...)``.)
    **fit_options
        Keyword arguments of :func:`torchql.fit` overriding those of the original fit
        (``method=``, ``grid=``, ``rtol=``, ``max_iter=``, ...), or ``options=`` a
        :class:`torchql.FitOptions` whose fields set away from their defaults override them.

    Returns
    -------
    ProfileResult

    Raises
    ------
    ValueError
        For an unknown ``name`` (the message lists the valid ones), a coefficient element of
        a vector or matrix buffer, a failed fit, a missing ``data``, or invalid options.
    """
    data = _check_arguments(result, name, data, level, growth, xtol, max_points, fit_options)
    names = list(result.unknown_names)
    theta_hat = float(result.estimates[names.index(name)])
    buffers = coefficients(result.model)
    params, fixed_x0, state_index = _held_fixed(result, name, buffers)
    options = _refit_options(result, name, fit_options)
    threshold = _threshold(result, level)
    h = _first_step(result, name, theta_hat, step)
    lower_bound, upper_bound = _check_bounds(_fit_bounds(result, name) if bounds is None else bounds, theta_hat)
    own = bounds is None  # the fit's own bounds end the unknown's range: an open side ends there

    refit = _Refitter(result, name, data, options, params, fixed_x0, state_index, buffers, threshold.likelihood)
    center = refit(theta_hat, result)
    if center is None:
        raise RuntimeError(f"re-fitting with {name} fixed at its estimate {theta_hat:g} failed "
                           f"({refit.failures[-1][1]})")
    points = [center]
    ends, closed, notes = [], [], []
    for direction, limit in ((-1.0, lower_bound), (1.0, upper_bound)):
        end, why, found, reached = _search_side(refit, center, direction, limit, threshold,
                                       first=0.5 * math.sqrt(threshold.q2) * h, growth=growth,
                                       max_points=max_points, tol=xtol * h, approach=own)
        points.extend(found)
        ends.append(limit if own and reached else direction * math.inf if end is None else end)
        closed.append(end is not None)
        if end is None:
            notes.append(f"open {'below' if direction < 0 else 'above'}: {why}")

    values, sses, estimates = _stack_points(points)
    wald = result.confidence_intervals(level)[name]
    message = _summary(name, level, theta_hat, ends, closed, notes, wald)
    note = _lower_sse_note(result, data, options, name, values, sses, threshold)
    if note:
        message += note
        warnings.warn(note.strip(), UserWarning, stacklevel=2)
    return ProfileResult(
        name=name, level=level, estimate=theta_hat, sse_min=threshold.sse_min,
        threshold=threshold.sse_min + threshold.delta, interval=(ends[0], ends[1]), closed=(closed[0], closed[1]),
        wald=(float(wald[0]), float(wald[1])), values=values, sse=sses, estimates=estimates, unknown_names=names,
        message=message, n_fits=refit.n_fits, failures=refit.failures, sigma_known=result.sigma_known,
        residual_variance=threshold.s2, likelihood=threshold.likelihood,
    )


def _check_arguments(result: FitResult, name: str, data: Observations | None, level: float, growth: float,
                     xtol: float, max_points: int, fit_options: dict) -> Observations:
    """Validate :func:`profile`'s arguments (but ``step`` and ``bounds``); the data to re-fit."""
    if not isinstance(result, FitResult):
        raise TypeError(f"`result` must be a torchql.FitResult (from torchql.fit); received {type(result).__name__}")
    names = list(result.unknown_names)
    if not isinstance(name, str) or name not in names:
        raise ValueError(f"`name` must be one of the fit's unknowns {names}; received {name!r}")
    if not (isinstance(level, float) and 0.0 < level < 1.0):
        raise ValueError(f"`level` must be a float strictly between 0 and 1; received {level!r}")
    if data is None:
        data = result.data
    if data is None:
        raise ValueError("`data` is required: this FitResult does not hold the observations it was fitted to")
    if isinstance(data, (list, tuple)) and result.experiment_t0 is not None:  # several experiments
        for e, item in enumerate(data):
            if not isinstance(item, Observations):
                raise TypeError(f"`data[{e}]` must be a torchql.Observations; received {type(item).__name__}")
        if len(names) == 1:
            raise ValueError(f"`name` {name!r} is the only unknown of a fit of {len(data)} experiments: its profile "
                             "is the sum of squares at each value, which `profile` re-fits only with other unknowns "
                             "left; compare fits with it held at chosen values instead")
    elif not isinstance(data, Observations):
        raise TypeError(f"`data` must be a torchql.Observations; received {type(data).__name__}")
    if not (result.success or result.status is Status.NOT_IDENTIFIABLE) or not math.isfinite(result.sse):
        raise ValueError(f"`result` must be a converged fit to profile; its status is {result.status.name}: {result.message}")
    for label, value, lo in (("growth", growth, 1.0), ("xtol", xtol, 0.0)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > lo or not math.isfinite(value):
            raise ValueError(f"`{label}` must be a finite number > {lo:g}; received {value!r}")
    if isinstance(max_points, bool) or not isinstance(max_points, int) or max_points < 1:
        raise ValueError(f"`max_points` must be a positive int; received {max_points!r}")
    for bad in ("params", "fixed_x0", "x0", "callback", "throw", "bounds", "scale"):
        if bad in fit_options:
            raise ValueError(f"`{bad}` cannot be overridden in a profile: it is set by the profile itself")
    from .fit import fit

    unknown = sorted(set(fit_options) - set(inspect.signature(fit).parameters) - {"options"})
    if unknown:
        raise TypeError(f"profile() got unexpected keyword argument(s) {unknown}: it takes its own and torchql.fit's")
    return data


def _held_fixed(result: FitResult, name: str, buffers: dict) -> tuple[list[str], list, int | tuple[int, int] | None]:
    """How the re-fits hold ``name`` fixed: ``(params, fixed_x0, state_index)``.

    ``params`` are the buffers to estimate, ``fixed_x0`` the states whose initial value is not
    estimated (one list per experiment for a fit of several), ``state_index`` the index of
    ``name``'s state when it is an initial state (``(experiment, state)`` for a fit of several; else None).
    """
    names = list(result.unknown_names)
    states = list(result.model.state_names)
    free_params = _original_params(result, buffers)
    given = {k.removesuffix("(t0)") for k in (result.fit_kwargs.get("x0_expr") or {})}  # follow the estimates
    if result.experiment_t0 is None:
        fixed = [s for s in states if f"{s}(t0)" not in names and s not in given]
        held = states.index(name[:-4]) if name.endswith("(t0)") and name[:-4] in states else None
    else:  # several experiments: states "y[e](t0)", fixed per experiment
        fixed = [[s for s in states if f"{experiment_state_name(s, e)}(t0)" not in names and s not in given]
                 for e in range(len(result.experiment_t0))]
        state = re.fullmatch(r"(.+)\[(\d+)\]\(t0\)", name)
        held = (int(state[2]), states.index(state[1])) if state and state[1] in states else None
    if held is not None and name not in buffers:
        if isinstance(held, tuple):
            fixed[held[0]].append(states[held[1]])
        else:
            fixed.append(states[held])
        return free_params, fixed, held
    if name in buffers and buffers[name].dim() == 0:
        return [p for p in free_params if p != name], fixed, None
    raise ValueError(
        f"`name` {name!r} is an element of a vector or matrix coefficient: only scalar coefficients and "
        "initial states can be profiled"
    )


def _refit_options(result: FitResult, name: str, fit_options: dict) -> dict:
    """Keyword arguments of the re-fits: the original fit's (less ``name``'s bound and scale), then ``fit_options``."""
    options = {k: result.fit_kwargs[k] for k in _INHERITED if k in result.fit_kwargs}
    options.setdefault("method", result.method)
    options.update({k: v for k, v in result.solver_options.items() if k not in options or options[k] is None})
    options["t0"] = result.t0 if result.experiment_t0 is None else list(result.experiment_t0)
    if options.get("solver") == "auto" and "solver" in result.solver_options:  # the fit's choice, kept
        options["solver"] = result.solver_options["solver"]
    for key in ("bounds", "scale"):  # the profiled unknown is held fixed: its own bound and scale go
        if result.fit_kwargs.get(key):
            options[key] = {k: v for k, v in result.fit_kwargs[key].items()
                            if k not in (name, name.removesuffix("(t0)"))}
    options.update(expand_options(fit_options))
    return options


def _threshold(result: FitResult, level: float) -> _Threshold:
    """The interval's threshold: on the SSE, or with estimated sigmas, a ``sigma(p)`` function or
    log-normal noise on 2 NLL.

    (The profile likelihood: 2 (NLL - NLL_min) is chi-square with one degree of freedom.)
    """
    p = 0.5 + 0.5 * level
    likelihood = result.likelihood
    if likelihood:
        s2, q2 = 1.0, normal_quantile(p) ** 2
    elif result.sigma_known:
        s2 = 1.0
        q2 = normal_quantile(p) ** 2
    else:
        if result.dof <= 0:
            raise ValueError(f"no degrees of freedom are left to estimate the residual variance (dof = {result.dof})")
        s2 = result.sse / result.dof
        q2 = student_t_quantile(p, result.dof) ** 2
    sse_min = 2 * result.nll if likelihood else result.sse
    if s2 <= 0:
        raise ValueError("the fit's SSE is zero: the data are met exactly and the profile threshold is zero-width")
    return _Threshold(likelihood, s2, q2, sse_min)


def _first_step(result: FitResult, name: str, theta_hat: float, step: float | None) -> float:
    """Scale ``h`` of the search steps, in ``name``'s units: ``step``, else its standard error or 10% of it."""
    se = result.stderr[name]
    if step is None:
        return se if (math.isfinite(se) and se > 0) else (0.1 * abs(theta_hat) if theta_hat != 0 else 0.1)
    if isinstance(step, bool) or not isinstance(step, (int, float)) or not (step > 0 and math.isfinite(step)):
        raise ValueError(f"`step` must be a finite number > 0; received {step!r}")
    return float(step)


@dataclass
class _Refitter:
    """Re-fits the model with the profiled unknown held at a value; counts the fits and records failures."""

    result: FitResult
    name: str
    data: Observations
    options: dict
    params: list[str]
    fixed_x0: list
    state_index: int | tuple[int, int] | None
    buffers: dict
    likelihood: bool
    n_fits: int = 0
    failures: list = field(default_factory=list)

    def __call__(self, value: float, warm) -> _Point | None:
        """The optimum with ``name = value``, warm-started from ``warm`` (a point or the result); None if it fails."""
        from .fit import fit

        result, name = self.result, self.name
        self.n_fits += 1
        model = copy.deepcopy(warm.model)
        x0 = warm.x0.clone()
        if self.state_index is None:
            buf = self.buffers[name]
            _set_buffer(model, name, torch.tensor(value, dtype=buf.dtype, device=buf.device))
        else:
            x0[self.state_index] = value
        if len(result.unknown_names) == 1:  # nothing left to fit: the SSE of the model itself
            if warm is not result and _fixed_by_exact(result):  # (as a re-fit: no other value meets them)
                self.failures.append((value, Status.EXACT_INFEASIBLE.name))
                return None
            x0 = _expressions_applied(model, x0, self.options.get("x0_expr"))
            sse = sse_of(model, x0, result.t0, self.data, self.options, self.likelihood)
            if not math.isfinite(sse):
                self.failures.append((value, "INTEGRATION_FAILED"))
                return None
            est = torch.tensor([value], dtype=result.estimates.dtype)
            return _Point(value, sse, est, model, x0)
        try:
            r = fit(model, self.data, x0, params=self.params, fixed_x0=self.fixed_x0, **self.options)
        except (ValueError, RuntimeError) as exc:
            if warm is result:
                raise
            self.failures.append((value, f"{type(exc).__name__}: {exc}"))
            return None
        if not (r.success or r.status is Status.NOT_IDENTIFIABLE) or not math.isfinite(r.sse):
            self.failures.append((value, r.status.name))
            return None
        by_name = dict(zip(r.unknown_names, r.estimates.tolist()))
        by_name[name] = value
        est = torch.tensor([by_name[u] for u in result.unknown_names], dtype=result.estimates.dtype)
        return _Point(value, 2 * r.nll if self.likelihood else r.sse, est, r.model, r.x0)


def _fixed_by_exact(result: FitResult) -> bool:
    """Whether the values marked exact of a fit of one unknown depend on it (their rows of the
    Jacobian above ``sqrt(eps)`` of its largest): then they fix it, and no other value meets them
    (one that does not depend on it, a known initial state also marked exact, leaves it free)."""
    J = result.jacobian.reshape(-1)
    exact = result.exact_mask.reshape(-1)
    if not bool(exact.any()) or not bool(torch.isfinite(J).all()):
        return False
    return bool((J[exact].abs() > torch.finfo(J.dtype).eps ** 0.5 * J.abs().max()).any())


def _search_side(refit: _Refitter, center: _Point, direction: float, limit: float | None, threshold: _Threshold,
                 *, first: float, growth: float, max_points: int, tol: float, approach: bool = False
                 ) -> tuple[float | None, str | None, list[_Point], bool]:
    """Walk out from ``center`` (``direction`` -1: below, +1: above) until the profile crosses the threshold.

    ``approach``: the ``limit`` is one of the fit's own bounds, approached to :data:`BOUND_APPROACH`
    of the distance, not evaluated on it. Returns the end (None when the side is open), why it is
    open, the points evaluated in order, and whether the search reached ``limit`` (below the threshold).
    """
    name = refit.name
    side = "below" if direction < 0 else "above"
    prev = center
    dist = first
    points: list[_Point] = []
    for _ in range(max_points):
        target = prev.value + direction * dist
        at_limit = limit is not None and (target - limit) * direction >= 0
        if at_limit:
            target = limit + (prev.value - limit) * BOUND_APPROACH if approach else limit
        point, halved = _step_out(refit, prev, target, direction)
        at_limit = at_limit and not halved
        if point is None and refit.failures[-1][1] == Status.EXACT_INFEASIBLE.name:
            # past here no value of the others meets the values marked exact: the profile is infinite
            # (an initial state measured exactly: its interval is the estimate itself)
            return prev.value, None, points, False
        if point is None:
            why = (f"the re-fits failed {side} {name} = {prev.value:.6g} "
                   f"({refit.failures[-1][1]}; the profile stays below the threshold up to there)")
            return None, why, points, False
        points.append(point)
        if threshold.excess(point) >= 0:
            end, extra = _crossing(prev, point, threshold.excess, refit, tol)
            return end, None, points + extra, False
        prev = point
        dist *= growth
        if at_limit:
            near = f" (to {point.value:.6g})" if approach else ""
            return (None, f"the search bound {limit:.6g} was reached{near} with the profile still below the threshold",
                    points, True)
    return None, (f"the profile stays below the threshold up to {name} = {prev.value:.6g} "
                  f"({max_points} steps; widen the search with `max_points=`/`growth=`/`step=`)"), points, False


def _step_out(refit: _Refitter, prev: _Point, target: float, direction: float) -> tuple[_Point | None, bool]:
    """Re-fit at ``target``; while that fails, halve the step from ``prev`` (up to ``_FAIL_HALVINGS`` times).

    Returns the point (None if every try failed) and whether the step was halved.
    """
    point = refit(target, prev)
    halvings, trial_dist = 0, abs(target - prev.value)
    while point is None and halvings < _FAIL_HALVINGS:
        halvings += 1
        trial_dist *= 0.5
        target = prev.value + direction * trial_dist
        point = refit(target, prev)
    return point, halvings > 0


def _stack_points(points: list[_Point]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Sort ``points`` by value (in place); their values ``(K,)``, SSEs ``(K,)`` and estimates ``(K, m)``."""
    points.sort(key=lambda pt: pt.value)
    values = torch.tensor([pt.value for pt in points], dtype=torch.float64)
    sses = torch.tensor([pt.sse for pt in points], dtype=torch.float64)
    estimates = torch.stack([pt.estimates for pt in points])
    return values, sses, estimates


def _summary(name: str, level: float, theta_hat: float, ends: list[float], closed: list[bool], notes: list[str],
             wald) -> str:
    """The result's message: the profile and Wald intervals, and why a side is open."""
    pct = f"{100 * level:g}%"
    message = (f"{name}: {pct} profile interval [{ends[0]:.6g}, {ends[1]:.6g}] "
               f"(Wald [{wald[0]:.6g}, {wald[1]:.6g}], estimate {theta_hat:.6g}).")
    if all(closed):
        return message + " The profile crosses the threshold on both sides."
    return message + " The interval is " + "; ".join(notes) + ": the data do not bound it there at this level."


def _lower_sse_note(result: FitResult, data: Observations, options: dict, name: str, values: torch.Tensor,
                    sses: torch.Tensor, threshold: _Threshold) -> str | None:
    """A note when the profile found an SSE clearly below the fit's (beyond integration error); else None."""
    sse_min = threshold.sse_min
    lowest = int(torch.argmin(sses))
    noise = sse_noise(result, data, options, threshold.likelihood)
    if float(sses[lowest]) < sse_min - 1e-6 * max(sse_min, threshold.delta) - noise:
        return (f" The profile found a lower SSE ({float(sses[lowest]):.6g} at {name} = {float(values[lowest]):.6g}) "
                f"than the fit ({sse_min:.6g}): the fit is not at the least-squares optimum; re-fit from there.")
    return None


def _crossing(inside: _Point, outside: _Point, excess, evaluate, tol: float):
    """Locate ``excess(theta) = 0`` between ``inside`` (< 0) and ``outside`` (>= 0): Illinois regula falsi.

    Returns the root and the points evaluated on the way.
    """
    a, b = inside, outside
    fa, fb = excess(a), excess(b)
    extra = []
    side = 0
    for _ in range(40):
        if abs(b.value - a.value) <= tol:
            break
        x = b.value - fb * (b.value - a.value) / (fb - fa) if fb != fa else math.nan
        lo, hi = sorted((a.value, b.value))
        if not lo < x < hi:  # (NaN too)
            x = 0.5 * (a.value + b.value)
        warm = a if abs(x - a.value) <= abs(x - b.value) else b
        pt = evaluate(x, warm)
        if pt is None:  # keep the last bracket; interpolate below
            break
        extra.append(pt)
        fx = excess(pt)
        if abs(fx) <= 1e-9 * max(1.0, abs(fa), abs(fb)):
            return x, extra
        if fx < 0:
            a, fa = pt, fx
            if side == -1:
                fb *= 0.5
            side = -1
        else:
            b, fb = pt, fx
            if side == 1:
                fa *= 0.5
            side = 1
    return a.value - excess(a) * (b.value - a.value) / (excess(b) - excess(a)), extra


def _original_params(result: FitResult, buffers: dict) -> list[str]:
    """The buffers estimated by the original fit."""
    given = result.fit_kwargs.get("params")
    if given is not None:
        return list(given)
    unknown = set(result.unknown_names)
    out = []
    for buf, value in buffers.items():
        if buf in unknown or any(u.startswith(buf + "[") for u in unknown):
            out.append(buf)
    return out


def _fit_bounds(result: FitResult, name: str) -> tuple[float | None, float | None] | None:
    """The fit's own bounds on the unknown ``name`` (``0`` below for one on a logarithmic scale): the
    profile's default search limits, so that it never re-fits at values the fit excludes."""
    i = list(result.unknown_names).index(name)
    lo = None if result.lower is None or not math.isfinite(float(result.lower[i])) else float(result.lower[i])
    hi = None if result.upper is None or not math.isfinite(float(result.upper[i])) else float(result.upper[i])
    if name in result.log_scaled:
        lo = 0.0 if lo is None else max(lo, 0.0)
    return None if lo is None and hi is None else (lo, hi)


def _check_bounds(bounds, theta_hat: float) -> tuple[float | None, float | None]:
    if bounds is None:
        return None, None
    try:
        lo, hi = bounds
    except (TypeError, ValueError) as exc:
        raise ValueError(f"`bounds` must be a pair (lower, upper), either may be None; received {bounds!r}") from exc
    lo = None if lo is None else float(lo)
    hi = None if hi is None else float(hi)
    if (lo is not None and not lo < theta_hat) or (hi is not None and not hi > theta_hat):
        raise ValueError(f"`bounds` {bounds!r} must enclose the estimate {theta_hat:.6g} strictly")
    return lo, hi


def _expressions_applied(model, x0: torch.Tensor, expressions: dict | None) -> torch.Tensor:
    """``x0`` with the initial states that ``x0_expr`` gives evaluated at ``model``'s coefficients,
    in the order given (as a fit completes its initial state)."""
    if not expressions:
        return x0
    names = list(model.state_names)
    x0 = x0.clone()
    for state, fn in check_expressions(expressions, names, None).items():  # (names as the fit takes them)
        values = dict(coefficients(model))
        values.update({name: x0[i] for i, name in enumerate(names)})
        x0[names.index(state)] = fn(values)
    return x0
