"""The first Kantorovich reference built from the data, with no integration (``initial_trajectory="data"``,
and what the default ``"auto"`` chooses where the data can give it).

The observed states are the data, smoothed (:func:`torchql.smoothing.smooth`) and interpolated
on the storage grid; the unobserved ones are derived from the model where the observed states'
equations involve them (``y' = v`` gives ``v`` from the smoothed ``y``); the first coefficients
are fitted to the data's slopes (gradient matching). None of this integrates the model, so it
does not depend on how poor the guesses are (the thesis' wide-basin start).

Batch-first: the smoothing is per series, the derivation of unobserved states and the gradient
matching are one vectorized computation over every sample (each sample with its own damping),
so ``fit`` (one sample) and ``fit_many`` (``S`` samples) compute the same start.

:func:`first_reference` is ``"auto"``'s choice between this start and the model integrated from
the guesses; :func:`fallback_rows` and :func:`keep_the_better_fit` fit a sample again from the
other start where its fit from the first failed (from the integrated guesses after the data; from
the data after the integrated guesses of a stiff model), and keep the better of the two.
"""

from __future__ import annotations

import math
from typing import Callable

import torch
from torch.func import jacrev

from .budget import TimeBudgetExceeded, check_time, until
from .linearize import node_jacobian
from .lstsq import solve_update_batch
from .schemes import scheme_strategy
from .damping import DAMPING_MAX as _DAMPING_MAX, DAMPING_START as _DAMPING_START
from .smoothing import interpolate, interpolate_each, smooth, smooth_each
from .status import Status

__all__ = ["data_reference", "first_reference", "derivation_uses_unknowns", "fallback_rows", "sse_at_guesses",
           "keep_the_better_fit", "slopes", "MIN_POINTS", "FALLBACK_STATUSES", "START_WORDS", "STIFF_REFIT"]

#: Accepted Gauss–Newton steps of the gradient matching that gives the first coefficients.
MATCH_STEPS = 30
#: Gauss–Newton steps that derive unobserved states for a first trajectory from the data.
DERIVE_STEPS = 8
#: Relative change of every coefficient below which the gradient matching has converged. Its
#: result only starts the fit's own iteration, which converges quadratically: a digit more costs
#: steps (Gauss–Newton converges only linearly where the slopes do not fit exactly) and no iteration
#: (on the random problems of experiments/random_problems.py 1e-6, 1e-3 and 1e-2 give the same
#: iterations and optima; 1e-3 saves a noisy Michaelis–Menten fit a fifth of its time).
MATCH_XTOL = 1e-3
#: Relative decrease of the matching's cost below which it has converged (round-off, or a flat minimum).
MATCH_FTOL = 1e-12


#: Used values of a directly measured state, in every sample, for ``initial_trajectory="auto"`` to
#: build the first reference from the data (fewer give no usable slopes: a line or a parabola).
MIN_POINTS = 4


def first_reference(initial_trajectory: str, method, observed_states: list, rows_mask: torch.Tensor,
                    stiff: bool = False, max_iter: int | None = None,
                    derivation_uses_unknowns: Callable[[list[int]], bool] | None = None) -> str:
    """The first reference a fit uses: ``"data"`` or ``"integrate"``.

    ``"auto"`` (the default) is ``"data"`` for Kantorovich on a non-stiff path when some output
    reads a state directly and has at least :data:`MIN_POINTS` used values in every sample
    (``rows_mask (S, T, K)``), and the states not measured so can be derived from those that are
    without the unknown coefficients (``derivation_uses_unknowns(measured states)`` false, see
    :func:`derivation_uses_unknowns`): ``y' = v`` gives ``v``, where SIR's ``I' = beta S I / N -
    gamma I`` gives ``S`` only through the guesses of ``beta`` and ``gamma``. Built from the data,
    the start does not depend on how poor the guesses are, where the model integrated from them
    may leave the basin of the optimum. Otherwise it is ``"integrate"``: for shooting (``method``, a
    name or a :class:`torchql.schemes.Scheme`, whose iterates solve the model); when no
    state is measured directly (a sum of states, a log-transformed output) or at too few times;
    when deriving the others needs the unknowns; when the solver is stiff (``stiff``), whose fast
    transients the data do not resolve; and with ``max_iter=0``, which evaluates the guesses.
    Decided once for a batch, as ``solver="auto"`` is. Explicit choices are returned unchanged.
    """
    if initial_trajectory != "auto":
        return initial_trajectory
    if scheme_strategy(method).integrates_model or stiff or max_iter == 0:
        return "integrate"
    counts = rows_mask.sum(dim=1).amin(dim=0)  # (K,): the fewest used values of each output in a sample
    measured = sorted({i for k, i in enumerate(observed_states) if i is not None and int(counts[k]) >= MIN_POINTS})
    if not measured or (derivation_uses_unknowns is not None and derivation_uses_unknowns(measured)):
        return "integrate"
    return "data"


def derivation_uses_unknowns(system, measured: list[int], unknown_index: torch.Tensor, z0: torch.Tensor,
                             t0: torch.Tensor) -> bool:
    """Whether the equations of the ``measured`` states involve an unknown coefficient while some
    state is not measured (the data-built start derives those from the measured states'
    equations, which would then rest on the coefficients' guesses). Tested at one generic point
    near the guesses ``z0 (M,)``: a fixed perturbation, so that no coincidental zero (``I = 0``)
    hides a term."""
    n = system.n
    coefficients = unknown_index[unknown_index >= n]
    if len(measured) == n or not coefficients.numel():
        return False
    generic = torch.randn(z0.shape, generator=torch.Generator().manual_seed(0), dtype=z0.dtype).to(z0.device)
    z = z0 + (0.1 * z0.abs() + 0.1) * generic
    with torch.no_grad():
        J = jacrev(lambda v: system.f(t0, v))(z)
    rows = torch.tensor(measured, device=z0.device)
    return bool((J.index_select(0, rows).index_select(1, coefficients) != 0).any())


#: The ends of a fit after which ``"auto"`` fits the sample again from its other first reference
#: (:attr:`torchql.problem.Problem.start_fallback`): the start led nowhere. Not ``MAX_TIME`` (the
#: fit was still on its way: it needs time, not another start), nor ``MAX_ITER`` after fewer than
#: :data:`LONG_PATH` iterations (a small ``max_iter``), nor a success. (After a long path
#: ``MAX_ITER`` is fitted again too, :func:`fallback_rows`: a ``sigma="estimate"`` fit from the
#: data whose initial state ran off along a direction the data barely see, 50 iterations to
#: ``x0 = -1.5e5``, converged from the integrated guesses to the optimum that ``sigma=None`` and
#: shooting reach.)
FALLBACK_STATUSES = (Status.DIVERGED, Status.INTEGRATION_FAILED, Status.STALLED, Status.NOT_IDENTIFIABLE)

#: A fit from the data that succeeded above the model's sum of squares at the guesses by more than
#: this fraction of its own is fitted again from the integrated guesses (:func:`fallback_rows`;
#: the guesses' is integrated loosely).
GUESSES_MARGIN = 1e-3

#: A data-started fit whose weighted residuals' lag-one autocorrelation (neighbours in time, each
#: output's) exceeds this in magnitude, and three times white noise's (``1 / sqrt(L)`` of ``L``
#: values), misfits the data systematically; with a sum of squares above :data:`MISFIT_FLOOR`
#: times the integration's own error, its sum of squares is compared with the model's at the
#: guesses (:func:`sse_at_guesses`).
MISFIT_CORRELATION = 0.5
MISFIT_FLOOR = 100.0
#: ... and so is one that took at least this many iterations.
LONG_PATH = 10
#: A data-started success after at least this many iterations is fitted again from the integrated
#: guesses whatever their sum of squares (:func:`fallback_rows`), and loses only to a success lower
#: by more than :data:`GUESSES_MARGIN` of its own: an oscillator sampled below its frequency took 27
#: to a wrong optimum, where fits that took 10 to 15 reached the right one.
LONG_SUCCESS = 20
#: ... and one whose data's ``sigma`` was given and whose sum of squares exceeds this many times the
#: number of values (each weighted residual ten standard deviations on average): a van der Pol
#: fit (20 values, sigma 0.01) from mu = 2.8 ended CONVERGED at mu = 8e-12 on its bound with SSE
#: 907,976, where the model at the guesses had 48,620 and the fit from them reaches 19.2 at mu = 3;
#: its residuals' lag-one correlation, 0.62, was below white noise's three deviations (0.67).
KNOWN_SIGMA_MISFIT = 100.0
#: The most steps of the adaptive solver per interval of the storage grid (which resolves the
#: fitted trajectory) in which the model at a sample's guesses must integrate for
#: :func:`sse_at_guesses`' check, else it is not made: the check is insurance, and a guess far off
#: may make the model oscillate or relax far faster than its fit (an oscillator's ``B = 3e6``
#: against 3 took 45 s of the 100,000 steps that ended in failure, for a fit of 0.04 s; one sampled
#: below its frequency, ``B = 400`` over 318 periods, needs about 2.5 on its automatic grid).
GUESSES_STEPS = 8

#: What :func:`keep_the_better_fit` appends to a message, by the second fit: where it won (before
#: and after the first fit's end), and where it did not (before its own end). From the second
#: first reference, ``"integrate"`` or ``"data"``; and by the stiff solver (:data:`STIFF_REFIT`).
START_WORDS = {"integrate": (" From the first reference built from the data the fit ended ",
                             "this fit integrated the model from the guesses.",
                             " Integrated from the guesses instead of starting from the data, the fit ended "),
               "data": (" Integrated from the guesses the fit ended ",
                        "this fit's first reference was built from the data.",
                        " From a first reference built from the data instead, the fit ended ")}
#: ... for a sample that ``solver="auto"``'s explicit solver found stiff during the fit, fitted
#: again as a stiff model (:meth:`torchql.problem.Problem.stiff_variant`).
STIFF_REFIT = (" The explicit solver that solver=\"auto\" chose found the model stiff during the fit, which stopped "
               "there: ",
               "this fit is the stiff solver's (solver=\"rodas5p\").",
               " The explicit solver that solver=\"auto\" chose found the model stiff during the fit; fitted "
               "again by the stiff solver (solver=\"rodas5p\"), it ended ")


def fallback_rows(chunk: dict, fallback: str | None) -> tuple[list[int], set[int]]:
    """The rows of an engine's ``chunk`` to fit again from the other first reference ``fallback``
    (None: none): those that ended in :data:`FALLBACK_STATUSES` or ran out of ``max_iter`` after at
    least :data:`LONG_PATH` iterations, and those whose fit from the data
    succeeded above the model's own sum of squares at the guesses (``chunk["sse_guesses"]``, by
    more than :data:`GUESSES_MARGIN` of it: the data's reference led it to a worse optimum than
    where the guesses lay), or ran out of ``max_iter`` above it. Returns ``(rows, above)``, ``above``
    the latter, and the data-started successes after at least :data:`LONG_SUCCESS` iterations."""
    if not fallback:
        return [], set()
    # (out of max_iter after a long path: wandering, not on its way; a runaway of an initial state
    # along a direction the data barely see, which another start avoids)
    failed = {k for k, code in enumerate(chunk["status"]) if code in FALLBACK_STATUSES
              or code is Status.MAX_ITER and int(chunk["iterations"][k]) >= LONG_PATH}
    at_guesses = chunk.get("sse_guesses")
    above = set() if at_guesses is None else set(
        (at_guesses < (1 - GUESSES_MARGIN) * chunk["sse_end"]).nonzero().flatten().tolist())
    # a success from the data after a long path: its matched start lay far from where it ended, and
    # may have misled it (an oscillator sampled below its frequency, B = 80 guessed 64: 27 iterations
    # to B = 0.26 at 40 times the optimum's SSE, the guesses' own above both)
    iterations = chunk.get("iterations")
    if fallback == "integrate" and iterations is not None:
        above |= {k for k, code in enumerate(chunk["status"]) if code.success and int(iterations[k]) >= LONG_SUCCESS}
    return sorted(failed | above), above


def sse_at_guesses(engine, codes: list, sse: torch.Tensor, residuals: torch.Tensor,
                   iterations: torch.Tensor) -> torch.Tensor:
    """The model's own sums of squares ``(S,)`` at the guesses (integrated loosely) of the
    ``engine``'s samples whose fit from a data-built first reference succeeded, or ran out of
    ``max_iter`` (a spline across a gap of 16 periods led an oscillator fitted from its true
    coefficients to 750 times their sum of squares, still moving), with a systematic misfit (weighted
    residuals ``residuals (S, T K)`` whose neighbours in time correlate, :data:`MISFIT_CORRELATION`,
    above the integration's error) or after a long path (``iterations (S,)`` at least
    :data:`LONG_PATH`: the matched start lay far from where it ended), or with a sum of squares far
    above the data's known sigmas allow (:data:`KNOWN_SIGMA_MISFIT`), where ``"auto"`` may fit
    them again from the integrated guesses; NaN elsewhere. (Integrating every fit's guesses cost
    a quarter of a small fit's time.) A fit that ends above it ended worse than where it could have
    started: the data's reference misled it (a spline across a gap of several periods of an
    oscillation, or through an oscillation sampled below its frequency), and
    its fallback (:func:`fallback_rows`) fits it again from the integrated guesses."""
    spec = engine.spec
    out = torch.full_like(sse, float("nan"))
    if engine.start != "data" or spec.start_fallback != "integrate" or spec.sigma_function is not None:
        return out
    S = sse.shape[0]
    ended = torch.tensor([c.success or c is Status.MAX_ITER for c in codes], dtype=torch.bool, device=sse.device)
    e = residuals.nan_to_num(0.0).reshape(engine.y.shape)  # (S, T, K), zero where missing
    lag = (e[:, 1:] * e[:, :-1]).sum(dim=(1, 2)) / e.square().sum(dim=(1, 2)).clamp_min(torch.finfo(e.dtype).tiny)
    floor = engine._integration_floor(torch.arange(S, device=sse.device), engine.w.reshape(S, -1))
    white = 3 / engine.L.to(lag.dtype).clamp_min(1).sqrt()  # three standard deviations of white noise's
    correlated = lag.abs() > torch.clamp(white, min=MISFIT_CORRELATION)
    misfit = (sse > KNOWN_SIGMA_MISFIT * engine.L.to(sse.dtype)) & (spec.sigma_known and not spec.sigma_estimated)
    suspect = (correlated & (sse > MISFIT_FLOOR * floor)) | (iterations >= LONG_PATH) | misfit
    rows = (ended & suspect).nonzero().flatten()
    if not rows.numel():
        return out
    z0 = engine.z0_guess[rows]
    try:  # a check, not the fit: within the fit's time budget, and on bounded steps (see GUESSES_STEPS)
        with until(getattr(engine, "deadline", None)):
            traj, errors = engine._nonlinear(rows, z0, loose=True, max_steps=GUESSES_STEPS * max(engine.G - 1, 1),
                                             guess=z0.unsqueeze(1).expand(rows.numel(), engine.G, -1))
    except TimeBudgetExceeded:
        return out
    value = engine._objective(rows, traj, engine.w[rows].reshape(rows.numel(), -1), torch.zeros_like(sse[rows]))
    failed = torch.tensor([e is not None for e in errors], dtype=torch.bool, device=sse.device)
    out[rows] = torch.where(failed, torch.full_like(value, float("nan")), value)
    return out


def keep_the_better_fit(chunk: dict, rows: list[int], other: dict, second: str | tuple = "integrate",
                        above: set[int] = frozenset()) -> list[int]:
    """Rows ``rows`` of the engine's ``chunk`` against ``other`` (the same samples fitted again, in
    that order: from the ``second`` first reference, ``"integrate"`` or ``"data"``, ``chunk``'s
    from the other one; or ``second`` the words of another second fit, as :data:`START_WORDS`'
    values, :data:`STIFF_REFIT`): each keeps the better fit (a success over a failure, else the lower sum of
    squares, a finite one over NaN; where neither has a sum of squares, one cut short by ``max_time``:
    the fit did not finish), its message saying what the other start gave. With a likelihood
    (estimated sigmas), the sums of squares compared are its objectives (``sse_end``): each
    fit's own sigmas make its sum of squares the number of values. The rows in ``above``
    (:func:`fallback_rows`) succeeded above the sum of squares at their guesses: there a success of
    the other start with a lower one wins. Updates ``chunk`` in place; returns the rows the second
    fit won."""
    S = len(chunk["status"])
    said = START_WORDS[second] if isinstance(second, str) else second
    won = []
    for j, k in enumerate(rows):
        first, end = chunk["status"][k], other["status"][j]
        sse_first, sse_second = float(chunk["sse"][k]), float(other["sse"][j])
        lower = float(other["sse_end"][j]) < float(chunk["sse_end"][k])
        unknown = sse_first != sse_first and sse_second != sse_second
        wins = not first.success and (end.success or lower
                                      or (sse_first != sse_first and sse_second == sse_second)
                                      or (unknown and end is Status.MAX_TIME))
        guesses = float(chunk["sse_guesses"][k]) if "sse_guesses" in chunk else math.nan
        by_guesses = guesses < (1 - GUESSES_MARGIN) * float(chunk["sse_end"][k])  # (else by its long path)
        clearly = by_guesses or float(other["sse_end"][j]) < (1 - GUESSES_MARGIN) * float(chunk["sse_end"][k])
        wins = wins or (k in above and end.success and lower and clearly)
        worse = ("" if k not in above else f", above the model's own at the guesses ({guesses:.6g})" if by_guesses
                 else f", after {int(chunk['iterations'][k])} iterations")
        if wins:
            for key, value in chunk.items():
                if isinstance(value, list) or (isinstance(value, torch.Tensor) and value.shape[:1] == (S,)):
                    value[k] = other[key][j]
            chunk["message"][k] += said[0] + f"{first.name} (SSE {sse_first:.6g}{worse}); " + said[1]
            won.append(k)
        else:
            chunk["message"][k] += said[2] + f"{end.name} (SSE {sse_second:.6g})."
    return won


#: :func:`slopes`: a difference is widened to the next neighbours while its span is below this
#: fraction of theirs (nodes that nearly coincide).
CLUSTER_RATIO = 1e-3
#: :func:`slopes`: the most neighbours on either side a difference is widened to.
MAX_WIDENING = 6


def slopes(grid: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """Node slopes of values ``z (G, M)`` on ``grid (G,)`` (zeros on a one-node grid).

    Central differences over the two neighbours, ``(z[i+1] - z[i-1]) / (t[i+1] - t[i-1])``, and
    over the first and last two intervals at the ends: where an observation time falls a hair
    from a uniform node, the grid has an interval of ~1e-15, over which a one-interval difference
    (or the second-order non-uniform formula) is round-off divided by that interval (slopes of
    1e12 that ruined the gradient matching). Where even the two intervals nearly vanish (a node
    with a neighbour a hair away on each side: a held input's switch, whose grid nodes lie 1e-8
    on either side of it, at an observation time), the difference is taken over the next
    neighbours, ``k`` on each side, for the first ``k`` whose span is at least
    :data:`CLUSTER_RATIO` of the next one's: a difference of values derived from the data across
    2e-8 made a slope of 3e6 that set the gradient matching's coefficients 1e5 times too large.
    """
    G = grid.shape[0]
    if G == 1:
        return torch.zeros_like(z)
    if G == 2:
        return ((z[1] - z[0]) / (grid[1] - grid[0])).expand_as(z).clone()
    span = grid[2:] - grid[:-2]
    wider = torch.cat([(grid[4] - grid[0]).reshape(1), grid[4:] - grid[:-4], (grid[-1] - grid[-5]).reshape(1)])
    if G < 5 or bool((span >= CLUSTER_RATIO * wider).all()):  # no cluster: over two intervals each
        out = torch.empty_like(z)
        out[1:-1] = (z[2:] - z[:-2]) / span.unsqueeze(-1)
        out[0] = (z[2] - z[0]) / span[0]
        out[-1] = (z[-1] - z[-3]) / span[-1]
        return out
    node = torch.arange(G, device=grid.device)
    left, right = [], []
    for k in range(1, MAX_WIDENING + 2):  # the window of k neighbours on each side, shifted inside at the ends
        lo = (node - k).clamp(min=0).clamp(max=max(G - 1 - 2 * k, 0))
        left.append(lo)
        right.append((lo + 2 * k).clamp(max=G - 1))
    left, right = torch.stack(left), torch.stack(right)  # (K + 1, G)
    span = grid[right] - grid[left]
    wide = span[:-1] >= CLUSTER_RATIO * span[1:]
    wide[-1] = True
    k = wide.to(torch.int8).argmax(dim=0)  # the first wide enough
    lo, hi = left.gather(0, k.unsqueeze(0))[0], right.gather(0, k.unsqueeze(0))[0]
    return (z[hi] - z[lo]) / (grid[hi] - grid[lo]).unsqueeze(-1)


def data_reference(system, grid: torch.Tensor, ends: list[int], t_obs: torch.Tensor, y: torch.Tensor,
                   sigma: torch.Tensor, rows_mask: torch.Tensor, observed_states: list, z0: torch.Tensor,
                   unknown_index: torch.Tensor, bounds, rcond: float
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The first reference of ``S`` samples, built from their data.

    Parameters
    ----------
    system : AugmentedSystem
    grid : Tensor ``(G,)`` shared, or ``(S, G)`` per sample
        The storage grid; sample ``s`` uses its first ``ends[s]`` nodes (the others pad it).
    ends : list of int
        The number of nodes of each sample's grid.
    t_obs : Tensor ``(T,)`` or ``(S, T)``; y, sigma : Tensor ``(S, T, K)``; rows_mask : bool Tensor ``(S, T, K)``
        The data, their standard deviations, and which values are used.
    observed_states : list
        For each output, the state it reads directly (``None`` otherwise).
    z0 : Tensor ``(S, M)``
        The guesses (states, then coefficients).
    unknown_index : Tensor ``(m,)`` of int; bounds : Bounds; rcond : float
        The unknowns, their bounds, and the rank threshold, for the gradient matching.

    Returns
    -------
    z_ref, z_dot : Tensor ``(S, G, M)``
        The references and their slopes at the nodes (a padding node repeats the sample's last
        node, with slope zero).
    z0 : Tensor ``(S, M)``
        The guesses with the coefficients from the gradient matching (where some state is observed).
    """
    S, M = z0.shape
    G = grid.shape[-1]
    z_ref = z0.unsqueeze(1).repeat(1, G, 1)
    observed = _measured_states(grid, ends, t_obs, y, sigma, rows_mask, observed_states, z_ref)
    z_dot = _node_slopes(grid, ends, z_ref)
    live = _live_nodes(ends, G, z0)
    for seen in sorted(set(observed)):  # samples that observe the same states derive the others alike
        rows = torch.tensor([s for s in range(S) if observed[s] == seen], device=z0.device)
        hidden = [i for i in range(system.n) if i not in seen]
        if seen and hidden:
            z_ref[rows] = _derive_hidden(system, grid if grid.dim() == 1 else grid[rows], z_ref[rows], z_dot[rows],
                                         list(seen), hidden)
            if grid.dim() == 2:
                _pad(z_ref, ends, rows.tolist())
            z_dot[rows] = _node_slopes(grid if grid.dim() == 1 else grid[rows], [ends[s] for s in rows.tolist()],
                                       z_ref[rows])
    matched = torch.tensor([bool(seen) for seen in observed], device=z0.device)
    if bool((unknown_index >= system.n).any()) and bool(matched.any()):
        rows = matched.nonzero().flatten()
        p = _match_slopes(system, grid if grid.dim() == 1 else grid[rows], live[rows], z_ref[rows], z_dot[rows],
                          z0[rows], unknown_index, bounds, rcond)
        z_ref[rows, :, system.n:] = p.unsqueeze(1)
        z0 = z0.clone()
        z0[rows, system.n:] = p
    return z_ref, z_dot, z0


def _measured_states(grid, ends, t_obs, y, sigma, rows_mask, observed_states, z_ref) -> list[tuple[int, ...]]:
    """Sets the states that outputs read directly in ``z_ref (S, G, M)`` to their smoothed data,
    interpolated on each sample's grid nodes (its padding repeating its last node); returns, per
    sample, the states so set. Samples on the shared grid and times, with every value of an
    output used and the same weights, are smoothed and interpolated together; the others, each on
    its own times, are smoothed together by their number of values (:func:`smooth_each`)."""
    S = z_ref.shape[0]
    seen: list[list[int]] = [[] for _ in range(S)]
    for k, i in enumerate(observed_states):
        if i is None:
            continue
        ok, w = rows_mask[:, :, k], sigma[:, :, k] ** -2
        together = torch.zeros(S, dtype=torch.bool, device=z_ref.device)
        if grid.dim() == 1 and t_obs.dim() == 1:
            full = ok.all(dim=1)
            first = int(full.nonzero()[0, 0]) if bool(full.any()) else 0
            together = full & (w == w[first]).all(dim=1)
        rows = together.nonzero().flatten()
        if rows.numel():
            values = smooth(t_obs, y[rows, :, k].T, w[rows[0]])  # (T, R)
            z_ref[rows, :, i] = interpolate(t_obs, values, grid).T
        some = ok.any(dim=1).tolist()
        alone = (~together & ok.any(dim=1)).nonzero().flatten()
        counts = ok[alone].sum(dim=1)
        for count in counts.unique().tolist():  # each on its own times, smoothed together by length
            rows = alone[counts == count]
            times = t_obs.expand(ok.shape)[rows][ok[rows]].reshape(-1, count)
            values = smooth_each(times, y[rows, :, k][ok[rows]].reshape(-1, count), w[rows][ok[rows]].reshape(-1, count))
            nodes = grid.expand(S, grid.shape[-1])[rows]  # a padded grid's last nodes repeat its end
            z_ref[rows, :, i] = interpolate_each(times, values, nodes)
        for s in range(S):
            if some[s]:
                seen[s].append(i)
    if grid.dim() == 2:
        _pad(z_ref, ends, range(S))
    return [tuple(states) for states in seen]


def _pad(z_ref: torch.Tensor, ends: list[int], rows) -> None:
    """Each sample ``s`` in ``rows`` of ``z_ref (S, G, M)`` repeats its last node over its padding."""
    for s in rows:
        z_ref[s, ends[s]:] = z_ref[s, ends[s] - 1]


def _node_slopes(grid, ends, z_ref) -> torch.Tensor:
    """:func:`slopes` of ``z_ref (S, G, M)`` on each sample's own nodes (zero on its padding)."""
    S, G, M = z_ref.shape
    if grid.dim() == 1:
        return slopes(grid, z_ref.transpose(0, 1).reshape(G, S * M)).reshape(G, S, M).transpose(0, 1).contiguous()
    z_dot = torch.zeros_like(z_ref)
    for s in range(S):
        z_dot[s, : ends[s]] = slopes(grid[s, : ends[s]], z_ref[s, : ends[s]])
    return z_dot


def _live_nodes(ends: list[int], G: int, like: torch.Tensor) -> torch.Tensor:
    """``(S, G)``: 1 on each sample's own grid nodes, 0 on its padding."""
    return (torch.arange(G, device=like.device) < torch.tensor(ends, device=like.device).unsqueeze(1)).to(like.dtype)


def _match_slopes(system, grid, live, z_ref, z_dot, z0, unknown_index, bounds, rcond) -> torch.Tensor:
    """First coefficients ``(S, P)`` from the data's slopes: ``min_p sum_j ||(z'_j - f(t_j, z_j; p)) / s||^2``.

    With the trajectory fixed at the smoothed data, the coefficients enter only the right-hand
    side, so this small least-squares problem (gradient matching) needs no integration and does
    not depend on how poor the guesses are. Damped Gauss–Newton steps from the guesses solve it
    (bounds honoured), every sample with its own damping: a step that lowers a sample's cost is
    kept (damping / 10), one that does not is retried with more damping; a sample stops after
    :data:`MATCH_STEPS` kept steps, a step below :data:`MATCH_XTOL` (kept, or undamped: the
    Gauss–Newton step at a stationary point), a change of cost below :data:`MATCH_FTOL`, or
    damping past its limit. Each evaluation gives the residuals and their Jacobian
    (:func:`torchql.linearize.node_jacobian`). ``s`` scales each state's slopes to unit size;
    padding nodes (``live`` 0) do not count.
    """
    n = system.n
    S = z0.shape[0]
    scale = (z_dot[:, :, :n].abs() * live.unsqueeze(-1)).amax(dim=1)
    scale = torch.where(scale > 0, scale, torch.ones_like(scale))

    def slope(p, t, z):
        return system.rhs(t, z[:n], p)

    G = z_ref.shape[1]
    times = (grid.expand(S, G) if grid.dim() == 1 else grid).reshape(-1)
    nodes = z_ref.reshape(S * G, -1)
    weight = (live.unsqueeze(-1) / scale.unsqueeze(1)).reshape(S, G * n)  # 1 / s on live nodes, 0 on padding
    target = z_dot[:, :, :n].reshape(S, G * n)
    m_states = int((unknown_index < n).sum())
    est = unknown_index[m_states:] - n  # the estimated coefficients among p (not the per-sample constants)

    def residuals_and_jacobian(p):
        value, (J,) = node_jacobian(slope, (p.repeat_interleave(G, dim=0), times, nodes), (0,), n)
        r = (value.reshape(S, G * n) - target) * weight
        return r, J[:, :, est].reshape(S, G * n, -1) * weight.unsqueeze(-1)

    u = z0[:, unknown_index].clone()
    p = z0[:, n:].clone()
    with torch.no_grad():
        r, J = residuals_and_jacobian(p)
        cost = r.square().sum(dim=1)
        running = torch.isfinite(cost)
        damping = torch.zeros(S, dtype=p.dtype, device=p.device)
        kept = torch.zeros(S, dtype=torch.long, device=p.device)
        while bool(running.any()):
            check_time()
            Jq = J * bounds.derivative(u)[:, m_states:].unsqueeze(1) if bounds.active else J
            alpha, _, _ = solve_update_batch(Jq, -r, torch.ones_like(r), rcond, damping)
            step = torch.cat([torch.zeros(S, m_states, dtype=u.dtype, device=u.device), alpha.nan_to_num(0.0)], dim=1)
            change, _ = bounds.step(u, step)
            p_new = p.index_add(1, est, change[:, m_states:])
            r_new, J_new = residuals_and_jacobian(p_new)
            new_cost = r_new.square().sum(dim=1)
            better = running & torch.isfinite(new_cost) & (new_cost < cost) & torch.isfinite(alpha).all(dim=1)
            # A small step is the end when it was kept, or undamped: the Gauss–Newton step of a
            # stationary point (a linear problem's second step), which round-off may not let lower the cost.
            small = (change.abs() <= MATCH_XTOL * (u.abs() + 1e-300)).all(dim=1) & (better | (damping == 0))
            flat = torch.isfinite(new_cost) & ((cost - new_cost).abs() <= MATCH_FTOL * cost)
            keep = better.unsqueeze(1)
            p, u = torch.where(keep, p_new, p), torch.where(keep, u + change, u)
            r, cost = torch.where(keep, r_new, r), torch.where(better, new_cost, cost)
            J = torch.where(better.view(S, 1, 1), J_new, J)
            kept += better.long()
            worse = running & ~better
            damping = torch.where(better, damping / 10, damping)
            damping = torch.where(worse, torch.where(damping == 0, torch.full_like(damping, _DAMPING_START),
                                                     10 * damping), damping)
            running &= ~small & ~flat & (kept < MATCH_STEPS) & (damping <= _DAMPING_MAX)
    return p


def _derive_hidden(system, grid, z_ref, z_dot, observed: list[int], hidden: list[int]) -> torch.Tensor:
    """Unobserved states at every node of ``S`` samples, from the model: ``min ||x_o' - f_o(x_o, x_h)||`` over ``x_h``.

    Where the observed states' equations involve the hidden ones (``y' = v`` gives ``v``
    from the smoothed ``y``), a few vectorized Gauss–Newton steps from the guess ``x0``
    find them at each node; nodes where this does not lower the mismatch, or becomes
    non-finite, keep the guess. ``grid (G,)`` or ``(S, G)``; ``z_ref, z_dot (S, G, M)``.
    """
    S, G, M = z_ref.shape
    obs = torch.tensor(observed, device=z_ref.device)
    hid = torch.tensor(hidden, device=z_ref.device)
    times = (grid.expand(S, G) if grid.dim() == 1 else grid).reshape(-1)
    z, zd = z_ref.reshape(S * G, M), z_dot.reshape(S * G, M)

    def mismatch(xh, t, z, zd):
        return system.f(t, z.index_put((hid,), xh))[obs] - zd[obs]

    def residuals_and_jacobian(xh, t, z, zd):
        r, (J,) = node_jacobian(mismatch, (xh, t, z, zd), (0,), len(observed))
        return J, r

    xh = z[:, hid].clone()
    with torch.no_grad():
        J, r = residuals_and_jacobian(xh, times, z, zd)
        best = r.square().sum(-1)
        for _ in range(DERIVE_STEPS):
            check_time()
            trial = xh - _least_squares_step(J, r)
            J_trial, r_trial = residuals_and_jacobian(trial, times, z, zd)
            norm = r_trial.square().sum(-1)
            better = torch.isfinite(norm) & (norm < best)
            if not bool(better.any()):  # nothing moved: every later step would repeat this one
                break
            xh = torch.where(better.unsqueeze(-1), trial, xh)
            r = torch.where(better.unsqueeze(-1), r_trial, r)
            J = torch.where(better.view(-1, 1, 1), J_trial, J)
            best = torch.where(better, norm, best)
    out = z.clone()
    out[:, hid] = xh
    return out.reshape(S, G, M)


def _least_squares_step(J: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
    """The minimum-norm least-squares solutions ``(N, h)`` of ``J d = r`` at ``N`` nodes (``J (N, k, h)``,
    ``r (N, k)``; singular values below ``1e-8`` of the largest dropped). One unknown (a hidden
    velocity, the common case) in closed form: ``pinv``'s batched SVD of ``10^5`` one-by-one matrices
    costs 70 ms, this 1 ms."""
    if J.shape[-1] == 1:
        column = J[..., 0]
        norm2 = column.square().sum(dim=-1)
        return torch.where(norm2 > 0, (column * r).sum(dim=-1) / torch.where(norm2 > 0, norm2, 1.0),
                           torch.zeros_like(norm2)).unsqueeze(-1)
    return (torch.linalg.pinv(J, rtol=1e-8) @ r.unsqueeze(-1)).squeeze(-1)
