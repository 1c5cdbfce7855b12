"""``fit``: identify an ODE model's coefficients and initial state by quasilinearization.

The loop (one per iteration):

1. propagate the particular and homogeneous solutions about the current reference
   (``method="kantorovich"``: the stored superposed trajectory; ``method="shooting"``: the
   nonlinear solution from the current initial estimate, with its variational equations);
2. form the rows ``C_k = H_k Z(t_k)`` and ``d_k = y_k - h(z_n(t_k)) - H_k (z0(t_k) - z_n(t_k))``;
3. solve for ``alpha`` (weighted least squares, exact rows met exactly);
4. update ``z(t0) <- z0(t0) + Z(t0) alpha`` (and, for Kantorovich, the stored trajectory);
5. stop when the scaled ``alpha`` (the relative change of the estimates) falls below ``xtol``,
   or the SSE stops changing, or after ``max_iter`` updates.

A final pass integrates the nonlinear model with its sensitivities at the estimates: the
reported SSE, residuals and Jacobian are those of the fitted model itself.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable, Sequence

import torch

from . import _checks
from .damping import Damping
from .schemes import Scheme
from .engine_run import run_engine
from .noise import run_with_noise
from .problem import Problem
from .model import ODEModel, _set_buffer
from .multi import experiment_result, stack_experiments
from .observations import Observations
from .options import METHODS, FitOptions, Limits, accepts_options, recorded_options
from .parameters import apply_parameters
from .result import FitError, FitResult, IterationRecord
from .propagators import LinearPropagator

__all__ = ["fit", "METHODS"]



@accepts_options
def fit(
    model: ODEModel,
    data: Observations,
    x0=None,
    *,
    params: Sequence[str] | None = None,
    fixed_x0: Sequence[str] | None = None,
    t0: float | None = None,
    method: str | Scheme = "kantorovich",
    bounds: dict | None = None,
    scale: dict | None = None,
    max_iter: int = 50,
    max_time: float | None = None,
    throw: bool = False,
    solver: str = "auto",
    rtol: float | None = None,
    atol: float | None = None,
    xtol: float | None = None,
    ftol: float | None = None,
    rcond: float | None = None,
    grid: int | str | torch.Tensor | None = None,
    initial_trajectory: str = "auto",
    max_steps: int | None = None,
    damping: str | Damping | None = "lm",
    linear_solver: "str | LinearPropagator | None" = None,
    callback: Callable[[IterationRecord], None] | None = None,
    conditions: Sequence[dict] | None = None,
    parameters: dict | None = None,
    x0_expr: dict | None = None,
    options: FitOptions | None = None,
) -> FitResult:
    """Fit the unknown coefficients and initial state of ``model`` to ``data``.

    Parameters
    ----------
    model : ODEModel
        The model; its coefficients' values (float buffers, and float ``nn.Parameter`` objects treated
        alike) are the initial guesses. Float32 or float64. Never modified.
    data : Observations or list of Observations
        Measurements; see :class:`torchql.Observations`. A list holds several experiments that
        share the coefficients, each with its own times and initial state, fitted as one problem
        (each experiment on its own normalized time ``(t - t0_e) / span_e``, see
        :mod:`torchql.multi`). ``x0`` is then ``(E, n_states)``, ``t0`` one time or one per
        experiment, ``fixed_x0`` (names, or one list of names per experiment) and state
        ``bounds`` apply to every experiment, ``conditions`` sets coefficients per experiment,
        and the result's ``x0`` is ``(E, n_states)`` (``result.predict(t, experiment=e)``).
    x0 : Tensor ``(n_states,)``, optional
        Initial-state guess at ``t0`` (exact values for the states in ``fixed_x0``). If
        omitted, every state must be observed directly at ``t0`` and the data are used. Its
        values are copied (a tensor that requires grad is read, not differentiated through).
    params : sequence of str, optional
        Coefficients to estimate. Default: every floating-point buffer and parameter not listed
        in the model's ``constants``. Vector and matrix coefficients are estimated element-wise.
    fixed_x0 : sequence of str, optional
        States whose initial value is known exactly (taken from ``x0``); they get no
        homogeneous solution and are honoured exactly.
    t0 : float, optional
        Time of the initial state; default the first observation time. May precede it.
    method : {"kantorovich", "shooting"} or torchql.schemes.Scheme
        ``"kantorovich"``: the Newton–Raphson–Kantorovich iteration of function space; the
        next linearization uses the stored superposed trajectory. ``"shooting"``:
        Gauss–Newton, re-integrating the nonlinear model with its variational equations. A
        :class:`torchql.schemes.Scheme` object (or a name registered by
        :func:`torchql.schemes.register_scheme`) is another scheme.
    bounds : dict, optional
        ``{name: (lower, upper)}`` with ``None`` for an open side, e.g. ``{"k": (0.0, None)}``.
        A name is a coefficient (a vector or matrix buffer's name bounds every element; an
        element is named like ``"W[0,1]"``) or a state (its initial value, also ``"x(t0)"``).
        Bounded unknowns are iterated in a transformed variable (logarithmic for one-sided
        bounds, logistic for two-sided), so every iterate stays strictly inside; estimates,
        covariance and reports are in the user's units, and an estimate that ends at a bound is
        named in the message. A guess on a bound or outside it (a rate guessed 0 with
        ``(0.0, None)``) is moved inside, to where one capped step of the transformed variable
        reaches the unknown's scale: to ``bound + 1e-3 * max(1, |bound|)`` (``bound - ...`` for an
        upper bound), or to ``1e-3`` of the width inside the nearer of two bounds (see
        :mod:`torchql.bounds`). The result's ``moved_guesses`` and message name each moved
        guess and where it went; the model and ``x0`` keep their values.
    scale : dict, optional
        ``{name: "lin" | "log" | "log10"}`` (names as in ``bounds``): the unknowns to iterate on a
        logarithmic scale (``"log"`` and ``"log10"`` iterate alike), for positive rates spanning
        decades. The step is then a relative change (capped at a factor 1000), the unknown stays
        positive, its ``bounds`` apply to its logarithm, and its confidence interval is that of
        its logarithm mapped back (``result.log_scaled`` names them). Its guess must be positive.
    max_iter : int
        Maximum number of updates.
    max_time : float, optional
        Wall-clock budget in seconds, checked between iterations and inside long phases (every
        right-hand-side evaluation of an integration). When it runs out the fit ends with
        ``Status.MAX_TIME`` and the last accepted estimates, without the final evaluation (its
        ``sse``, residuals and covariance are NaN; ``history`` holds the last iterate's SSE).
        Default: none.
    throw : bool
        Raise :class:`torchql.FitError` instead of returning an unsuccessful result.
    solver : str
        Nonlinear integrator: ``"auto"`` (default), a torchdiffeq method (``torchql.SOLVER_NAMES``),
        ``"dop853"`` (Hairer's eighth-order Dormand–Prince pair, torchql's own batched integrator,
        :mod:`torchql.rk_pairs`; ``"dopri5"`` is the fifth-order one, likewise batched) or
        ``"rodas5p"`` for stiff models (:mod:`torchql.solvers`: implicit, L-stable; every
        nonlinear pass uses it, none goes through the explicit grid solver, and the storage grid
        gains geometric nodes after ``t0``, :func:`torchql.grid.make_grid`). ``"auto"`` takes
        ``"rodas5p"`` when the model is stiff on the data's span (:mod:`torchql.stiffness`: the
        Jacobian's fastest decay rate times the span, along the data, above ``1e4``), else
        ``"dop853"`` (``"dopri5"`` with ``linear_solver="torchdiffeq"``, which integrates with
        torchdiffeq); ``result.solver_options["solver"]`` says which. A fit on ``"dop853"`` whose model
        becomes stiff as the estimates move (the explicit pair's stiffness test, or the same test
        as along the data along an accepted iterate) stops, and is fitted again as ``"auto"`` fits
        a stiff model (:mod:`torchql.engine_run`), the better fit kept.
    rtol, atol : float, optional
        Integrator tolerances; default ``1e-10``/``1e-12`` in float64, ``1e-6``/``1e-8`` below.
    xtol : float, optional
        Convergence when ``max_i |alpha_i| / max(|u_i|, s_i) <= xtol`` (``u`` the unknowns, ``s``
        their typical magnitude: the largest ``|x_i(t)|`` of the first trajectory for states,
        the guess for coefficients). Default ``max(1e-8, 100 * rtol)``.
    ftol : float, optional
        Convergence also when the SSE changes by less than ``ftol`` relative (and the scaled
        update is below ``sqrt(xtol)``). Default ``max(1e-12, rtol)`` in float64, ``max(1e-6, rtol)``
        below: the SSE of an integrated model is not known more closely than the integration.
    rcond : float, optional
        Relative singular-value threshold below which a direction of the unknowns counts as
        not identifiable. Default ``max(min(1e3 * rtol, sqrt(rtol)), 1e3 * eps)``.
    grid : int, "auto", "smooth" or Tensor, optional
        Kantorovich's storage grid: the number of uniform intervals over ``[t0, t_last]``, or
        extra times to include (with 1000 uniform intervals; times outside ``(t0, t_last)`` lie
        outside the integration and are not nodes). Observation times and ``t0`` are
        always nodes. ``"auto"`` (default, also ``None``): each dataset's own count, 20 to 1000,
        chosen from its first reference (built on 100 intervals): the fewest whose cubic Hermite
        interpolation of the model's solutions through it stays within ``sqrt(rtol) / 16`` of the
        states (:mod:`torchql.engine_grid`); a stiff model's grid has geometric early nodes besides,
        and its count (20 to 100, more only where half the probe's is far off) is the fewest that
        interpolates the first reference's values at the probe's nodes within that bound (a
        reference built from the data keeps the probe's 100). On any grid the final pass takes the Gauss–Newton steps on the model itself
        that the grid's interpolation error leaves (:mod:`torchql.engine_final`).
        ``"smooth"``: as few intervals as the guesses' integrated trajectories need for their
        interpolation to stay within a sixteenth of the tolerance (:func:`torchql.grid.smooth_intervals`;
        the largest any sample needs in ``fit_many``).
    initial_trajectory : {"auto", "integrate", "data"}
        The first reference. ``"auto"`` (default): ``"data"`` where the data can give
        it, else ``"integrate"`` (:func:`torchql.data_start.first_reference`: shooting, no state
        measured directly at four or more times, unmeasured states that only the unknown
        coefficients would give, a stiff model, ``max_iter=0``); a fit from the data that ends
        ``DIVERGED``, ``INTEGRATION_FAILED``, ``STALLED`` or ``NOT_IDENTIFIABLE`` is run again
        from the integrated guesses and the better of the two kept, its message saying so (and
        the other way round where only the stiffness chose the integrated guesses).
        ``"integrate"``: the nonlinear model integrated from the guesses (the thesis' start;
        its first iterate is the guesses). ``"data"``: built from the data, so that no
        integration from poor guesses is needed: directly
        observed states smoothed (a discrete smoothing spline, its smoothing chosen by
        generalized cross-validation; see :mod:`torchql.smoothing`) and interpolated;
        unobserved states derived from the model where the observed states' equations
        involve them (at each node, the values that best reproduce the smoothed observed
        slopes), otherwise held at ``x0``; and the first coefficients fitted to that
        trajectory's slopes (gradient matching: a least-squares problem without integration,
        solved from the guesses), so that the iteration starts near the optimum whatever
        the guesses were. Shooting, whose iterates solve the model, starts from the model
        integrated from those coefficients and the data's own initial states (that
        trajectory at ``t0``).
    max_steps : int, optional
        Step budget of the adaptive solver integrating the nonlinear model, per interval between
        grid nodes: trial steps, accepted or not, as torchdiffeq counts them per output time (the
        batched ``"dop853"`` and ``"dopri5"`` count alike); exceeding it is
        INTEGRATION_FAILED.
        It caps the grid solver's RK4 steps per interval too (see ``linear_solver``).
    damping : {"lm", None} or torchql.damping.Damping
        ``"lm"`` (default): globalized by Levenberg–Marquardt damping. The undamped
        quasilinearization step is always tried first and kept when it lowers the sum of
        squares (so near the optimum the iteration is the thesis' one, quadratically
        convergent); otherwise, or when its trajectory cannot be integrated, the step is
        damped until it does. ``None``: the undamped iteration of the thesis, step for step.
        A :class:`torchql.damping.Damping` object sets the strategy itself, e.g.
        ``LevenbergMarquardt(start=1e-2)``.
    linear_solver : str or torchql.propagators.LinearPropagator, optional
        How the linear (particular and homogeneous) system is propagated over the grid: one of
        ``torchql.LINEAR_SOLVERS``. Default: ``"radau"`` with a stiff ``solver``, else
        ``"taylor"``. ``"taylor"``: every grid interval's transfer
        matrix at once from its Taylor series (exact for the interpolated coefficients, summed
        to a bounded truncation error), composed by a parallel prefix scan; ``"rk4_doubling"``:
        the same transfers by RK4 with step-doubling error control. With either, the nonlinear
        model too is solved on the grid (every interval at once by RK4, the nodes matched by
        Newton's method, :mod:`torchql.grid_solve`) wherever a prediction of its trajectory is at
        hand (the first reference, trial steps, the final pass), falling back to ``solver``.
        ``"torchdiffeq"``: the intervals' transfers integrated by torchdiffeq with ``solver``,
        which integrates the nonlinear model too. ``"radau"`` (stiff models: Radau IIA
        collocation, stable at every stiffness) and ``"exponential"`` (the matrix exponential of
        frozen coefficients plus a Radau correction: exact for constant coefficients, fails at
        intermediate stiffness): the nonlinear passes then use ``solver``. ``"rodas5p"``: as
        ``"radau"``, but where the reference is the model's own solution (``method="shooting"``,
        every fit's final pass) its sensitivities are integrated with it by Rodas5P on the
        solution's adaptive steps (:mod:`torchql.solvers.sensitivity`): for stiff models with fast
        jumps inside grid intervals (relaxation oscillations) or intermediate stiffness per
        interval, where the grid's transfers fail or need many substeps. A
        :class:`torchql.propagators.LinearPropagator` object is used as given (its ``grid_solver`` says whether the grid solver may be used).
    callback : callable, optional
        Called with each :class:`IterationRecord` as it is made.
    conditions : list of dict, optional
        With several experiments: one dict per experiment, ``{coefficient: value}``, the
        experiment's own value of a coefficient: a number (a constant of that experiment, such
        as a dose, or 0 to switch a reaction off) or another coefficient's name (a parameter of
        that experiment: ``{"k_mult": "s_high"}`` in two experiments and ``{"k_mult": 1.0}`` in
        the others makes ``s_high`` an unknown that only those two determine). A coefficient
        that every experiment sets is not an unknown by default.
    parameters : dict, optional
        ``{name: torchql.Parameter(value, vary, min, max, scale) or number}`` for coefficients
        and states (:mod:`torchql.parameters`): each one's value, whether it is estimated, its
        bounds and scale in one place, written into ``params``, ``fixed_x0``, ``x0``, ``bounds``
        and ``scale`` (a name may not be given in both); with several experiments a state's
        value and role apply to every experiment.
    x0_expr : dict, optional
        ``{state: callable(values) -> scalar}``: initial states given as expressions of the other
        values (:mod:`torchql.initial_state`), e.g. ``{"S": lambda v: v["N"] - v["I"]}``: ``values``
        holds the coefficients and the initial states by name. Such a state is neither an unknown
        nor fixed: it follows the estimates (its value in ``x0`` is ignored). With several
        experiments it applies to each, with that experiment's values.
    options : FitOptions, optional
        The options as one object (:class:`torchql.FitOptions`: method, solvers, damping, grid,
        limits and tolerances), to reuse across fits; a keyword left at its default takes the
        field's value, and one given both ways with different values is an error.

    Returns
    -------
    FitResult

    Raises
    ------
    TypeError, ValueError
        For invalid arguments (the message names the argument, what was expected and received).
    FitError
        When ``throw=True`` and the fit does not converge.
    """
    started = time.monotonic()  # max_time counts from here: the problem's set-up (stiffness test) too
    if callback is not None and not callable(callback):
        raise TypeError(f"`callback` must be callable (it receives each IterationRecord); received {callback!r}")
    throw = _checks.flag("throw", throw)
    _checks.single_observations("data", data)
    if parameters is not None:
        _checks.model_class(model)
        rows = len(data) if isinstance(data, (list, tuple)) else None
        spec = apply_parameters(model, parameters, x0=x0, params=params, fixed_x0=fixed_x0, bounds=bounds,
                                scale=scale, x0_expr=x0_expr, rows=rows, conditions=conditions)
        model, x0, params, fixed_x0, bounds, scale, x0_expr = (
            spec[k] for k in ("model", "x0", "params", "fixed_x0", "bounds", "scale", "x0_expr"))
    if isinstance(data, (list, tuple)):
        return _fit_experiments(
            model, list(data), x0, params=params, fixed_x0=fixed_x0, t0=t0, method=method, bounds=bounds,
            scale=scale, x0_expr=x0_expr, max_iter=max_iter, max_time=max_time, throw=throw, solver=solver, rtol=rtol,
            atol=atol, xtol=xtol, ftol=ftol, rcond=rcond, grid=grid, initial_trajectory=initial_trajectory,
            max_steps=max_steps, damping=damping, linear_solver=linear_solver, callback=callback,
            conditions=conditions)
    if conditions is not None:
        raise ValueError("`conditions` applies to several experiments (`data` a list of Observations)")
    spec = _single_spec(model, data, x0, params, fixed_x0, t0, method, bounds, max_iter, solver, rtol, atol, xtol,
                        ftol, rcond, grid, initial_trajectory, max_steps, damping, linear_solver, scale, x0_expr)
    max_time = Limits.resolve(max_time=max_time).max_time
    batch = run_with_noise(spec, lambda problem: run_engine(
        problem, 1, max_time, lambda done: None, history=True,
        callback=None if callback is None else lambda sample, record: callback(record), started=started))
    result = batch.sample(0)
    result.index, result.method, result.data = None, spec.method, data
    result.fit_kwargs = recorded_options(
        x0=x0, params=params, fixed_x0=fixed_x0, t0=t0, method=method, max_iter=max_iter, max_time=max_time,
        solver=solver, rtol=rtol, atol=atol, xtol=xtol, ftol=ftol, rcond=rcond, grid=grid,
        initial_trajectory=initial_trajectory, max_steps=max_steps, damping=damping, linear_solver=linear_solver,
        bounds=bounds, scale=scale, x0_expr=x0_expr)
    if throw and not result.success:
        raise FitError(result)
    return result


def _single_spec(model, data, x0, params, fixed_x0, t0, method, bounds, max_iter, solver, rtol, atol, xtol, ftol,
                 rcond, grid, initial_trajectory, max_steps, damping="lm", linear_solver=None, scale=None,
                 x0_expr=None) -> Problem:
    """One dataset's validated problem: the engine's (:mod:`torchql.batch`) with one sample, its
    errors worded for ``fit``."""
    _checks.model_class(model)
    if not isinstance(data, Observations):
        raise TypeError(f"`data` must be a torchql.Observations or a list of them; received {type(data).__name__}")
    return Problem(model, [data], x0, params, None, fixed_x0, t0, max_iter, rtol, atol, xtol, ftol, rcond, grid,
                 damping, solver, max_steps, bounds, linear_solver, method, initial_trajectory, single=True,
                   scale=scale, x0_expr=x0_expr)


class _Problem:
    """One dataset's validated problem as plain attributes (for :func:`torchql.adjoint_fit`):
    ``system``, ``operator``, ``dtype``, ``device``, tolerances, ``solver``, ``t0 ()``,
    ``t_obs (T,)``, ``y (T, K)``, ``rows_mask (T, K)``, ``weights (L,)`` of the used values,
    ``z0 (M,)`` (the guesses), ``unknown_index``, ``unknown_names``."""

    def __init__(self, model, data, x0, params, fixed_x0, t0, method, bounds, max_iter, solver, rtol, atol, xtol,
                 ftol, rcond, grid, initial_trajectory, max_steps, damping="lm", linear_solver=None) -> None:
        if isinstance(data, (list, tuple)):
            raise TypeError(f"`data` must be one torchql.Observations: gradient fitting takes one experiment; received "
                            f"a {type(data).__name__} of {len(data)} (fit several experiments with torchql.fit)")
        spec = _single_spec(model, data, x0, params, fixed_x0, t0, method, bounds, max_iter, solver, rtol, atol,
                            xtol, ftol, rcond, grid, initial_trajectory, max_steps, damping, linear_solver)
        if spec.sigma_estimated:
            raise ValueError("`data` asks to estimate sigma (sigma='estimate'), which gradient fitting does not do: "
                             "give sigma, or fit with torchql.fit")
        if spec.sigma_function is not None:
            raise ValueError("`data` gives sigma as a function sigma(p) of the coefficients, whose likelihood "
                             "gradient fitting does not minimize: give sigma values, or fit with torchql.fit")
        self.system, self.operator, self.dtype, self.device = spec.system, spec.operator, spec.dtype, spec.device
        self.rtol, self.atol, self.rcond, self.solver = spec.rtol, spec.atol, spec.rcond, spec.solver
        self.t0, self.t_obs, self.data_t0 = spec.t0, spec.t_obs, spec.data_t0  # (local times: Problem.origin)
        self.rows_mask, self.y = spec.mask[0], spec.y[0]
        self.weights = spec.weights[0][self.rows_mask]
        self.z0 = spec.z0[0].clone()
        self.unknown_index, self.unknown_names = spec.unknown_index, list(spec.unknown_names)


def _fit_experiments(model, datasets: list, x0, *, params, fixed_x0, t0, bounds, scale, x0_expr, grid, throw,
                     callback, conditions, **options) -> FitResult:
    """Several experiments sharing the coefficients: the stacked problem of :mod:`torchql.multi`."""
    st = stack_experiments(model, datasets, x0, t0=t0, fixed_x0=fixed_x0, bounds=bounds, scale=scale,
                           x0_expr=x0_expr, grid=grid, conditions=conditions)
    result = fit(st.model, st.data, st.x0, params=params, fixed_x0=st.fixed_x0, t0=0.0, bounds=st.bounds,
                 scale=st.scale, grid=grid, x0_expr=st.x0_expr, throw=False, callback=callback, **options)
    experiment_result(result, model, st, datasets)
    fitted = copy.deepcopy(model)
    for name, value in result.params.items():
        _set_buffer(fitted, name, value)
    result.model = fitted
    result.fit_kwargs = recorded_options(x0=x0, params=params, fixed_x0=fixed_x0, t0=t0, grid=grid, bounds=bounds,
                                         scale=scale, x0_expr=x0_expr, conditions=conditions,
                                         **options)
    if throw and not result.success:
        raise FitError(result)
    return result
