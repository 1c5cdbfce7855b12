"""Integration: solver choice (torchdiffeq's explicit solvers, torchql's eighth-order ``"dop853"``
and implicit ``"rodas5p"`` for stiff models), tolerances, and plain forward simulation."""

from __future__ import annotations

import torch
from torchdiffeq import odeint
from torchdiffeq._impl.odeint import SOLVERS

from . import _checks
from ._arrays import float_tensor
from .budget import check_time
from .inputs import Inputs
from .dopri import STIFF_EVERY, dopri_batch, found_stiff
from .model import ODEModel, model_dtype_device
from .solvers import STIFF_SOLVERS, JacobianError, rodas5p_solve
from .stiffness import AUTO, EXPLICIT_SOLVER, STIFF_SOLVER, stiff_along

#: :func:`simulate`'s ``"auto"``: DOP853 tests its steps for stiffness every 10 accepted steps (and
#: at every step once one failed), not Hairer's every 1,000. The test still asks 15 failures with few
#: passes between, and failing costs a switch to Rodas5P rather than the user's request. On
#: Robertson's kinetics and HIRES (not stiff at their initial states) the 1,000 DOP853 steps before
#: the first test were most of the time (0.72 s -> 0.11 s and 1.6 s -> 0.51 s); on non-stiff models
#: (Lorenz, van der Pol at mu = 5) the test costs about 1 % (``benchmarks/stiff_simulate.py``).
AUTO_STIFF_EVERY = 10

__all__ = ["SOLVER_NAMES", "ADAPTIVE_SOLVERS", "OWN_EXPLICIT_SOLVERS", "IntegrationError", "check_solver",
           "default_tolerances", "interval_tolerances", "solve", "simulate", "CountedField"]

#: torchql's own explicit solvers (:func:`torchql.dopri.dopri_batch`'s pairs) that torchdiffeq has not:
#: Hairer's eighth-order DOP853, the one for tight tolerances (:mod:`torchql.rk_pairs`).
OWN_EXPLICIT_SOLVERS: tuple[str, ...] = ("dop853",)
#: Every solver name: torchdiffeq's, torchql's explicit ones, then the implicit solvers of
#: :mod:`torchql.solvers` (for stiff models).
SOLVER_NAMES: tuple[str, ...] = (tuple(name for name in SOLVERS if name != "scipy_solver") + OWN_EXPLICIT_SOLVERS
                                 + STIFF_SOLVERS)
#: Solvers with step-size control (they accept ``rtol``/``atol`` and land steps on ``step_t``).
ADAPTIVE_SOLVERS: tuple[str, ...] = (("dopri8", "dopri5", "bosh3", "fehlberg2", "adaptive_heun") + OWN_EXPLICIT_SOLVERS
                                     + STIFF_SOLVERS)


class IntegrationError(RuntimeError):
    """The ODE solver failed (step-size underflow, step budget exceeded, non-finite state)."""


class CountedField:
    """A right-hand side ``func(t, y)`` that counts its evaluations and checks the fit's time budget.

    Every integration a fit runs goes through one, so that an integration that crawls (a stiff
    stretch, a blow-up) ends at ``max_time`` (see :mod:`torchql.budget`) instead of running on.
    """

    def __init__(self, func) -> None:
        self.func, self.n_evals = func, 0

    def __call__(self, t, y):
        check_time()
        self.n_evals += 1
        return self.func(t, y)


def check_solver(solver: str, auto: bool = False) -> None:
    """Raise ``ValueError`` naming the valid solvers when ``solver`` is not one of them
    (``auto``: ``"auto"`` is valid too, as in :func:`torchql.fit`)."""
    names = (("auto",) if auto else ()) + SOLVER_NAMES
    if solver not in names:
        raise ValueError(f"`solver` must be one of {names}; received {solver!r}")


def default_tolerances(dtype: torch.dtype, rtol: float | None, atol: float | None) -> tuple[float, float]:
    """Integrator tolerances: ``1e-10``/``1e-12`` in float64, ``1e-6``/``1e-8`` in lower precision."""
    if dtype == torch.float64:
        return (1e-10 if rtol is None else rtol), (1e-12 if atol is None else atol)
    return (1e-6 if rtol is None else rtol), (1e-8 if atol is None else atol)


def interval_tolerances(rtol: float, atol: float, intervals: int, dtype: torch.dtype) -> tuple[float, float]:
    """Tolerances of one interval of a grid of ``intervals`` integrated separately: the whole solution's
    over ``sqrt(intervals)`` (independent errors add in quadrature), never below ten roundoffs."""
    tiny = 10 * torch.finfo(dtype).eps
    intervals = max(intervals, 1)
    return max(rtol / intervals**0.5, tiny), max(atol / intervals**0.5, tiny)


def solve(func, y0: torch.Tensor, t: torch.Tensor, *, solver: str, rtol: float, atol: float,
          hit: torch.Tensor | None = None, max_steps: int | None = None, norm=None,
          first_step: float | None = None, jumps: torch.Tensor | None = None,
          stiff_every: int = STIFF_EVERY) -> torch.Tensor:
    """``odeint`` with our conventions; solver failures become :class:`IntegrationError`.

    Parameters
    ----------
    func : callable ``(t, y) -> dy/dt``
    y0 : Tensor
        State at ``t[0]``.
    t : Tensor ``(G,)``
        Strictly monotonic output times (``t[0]`` is the initial time; decreasing integrates backwards).
    solver : str
        A torchdiffeq method name, ``"dop853"`` (:func:`_solve_own`: Hairer's eighth-order pair,
        torchql's own integrator) or
        ``"rodas5p"`` (:func:`torchql.solvers.rodas5p_solve`: implicit, for stiff systems; ``func``
        must be differentiable by ``torch.func.jacrev``).
    rtol, atol : float
        Tolerances of adaptive solvers.
    hit : Tensor, optional
        Times that adaptive solvers must step onto exactly (observation times), rather than
        interpolate to. Fixed-grid solvers step on every output time anyway.
    max_steps : int, optional
        Step budget of adaptive solvers.
    norm : callable, optional
        Error norm of adaptive solvers (torchdiffeq's RMS norm by default).
    first_step : float, optional
        First step tried by adaptive solvers (default: torchdiffeq's estimate).
    jumps : Tensor, optional
        Times where ``func`` is not smooth (a measured input's samples): adaptive torchdiffeq
        solvers restart there instead of rejecting steps across them.
    stiff_every : int, optional
        How often (accepted steps) torchql's own explicit pairs test for stiffness
        (:func:`~torchql.dopri.dopri_batch`; Hairer's 1,000 by default).

    Returns
    -------
    Tensor ``(G, *y0.shape)``
    """
    if t.numel() == 1:
        return y0.unsqueeze(0)
    if solver in STIFF_SOLVERS:
        return _solve_stiff(func, y0, t, rtol=rtol, atol=atol, hit=hit, max_steps=max_steps, norm=norm,
                            first_step=first_step)
    if solver in OWN_EXPLICIT_SOLVERS:
        return _solve_own(func, y0, t, solver=solver, rtol=rtol, atol=atol, hit=hit, max_steps=max_steps, jumps=jumps,
                          norm=norm, first_step=first_step, stiff_every=stiff_every)
    options = {}
    if solver in ADAPTIVE_SOLVERS:
        if jumps is not None:
            low, high = torch.minimum(t[0], t[-1]), torch.maximum(t[0], t[-1])
            jumps = jumps.to(t)
            jumps = torch.unique(jumps[(jumps > low) & (jumps < high)])  # torchdiffeq takes a time once
            if jumps.numel():
                options["jump_t"] = jumps  # the solver lands on these too
        if hit is not None:
            inner = hit[(hit > t[0]) & (hit < t[-1])]
            if "jump_t" in options:
                inner = inner[~torch.isin(inner, options["jump_t"])]  # torchdiffeq takes a time once
            if inner.numel():
                options["step_t"] = inner
        if max_steps is not None:
            options["max_num_steps"] = max_steps
        if norm is not None:
            options["norm"] = norm
        if first_step is not None:
            options["first_step"] = first_step
    try:
        out = odeint(func, y0, t, rtol=rtol, atol=atol, method=solver, options=options)
    except AssertionError as exc:  # torchdiffeq reports solver failures by assert
        raise IntegrationError(str(exc)) from exc
    if not torch.isfinite(out).all():
        raise IntegrationError("the solution became non-finite (NaN or inf)")
    return out


class _OwnField:
    """``func(t, y)`` of :func:`solve`, as :func:`~torchql.dopri.dopri_batch` takes a model: ``f(t,
    z)`` on one flat state ``(n,)``, every component under error control (``n``), in the time
    ``s = sign t`` (``sign = -1`` integrates backwards as forwards)."""

    def __init__(self, func, shape: torch.Size, sign: float) -> None:
        self.func, self.shape, self.sign = func, shape, sign
        self.n = shape.numel()
        self.time_sign = sign  # the solver's messages give the time ``t = sign s``

    def f(self, s: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        return self.sign * self.func(self.sign * s, z.reshape(self.shape)).reshape(-1)


def _solve_own(func, y0: torch.Tensor, t: torch.Tensor, *, solver: str, rtol: float, atol: float,
               hit: torch.Tensor | None, max_steps: int | None, jumps: torch.Tensor | None, norm=None,
               first_step: float | None = None, stiff_every: int = STIFF_EVERY) -> torch.Tensor:
    """:func:`solve` by torchql's own explicit integrator (:func:`~torchql.dopri.dopri_batch`, the
    pair ``solver``) on one sample: as torchdiffeq's solvers, its steps land on the times in
    ``hit`` and ``jumps`` inside the span and on the last output time, and the other output
    times are read from its dense output; ``max_steps`` caps its trial steps between two output
    times; ``norm`` (of the scaled error, shaped as ``y0``) and ``first_step`` as torchdiffeq takes them."""
    sign = 1.0 if bool(t[-1] > t[0]) else -1.0
    s = sign * t
    extra = [sign * v.to(t).reshape(-1) for v in (hit, jumps) if v is not None]
    extra = torch.cat([v[(v > s[0]) & (v < s[-1])] for v in extra]) if extra else s[:0]
    nodes = torch.unique(torch.cat([s, extra]))
    output = torch.searchsorted(nodes, s)
    land = torch.isin(nodes, extra)
    messages: list = []
    rows = None if norm is None else (lambda x: torch.stack([norm(row.reshape(y0.shape)) for row in x]))
    out, ok, _ = dopri_batch(_OwnField(func, y0.shape, sign), y0.reshape(1, -1), nodes, rtol=rtol, atol=atol,
                             land=land, messages=messages, interval_steps=max_steps, method=solver, norm=rows,
                             first_step=first_step, stiff_every=stiff_every)
    if not bool(ok[0]):
        raise IntegrationError(messages[0] or "the solution became non-finite (NaN or inf)")
    return out[0, output].reshape(t.shape[0], *y0.shape)


def _solve_stiff(func, y0, t, **options) -> torch.Tensor:
    """:func:`solve` by Rodas5P; its per-sample failure statuses become :class:`IntegrationError`."""
    try:
        out, solution = rodas5p_solve(func, y0, t, **options)
    except JacobianError as exc:
        raise IntegrationError(str(exc)) from exc
    if not bool(solution.ok[0]):
        raise IntegrationError(solution.message(0))
    return out


def simulate(model: ODEModel, x0, t, *, t0: float | None = None, solver: str = "auto",
             rtol: float | None = None, atol: float | None = None, inputs: Inputs | None = None) -> torch.Tensor:
    """Integrate ``model`` from ``x0`` at time ``t0`` and return the states at times ``t``.

    Parameters
    ----------
    model : ODEModel
        Its buffers (and parameters) are the coefficients used; float32 or float64. Their values
        only: the result carries no gradient to them, nor to ``x0`` (a solution to differentiate is
        ``torchdiffeq.odeint``'s; :func:`torchql.baselines.adjoint_fit` fits so).
    x0 : Tensor ``(n_states,)``
        State at ``t0`` (its values; not differentiated through).
    t : Tensor ``(T,)``
        Output times, strictly increasing; they may lie before ``t0`` (integrated backwards).
    t0 : float, optional
        Time of ``x0``; default ``t[0]``.
    solver : str
        Default ``"auto"``, as :func:`torchql.fit`'s: ``"rodas5p"`` where the model is stiff at
        ``x0`` in a direction integrated (its fastest decay rate, backwards its growth rate, times
        that span above :data:`torchql.stiffness.STIFF_RATIO`), else ``"dop853"``, integrated
        again by ``"rodas5p"`` where it becomes stiff on the way (its stiffness test fails it);
        explicit solvers crawl through a stiff model, torchdiffeq's ``"dopri5"`` with no end (a
        Robertson kinetics ran over 100 s). A model that ``torch.func`` cannot vmap or
        differentiate (NumPy inside) is integrated by ``"dopri5"``. Or any of :data:`SOLVER_NAMES`: ``"dop853"`` is
        torchql's own explicit pair, which fails, saying so, where the solution becomes stiff;
        ``"rodas5p"`` for stiff models (fast chemistry, relaxation oscillations): an implicit
        Rosenbrock method, see :mod:`torchql.solvers`; ``"dopri5"``, torchdiffeq's, was the default
        before ``"auto"``.
    rtol, atol
        As in :func:`torchql.fit`.
    inputs : Inputs, optional
        Measured inputs ``u(t)`` for a model with ``input_names``; default the inputs attached to
        the model (a fitted model, ``result.model``, holds its data's). They must cover ``t0`` and
        ``t``.

    Returns
    -------
    Tensor ``(T, n_states)``
    """
    _checks.model_class(model, fitted=False)
    check_solver(solver, auto=True)
    dtype, device = model_dtype_device(model)
    n = len(model.state_names)
    t = float_tensor(t, "t", dtype, device, expected="a one-dimensional tensor of times")
    x0 = float_tensor(x0, "x0", dtype, device, expected=f"a tensor of shape (n_states,) = ({n},)")
    if t.dim() != 1 or t.numel() == 0:
        raise ValueError(f"`t` must be a non-empty one-dimensional tensor; received shape {tuple(t.shape)}")
    if not torch.isfinite(t).all():
        raise ValueError("`t` must be finite; received NaN or inf times")
    if t.numel() > 1 and not bool((t[1:] > t[:-1]).all()):
        j = int((t[1:] <= t[:-1]).nonzero()[0, 0])
        raise ValueError(f"`t` must be strictly increasing; received t[{j}] = {t[j].item():g} followed by "
                         f"t[{j + 1}] = {t[j + 1].item():g}")
    if x0.shape != (n,):
        raise ValueError(f"`x0` must have shape (n_states,) = ({n},); received shape {tuple(x0.shape)}")
    if not torch.isfinite(x0).all():
        raise ValueError("`x0` must be finite; received NaN or inf")
    rtol, atol = default_tolerances(dtype, rtol, atol)
    rtol, atol = _checks.positive_number("rtol", rtol), _checks.positive_number("atol", atol)
    t0_ = t[0] if t0 is None else torch.as_tensor(_checks.finite_number("t0", t0), dtype=dtype, device=device)
    func = _with_inputs(model, inputs, min(float(t0_), float(t[0])), max(float(t0_), float(t[-1])), dtype, device,
                        origin=float(t0_))
    # in-place updates of `x` and the output's shape and dtype (a non-finite derivative is an
    # IntegrationError, like one met later on)
    origin = 0.0 if func is model else func.origin  # with inputs: in local time from t0 (see _with_inputs)
    if origin:
        t, t0_ = t - origin, t0_ - origin
    slope = _checks.model_forward(func, t0_, x0, model.state_names, {}, dtype, finite=False)
    bad = _checks.non_finite_slopes(slope, model.state_names)
    if bad:
        raise IntegrationError(f"`model` forward is not finite at `x0` = {x0.tolist()}: {bad} at t0 = "
                               f"{float(t0_) + origin:g}; the solution cannot start there")
    with torch.no_grad():
        if solver != AUTO:
            return _integrate_both_ways(func, x0, t, t0_, solver, rtol, atol)
        return _simulate_auto(func, x0, t, t0_, rtol, atol)


def _simulate_auto(func, x0: torch.Tensor, t: torch.Tensor, t0: torch.Tensor, rtol: float, atol: float):
    """:func:`simulate`'s ``solver="auto"``: Rodas5P where the model is stiff at ``x0`` in a direction it
    is integrated in, else DOP853, and Rodas5P again where DOP853's stiffness test fails it. A model
    that neither can run (its ``forward`` leaves torch: NumPy, ``.item()``; they vmap and
    differentiate it) is integrated by torchdiffeq's ``"dopri5"``, which calls it as it is."""
    try:
        stiff = _stiff_at(func, t0, x0, t)
        try:
            return _integrate_both_ways(func, x0, t, t0, STIFF_SOLVER if stiff else EXPLICIT_SOLVER, rtol, atol,
                                        stiff_every=AUTO_STIFF_EVERY)
        except IntegrationError as exc:
            if stiff or not found_stiff(str(exc)):
                raise
            return _integrate_both_ways(func, x0, t, t0, STIFF_SOLVER, rtol, atol)
    except IntegrationError:
        raise
    except RuntimeError:  # not vmapped or differentiated by torch.func: called as it is
        return _integrate_both_ways(func, x0, t, t0, "dopri5", rtol, atol)


def _stiff_at(func, t0: torch.Tensor, x0: torch.Tensor, t: torch.Tensor) -> bool:
    """Whether the model ``func(t, x)`` is stiff at ``(t0, x0)`` in a direction it is integrated in to the
    times ``t``, by ``solver="auto"``'s test (:func:`torchql.stiffness.stiff_along`): forwards its
    decay rates, backwards its growth rates (the reversed field's decay rates), each times its span.
    Raises RuntimeError where the Jacobian cannot be taken (a model that leaves torch)."""
    jac = torch.func.jacrev(lambda x: func(t0, x))(x0)
    n = x0.shape[0]
    jac = jac.reshape(1, 1, n, n)
    forward, backward = (t[-1] - t0).clamp(min=0), (t0 - t[0]).clamp(min=0)
    return any(bool(stiff_along(sign * jac, n, span.reshape(1))[0])
               for sign, span in ((1.0, forward), (-1.0, backward)) if float(span) > 0)


def _with_inputs(model: ODEModel, inputs: Inputs | None, start: float, end: float, dtype, device,
                 origin: float = 0.0):
    """The right-hand side ``f(s, x)`` of ``model`` with its inputs (the given ones, else those it
    holds), checked against its ``input_names`` and the span ``[start, end]``, in the local time
    ``s = t - origin`` (its ``origin`` attribute; the model is given ``t``): at ``t ~ 1e8`` a held input's
    step spanned 1e5 roundoffs of ``t``, and DOP853's step size underflowed in it. The model itself
    when it has none."""
    names = tuple(getattr(model, "input_names", ()))
    if inputs is not None and not isinstance(inputs, Inputs):
        raise TypeError(f"`inputs` must be a torchql.Inputs; received {type(inputs).__name__}")
    if not names:
        if inputs is not None:
            raise ValueError(f"`inputs` {list(inputs.names)} given but `model` declares no `input_names`")
        return model
    signals = inputs if inputs is not None else model.inputs
    if signals is None:
        raise ValueError(f"`model` takes inputs {names} (its `input_names`): pass `inputs=torchql.Inputs(t_u, u, "
                         f"names={list(names)})`")
    held = "" if inputs is not None else (" (no `inputs` was passed: these are the ones the model holds, its fitted "
                                          "data's; pass `inputs=torchql.Inputs(...)` that cover the times)")
    signals = signals.for_model(names, start, end, dtype, device, where="inputs", span="the simulated times",
                                note=held).shifted(origin)

    def func(s, x):
        return model(s + origin, x, signals(s))

    func.jumps, func.origin = signals.jumps, origin
    return func


def _integrate_both_ways(func, x0, t, t0, solver, rtol, atol, stiff_every: int = STIFF_EVERY):
    """States at ``t`` from ``x0`` at ``t0``, integrating forward and backward as needed."""
    pieces = []
    options = dict(solver=solver, rtol=rtol, atol=atol, jumps=getattr(func, "jumps", None), stiff_every=stiff_every)
    before = t[t < t0]
    if before.numel():
        times = torch.cat([t0.reshape(1), before.flip(0)])
        pieces.append(solve(func, x0, times, **options)[1:].flip(0))
    after = t[t >= t0]
    if after.numel():
        starts_at_t0 = bool(after[0] == t0)
        times = after if starts_at_t0 else torch.cat([t0.reshape(1), after])
        out = solve(func, x0, times, **options)
        pieces.append(out if starts_at_t0 else out[1:])
    return torch.cat(pieces)
