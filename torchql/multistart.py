"""Multi-start: fit from many guesses and keep the best, reporting the spread of optima.

A nonlinear least-squares problem may have several local optima, and any local method
converges to the one whose basin holds its start. ``multistart`` draws ``starts`` guesses of
the coefficients (log-uniform over a range around the model's own values, or within
``bounds``), fits from each, and returns the best fit together with every fit and the
distinct optima found, so that a user can see whether the best is likely global (most starts
reach it) or fragile (few do).

Every start is fitted in one :func:`torchql.fit_many` call, each sample from its own guesses on
``torchql.fit``'s iteration (one dataset or one list of experiments, with any of ``fit``'s options:
``fit_many`` gives each sample its own ``fit``); the best start is then fitted once more with
:func:`torchql.fit`, so that ``best`` is the full :class:`~torchql.FitResult` a loop would
give. With a ``max_time`` (one per start), a per-iteration ``callback`` or a ``linear_solver``
without a batched form, each start is one ``torchql.fit``.
"""

from __future__ import annotations

import copy
import inspect
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import torch

from . import _checks
from ._arrays import float_tensor
from .batch import fit_many
from .bounds import bound_pair
from .fit import fit
from .model import AugmentedSystem, _set_buffer, coefficient_names, model_dtype_device
from .multi import replaced_everywhere
from .observations import Observations
from .options import expand_options
from .parameters import apply_parameters
from .result import FitResult
from .propagators import linear_propagator

__all__ = ["multistart", "MultiStartResult", "Optimum"]

#: Options of :func:`torchql.fit` whose meaning differs in :func:`torchql.fit_many` (one time budget
#: for the batch; a callback that also receives the sample): given, each start is one ``fit``.
_FIT_ALONE = frozenset({"max_time", "callback"})
#: The keywords of :func:`torchql.fit` (``options`` included), which ``multistart`` passes on.
_FIT_KEYWORDS = frozenset(inspect.signature(fit).parameters) | {"options"}


@dataclass
class Optimum:
    """A distinct optimum reached by some of the starts.

    Attributes
    ----------
    sse : float
        Its weighted sum of squares (of the best fit that reached it).
    estimates : Tensor ``(m,)``
        The unknowns there (``unknown_names`` order of the fits).
    starts : list of int
        Indices of the starts that converged to it.
    nll : float or None
        Its negative log-likelihood, where the fits maximized one (estimated sigmas, a ``sigma(p)``
        function, log-normal noise: :attr:`torchql.FitResult.likelihood`), which then ranks the
        optima; ``None`` where the SSE does.
    """

    sse: float
    estimates: torch.Tensor
    starts: list[int]
    nll: float | None = None


@dataclass
class MultiStartResult:
    """What :func:`multistart` found.

    Attributes
    ----------
    best : FitResult
        The successful fit with the smallest objective (:attr:`torchql.FitResult.objective`: the
        SSE, or the negative log-likelihood where the fits maximized one; if none succeeded, the
        fit with the smallest finite one, whose ``success`` is False).
    results : list of FitResult
        Every start's fit, in the order of ``guesses``. Batched, each is one sample of the
        ``fit_many`` result (status, message, estimates, SSE, covariance, ...; no trajectory).
    guesses : Tensor ``(N, P)``
        The drawn coefficient guesses (columns ``param_names``).
    param_names : list of str
        Names of the drawn coefficients (vector/matrix buffers element-wise).
    optima : list of Optimum
        Distinct optima of the successful fits, best first.
    batched : bool
        Whether the starts were fitted in one :func:`torchql.fit_many` call (and ``best`` by
        one more :func:`torchql.fit` from its start) rather than by one ``fit`` each.
    """

    best: FitResult
    results: list[FitResult]
    guesses: torch.Tensor
    param_names: list[str]
    optima: list[Optimum] = field(default_factory=list)
    batched: bool = False

    @property
    def n_converged(self) -> int:
        """Number of successful fits."""
        return sum(r.success for r in self.results)

    @property
    def fraction_best(self) -> float:
        """Fraction of all starts that reached the best optimum."""
        return len(self.optima[0].starts) / len(self.results) if self.optima else 0.0

    def summary(self) -> str:
        """A short table of the optima: SSE (or NLL), how many starts reached each, and the estimates."""
        lines = [f"{len(self.results)} starts, {self.n_converged} converged, {len(self.optima)} distinct optima"]
        names = self.best.unknown_names
        for k, opt in enumerate(self.optima):
            values = ", ".join(f"{n}={v:.6g}" for n, v in zip(names, opt.estimates.tolist()))
            value = f"SSE {opt.sse:.6g}" if opt.nll is None else f"NLL {opt.nll:.6g}"
            lines.append(f"  #{k}: {value} reached by {len(opt.starts)} start(s): {values}")
        return "\n".join(lines + self._lower_unconverged())

    def _lower_unconverged(self) -> list[str]:
        """The summary's line on the starts that did not converge but ended below the best optimum
        (a stalled oscillator fit at SSE 39.7 beside the one converged at 41.6): a local optimum
        their iteration could not confirm, or the way to a better one."""
        best = self.results[self.optima[0].starts[0]].objective if self.optima else math.inf
        lower = [r for r in self.results if not r.success and math.isfinite(r.objective) and r.objective < best]
        if not lower:
            return []
        low = min(lower, key=lambda r: r.objective)
        kind = "NLL" if low.likelihood else "SSE"
        value = low.nll if low.likelihood else low.sse
        statuses = sorted({r.status.name for r in lower})
        values = ", ".join(f"{n}={v:.6g}" for n, v in zip(low.unknown_names, low.estimates.tolist()))
        where = (f"{len(lower)} start(s) that did not converge ({', '.join(statuses)}) ended below the best "
                 "optimum, the lowest" if self.optima else f"No start converged; the lowest ({low.status.name}) ended")
        return [f"  {where} at {kind} {value:.6g}: {values}. Refit from there, or with more starts, to see whether "
                "an optimum lies near."]

    def __repr__(self) -> str:
        return (f"MultiStartResult(starts={len(self.results)}, converged={self.n_converged}, "
                f"optima={len(self.optima)}, " + (f"best_nll={self.best.nll:.6g})" if self.best.likelihood
                                                  else f"best_sse={self.best.sse:.6g})"))


def multistart(model, data, x0=None, *, starts: int = 20, spread: float = 10.0, bounds: dict | None = None,
               params=None, seed: int = 0, include_guess: bool = True, x_rtol: float = 1e-4,
               x_atol: float = 1e-8, callback: Callable[[int, FitResult], None] | None = None,
               **fit_kwargs) -> MultiStartResult:
    """Fit ``model`` to ``data`` from ``starts`` guesses of the coefficients; keep the best.

    Parameters
    ----------
    model : ODEModel
        Its buffers are the central guesses (never modified).
    data, x0, params, bounds
        As in :func:`torchql.fit` (the same ``x0`` for every start). Each start's first iterate is
        the model integrated from its own guesses: ``initial_trajectory`` defaults to
        ``"integrate"`` here, since a first reference built from the data (``fit``'s ``"auto"``
        where a state is measured) would be the same for every start and make the draws moot;
        pass ``initial_trajectory="auto"`` or ``"data"`` for those.
    starts : int
        Number of fits.
    spread : float
        Each estimated coefficient ``c`` is drawn log-uniformly in ``[c / spread, c * spread]``
        (its sign kept; a zero guess is drawn uniformly in ``[-1, 1]``). A coefficient with
        both bounds finite is drawn within them instead (log-uniformly when they are positive),
        one with one bound is drawn as above and clipped strictly inside it; if its guess lies
        on that bound (a rate guessed 0 with ``(0, None)``) or beyond it, its distance from the
        bound is drawn log-uniformly in ``[s / spread, s * spread]``, ``s = max(1, |bound|)``.
        The first start (``include_guess``) is the guess itself, which :func:`torchql.fit`
        moves inside its bounds (see its ``bounds``).
    seed : int
        Seed of the draws (reproducible).
    include_guess : bool
        Whether the first start is the model's own values.
    x_rtol, x_atol : float
        Two successful fits are the same optimum when every estimate agrees to within
        ``x_rtol`` times its magnitude plus ``x_atol``, or within a hundredth of its standard
        error (:data:`SAME_OPTIMUM_STDERR`: the data cannot tell them apart).
    callback : callable, optional
        Called as ``callback(k, result)`` after each fit (progress reporting); when the starts
        are fitted in one batch, for every start once the batch is done.
    **fit_kwargs
        Further arguments of :func:`torchql.fit` (``method``, ``initial_trajectory``, ...; or
        ``options=`` a :class:`torchql.FitOptions`, whose fields set away from their defaults apply).
        With the options ``fit_many`` supports, the starts are fitted in one batch (see the
        module's description and ``MultiStartResult.batched``).

    Returns
    -------
    MultiStartResult
    """
    _checks.model_class(model)
    _checks.single_observations("data", data)
    starts = _checks.positive_int("starts", starts)
    spread = _checks.positive_number("spread", spread)
    if spread < 1:
        raise ValueError(f"`spread` must be >= 1 (a factor around the guesses); received {spread:g}")
    seed = _checks.positive_int("seed", seed, minimum=0)
    include_guess = _checks.flag("include_guess", include_guess)
    x_rtol, x_atol = _checks.non_negative_number("x_rtol", x_rtol), _checks.non_negative_number("x_atol", x_atol)
    if callback is not None and not callable(callback):
        raise TypeError(f"`callback` must be callable as callback(k, result); received {callback!r}")
    unknown = sorted(set(fit_kwargs) - _FIT_KEYWORDS)
    if unknown:
        raise TypeError(f"multistart() got unexpected keyword argument(s) {unknown}: it takes its own and "
                        "torchql.fit's")
    fit_kwargs = expand_options(fit_kwargs)
    # each start from its own guesses: a first reference built from the data ("auto"'s, where a state
    # is measured) is the same for every start, and so would the fits be
    fit_kwargs.setdefault("initial_trajectory", "integrate")
    if "throw" in fit_kwargs:
        raise TypeError("`throw` is not accepted by multistart: failed starts are part of the result")
    if fit_kwargs.get("parameters") is not None:  # the specification's bounds bound the draws too
        spec = apply_parameters(model, fit_kwargs.pop("parameters"), x0=x0, params=params,
                                fixed_x0=fit_kwargs.get("fixed_x0"), bounds=bounds, scale=fit_kwargs.get("scale"),
                                x0_expr=fit_kwargs.get("x0_expr"),
                                rows=len(data) if isinstance(data, (list, tuple)) else None)
        model, x0, params, bounds = spec["model"], spec["x0"], spec["params"], spec["bounds"]
        fit_kwargs.update({key: spec[key] for key in ("fixed_x0", "scale", "x0_expr") if spec[key] is not None})
    if params is None:  # (fit's default: not the constants, nor a coefficient every experiment's condition sets)
        held = tuple(model.constants) + replaced_everywhere(fit_kwargs.get("conditions"))
        params = [name for name in coefficient_names(model) if name not in held]
    params = _checks.distinct_names("params", params, coefficient_names(model), "buffer",
                                    _checks.coefficients_text(model))
    if isinstance(data, Observations) and x0 is not None:  # (a batch of starts must not show in its shape)
        n = len(model.state_names)
        shape = tuple(float_tensor(x0, "x0", *model_dtype_device(model), expected=f"a tensor of shape ({n},)").shape)
        if shape != (n,):
            raise ValueError(f"`x0` must have shape (n_states,) = ({n},); received shape {shape}")
    system = AugmentedSystem(model, list(params), *model_dtype_device(model))
    center = system.pack_params()
    lower, upper = _element_bounds(bounds, system)
    gen = torch.Generator().manual_seed(seed)
    guesses = torch.stack([_draw(center, lower, upper, spread, gen) for _ in range(starts)])
    if include_guess:
        guesses[0] = center

    def fit_start(k: int) -> FitResult:
        trial = copy.deepcopy(model)
        for name, value in system.unpack_params(guesses[k]).items():
            _set_buffer(trial, name, value)
        return fit(trial, data, x0, params=params, bounds=bounds, **fit_kwargs)

    batched = _fit_many_serves(data, fit_kwargs)
    results: list[FitResult] = []
    if batched:
        rows = [system.unpack_params(g) for g in guesses]
        per_start = {name: torch.stack([row[name] for row in rows]) for name in system.param_names}
        options = {key: value for key, value in fit_kwargs.items() if key not in _FIT_ALONE}
        results += fit_many(model, [data] * starts, x0, params=params, guesses=per_start, bounds=bounds, **options)
        if callback is not None:
            for k, r in enumerate(results):
                callback(k, r)
    else:
        for k in range(starts):
            results.append(fit_start(k))
            if callback is not None:
                callback(k, results[-1])
    optima = _cluster(results, x_rtol, x_atol)
    if optima:
        k_best = optima[0].starts[0]
    else:
        finite = [k for k, r in enumerate(results) if math.isfinite(r.objective)]
        k_best = min(finite, key=lambda k: results[k].objective) if finite else 0
    best = fit_start(k_best) if batched else results[k_best]  # the full FitResult a loop gives that start
    return MultiStartResult(best=best, results=results, guesses=guesses, param_names=list(system.element_names),
                            optima=optima, batched=batched)


def _fit_many_serves(data, fit_kwargs: dict) -> bool:
    """Whether :func:`torchql.fit_many` fits every start as ``torchql.fit(..., **fit_kwargs)`` would:
    for one dataset or one list of experiments, with any option but a ``max_time`` (a batch has one
    budget for all its starts, a loop one per start), a ``callback`` (``fit_many``'s names the
    sample) and a ``linear_solver`` without a batched form."""
    if not (isinstance(data, Observations)
            or (isinstance(data, (list, tuple)) and data and all(isinstance(d, Observations) for d in data))):
        return False

    def served(key, value) -> bool:
        if key == "linear_solver":
            return value is None or linear_propagator(value).batched
        return key not in _FIT_ALONE or value is None
    return all(served(key, value) for key, value in fit_kwargs.items())


def _element_bounds(bounds, system: AugmentedSystem) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-element ``(lower, upper)`` of the drawn coefficients (infinite where open)."""
    P = system.P
    lower = torch.full((P,), -math.inf, dtype=torch.float64)
    upper = torch.full((P,), math.inf, dtype=torch.float64)
    if bounds:
        k = 0
        for name, size in zip(system.param_names, system.param_sizes):
            for j, element in enumerate(system.element_names[k:k + size]):
                key = element if element in bounds else name
                if key in bounds:  # validated as fit validates it, before any draw
                    lower[k + j], upper[k + j] = bound_pair(key, bounds[key])
            k += size
    return lower, upper


def _draw(center: torch.Tensor, lower: torch.Tensor, upper: torch.Tensor, spread: float,
          gen: torch.Generator) -> torch.Tensor:
    out = torch.empty_like(center)
    u = torch.rand(center.shape[0], generator=gen, dtype=torch.float64)
    for i, c in enumerate(center.tolist()):
        lo, hi = lower[i].item(), upper[i].item()
        if math.isfinite(lo) and math.isfinite(hi):
            if lo > 0:
                value = math.exp(math.log(lo) + u[i].item() * (math.log(hi) - math.log(lo)))
            else:
                value = lo + u[i].item() * (hi - lo)
        elif math.isfinite(lo) and not c > lo or math.isfinite(hi) and not c < hi:
            # the guess on (or beyond) its one bound: the distance from that bound drawn
            # log-uniformly around the bound's scale max(1, |bound|)
            bound, side = (lo, 1.0) if math.isfinite(lo) else (hi, -1.0)
            value = bound + side * max(1.0, abs(bound)) * math.exp((2 * u[i].item() - 1) * math.log(spread))
        elif c == 0:
            value = 2 * u[i].item() - 1
        else:
            value = math.copysign(math.exp(math.log(abs(c)) + (2 * u[i].item() - 1) * math.log(spread)), c)
        # outside a one-sided bound: between the bound and the (inside) central guess instead
        if math.isfinite(lo) and value <= lo:
            value = lo + (c - lo) * max(u[i].item(), 1e-3)
        if math.isfinite(hi) and value >= hi:
            value = hi - (hi - c) * max(u[i].item(), 1e-3)
        out[i] = value
    return out


#: Two fits are at one optimum where every estimate is within this fraction of its standard error of the
#: other's (or within ``x_rtol``): the data cannot tell them apart. (A flat optimum's fits, each
#: converged on the sum of squares to its tolerance, stop 1e-4 standard errors apart; float32 fits
#: 2e-4 apart relative, beyond ``x_rtol``. Each was listed as an optimum of its own.)
SAME_OPTIMUM_STDERR = 0.01


def _cluster(results: list[FitResult], x_rtol: float, x_atol: float) -> list[Optimum]:
    """Group the successful fits into distinct optima, best first: each fit joins the first optimum
    whose estimates its own match (``x_rtol``, ``x_atol``, or :data:`SAME_OPTIMUM_STDERR`)."""
    ok = sorted((k for k, r in enumerate(results) if r.success and math.isfinite(r.objective)),
                key=lambda k: results[k].objective)
    optima: list[Optimum] = []
    if not ok:
        return optima
    for k in ok:
        r = results[k]
        for opt in optima:
            apart = (r.estimates - opt.estimates).abs()
            close = apart <= x_rtol * opt.estimates.abs() + x_atol
            covariance = results[opt.starts[0]].covariance  # the best fit's at this optimum
            if covariance is not None and covariance.shape[-1] == apart.shape[-1]:
                stderr = torch.diagonal(covariance).clamp_min(0).sqrt().to(apart)
                close |= apart <= SAME_OPTIMUM_STDERR * stderr  # (NaN standard errors: not close)
            if bool(close.all()):
                opt.starts.append(k)
                break
        else:
            optima.append(Optimum(sse=r.sse, estimates=r.estimates.clone(), starts=[k],
                                  nll=r.nll if r.likelihood else None))
    return optima
