"""A text report of a fit, in the manner of lmfit's ``fit_report``.

The report has five parts: the fit (method, status, message, iterations, evaluations, and
the guesses moved inside their bounds, if any); its
statistics (values, unknowns, degrees of freedom, SSE, residual standard deviation, reduced
chi-square when ``sigma`` was given, AIC and BIC, condition number of the scaled Jacobian);
every unknown as ``value +/- stderr (relative %)`` with its Wald interval; the correlations
above a threshold; the unknowns without error bars and why; and the iteration table (SSE,
scaled ``|alpha|`` and every unknown per iterate, like the thesis' Table 3.2). A fit that did
not converge shows its estimates without error bars or intervals, and says why. Bounded
unknowns' intervals are Wald intervals in the bounds' internal variable, mapped back (see
:meth:`torchql.FitResult.confidence_intervals`); the header line names them. The iteration
table's SSE is :attr:`torchql.IterationRecord.sse` (for Kantorovich, that of the iterate's
stored linear trajectory; see there).

AIC and BIC are computed from the SSE as lmfit does (a Gaussian likelihood with the variance
profiled out): ``N ln(SSE / N) + 2 m`` and ``N ln(SSE / N) + ln(N) m``, with ``N`` the
least-squares values (exact ones excluded) and ``m`` the unknowns.
"""

from __future__ import annotations

import builtins
import math
from typing import TYPE_CHECKING

import torch

from . import _checks
from .model import _element_names
from .multi import experiment_state_name
from .status import Status

if TYPE_CHECKING:  # pragma: no cover
    from .result import FitResult, IterationRecord

__all__ = ["fit_report", "condition_number", "information_criteria", "unknown_values"]


def condition_number(result: "FitResult") -> float:
    """``max / min`` singular value of the column-scaled weighted Jacobian at the estimates.

    ``inf`` when the problem is rank deficient (``Status.NOT_IDENTIFIABLE`` or a zero singular
    value), ``nan`` when the Jacobian was not evaluated (the fit failed).
    """
    s = result.singular_values
    if result.status is Status.NOT_IDENTIFIABLE:
        return math.inf
    if s.numel() == 0 or not bool(torch.isfinite(s).all()):
        return math.nan
    smin, smax = float(s.min()), float(s.max())
    if smin <= 0.0:
        return math.inf
    return smax / smin


def information_criteria(result: "FitResult") -> tuple[float, float]:
    """``(AIC, BIC)`` from the SSE, as lmfit computes them.

    ``N ln(SSE/N) + 2 m`` and ``N ln(SSE/N) + ln(N) m``, ``N`` the least-squares values (the
    values marked exact are met exactly and do not count), ``m`` the number of unknowns less
    those the exact values fix (one each, but those that repeat what others fix: ``N - m`` is the
    fit's ``dof``).
    ``nan`` when the SSE is not finite, ``-inf`` when it is zero. With estimated sigmas or
    log-normal noise, from the negative log-likelihood instead: ``2 NLL + 2 k`` and
    ``2 NLL + ln(N) k``, ``k`` the unknowns and the estimated sigmas (:mod:`torchql.noise`; the
    one variance of log-normal values without ``sigma``, at its maximum ``SSE / N``); so too with a
    ``sigma(p)`` function (whose parameters are among the unknowns).
    """
    n_exact = int(result.exact_mask.sum())
    n = result.n_observations - n_exact
    m = max(n - result.dof, 0)  # (the unknowns the exact values leave free: the dof's count)
    if result.sigma is not None or result.noise != "normal" or result.sigma_function:  # 2 NLL + penalty
        k = m + (len(result.sigma) if result.sigma is not None else 0)
        if result.sigma is None and not result.sigma_known and not result.sigma_function:
            k += 1  # (log-normal values without sigma: their variance at its maximum, SSE / n, estimated)
        if not math.isfinite(result.nll) or n <= 0:
            return math.nan, math.nan
        return 2 * result.nll + 2 * k, 2 * result.nll + math.log(n) * k
    sse = result.sse
    if not math.isfinite(sse) or n <= 0:
        return math.nan, math.nan
    if sse <= 0.0:
        return -math.inf, -math.inf
    neg2_log_likelihood = n * math.log(sse / n)
    return neg2_log_likelihood + 2 * m, neg2_log_likelihood + math.log(n) * m


def unknown_values(result: "FitResult", record: "IterationRecord") -> list[float]:
    """The unknowns of one iterate, in ``result.unknown_names`` order. With several experiments the
    iterate's ``x0`` holds every experiment's initial state in turn, named ``"y[e](t0)"``."""
    states = list(result.model.state_names)
    if record.x0.numel() > len(states):  # several experiments, stacked
        states = [experiment_state_name(s, e) for e in range(record.x0.numel() // len(states)) for s in states]
    elements = {}
    for name, value in record.params.items():
        flat = value.reshape(-1)
        for i, el in enumerate(_element_names(name, value.shape)):
            elements[el] = flat[i]
    out = []
    for name in result.unknown_names:
        if name in elements:
            out.append(float(elements[name]))
        elif name.endswith("(t0)") and name[:-4] in states:
            out.append(float(record.x0.reshape(-1)[states.index(name[:-4])]))
        else:  # pragma: no cover - every unknown is a state or a coefficient element
            out.append(math.nan)
    return out


def _g(x: float, digits: int = 7) -> str:
    if isinstance(x, float) and math.isnan(x):
        return "nan"
    return f"{x:.{digits}g}"


def _no_errorbar_reason(result: "FitResult") -> str:
    if result.status is Status.NOT_IDENTIFIABLE:
        detail = result.message[len(result.status.value):].strip()
        return "not identifiable: the scaled Jacobian is rank deficient" + (f" ({detail})" if detail else "")
    if not result.success:
        return f"the fit did not converge ({result.status.name})"
    if not result.sigma_known and result.dof <= 0:
        return f"no degrees of freedom are left to estimate the residual variance (dof = {result.dof})"
    return "the covariance could not be computed (the scaled Jacobian is numerically singular)"


def fit_report(result: "FitResult", *, level: float = 0.95, min_correlation: float = 0.1,
               iterations: bool = True, print: bool = False) -> str:
    """A text report of ``result``.

    Parameters
    ----------
    result : FitResult
    level : float
        Confidence level of the Wald intervals shown with the unknowns.
    min_correlation : float
        Correlations with ``|r|`` at or below this are not listed.
    iterations : bool
        Include the iteration table.
    print : bool
        Also print the report.

    Returns
    -------
    str
    """
    if not (isinstance(level, float) and 0.0 < level < 1.0):
        raise ValueError(f"`level` must be a float strictly between 0 and 1; received {level!r}")
    if isinstance(min_correlation, bool) or not isinstance(min_correlation, (int, float)) or not 0 <= min_correlation < 1:
        raise ValueError(f"`min_correlation` must be a number in [0, 1); received {min_correlation!r}")
    iterations, print = _checks.flag("iterations", iterations), _checks.flag("print", print)
    lines = _fit_section(result) + _statistics_section(result)
    unknowns, missing = _unknowns_section(result, level)
    lines += unknowns
    if len(result.unknown_names) > 1 and not missing:
        lines += _correlations_section(result, min_correlation)
    if iterations and result.history:
        lines += _iterations_section(result)
    text = "\n".join(lines)
    if print:
        builtins.print(text)
    return text


def _fit_section(result: "FitResult") -> list[str]:
    """The ``[[Fit]]`` lines: method, status, message, iterations, evaluations, moved guesses."""
    lines = [
        "[[Fit]]",
        f"    method             = {result.method}",
        f"    status             = {result.status.name}",
        f"    success            = {result.success}",
        f"    message            = {result.message}",
        f"    iterations         = {result.iterations}",
        f"    function evals     = {result.nfev}",
    ]
    if result.moved_guesses:
        lines.append("    moved guesses      = " + ", ".join(f"{name}: {given:g} -> {used:.6g}"
                                                             for name, (given, used) in result.moved_guesses.items())
                     + " (on or outside their bounds: moved inside)")
    return lines


def _statistics_section(result: "FitResult") -> list[str]:
    """The ``[[Fit statistics]]`` lines: counts, SSE, noise, sigma or residual std, NLL, AIC, BIC, condition."""
    n_exact = int(result.exact_mask.sum())
    aic, bic = information_criteria(result)
    lines = ["[[Fit statistics]]"]
    add = lines.append
    add(f"    data points        = {result.n_observations}" + (f" ({n_exact} met exactly)" if n_exact else ""))
    add(f"    unknowns           = {len(result.unknown_names)}")
    add(f"    degrees of freedom = {result.dof}")
    add(f"    SSE (chi-square)   = {_g(result.sse)}")
    if result.noise != "normal":
        add(f"    noise              = {result.noise} (fitted on log y; sigma is that of log y)")
    if result.sigma is not None:
        stderr = result.sigma_stderr or {}
        add("    sigma (estimated)  = " + ", ".join(
            f"{name}: {_g(value)}" + (f" ± {_g(stderr[name], 3)}" if math.isfinite(stderr.get(name, math.nan)) else "")
            for name, value in result.sigma.items()) + " (maximum likelihood; the residuals are in units of it)")
    elif result.sigma_function:
        add("    sigma              = sigma(p), a function of the unknowns (maximum likelihood; the residuals are "
            "in units of it)")
    elif result.sigma_known:
        red = result.sse / result.dof if result.dof > 0 else math.nan
        add(f"    reduced chi-square = {_g(red)}")
        add("    residual std       = 1 (sigma given: the residuals are in units of sigma)")
    else:
        rv = result.residual_variance
        add(f"    residual std       = {_g(math.sqrt(rv) if rv >= 0 else math.nan)} (estimated, sqrt(SSE / dof))")
    add(f"    -log likelihood    = {_g(result.nll)}")
    likelihood = result.sigma is not None or result.noise != "normal" or bool(result.sigma_function)
    convention = (" (2 NLL + 2 k, k: the unknowns and the estimated sigmas)" if likelihood
                  else " (lmfit's: N ln(SSE/N) + 2 m, from the SSE; not 2 NLL + 2 m)")
    add(f"    AIC                = {_g(aic)}" + convention)
    add(f"    BIC                = {_g(bic)}" + (" (2 NLL + ln(N) k)" if likelihood else " (N ln(SSE/N) + ln(N) m)"))
    add(f"    condition number   = {_g(condition_number(result), 4)} (column-scaled weighted Jacobian)")
    return lines


def _unknowns_section(result: "FitResult", level: float) -> tuple[list[str], list[str]]:
    """The ``[[Unknowns]]`` lines (values, standard errors, Wald intervals at ``level``), and the unknowns
    without an error bar (all of them when the fit did not converge)."""
    names = list(result.unknown_names)
    width = max([len(n) for n in names] + [10])
    est = result.estimates.tolist()
    if not (result.success or result.status is Status.NOT_IDENTIFIABLE):
        # estimates that are not an optimum: no error bar or interval about them means anything
        lines = [f"[[Unknowns]] (value; no standard errors or intervals: {_no_errorbar_reason(result)})"]
        lines += [f"    {name:<{width}} = {_g(value)}" for name, value in zip(names, est)]
        return lines, names
    se = result.stderr
    pct = f"{100 * level:g}%"
    cis, kinds = result._intervals(level)
    bounded = [name for name in names if kinds.get(name) == "mapped" and name not in result.log_scaled]
    clipped = [name for name in names if kinds.get(name) == "clipped"]
    header = f"[[Unknowns]] (value +/- standard error (relative), {pct} Wald interval"
    if bounded:
        header += (f"; of {', '.join(bounded)} in the bounds' internal variable (log of the distance to "
                   "one bound, logit between two), mapped back: inside the bounds, asymmetric")
    if clipped:
        header += f"; of {', '.join(clipped)} (on or near a bound) clipped to the bounds"
    logged = [name for name in result.log_scaled if kinds.get(name) != "clipped"]
    if logged:
        header += (f"; of {', '.join(logged)} on the log scale (the interval of log u, inside its "
                   "bounds), mapped back: asymmetric")
    lines = [header + ")"]
    missing = []
    for name, value in zip(names, est):
        s = se[name]
        if not math.isfinite(s):
            missing.append(name)
            lines.append(f"    {name:<{width}} = {_g(value)} +/- nan (no error bar)")
            continue
        rel = "n/a" if value == 0 else _percent(100 * s / abs(value))
        lo, hi = cis[name]
        lines.append(f"    {name:<{width}} = {_g(value)} +/- {_g(s, 4)} ({rel})   {pct} CI [{_g(lo)}, {_g(hi)}]")
    if missing:
        lines += ["[[Unknowns without error bars]]", f"    {', '.join(missing)}: {_no_errorbar_reason(result)}"]
    return lines, missing


def _percent(value: float) -> str:
    """A relative error in percent: two decimals, or two digits where it is huge (an estimate on a
    bound at 0, whose standard error is 1e35 times it, printed 36 digits)."""
    return f"{value:.2f}%" if value < 1e4 else f"{value:.2g}%"


def _correlations_section(result: "FitResult", min_correlation: float) -> list[str]:
    """The ``[[Correlations]]`` lines: the pairs with ``|r| > min_correlation``, strongest first."""
    names = list(result.unknown_names)
    m = len(names)
    corr = result.correlation
    pairs = [(abs(float(corr[i, j])), float(corr[i, j]), names[i], names[j])
             for i in range(m) for j in range(i + 1, m)]
    shown = sorted((p for p in pairs if math.isfinite(p[1]) and p[0] > min_correlation), reverse=True)
    lines = [f"[[Correlations]] (|r| > {min_correlation:g})"]
    if not shown:
        lines.append("    none")
    cw = max([len(f"C({a}, {b})") for _, _, a, b in shown] + [0])
    lines += [f"    {f'C({a}, {b})':<{cw}} = {r:+.4f}" for _, r, a, b in shown]
    return lines


def _iterations_section(result: "FitResult") -> list[str]:
    """The ``[[Iterations]]`` table: SSE, scaled ``|alpha|`` and every unknown per iterate."""
    names = list(result.unknown_names)
    if result.method == "kantorovich":
        what = ("SSE: of the iterate's stored trajectory, the linear prediction w_0 + W alpha of the step "
                "that led to it (not the model's solution: it need not fall, and may dip below the optimum); "
                "steps are accepted on IterationRecord.merit or the model's own sum of squares")
    else:
        what = "SSE: of the model's solution from the iterate's estimates"
    if result.sigma_function or result.sigma is not None:
        what += (f"; with {'sigma(p)' if result.sigma_function else 'estimated sigmas'}, SSE + 2 sum log sigma, the "
                 "objective (twice the negative log-likelihood less n log 2 pi)")
    cols = [max(14, len(n) + 1) for n in names]
    lines = [f"[[Iterations]] ({what}; |alpha|: the update scaled by the unknowns' magnitudes)",
             f"    {'iter':>4} {'SSE':>12} {'|alpha|':>10} " + " ".join(f"{n:>{w}}" for n, w in zip(names, cols))]
    for rec in result.history:
        vals = unknown_values(result, rec)
        alpha = "-" if not math.isfinite(rec.alpha_norm) else f"{rec.alpha_norm:.3e}"
        sse = f"{rec.sse:.6g}" if math.isfinite(rec.sse) else "nan"
        lines.append(f"    {rec.iteration:>4} {sse:>12} {alpha:>10} "
                     + " ".join(f"{_g(v, 10):>{w}}" for v, w in zip(vals, cols)))
    return lines
