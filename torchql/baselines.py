"""Gradient-descent baselines: the same fitting problem solved by a neural-ODE style optimizer.

:func:`adjoint_fit` takes the model, data and guesses :func:`torchql.fit` takes, and minimizes
the same weighted sum of squares

    ``SSE(u) = sum_k ((y_k - h(x(t_k; u))) / sigma_k)^2``

over the unknowns ``u`` (free initial states, then coefficient elements, ``unknown_names``
order) with a first-order optimizer from :mod:`torch.optim`. Gradients come from
``torchdiffeq.odeint_adjoint`` (the adjoint method: the state is integrated forward, the adjoint
and the parameter gradient backward) or, with ``adjoint=False``, from plain backpropagation
through the solver's operations (``torchdiffeq.odeint``).

It exists to compare quasilinearization with what a machine-learning practitioner would reach
for first (``experiments/vs_gradient.py``); it returns the same :class:`torchql.FitResult`, so
the covariance, report and plots work on its answer too.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence

import torch
from torch import nn
from torchdiffeq import odeint, odeint_adjoint

from . import _checks
from .budget import TimeBudgetExceeded, check_time, time_budget
from .diagnosis import null_detail
from .fit import _Problem, fit
from .integrate import OWN_EXPLICIT_SOLVERS, SOLVER_NAMES, IntegrationError, check_solver, solve
from .lstsq import solve_update
from .model import ODEModel, _set_buffer
from .observations import Observations
from .options import FitOptions, accepts_options
from .result import FitResult, IterationRecord, Status
from .solvers import STIFF_SOLVERS
from .uncertainty import covariance

__all__ = ["adjoint_fit", "OPTIMIZERS"]

#: The optimizers :func:`adjoint_fit` offers.
OPTIMIZERS: tuple[str, ...] = ("adam", "lbfgs")

#: Defaults by optimizer: learning rate (in the normalized space), step budget, tolerance, window.
_DEFAULTS = {
    "adam": {"lr": 1e-2, "max_steps": 20000, "tol": 1e-6, "window": 10},
    "lbfgs": {"lr": 1.0, "max_steps": 500, "tol": 1e-8, "window": 2},
}
#: Integrator tolerances of the gradient runs (float64; lower precisions get torchql's 1e-6/1e-8).
_RTOL, _ATOL = 1e-7, 1e-9
#: Largest number of loss evaluations of one L-BFGS line search.
_MAX_LINE_SEARCH = 25


def _gradient_solver(solver) -> str:
    """``adjoint_fit``'s ``solver`` checked: a torchdiffeq method, through whose operations the gradients
    flow (torchql's own DOP853 and implicit solvers are not differentiable so); ``"auto"``, the
    default of :class:`torchql.FitOptions`, is ``"dopri5"``, this function's own default."""
    if not isinstance(solver, str):
        raise TypeError(f"`solver` must be a string; received {type(solver).__name__}")
    check_solver(solver, auto=True)
    if solver == "auto":
        return "dopri5"
    own = OWN_EXPLICIT_SOLVERS + STIFF_SOLVERS
    if solver in own:
        methods = tuple(name for name in SOLVER_NAMES if name not in own)
        advice = " (use torchql.fit for stiff models)" if solver in STIFF_SOLVERS else ""
        raise ValueError(f"`solver` of adjoint_fit must be a torchdiffeq method, differentiated through torchdiffeq: "
                         f"one of {methods}, or \"auto\" (\"dopri5\"); received {solver!r}{advice}")
    return solver


@accepts_options(unlike=("max_steps",))
def adjoint_fit(
    model: ODEModel,
    data: Observations,
    *,
    x0=None,
    params: Sequence[str] | None = None,
    fixed_x0: Sequence[str] | None = None,
    t0: float | None = None,
    optimizer: str = "adam",
    lr: float | None = None,
    max_steps: int | None = None,
    max_time: float | None = None,
    tol: float | None = None,
    gtol: float | None = None,
    window: int | None = None,
    adjoint: bool = True,
    callback: Callable[[int, float, torch.Tensor], None] | None = None,
    solver: str = "dopri5",
    rtol: float | None = None,
    atol: float | None = None,
    progress: bool = False,
    options: FitOptions | None = None,
) -> FitResult:
    """Fit ``model`` to ``data`` by gradient-based optimization of the weighted SSE.

    Parameters
    ----------
    model, data, x0, params, fixed_x0, t0
        As in :func:`torchql.fit` (validated by the same checks), for one experiment: ``data`` is
        one :class:`torchql.Observations`, not a list. The model is never modified. Values marked
        ``exact`` in ``data`` are not supported (a gradient method has no equality constraints):
        ``ValueError``.
    optimizer : {"adam", "lbfgs"}
        ``"adam"``: :class:`torch.optim.Adam`, one step per gradient. ``"lbfgs"``:
        :class:`torch.optim.LBFGS` with the strong-Wolfe line search (history 20); one step
        is one quasi-Newton iteration (its line search may evaluate the loss more than once).
    lr : float, optional
        Learning rate in the normalized space (below). Default ``1e-2`` for Adam (every unknown
        moves by about 1 % of its magnitude per step at first), ``1`` for L-BFGS.
    max_steps : int, optional
        Budget of optimizer steps (not of solver steps, unlike ``fit(max_steps=)``). Default
        20000 for Adam, 500 for L-BFGS. ``0`` evaluates the guess only.
    max_time : float, optional
        Wall-time budget in seconds, checked after each step and at every evaluation of the
        model inside one (a step cut short is given up for the last iterate evaluated);
        ``Status.MAX_ITER`` with a message naming ``max_time`` when it runs out first. The
        evaluation at the final estimates gets what is left of it, at least a quarter (where
        that runs out too, ``sse`` is NaN). Default: none.
    tol : float, optional
        Convergence when, over the last ``window`` steps, every relative change of the SSE
        and every scaled change of the estimates ``max_i |du_i| / max(|u_i|, s_i)`` is at most
        ``tol``. Default ``1e-6`` for Adam, ``1e-8`` for L-BFGS.
    gtol : float, optional
        Convergence also when the gradient's largest component (normalized space) falls below
        ``gtol`` times its value at the guess. Default ``tol``.
    window : int, optional
        Number of consecutive steps the ``tol`` test must hold; default 10 (Adam), 2 (L-BFGS).
    adjoint : bool
        ``True``: gradients by the adjoint method (``torchdiffeq.odeint_adjoint``, memory
        independent of the number of solver steps). ``False``: backpropagation through
        ``torchdiffeq.odeint``.
    callback : callable, optional
        ``callback(step, sse, estimates)`` after each evaluation of an iterate (step 0 is the
        guess; ``estimates`` in ``unknown_names`` order).
    solver : str
        torchdiffeq method; default ``"dopri5"`` (``"auto"``, :class:`torchql.FitOptions`' default,
        is ``"dopri5"`` too). torchql's own ``"dop853"`` and implicit solvers are not differentiated
        through torchdiffeq: a clear ``ValueError``.
    rtol, atol : float, optional
        Integrator tolerances of the forward and adjoint solves, and of the final evaluation.
        Default ``1e-7``/``1e-9`` (torchdiffeq's own defaults: what a neural-ODE user gets)
        in float64, ``1e-6``/``1e-8`` below. Each loss evaluation is a full forward (and
        backward) solve, so tighter tolerances cost every step.
    progress : bool
        Show a ``tqdm`` progress bar if ``tqdm`` is installed (silently nothing otherwise).
    options : FitOptions, optional
        Of :class:`torchql.FitOptions` only ``solver``, ``rtol``, ``atol`` and ``max_time`` apply here
        (a keyword left at its default takes the field); another field set is an error, ``max_steps``
        too (the solver's step budget there, the optimizer's here).

    Returns
    -------
    FitResult
        ``status`` is ``Status.CONVERGED`` (the ``tol``/``gtol`` test held; the message says
        which), ``Status.MAX_ITER`` (the budget ``max_steps`` ran out; the message names it),
        ``Status.DIVERGED`` (non-finite SSE or gradient) or ``Status.INTEGRATION_FAILED``; a
        converged fit whose Jacobian is rank deficient is ``Status.NOT_IDENTIFIABLE``, as in
        :func:`torchql.fit`. ``method`` is ``"adam"`` or ``"lbfgs"``; ``iterations`` the number
        of optimizer steps; ``history`` one :class:`IterationRecord` per step (every iterate,
        with ``params``, ``x0``, ``sse``; ``alpha`` holds the change the step made to the
        unknowns and ``alpha_norm`` its scaled size; no trajectories); ``nfev`` counts every
        call of the model's right-hand side during the optimization: forward solves, and for
        the adjoint method the backward solves too (with backpropagation the backward pass
        re-uses the recorded graph and calls nothing). ``sse``, ``residuals``, ``jacobian``,
        ``covariance`` are evaluated at the final estimates by :func:`torchql.fit` with
        ``max_iter=0`` (not counted in ``nfev``). ``fit_kwargs`` are those of a
        :func:`torchql.fit` from the estimates, so :func:`torchql.profile` works.

    Notes
    -----
    Parameter scaling: the optimizer works on ``theta`` with ``u = u0 + s * theta``,
    ``theta = 0`` at the guess ``u0``, and ``s_i = max(|u0_i|, typical_i)``: for an initial
    state, ``typical_i`` is the largest ``|x_i(t)|`` of the guess' trajectory at the observation
    times; for a coefficient, 1 when its guess is 0 (else ``|u0_i|``). A unit step in ``theta``
    is then a change of the unknowns' own magnitude, and one learning rate suits unknowns of
    any units (the coasting car's ``mu ~ 0.02`` beside ``v0 ~ 117``).
    """
    if optimizer not in OPTIMIZERS:
        raise ValueError(f"`optimizer` must be one of {OPTIMIZERS}; received {optimizer!r}")
    if not isinstance(adjoint, bool):
        raise TypeError(f"`adjoint` must be True or False; received {adjoint!r}")
    solver = _gradient_solver(solver)
    if callback is not None and not callable(callback):
        raise TypeError(f"`callback` must be callable as callback(step, sse, estimates); received {callback!r}")
    defaults = _DEFAULTS[optimizer]
    lr = defaults["lr"] if lr is None else _checks.positive_number("lr", lr)
    max_steps = defaults["max_steps"] if max_steps is None else _checks.positive_int("max_steps", max_steps, minimum=0)
    tol = defaults["tol"] if tol is None else _checks.positive_number("tol", tol)
    max_time = None if max_time is None else _checks.positive_number("max_time", max_time)
    gtol = tol if gtol is None else _checks.positive_number("gtol", gtol)
    window = defaults["window"] if window is None else _checks.positive_int("window", window)

    # the same validation (and the same prepared problem) as torchql.fit
    _checks.single_observations("data", data)
    if isinstance(data, Observations) and bool(data.exact.any()):
        raise ValueError(
            "adjoint_fit does not support values marked `exact` (a gradient method has no equality "
            "constraints); use torchql.fit, or drop `exact=` from the Observations"
        )
    problem = _Problem(model, data, x0, params, fixed_x0, t0, "kantorovich", None, 0, solver, rtol, atol,
                       None, None, None, None, "integrate", None)
    dtype = problem.dtype
    if rtol is None and dtype == torch.float64:
        problem.rtol = _RTOL
    if atol is None and dtype == torch.float64:
        problem.atol = _ATOL
    run = _GradientRun(problem, optimizer, lr, max_steps, tol, gtol, window, adjoint, callback, progress, max_time)
    return run.result(model, data)


class _RHS(nn.Module):
    """The model's right-hand side with the unknowns substituted from ``theta`` (counted calls).

    :meth:`bind` writes ``u0 + s * theta`` into the unknown buffers of torchql's private copy of
    the model (a graph back to ``theta``, built once per loss evaluation; cheaper than
    ``functional_call`` at every right-hand-side call); :meth:`unbind` writes detached values.
    """

    def __init__(self, problem: _Problem, scale: torch.Tensor) -> None:
        super().__init__()
        system = problem.system
        self.n = system.n
        self.unpack = system.unpack_params
        self.model = system.model  # torchql's private deep copy: the user's model is never touched
        m = problem.unknown_index.numel()
        self.theta = nn.Parameter(torch.zeros(m, dtype=problem.dtype, device=problem.device))
        self.register_buffer("base", problem.z0.clone())
        select = torch.zeros(system.M, m, dtype=problem.dtype, device=problem.device)
        select[problem.unknown_index, torch.arange(m, device=problem.device)] = 1.0
        self.register_buffer("embed", select * scale)  # z = base + embed @ theta
        self.n_evals = 0

    def z0(self) -> torch.Tensor:
        return self.base + self.embed @ self.theta

    def bind(self) -> torch.Tensor:
        """Substitute the current unknowns (differentiably); returns the full ``z0``."""
        z = self.z0()
        for name, value in self.unpack(z[self.n:]).items():
            _set_buffer(self.model, name, value)
        return z

    def unbind(self) -> None:
        """Substitute the current unknowns as plain (detached) tensors."""
        with torch.no_grad():
            z = self.z0()
        for name, value in self.unpack(z[self.n:]).items():
            _set_buffer(self.model, name, value.detach().clone())

    def forward(self, t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        check_time()  # (the run's max_time, inside a solve or its adjoint too)
        self.n_evals += 1
        return self.model(t, x)


class _GradientRun:
    """One optimization: the loss, its gradient, the optimizer loop and the stopping tests."""

    def __init__(self, problem, optimizer, lr, max_steps, tol, gtol, window, adjoint, callback, progress,
                 max_time=None):
        self.problem = problem
        self.max_time = max_time
        self.optimizer_name, self.lr, self.max_steps = optimizer, lr, max_steps
        self.tol, self.gtol, self.window = tol, gtol, window
        self.adjoint, self.callback, self.progress = adjoint, callback, progress
        p = problem
        self.n = p.system.n
        self.prepend = bool(p.t0 < p.t_obs[0])
        self.t_eval = torch.cat([p.t0.reshape(1), p.t_obs]) if self.prepend else p.t_obs
        self.scale = self._scale()
        self.rhs = _RHS(p, self.scale)
        self.typical = self.scale  # the floor of the scaled-change test, as fit's `s_i`

    # ------------------------------------------------------------------------------------
    def _scale(self) -> torch.Tensor:
        p, n = self.problem, self.problem.system.n
        z0 = p.z0
        typical = z0.abs().clone()
        try:
            with torch.no_grad():
                x = solve(p.system.model, z0[:n], self.t_eval, solver=p.solver, rtol=max(p.rtol, 1e-6),
                          atol=max(p.atol, 1e-8))
            typical[:n] = torch.maximum(typical[:n], x.abs().amax(dim=0))
        except IntegrationError:
            pass
        typical = torch.where(typical > 0, typical, torch.ones_like(typical))
        return typical[p.unknown_index]

    def _observe(self, x: torch.Tensor, z0: torch.Tensor) -> torch.Tensor:
        """The outputs ``(T, K)`` of the states ``x (T, n)``, as ``fit`` takes them: ``h(x)``, ``h(x, p)``
        with the coefficients of the augmented ``z0 (M,)`` (differentiable in them), their
        logarithms with log-normal noise."""
        op = self.problem.operator
        params = self.problem.system.coefficient_values(z0) if op.takes_params else None
        return op.values(x, params)

    def loss(self) -> torch.Tensor:
        """The weighted SSE at the current ``theta``, differentiable in it."""
        p, rhs = self.problem, self.rhs
        z0 = rhs.bind()
        x0 = z0[: self.n]
        kwargs = dict(rtol=p.rtol, atol=p.atol, method=p.solver)
        if self.adjoint:
            x = odeint_adjoint(rhs, x0, self.t_eval, adjoint_params=(rhs.theta,), **kwargs)
        else:
            x = odeint(rhs, x0, self.t_eval, **kwargs)
        if self.prepend:
            x = x[1:]
        r = (p.y - self._observe(x, z0))[p.rows_mask] * p.weights
        return (r**2).sum()

    def evaluate(self) -> tuple[float, torch.Tensor]:
        """SSE and its gradient in ``theta`` at the current ``theta`` (raises on solver failure)."""
        theta = self.rhs.theta
        theta.grad = None
        with torch.enable_grad():
            try:
                value = self.loss()
                value.backward()
            except AssertionError as exc:  # torchdiffeq reports solver failures by assert
                raise IntegrationError(str(exc)) from exc
            finally:
                self.rhs.unbind()
        grad = theta.grad.detach().clone() if theta.grad is not None else torch.zeros_like(theta)
        return float(value.detach()), grad

    def estimates(self) -> torch.Tensor:
        with torch.no_grad():
            return self.rhs.z0()[self.problem.unknown_index].clone()

    # ------------------------------------------------------------------------------------
    def _record(self, step: int, sse: float) -> IterationRecord:
        p = self.problem
        with torch.no_grad():
            z = self.rhs.z0().detach()
        params = {k: v.clone() for k, v in p.system.unpack_params(z[self.n:]).items()}
        return IterationRecord(iteration=step, params=params, x0=z[: self.n].clone(), sse=sse)

    def _scaled_change(self, u_new: torch.Tensor, u_old: torch.Tensor) -> float:
        return float(((u_new - u_old).abs() / torch.maximum(u_new.abs(), self.typical)).max())

    def optimize(self):
        """Run the optimizer; returns ``(status, message, iterations, history)``. The time budget
        ``max_time`` is checked after each step and at every evaluation of the model inside one."""
        lbfgs = self.optimizer_name == "lbfgs"
        opt = self._optimizer(lbfgs)
        closure = self._closure()
        bar = _progress_bar(self.max_steps) if self.progress else None
        history: list[IterationRecord] = []
        step = 0
        try:
            with time_budget(self.max_time):
                status, message, step = self._loop(opt, closure, lbfgs, history, bar)
        except TimeBudgetExceeded:  # inside a step: the last iterate evaluated
            if history:
                step = self._restore(history[-1])
            status, message = self._out_of_time(step)
        except IntegrationError as exc:
            if history:  # return the last iterate that could be evaluated
                step = self._restore(history[-1])
            status = Status.INTEGRATION_FAILED
            message = Status.INTEGRATION_FAILED.value + f" The solver said: {exc}."
        finally:
            if bar is not None:
                bar.close()
        return status, message, step, history

    def _loop(self, opt, closure, lbfgs: bool, history: list, bar) -> tuple[Status, str, int]:
        """:meth:`optimize`'s steps until a stopping test: ``(status, message, step)``; each iterate's
        record in ``history``."""
        u_prev, sse_prev, g0 = None, None, None
        quiet = 0  # consecutive steps passing the tol test
        step = 0
        started = time.perf_counter()
        while True:
            sse, grad = self._evaluate_iterate(lbfgs, closure)
            u = self.estimates()
            self._log_iterate(step, sse, u, u_prev, history, bar)
            if not (math.isfinite(sse) and bool(torch.isfinite(grad).all())):
                return (Status.DIVERGED, Status.DIVERGED.value
                        + f" (the SSE or its gradient became non-finite at step {step}).", step)
            gmax = float(grad.abs().max())
            if g0 is None:
                g0 = gmax
            if u_prev is not None:
                quiet = quiet + 1 if self._small_change(sse, sse_prev, u, u_prev) else 0
            stop = self._stop(step, sse, gmax, g0, quiet, started)
            if stop is not None:
                return (*stop, step)
            u_prev, sse_prev = u, sse
            if lbfgs:
                opt.step(closure)
            else:
                self.rhs.theta.grad = grad
                opt.step()
            step += 1

    def _optimizer(self, lbfgs: bool) -> torch.optim.Optimizer:
        """The torch optimizer of ``theta``: L-BFGS (one quasi-Newton iteration per step) or Adam."""
        theta = self.rhs.theta
        if lbfgs:
            return torch.optim.LBFGS([theta], lr=self.lr, max_iter=1, max_eval=_MAX_LINE_SEARCH, history_size=20,
                                     tolerance_grad=0.0, tolerance_change=0.0, line_search_fn="strong_wolfe")
        return torch.optim.Adam([theta], lr=self.lr)

    def _closure(self) -> Callable[[], torch.Tensor]:
        """L-BFGS's closure: the SSE at the current ``theta`` (0-dim tensor; ``inf`` where the solver fails),
        its gradient left in ``theta.grad``; re-uses the last evaluation if ``theta`` is unchanged."""
        theta = self.rhs.theta
        cache: dict = {}

        def closure():
            key = theta.detach()
            if "theta" in cache and torch.equal(cache["theta"], key):
                theta.grad = cache["grad"].clone()
                return torch.tensor(cache["sse"], dtype=theta.dtype)
            try:
                sse, grad = self.evaluate()
            except IntegrationError:
                sse, grad = math.inf, torch.zeros_like(theta)
            cache.update(theta=key.clone(), sse=sse, grad=grad)
            theta.grad = grad.clone()
            return torch.tensor(sse, dtype=theta.dtype)

        return closure

    def _evaluate_iterate(self, lbfgs: bool, closure: Callable[[], torch.Tensor]) -> tuple[float, torch.Tensor]:
        """SSE and gradient ``(m,)`` at the current ``theta`` (L-BFGS: by ``closure``; raises on solver failure)."""
        if not lbfgs:
            return self.evaluate()
        sse = float(closure())
        grad = self.rhs.theta.grad.detach().clone()
        if not math.isfinite(sse):
            raise IntegrationError("the solver failed at the current iterate")
        return sse, grad

    def _log_iterate(self, step: int, sse: float, u: torch.Tensor, u_prev: torch.Tensor | None,
                     history: list[IterationRecord], bar) -> None:
        """Records iterate ``step`` in ``history`` (the previous record gets the change to ``u``), calls the
        callback and updates the progress ``bar``."""
        history.append(self._record(step, sse))
        if history[:-1]:
            prev = history[-2]
            prev.alpha = u - u_prev
            prev.alpha_norm = self._scaled_change(u, u_prev)
        if self.callback is not None:
            self.callback(step, sse, u.clone())
        if bar is not None:
            bar.update(1 if step else 0)
            bar.set_postfix(sse=f"{sse:.3e}")

    def _small_change(self, sse: float, sse_prev: float, u: torch.Tensor, u_prev: torch.Tensor) -> bool:
        """Whether the step's relative change of the SSE and scaled change of the estimates are within ``tol``."""
        dsse = abs(sse - sse_prev) / max(sse, torch.finfo(self.rhs.theta.dtype).tiny)
        return dsse <= self.tol and self._scaled_change(u, u_prev) <= self.tol

    def _stop(self, step: int, sse: float, gmax: float, g0: float, quiet: int,
              started: float) -> tuple[Status, str] | None:
        """``(status, message)`` if the run stops at iterate ``step`` (converged or out of budget), else ``None``."""
        if sse == 0.0 or gmax <= self.gtol * g0:
            return Status.CONVERGED, (
                f"Converged: the gradient of the SSE fell below `gtol` = {self.gtol:g} times its "
                f"value at the guess (after {step} {self.optimizer_name} steps).")
        if quiet >= self.window:
            return Status.CONVERGED, (
                f"Converged: the relative change of the SSE and of the scaled estimates stayed "
                f"below `tol` = {self.tol:g} over the last {self.window} steps (after {step} "
                f"{self.optimizer_name} steps).")
        if step >= self.max_steps:
            return Status.MAX_ITER, (
                f"The step budget `max_steps` = {self.max_steps} of the {self.optimizer_name} "
                "optimizer was reached before convergence. Increase `max_steps` (or `lr`), "
                "or start from guesses closer to the solution.")
        if self.max_time is not None and time.perf_counter() - started >= self.max_time:
            return self._out_of_time(step)
        return None

    def _out_of_time(self, step: int) -> tuple[Status, str]:
        """The status and message of a run whose ``max_time`` ran out after ``step`` steps."""
        return Status.MAX_ITER, (
            f"The wall-time budget `max_time` = {self.max_time:g} s was used up after {step} "
            f"{self.optimizer_name} steps, before convergence (`max_steps` = {self.max_steps}). "
            "Increase `max_time`, or start from guesses closer to the solution.")

    def _restore(self, last: IterationRecord) -> int:
        """Sets ``theta`` to the iterate of record ``last``; returns its step."""
        with torch.no_grad():
            z = torch.cat([last.x0, torch.cat([v.reshape(-1) for v in last.params.values()])
                           if last.params else last.x0.new_zeros(0)])
            self.rhs.theta.copy_((z[self.problem.unknown_index] - self.rhs.base[self.problem.unknown_index])
                                 / self.scale)
        return last.iteration

    # ------------------------------------------------------------------------------------
    def result(self, model, data) -> FitResult:
        p = self.problem
        started = time.perf_counter()
        status, message, iterations, history = self.optimize()
        elapsed = time.perf_counter() - started
        with torch.no_grad():
            z = self.rhs.z0().detach().clone()
        n = self.n
        fixed = [s for i, s in enumerate(p.system.state_names) if i not in p.unknown_index.tolist()]
        # the evaluation at the estimates within what is left of the budget, at least a quarter of it
        left = None if self.max_time is None else max(self.max_time - elapsed, self.max_time / 4)
        final = fit(p.system.model_with(z[n:]), data, x0=z[:n], params=list(p.system.param_names),
                    fixed_x0=fixed, t0=float(p.data_t0), max_iter=0, solver=p.solver, rtol=p.rtol, atol=p.atol,
                    max_time=left)
        if final.status in (Status.INTEGRATION_FAILED, Status.DIVERGED):
            status = final.status
            message = final.message + " (at the final estimates)"
        elif status.success and final.singular_values.numel():
            sol = solve_update(final.jacobian, torch.zeros_like(final.residuals), torch.ones_like(final.residuals),
                               torch.zeros_like(final.exact_mask), p.rcond)
            if sol.rank_deficient:
                status = Status.NOT_IDENTIFIABLE
                message = Status.NOT_IDENTIFIABLE.value + null_detail(sol.null_vectors, p.unknown_names)
        kwargs = dict(final.fit_kwargs)
        kwargs["max_iter"] = 50  # a re-fit (torchql.profile) iterates with fit's own default
        kwargs["method"] = "kantorovich"
        kwargs["gradient_run"] = dict(optimizer=self.optimizer_name, lr=self.lr, max_steps=self.max_steps,
                                      max_time=self.max_time, tol=self.tol, gtol=self.gtol, window=self.window,
                                      adjoint=self.adjoint,
                                      wall_time=elapsed)
        # the evaluation at the estimates (max_iter=0) is no converged fit, so its covariance is NaN;
        # error bars belong to the gradient run's estimates when that run converged
        cov = final.covariance
        if status.success and torch.isfinite(final.jacobian).all():
            cov = covariance(final.jacobian, final.exact_mask, final.sse, final.sigma_known, p.rcond).matrix
        return dataclasses.replace(
            final, success=status.success, status=status, message=message, iterations=iterations, covariance=cov,
            history=history, nfev=self.rhs.n_evals, method=self.optimizer_name, data=data, fit_kwargs=kwargs,
        )


def _progress_bar(total: int):
    try:
        from tqdm.auto import tqdm
    except ImportError:  # optional dependency: no bar
        return None
    return tqdm(total=total, unit="step")
