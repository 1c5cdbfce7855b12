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
import math
import warnings
from collections.abc import Callable, Sequence

import torch

from . import _checks
from .bounds import Bounds, at_bound_note, moved_guesses_note, moved_record
from .budget import TimeBudgetExceeded, time_budget, time_left
from .integrate import CountedField, IntegrationError, check_solver, solve
from .solvers import STIFF_SOLVERS
from .stiffness import choose_solver, linear_solver_for
from .linearize import linearize
from .grid import make_grid
from .grid_solve import IntervalBudgetError, solve_on_grid
from .diagnosis import final_status, null_detail, typical_magnitudes
from .lstsq import ExactRowsError, solve_update
from .model import AugmentedSystem, ODEModel, _set_buffer, coefficient_names, coefficients, model_dtype_device
from .multi import StackedModel, experiment_state_name, stack_observations
from .observations import ObservationOperator, Observations
from .options import (DAMPING_MAX, DAMPING_MIN, DAMPING_START, METHODS, Limits, Tolerances,
                      check_damping, check_scheme)
from .data_start import data_reference
from .result import FitError, FitResult, IterationRecord, Status
from .propagators import LinearPropagator
from .superposition import DEFAULT_LINEAR_SOLVER, check_linear_solver, initial_columns, propagate_linear
from .uncertainty import covariance
from .trajectory import DEFECT_TRUST, LinearizedReference, model_defect

__all__ = ["fit", "METHODS"]



def fit(
    model: ODEModel,
    data: Observations,
    x0=None,
    *,
    params: Sequence[str] | None = None,
    fixed_x0: Sequence[str] | None = None,
    t0: float | None = None,
    method: str = "kantorovich",
    bounds: dict | None = None,
    max_iter: int = 50,
    max_time: float | None = None,
    throw: bool = False,
    solver: str = "auto",
    rtol: float | None = None,
    atol: float | None = None,
    xtol: float | None = None,
    ftol: float | None = None,
    rcond: float | None = None,
    grid: int | torch.Tensor | None = None,
    initial_trajectory: str = "integrate",
    max_steps: int | None = None,
    damping: str | None = "lm",
    linear_solver: "str | LinearPropagator | None" = None,
    callback: Callable[[IterationRecord], None] | None = None,
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
        experiment, ``fixed_x0`` and state ``bounds`` apply to every experiment, and the
        result's ``x0`` is ``(E, n_states)`` (``result.predict(t, experiment=e)``).
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
    method : {"kantorovich", "shooting"}
        ``"kantorovich"``: the Newton–Raphson–Kantorovich iteration of function space; the
        next linearization uses the stored superposed trajectory. ``"shooting"``:
        Gauss–Newton, re-integrating the nonlinear model with its variational equations.
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
        Nonlinear integrator: ``"auto"`` (default), a torchdiffeq method (``torchql.SOLVER_NAMES``)
        or ``"rodas5p"`` for stiff models (:mod:`torchql.solvers`: implicit, L-stable; every
        nonlinear pass uses it, none goes through the explicit grid solver, and the storage grid
        gains geometric nodes after ``t0``, :func:`torchql.grid.make_grid`). ``"auto"`` takes
        ``"rodas5p"`` when the model is stiff on the data's span (:mod:`torchql.stiffness`: the
        Jacobian's fastest decay rate times the span, along the data, above ``1e4``), else
        ``"dopri5"``; ``result.solver_options["solver"]`` says which.
    rtol, atol : float, optional
        Integrator tolerances; default ``1e-10``/``1e-12`` in float64, ``1e-6``/``1e-8`` below.
    xtol : float, optional
        Convergence when ``max_i |alpha_i| / max(|u_i|, s_i) <= xtol`` (``u`` the unknowns, ``s``
        their typical magnitude: the largest ``|x_i(t)|`` of the first trajectory for states,
        the guess for coefficients). Default ``max(1e-8, 100 * rtol)``.
    ftol : float, optional
        Convergence also when the SSE changes by less than ``ftol`` relative (and the scaled
        update is below ``sqrt(xtol)``). Default ``1e-12`` (float64), ``1e-6`` below.
    rcond : float, optional
        Relative singular-value threshold below which a direction of the unknowns counts as
        not identifiable. Default ``max(1e3 * rtol, 1e3 * eps)``.
    grid : int or Tensor, optional
        Kantorovich's storage grid: the number of uniform intervals over ``[t0, t_last]``
        (default 1000), or extra times to include. Observation times and ``t0`` are always nodes.
    initial_trajectory : {"integrate", "data"}
        Kantorovich's first reference: the nonlinear model integrated from the guesses, or
        built from the data, so that no integration from poor guesses is needed: directly
        observed states smoothed (a discrete smoothing spline, its smoothing chosen by
        generalized cross-validation; see :mod:`torchql.smoothing`) and interpolated;
        unobserved states derived from the model where the observed states' equations
        involve them (at each node, the values that best reproduce the smoothed observed
        slopes), otherwise held at ``x0``; and the first coefficients fitted to that
        trajectory's slopes (gradient matching: a least-squares problem without integration,
        solved from the guesses), so that the iteration starts near the optimum whatever
        the guesses were.
    max_steps : int, optional
        Step budget of the adaptive solver integrating the nonlinear model, per interval between
        grid nodes (torchdiffeq counts steps per output time); exceeding it is INTEGRATION_FAILED.
        It caps the grid solver's RK4 steps per interval too (see ``linear_solver``).
    damping : {"lm", None}
        ``"lm"`` (default): globalized by Levenberg–Marquardt damping. The undamped
        quasilinearization step is always tried first and kept when it lowers the sum of
        squares (so near the optimum the iteration is the thesis' one, quadratically
        convergent); otherwise, or when its trajectory cannot be integrated, the step is
        damped until it does. ``None``: the undamped iteration of the thesis, step for step.
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
        intermediate stiffness): the nonlinear passes then use ``solver``. A
        :class:`torchql.propagators.LinearPropagator` object is used as given (its ``grid_solver`` says whether the grid solver may be used).
    callback : callable, optional
        Called with each :class:`IterationRecord` as it is made.

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
    if callback is not None and not callable(callback):
        raise TypeError(f"`callback` must be callable (it receives each IterationRecord); received {callback!r}")
    _checks.single_observations("data", data)
    if isinstance(data, (list, tuple)):
        return _fit_experiments(
            model, list(data), x0, params=params, fixed_x0=fixed_x0, t0=t0, method=method, bounds=bounds,
            max_iter=max_iter, max_time=max_time, throw=throw, solver=solver, rtol=rtol, atol=atol, xtol=xtol,
            ftol=ftol, rcond=rcond, grid=grid, initial_trajectory=initial_trajectory, max_steps=max_steps,
            damping=damping, linear_solver=linear_solver, callback=callback)
    problem = _Problem(
        model, data, x0, params, fixed_x0, t0, method, bounds, max_iter, solver, rtol, atol, xtol, ftol,
        rcond, grid, initial_trajectory, max_steps, damping, linear_solver, max_time,
    )
    with time_budget(problem.max_time):
        result = problem.run(callback)
    result.data = data
    result.fit_kwargs = dict(
        x0=None if x0 is None else torch.as_tensor(x0).detach().clone(), params=None if params is None else list(params),
        fixed_x0=None if fixed_x0 is None else list(fixed_x0), t0=t0, method=method, max_iter=max_iter,
        max_time=max_time, solver=solver,
        rtol=rtol, atol=atol, xtol=xtol, ftol=ftol, rcond=rcond, grid=grid, initial_trajectory=initial_trajectory,
        max_steps=max_steps, damping=damping, linear_solver=linear_solver, bounds=None if bounds is None else dict(bounds),
    )
    if throw and not result.success:
        raise FitError(result)
    return result


class _Problem:
    """A validated fitting problem and its iteration."""

    def __init__(self, model, data, x0, params, fixed_x0, t0, method, bounds, max_iter, solver, rtol, atol,
                 xtol, ftol, rcond, grid, initial_trajectory, max_steps, damping="lm",
                 linear_solver=None, max_time=None):
        _checks.model_class(model)
        names = tuple(model.state_names)
        if not isinstance(data, Observations):
            raise TypeError(
                f"`data` must be a torchql.Observations or a list of them; received {type(data).__name__}")
        method, initial_trajectory = check_scheme(method, initial_trajectory)
        if not isinstance(solver, str):
            raise TypeError(f"`solver` must be a string; received {type(solver).__name__}")
        check_solver(solver, auto=True)
        self.damping = check_damping(damping)
        if linear_solver is not None:
            check_linear_solver(linear_solver)
        limits = Limits.resolve(max_iter, max_steps, max_time)
        max_iter, max_steps, self.max_time = limits.max_iter, limits.max_steps, limits.max_time

        self.dtype, self.device = model_dtype_device(model)
        dtype, device = self.dtype, self.device
        tol = Tolerances.resolve(dtype, rtol, atol, xtol, ftol, rcond)
        self.rtol, self.atol, self.xtol, self.ftol, self.rcond = tol.rtol, tol.atol, tol.xtol, tol.ftol, tol.rcond
        self.method, self.solver, self.max_iter, self.max_steps = method, solver, max_iter, max_steps
        self.initial_trajectory = initial_trajectory

        # --- unknown coefficients
        available = coefficient_names(model)
        if params is None:
            params = [name for name in available if name not in tuple(model.constants)]
        else:
            params = _checks.distinct_names("params", params, available, "buffer", _checks.coefficients_text(model))
        self.system = AugmentedSystem(model, params, dtype, device)
        system = self.system
        n = system.n

        # --- observations
        if torch.finfo(data.y.dtype).eps > torch.finfo(dtype).eps:
            warnings.warn(
                f"`data` holds {data.y.dtype} values but the model computes in {dtype}: the data's own "
                "rounding limits the fit's accuracy; build the Observations from float64 tensors",
                UserWarning, stacklevel=3,
            )
        self.t_obs = data.t.to(dtype=dtype, device=device)
        self.y = data.y.to(dtype=dtype, device=device)
        self.operator = ObservationOperator(data.observe, names, data.n_outputs, dtype, device)
        mask = data.mask.to(device)
        self.rows_mask = mask  # (T, K)
        self.weights = (1.0 / data.sigma.to(dtype=dtype, device=device))[mask]
        self.exact = data.exact.to(device)[mask]
        self.y_rows = self.y[mask]
        self.sigma_known = data.sigma_given
        self.sigma = data.sigma.to(dtype=dtype, device=device)  # (T, K)

        # --- times
        if t0 is None:
            self.t0 = self.t_obs[0].clone()
        else:
            self.t0 = torch.as_tensor(_checks.finite_number("t0", t0), dtype=dtype, device=device)
            if self.t0 > self.t_obs[0]:
                raise ValueError(
                    f"`t0` must not be later than the first observation time {self.t_obs[0].item():g}; received {float(t0):g}"
                )

        # --- initial state
        if x0 is None:
            x0 = self._x0_from_data(names)
        else:
            try:
                x0 = torch.as_tensor(x0, dtype=dtype, device=device).detach().clone()
            except (TypeError, ValueError) as exc:
                raise TypeError(f"`x0` must be a tensor of shape (n_states,) = ({n},); received {type(x0).__name__}") from exc
        if x0.shape != (n,):
            raise ValueError(f"`x0` must have shape (n_states,) = ({n},); received shape {tuple(x0.shape)}")
        if not torch.isfinite(x0).all():
            raise ValueError("`x0` must be finite; received NaN or inf")
        p0 = system.pack_params()
        if not torch.isfinite(p0).all():
            bad = [nm for nm, v in zip(system.element_names, p0.tolist()) if not math.isfinite(v)]
            raise ValueError(f"the guesses of {bad} (the model's buffers) must be finite")
        self.z0 = torch.cat([x0, p0])

        fixed_x0 = _checks.distinct_names("fixed_x0", [] if fixed_x0 is None else fixed_x0, names, "state",
                                          f"the model's states are {names}")
        free_states = [i for i, s in enumerate(names) if s not in fixed_x0]
        self.unknown_index = torch.tensor(free_states + list(range(n, system.M)), dtype=torch.long, device=device)
        self.unknown_names = [f"{names[i]}(t0)" for i in free_states] + system.element_names
        m = self.unknown_index.numel()
        if m == 0:
            raise ValueError("nothing to estimate: every initial state is in `fixed_x0` and `params` is empty")
        L = int(mask.sum())
        if L < m:
            raise ValueError(
                f"fewer usable observations ({L}) than unknowns ({m}: {self.unknown_names}); "
                "add observations, or fix some unknowns with `params=`/`fixed_x0=`"
            )
        if int(self.exact.sum()) > m:
            raise ValueError(
                f"more values are marked `exact` ({int(self.exact.sum())}) than there are unknowns ({m}); "
                "at most one exact value per unknown can be met"
            )

        # --- bounds (guesses on or outside a bound moved strictly inside; see Bounds.move_inside)
        self.bounds = Bounds.for_unknowns(bounds, self.unknown_names, len(free_states), system.param_names,
                                          system.param_sizes, list(names) + list(available), dtype, device)
        given = self.z0[self.unknown_index]
        used, moved = self.bounds.move_inside(given)
        self.moved_guesses = moved_record(self.unknown_names, given, used, moved)
        if self.moved_guesses:
            self.z0[self.unknown_index] = used
            x0 = self.z0[:n]
        self.u_guess = self.z0[self.unknown_index].clone()  # the guesses used, before any data-built start

        # --- the model and the observation operator on the guesses
        self._check_model(x0)
        self.operator.check(x0)

        # --- the solver ("auto": stiff or not along the data) and the grids
        self.solver = choose_solver(self.solver, system, self.t_obs,
                                    self.y.masked_fill(~self.rows_mask, float("nan")).unsqueeze(0),
                                    self.operator.observed_states, x0.unsqueeze(0), self.z0[n:].unsqueeze(0),
                                    (self.t_obs[-1] - self.t0).reshape(1))
        self.linear_solver = check_linear_solver(linear_solver_for(self.solver, linear_solver, DEFAULT_LINEAR_SOLVER))
        self.grid = make_grid(grid, self.t0, self.t_obs, stiff=self.solver in STIFF_SOLVERS)
        self.obs_in_grid = torch.searchsorted(self.grid, self.t_obs)
        self.nfev = 0

    # ------------------------------------------------------------------------------------
    def _x0_from_data(self, names) -> torch.Tensor:
        if self.t0 != self.t_obs[0]:
            raise ValueError("`x0` is required when `t0` precedes the first observation")
        direct = self.operator.observed_states
        x0 = torch.full((len(names),), float("nan"), dtype=self.dtype, device=self.device)
        for k, i in enumerate(direct):
            if i is not None and self.rows_mask[0, k]:
                x0[i] = self.y[0, k]
        if torch.isnan(x0).any():
            missing = [names[i] for i in range(len(names)) if torch.isnan(x0[i])]
            raise ValueError(f"`x0` is required: the states {missing} are not observed directly at t0")
        return x0

    def _check_model(self, x0: torch.Tensor) -> None:
        system = self.system
        p0 = self.z0[system.n:]
        _checks.model_forward(lambda t, x: system.rhs(t, x, p0), self.t0, x0, system.state_names,
                              dict(zip(system.element_names, p0.tolist())), self.dtype)
        try:
            linearize(self.system, self.t0.reshape(1), self.z0.unsqueeze(0))
        except Exception as exc:  # noqa: BLE001
            raise ValueError(
                "`model` forward could not be differentiated with torch.func (jacfwd and jvp under vmap): "
                f"{exc}. Avoid .item(), in-place updates of inputs and Python branching on tensor values."
            ) from exc

    # ------------------------------------------------------------------------------------
    def _rows(self, z_ref_obs, zp_obs, Z_obs):
        """Least-squares rows at the observations: ``C (L, m)``, ``d (L,)``, current residuals ``(L,)``."""
        n = self.system.n
        x_ref = z_ref_obs[:, :n]
        h_ref, H = self.operator.value_and_jacobian(x_ref)
        predicted = h_ref + torch.einsum("tkn,tn->tk", H, zp_obs[:, :n] - x_ref)
        C = torch.einsum("tkn,tnm->tkm", H, Z_obs[:, :n, :])
        mask = self.rows_mask
        return C[mask], (self.y - predicted)[mask], (self.y - h_ref)[mask]

    def _residual(self, z_obs: torch.Tensor) -> torch.Tensor:
        """Unweighted residuals ``y - h(x(t_k))`` of a trajectory at the observations: ``(L,)``."""
        value, _ = self.operator.value_and_jacobian(z_obs[:, : self.system.n])
        return (self.y - value)[self.rows_mask]

    def _sse(self, residual: torch.Tensor) -> float:
        r = residual * self.weights
        return float((r[~self.exact] ** 2).sum())

    def _merit(self, residual: torch.Tensor) -> float:
        """Weighted sum of squares plus ``_EXACT_PENALTY`` times the exact rows' squared misfit."""
        r = residual * self.weights
        return float((r[~self.exact] ** 2).sum() + _EXACT_PENALTY * (r[self.exact] ** 2).sum())

    def _record(self, iteration, z0, sse, trajectory_t=None, trajectory=None) -> IterationRecord:
        n = self.system.n
        params = {k: v.detach().clone() for k, v in self.system.unpack_params(z0[n:]).items()}
        return IterationRecord(
            iteration=iteration, params=params, x0=z0[:n].detach().clone(), sse=sse,
            trajectory=None if trajectory is None else trajectory.detach().clone(),
            trajectory_t=trajectory_t,
        )

    def _forward(self, z0: torch.Tensor, loose: bool = False, guess: torch.Tensor | None = None,
                 budget_is_final: bool = False) -> torch.Tensor:
        """The nonlinear model integrated from ``z0 (M,)`` over the grid: ``(G, M)``.

        Observation times are grid nodes the solver steps onto exactly. ``loose`` integrates
        at ``_LOOSE_RTOL`` (or ``rtol`` if looser): enough for a first reference trajectory,
        whose only role is to be linearized about.

        ``guess (G, >= n)``, a prediction of the solution at the nodes (the iterate's linear
        solution), lets the grid solver (:func:`~torchql.grid_solve.solve_on_grid`: every grid
        interval integrated at once, the nodes matched by Newton's method) replace the adaptive
        solver unless ``linear_solver="torchdiffeq"``. If Newton does not settle within
        ``_GRID_NEWTON`` iterations or an interval needs more than ``_GRID_SUBSTEPS`` steps
        (``_GRID_SUBSTEPS_LOOSE`` when ``loose``), the
        adaptive solver integrates as without a guess; with ``budget_is_final`` the latter is
        taken as the blow-up it nearly always is, and raised (a trial step: the adaptive solver
        would only crawl to the same failure, or through a stiff stretch that a step far from
        the current iterate led into; the damping shortens the step instead). Then an interval
        may take ``_BLOWUP_STEPS / (G - 1)`` steps if that is more, so that a coarse grid does
        not turn a smooth trial into a blow-up.
        """
        n = self.system.n
        counter = CountedField(self.system.model_with(z0[n:]))
        rtol = max(self.rtol, _LOOSE_RTOL) if loose else self.rtol
        atol = self.atol * rtol / self.rtol
        x = None
        substeps = _GRID_SUBSTEPS_LOOSE if loose else _GRID_SUBSTEPS
        intervals = self.grid.shape[0] - 1
        if budget_is_final and intervals > 0:
            substeps = max(substeps, 1 << max(0, (_BLOWUP_STEPS // intervals).bit_length() - 1))
        if self.max_steps is not None:  # the user's step budget per grid interval binds this solver too
            substeps = min(substeps, 1 << (self.max_steps.bit_length() - 1))
        with torch.no_grad():
            if (guess is not None and self.linear_solver.grid_solver and substeps >= 2
                    and self.solver not in STIFF_SOLVERS and bool(torch.isfinite(guess).all())):
                try:
                    x, _ = solve_on_grid(counter, z0[:n], self.grid, rtol=rtol, atol=atol, guess=guess[:, :n],
                                         max_newton=_GRID_NEWTON, max_substeps=substeps)
                except IntervalBudgetError:
                    if budget_is_final:
                        self.nfev += counter.n_evals
                        raise
                    x = None
                except IntegrationError:
                    x = None
            if x is None:
                x = solve(counter, z0[:n], self.grid, solver=self.solver, rtol=rtol, atol=atol,
                          hit=self.t_obs, max_steps=self.max_steps)
        self.nfev += counter.n_evals
        return torch.cat([x, z0[n:].expand(x.shape[0], -1)], dim=1)

    def _about_nonlinear(self, z0: torch.Tensor, z_traj: torch.Tensor) -> torch.Tensor:
        """Sensitivities along the nonlinear solution ``z_traj``: ``W (G, M, 1 + m)``, column 0 = ``z_traj``.

        The variational equations ``Z' = df/dz(z(t)) Z`` are the homogeneous part of the
        linearization about ``z_traj``, propagated on the grid like Kantorovich's system.
        """
        lin = linearize(self.system, self.grid, z_traj)
        reference = LinearizedReference(self.grid, z_traj, lin.f, lin)
        W, evals = propagate_linear(reference, initial_columns(z0, self.unknown_index), solver=self.solver,
                                    rtol=self.rtol, atol=self.atol, max_steps=self.max_steps,
                                    linear_solver=self.linear_solver)
        self.nfev += evals
        W = W.clone()
        W[:, :, 0] = z_traj
        return W

    def _initial_reference(self) -> LinearizedReference:
        system, grid = self.system, self.grid
        if self.initial_trajectory == "integrate":
            # from a constant guess: one Newton step when the states enter linearly, else a few
            z_ref = self._forward(self.z0, loose=True, guess=self.z0.expand(grid.shape[0], -1))
            lin = linearize(system, grid, z_ref)
            return LinearizedReference(grid, z_ref, lin.f, lin)
        z_ref, z_dot, self.z0 = data_reference(
            system, grid, self.t_obs, self.y, self.sigma, self.rows_mask, self.operator.observed_states, self.z0,
            self.unknown_index, self.bounds, self.rcond)
        return LinearizedReference(grid, z_ref, z_dot, linearize(system, grid, z_ref, z_dot))

    # ------------------------------------------------------------------------------------
    def run(self, callback) -> FitResult:
        state = _IterationState(self.z0.clone(), callback)
        try:
            if self.method == "kantorovich":
                reference = self._initial_reference()  # from the data, it may refine the first coefficients
                state.z0 = self.z0.clone()
                first = self._evaluate_kantorovich(self.z0, reference)
            else:
                first = self._evaluate_shooting(self.z0)
            self._iterate(state, first)
        except IntegrationError as exc:
            state.status, state.detail = Status.INTEGRATION_FAILED, f" The solver said: {exc}."
        except TimeBudgetExceeded:
            state.status = Status.MAX_TIME
        if state.status is Status.MAX_TIME:
            state.detail = (f" Stopped after {state.iterations} iterations (max_time = {self.max_time:g} s)."
                            + state.detail)
        return self._finish(state)

    # ------------------------------------------------------------------------------------
    def _evaluate_kantorovich(self, z0: torch.Tensor, reference: LinearizedReference) -> _Iterate:
        """Propagate the linear system about ``reference`` from ``z0``; rows at the observations."""
        n, obs = self.system.n, self.obs_in_grid
        W, evals = propagate_linear(reference, initial_columns(z0, self.unknown_index), solver=self.solver,
                                    rtol=self.rtol, atol=self.atol, max_steps=self.max_steps,
                                    linear_solver=self.linear_solver)
        self.nfev += evals
        C, d, resid = self._rows(reference.z[obs], W[obs, :, 0], W[obs, :, 1:])
        return _Iterate(z0, reference.z[:, :n], W, C, d, self._sse(resid), self._merit(d), reference)

    def _evaluate_shooting(self, z0: torch.Tensor, guess: torch.Tensor | None = None) -> _Iterate:
        """Integrate the nonlinear model from ``z0`` with its sensitivities; rows at the observations.

        ``guess (G, M)``: the previous iterate's linear prediction of the trajectory, given for
        trial steps (see :meth:`_forward`; a trial that exceeds the grid solver's step budget is
        rejected as a blow-up).
        """
        n, obs = self.system.n, self.obs_in_grid
        z_traj = self._forward(z0, guess=guess, budget_is_final=guess is not None)
        W = self._about_nonlinear(z0, z_traj)
        C, d, _ = self._rows(z_traj[obs], z_traj[obs], W[obs, :, 1:])
        return _Iterate(z0, z_traj[:, :n], W, C, d, self._sse(d), self._merit(d), z_traj)

    def _propose(self, current: _Iterate, alpha: torch.Tensor) -> _Iterate:
        """Evaluate the iterate that ``alpha`` leads to from ``current``.

        Kantorovich: the superposed solution becomes the next reference, linearized and
        propagated. Shooting: the nonlinear model is integrated from the shifted initial state.
        """
        z0 = self._shifted(current.z0, alpha)
        W = current.W
        z_new = W[:, :, 0] + W[:, :, 1:] @ alpha
        if self.method == "shooting":
            return self._evaluate_shooting(z0, guess=z_new)
        if not torch.isfinite(z_new).all():
            raise IntegrationError("the superposed trajectory became non-finite")
        reference = current.reference
        z_dot = reference.slopes_of(z_new)
        lin = linearize(self.system, self.grid, z_new, z_dot)
        trial = self._evaluate_kantorovich(z0, LinearizedReference(self.grid, z_new, z_dot, lin))
        trial.defect = float(model_defect(lin.f, z_dot, self.system.n))
        return trial

    def _iterate(self, state, current: _Iterate) -> None:
        """Quasilinearization steps, globalized by Levenberg–Marquardt damping.

        From each iterate the undamped step (``damping = 0``: the thesis' iteration) is tried
        first, so the iteration is the thesis' one wherever that step works and convergence
        near the optimum stays quadratic. A trial step is accepted when it lowers the sum of
        squares (see :meth:`_better`). When it does not (or its trajectory cannot be
        integrated), Kantorovich first re-anchors: the reference becomes the model's own
        solution from the current estimates (integrated for that test anyway), so that the
        linear problem is the true one's linearization, and the undamped step is retried from
        there. Then the step is re-solved with the damping raised: first to a tenth of what the
        previous iterate needed (``_DAMPING_START`` when it needed none; at least
        ``_DAMPING_MIN``), then tenfold each time, which shortens it and turns it toward
        steepest descent, until a step lowers the sum of squares or the damping exceeds
        ``_DAMPING_MAX`` (the iteration has stalled). The tenth lets the damping fall from one
        iterate to the next, as Levenberg–Marquardt's does after a success: on an
        ill-conditioned problem whose undamped steps keep failing, a damping held at
        ``_DAMPING_START`` would all but freeze the directions of small singular values.
        """
        damping = last_damping = 0.0
        while True:
            if state.iterations >= self.max_iter:
                state.status = Status.MAX_ITER
                return
            if time_left() <= 0:
                state.status = Status.MAX_TIME
                return
            record = self._record_iterate(state, current)
            if record is None:
                return
            rejected = 0
            while True:
                solved = self._solve(state, current, damping)
                if solved is None:
                    return
                alpha, scaled = solved
                record.alpha, record.alpha_norm, record.damping, record.rejected = (
                    alpha.detach().clone(), scaled, damping, rejected)
                if damping == 0.0 and self._converged(state, scaled, current.sse):
                    state.z0 = self._shifted(current.z0, alpha)
                    state.iterations += 1
                    state.final_traj = None  # the final pass integrates the shifted estimates
                    state.final_guess = current.W[:, :, 0] + current.W[:, :, 1:] @ alpha
                    record.model_merit = _or_nan(current.nonlinear_sse)
                    self._notify(state, record)
                    return
                try:
                    trial = self._propose(current, alpha)
                    ok = math.isfinite(trial.merit) and bool(torch.isfinite(trial.C).all())
                except IntegrationError:
                    ok = False
                if ok and (self.damping is None or self._better(trial, current, state.capped)):
                    break
                if self.damping is None:  # the thesis' iteration: the step is taken, and fails
                    state.z0 = self._shifted(current.z0, alpha)
                    state.iterations += 1
                    self._notify(state, record)
                    state.status, state.detail = Status.INTEGRATION_FAILED, (
                        " The undamped step led to a trajectory that cannot be integrated; the default "
                        "damping=\"lm\" would have shortened it.")
                    return
                rejected += 1
                anchored = self._anchored(current) if damping == 0.0 else None
                if anchored is not None:
                    current = anchored
                    record.sse, record.trajectory = current.sse, current.traj.detach().clone()
                    record.merit = current.merit
                    continue
                damping = _first_damping(last_damping) if damping == 0.0 else 10 * damping
                if damping > _DAMPING_MAX:
                    record.rejected = rejected
                    record.model_merit = _or_nan(current.nonlinear_sse)
                    state.status = Status.STALLED
                    self._notify(state, record)
                    return
            record.model_merit = _or_nan(current.nonlinear_sse)
            self._notify(state, record)
            last_damping, damping = damping, 0.0
            state.iterations += 1
            if self.method == "shooting":
                state.final_traj = trial.reference
            state.z0 = trial.z0
            state.final_guess = trial.W[:, :, 0]
            current = trial

    def _anchored(self, current: _Iterate) -> _Iterate | None:
        """Kantorovich's iterate re-linearized about the model's solution from its estimates.

        ``None`` when there is nothing to gain: shooting (always anchored), an iterate already
        anchored, or estimates from which the model cannot be integrated.
        """
        if self.method != "kantorovich" or current.anchored:
            return None
        self._nonlinear_sse(current)
        if current.nonlinear_traj is None:
            return None
        z_traj = current.nonlinear_traj
        lin = linearize(self.system, self.grid, z_traj)
        anchored = self._evaluate_kantorovich(current.z0, LinearizedReference(self.grid, z_traj, lin.f, lin))
        anchored.anchored = True
        anchored.nonlinear_sse, anchored.nonlinear_traj = current.nonlinear_sse, z_traj
        return anchored

    def _better(self, trial: _Iterate, current: _Iterate, capped: bool = False) -> bool:
        """Whether ``trial`` lowers the sum of squares relative to ``current``.

        The cheap test compares the merits (for Kantorovich, the particular solutions' sums of
        squares, which approximate the nonlinear ones to second order in the trajectory's
        distance from the model's solution). Far from the solution, where a Kantorovich step
        can raise that approximation and still be a good step, the model is integrated from
        both initial estimates and the nonlinear sums of squares decide. They decide too when
        the step was ``capped`` (a bounded unknown asked to move by more than a factor
        ``e^MAX_INTERNAL_STEP``): the linear solution then lies far outside the region where it
        approximates the model, and its own small misfit says nothing about the model's
        (shooting's merit is the model's sum of squares already). And they decide when the
        trial trajectory is far from solving the model (its :func:`~torchql.trajectory.model_defect`
        above ``DEFECT_TRUST``): a step into a region where the linearization is poor can lower
        the linear problem's misfit while the model's own rises (a Michaelis–Menten step to a
        negative ``Km`` whose model solution is singular).
        """
        trusted = (not capped and trial.defect <= DEFECT_TRUST) or self.method == "shooting"
        if trusted and trial.merit <= current.merit * (1 + _MERIT_SLACK):
            return True
        if self.method == "shooting":
            return False
        return self._nonlinear_sse(trial) <= self._nonlinear_sse(current) * (1 + _MERIT_SLACK)

    def _nonlinear_sse(self, it: _Iterate) -> float:
        """Sum of squares of the nonlinear model integrated from ``it.z0`` (inf if it fails); cached.

        Integrated at the loose first-reference tolerance: it only has to rank two iterates far
        from the optimum (near it, the particular solutions' sums of squares decide).
        """
        if it.nonlinear_sse is None:
            try:
                # to rank two iterates far from the optimum; the particular solution predicts it
                z_traj = self._forward(it.z0, loose=True, guess=it.W[:, :, 0], budget_is_final=True)
                it.nonlinear_sse = self._merit(self._residual(z_traj[self.obs_in_grid]))
                it.nonlinear_traj = z_traj
            except IntegrationError:
                it.nonlinear_sse = math.inf
            if not math.isfinite(it.nonlinear_sse):
                it.nonlinear_sse = math.inf
        return it.nonlinear_sse

    def _record_iterate(self, state, current: _Iterate) -> IterationRecord | None:
        """Append the iterate to the history; ``None`` (status set) when its rows are non-finite."""
        record = self._record(state.iterations, current.z0, current.sse, self.grid, current.traj)
        record.merit = current.merit
        state.history.append(record)
        if state.scale is None:
            state.scale = self._typical_scale(current.traj)
        if not (math.isfinite(current.sse) and torch.isfinite(current.C).all() and torch.isfinite(current.d).all()):
            state.status, state.detail = Status.DIVERGED, " The residuals became non-finite."
            self._notify(state, record)
            return None
        return record

    def _solve(self, state, current: _Iterate, damping: float):
        """``(alpha, scaled size)`` of the damped update, or ``None`` (status set)."""
        u = current.z0[self.unknown_index]
        C = current.C * self.bounds.derivative(u) if self.bounds.active else current.C
        try:
            sol = solve_update(C, current.d, self.weights, self.exact, self.rcond, damping)
            state.capped = self.bounds.capped(sol.alpha)
            alpha, blocked = self.bounds.step(u, sol.alpha)
            if bool(blocked.any()):  # moved onto their bounds and held; the others re-solved
                move = alpha.masked_fill(~blocked, 0.0)
                sol = solve_update(C.masked_fill(blocked, 0.0), current.d - current.C @ move, self.weights,
                                   self.exact, self.rcond, damping)
                rest, _ = self.bounds.step(u, sol.alpha.masked_fill(blocked, 0.0))
                alpha = torch.where(blocked, move, rest)
        except ExactRowsError:
            state.status = Status.EXACT_INFEASIBLE
            return None
        scaled = float((alpha.abs() / torch.maximum(u.abs(), state.scale)).max())
        if not (torch.isfinite(alpha).all() and math.isfinite(scaled)):
            state.status, state.detail = Status.DIVERGED, " The update alpha became non-finite."
            return None
        return alpha, scaled

    @staticmethod
    def _notify(state, record: IterationRecord) -> None:
        if state.callback is not None:
            state.callback(record)

    def _shifted(self, z0, alpha):
        z = z0.clone()
        z[self.unknown_index] = z0[self.unknown_index] + alpha
        return z

    def _converged(self, state, scaled, sse) -> bool:
        if scaled <= self.xtol:
            state.status = Status.CONVERGED
            return True
        if (state.sse_prev is not None and sse > 0 and abs(sse - state.sse_prev) <= self.ftol * sse
                and scaled <= math.sqrt(self.xtol)):
            state.status = Status.CONVERGED_SSE
            return True
        state.sse_prev = sse
        return False

    def _typical_scale(self, traj: torch.Tensor) -> torch.Tensor:
        """Magnitudes ``s_i`` of the unknowns for the relative step test (never zero)."""
        n = self.system.n
        typical = torch.cat([traj.abs().amax(dim=0), self.z0[n:].abs()])
        typical = torch.where(typical > 0, typical, torch.ones_like(typical))
        return typical[self.unknown_index]

    def _finish(self, state) -> FitResult:
        system, n = self.system, self.system.n
        z0, history, status, detail = state.z0, state.history, state.status, state.detail
        iterations, callback = state.iterations, state.callback
        m = self.unknown_index.numel()
        L = self.y_rows.numel()
        nan = torch.full((L,), float("nan"), dtype=self.dtype, device=self.device)
        residuals, jacobian = nan, torch.full((L, m), float("nan"), dtype=self.dtype, device=self.device)
        sse, exact_residual = float("nan"), float("nan")
        singular_values = torch.zeros(0, dtype=self.dtype, device=self.device)
        cov = covariance(jacobian, self.exact, sse, self.sigma_known, self.rcond)
        final_ok = status not in (Status.DIVERGED, Status.INTEGRATION_FAILED, Status.MAX_TIME)
        if not final_ok and (not history or not torch.equal(history[-1].x0, z0[:n])
                             or history[-1].iteration != iterations):
            history.append(self._record(iterations, z0, float("nan")))  # the estimate returned, unevaluated
        if final_ok:
            try:
                z_traj = (state.final_traj if state.final_traj is not None
                          else self._forward(z0, guess=state.final_guess))
                W = self._about_nonlinear(z0, z_traj)
                obs = self.obs_in_grid
                C, _, resid = self._rows(W[obs, :, 0], W[obs, :, 0], W[obs, :, 1:])
                residuals = resid * self.weights
                jacobian = C * self.weights.unsqueeze(-1)
                sse = self._sse(resid)
                exact_residual = float(resid[self.exact].abs().max()) if bool(self.exact.any()) else 0.0
                record = self._record(iterations, z0, sse, self.grid, z_traj[:, :n])
                history.append(record)
                if callback is not None:
                    callback(record)
                if not math.isfinite(sse):
                    status, detail = Status.DIVERGED, " The fitted trajectory is non-finite."
                else:
                    # the Gauss-Newton step at the estimates (their stationarity), and the Jacobian's rank
                    sol = solve_update(jacobian, residuals, torch.ones(L, dtype=self.dtype, device=self.device),
                                       torch.zeros(L, dtype=torch.bool, device=self.device), self.rcond)
                    singular_values = sol.singular_values
                    converged = status.success
                    null_text = null_detail(sol.null_vectors, self.unknown_names) if sol.rank_deficient else ""
                    status, more = final_status(
                        status, rank_deficient=sol.rank_deficient, null_text=null_text,
                        estimates=z0[self.unknown_index], scale=typical_magnitudes(self.u_guess, state.scale),
                        unknown_names=self.unknown_names, sse=sse, sse_start=self._model_sse_at_start(history),
                        step=sol.alpha)
                    detail = more if converged else detail + more
                    cov = covariance(jacobian, self.exact, sse, self.sigma_known, self.rcond)
                    if not converged:  # error bars about estimates that are not an optimum mean nothing
                        cov = cov._replace(matrix=torch.full_like(cov.matrix, float("nan")))
            except IntegrationError as exc:
                status, detail = Status.INTEGRATION_FAILED, f" The solver said, at the final estimates: {exc}."
        if self.bounds.active:
            detail += at_bound_note(self.bounds.at_bound(z0[self.unknown_index]))
        if self.moved_guesses:
            detail += " " + moved_guesses_note(self.moved_guesses)
        fitted = system.model_with(z0[n:])
        return FitResult(
            success=status.success,
            status=status,
            message=status.value + detail,
            params={k: v.detach().clone() for k, v in coefficients(fitted).items()},
            x0=z0[:n].detach().clone(),
            t0=float(self.t0),
            unknown_names=list(self.unknown_names),
            estimates=z0[self.unknown_index].detach().clone(),
            iterations=iterations,
            history=history,
            sse=sse,
            residuals=residuals.detach(),
            jacobian=jacobian.detach(),
            exact_residual=exact_residual,
            singular_values=singular_values.detach(),
            covariance=cov.matrix.detach(),
            dof=cov.dof,
            residual_variance=cov.residual_variance,
            sigma_known=self.sigma_known,
            exact_mask=self.exact.clone(),
            n_observations=L,
            nfev=self.nfev,
            method=self.method,
            model=fitted,
            solver_options={"solver": self.solver, "rtol": self.rtol, "atol": self.atol},
            lower=self.bounds.lower.clone() if self.bounds.active else None,
            upper=self.bounds.upper.clone() if self.bounds.active else None,
            moved_guesses=dict(self.moved_guesses),
        )

    def _model_sse_at_start(self, history: list[IterationRecord]) -> float | None:
        """The model's own sum of squares at the guesses, when the first iterate is its solution."""
        integrated = self.method == "shooting" or self.initial_trajectory == "integrate"
        return history[0].sse if integrated and history else None


#: Newton iterations the grid solver gets from a trajectory's linear prediction before the
#: adaptive solver takes over (from a good prediction it needs two or three).
_GRID_NEWTON = 8
#: Most RK4 steps per grid interval in that solver: an interval that needs more (a trajectory
#: that blows up, a stiff stretch) is left to the adaptive solver rather than subdivided further.
_GRID_SUBSTEPS, _GRID_SUBSTEPS_LOOSE = 32, 16
#: RK4 steps over the whole span beyond which a trial step's trajectory counts as a blow-up
#: (spread over the grid's intervals; on the default grid the per-interval caps above bind).
_BLOWUP_STEPS = 16384
#: Tolerance of the first Kantorovich reference, integrated from the guesses.
_LOOSE_RTOL = 1e-6
#: Levenberg–Marquardt damping limits (:mod:`torchql.options`; see :func:`_first_damping`).
_DAMPING_START, _DAMPING_MIN, _DAMPING_MAX = DAMPING_START, DAMPING_MIN, DAMPING_MAX


def _or_nan(value: float | None) -> float:
    return float("nan") if value is None else value


def _first_damping(last: float) -> float:
    """The first damping tried after a rejected undamped step: a tenth of ``last``, the previous iterate's."""
    return max(_DAMPING_MIN, last / 10) if last > 0 else _DAMPING_START
#: A trial step is accepted when its merit is at most ``(1 + _MERIT_SLACK)`` times the current one
#: (rounding of the sums of squares must not reject a converging step).
_MERIT_SLACK = 1e-10
#: Weight of the exact rows' squared misfit in the merit (exact values are constraints).
_EXACT_PENALTY = 1e6


class _Iterate:
    """One iterate, evaluated: its linear system's rows at the observations.

    Attributes: ``z0 (M,)``; ``traj (G, n)`` its trajectory (Kantorovich: the reference, the
    previous superposed solution; shooting: the nonlinear solution); ``W (G, M, 1 + m)`` the
    particular and homogeneous solutions; ``C (L, m)``, ``d (L,)`` the rows; ``sse`` of ``traj``;
    ``merit``, the sum of squares of the particular solution (for shooting, equal to ``sse``);
    ``reference``, the LinearizedReference (Kantorovich) or the nonlinear trajectory ``(G, M)``;
    ``nonlinear_sse``/``nonlinear_traj``, the model's own from ``z0`` once integrated; ``anchored``,
    whether the reference is that solution.
    """

    def __init__(self, z0, traj, W, C, d, sse, merit, reference) -> None:
        self.z0, self.traj, self.W, self.C, self.d = z0, traj, W, C, d
        self.sse, self.merit, self.reference = sse, merit, reference
        shooting = isinstance(reference, torch.Tensor)
        self.nonlinear_sse: float | None = merit if shooting else None
        self.nonlinear_traj: torch.Tensor | None = reference if shooting else None
        self.anchored = shooting  # linearized about the model's own solution from z0
        self.defect = 0.0  # model_defect of the reference (Kantorovich trial steps; 0 otherwise)


class _IterationState:
    """Mutable state of one fit's iteration."""

    def __init__(self, z0: torch.Tensor, callback) -> None:
        self.z0 = z0
        self.callback = callback
        self.history: list[IterationRecord] = []
        self.status, self.detail = Status.MAX_ITER, ""
        self.scale: torch.Tensor | None = None
        self.sse_prev: float | None = None
        self.iterations = 0
        self.final_traj: torch.Tensor | None = None  # nonlinear trajectory of z0, when already computed
        self.final_guess: torch.Tensor | None = None  # a prediction of it (G, M), when there is one
        self.capped = False  # whether the last solved step was capped (see Bounds.capped)


def _fit_experiments(model, datasets: list, x0, *, params, fixed_x0, t0, bounds, grid, throw, callback,
                     **options) -> FitResult:
    """Several experiments sharing the coefficients: the stacked problem of :mod:`torchql.multi`."""
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
        try:
            x0_t = torch.as_tensor(x0, dtype=dtype, device=device).detach()
        except (TypeError, ValueError) as exc:
            raise TypeError(f"`x0` must be a tensor of shape (E, n_states) = ({E}, {n}); received {type(x0).__name__}") from exc
        if x0_t.shape != (E, n):
            raise ValueError(f"`x0` must have shape (E, n_states) = ({E}, {n}) with {E} experiments; "
                             f"received shape {tuple(x0_t.shape)}")
        x0_flat = x0_t.reshape(-1).clone()
    else:
        if t0 is not None and bool((t0s != first).any()):
            raise ValueError("`x0` is required when `t0` precedes an experiment's first observation")
        x0_flat = None
    if isinstance(grid, torch.Tensor):
        raise ValueError("`grid` must be a number of intervals (per experiment) with several experiments; "
                         "received a tensor of times")
    stacked = StackedModel(model, t0s, span)
    data = stack_observations(datasets, names, t0s, span, dtype, device)
    if isinstance(fixed_x0, str):
        raise TypeError(f"`fixed_x0` must be a sequence of state names, not a string; use [{fixed_x0!r}]")
    fixed = None
    if fixed_x0 is not None:
        for name in fixed_x0:
            if name not in names:
                raise ValueError(f"`fixed_x0` names unknown state {name!r}; the model's states are {tuple(names)}")
        fixed = [experiment_state_name(s, e) for e in range(E) for s in fixed_x0]
    stacked_bounds = None
    if bounds is not None:
        if not isinstance(bounds, dict):
            raise TypeError(f"`bounds` must be a dict {{name: (lower, upper)}}; received {type(bounds).__name__}")
        stacked_bounds = {}
        for key, pair in bounds.items():
            state = key.removesuffix("(t0)") if isinstance(key, str) else key
            if state in names:
                stacked_bounds.update({experiment_state_name(state, e): pair for e in range(E)})
            else:
                stacked_bounds[key] = pair
    result = fit(stacked, data, x0_flat, params=params, fixed_x0=fixed, t0=0.0, bounds=stacked_bounds, grid=grid,
                 throw=False, callback=callback, **options)
    fitted = copy.deepcopy(model)
    own = coefficients(model)
    result.params = {name: value for name, value in result.params.items() if name in own}
    for name, value in result.params.items():
        _set_buffer(fitted, name, value)
    result.model = fitted
    result.x0 = result.x0.reshape(E, n)
    result.experiment_t0 = [float(v) for v in t0s]
    result.data = datasets
    result.fit_kwargs = dict(
        x0=None if x0 is None else torch.as_tensor(x0).detach().clone(),
        params=None if params is None else list(params), fixed_x0=None if fixed_x0 is None else list(fixed_x0),
        t0=t0, grid=grid, bounds=None if bounds is None else dict(bounds), **options)
    if throw and not result.success:
        raise FitError(result)
    return result
