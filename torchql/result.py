"""The result of a fit: estimates, status with an actionable message, and iteration history."""

from __future__ import annotations

import math
import operator

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import torch

from .status import Status

if TYPE_CHECKING:  # pragma: no cover
    from .model import ODEModel
    from .options import FitOptions
    from .observations import Observations

__all__ = ["Status", "IterationRecord", "FitResult", "FitError"]


class FitError(RuntimeError):
    """Raised by ``fit(..., throw=True)`` when the fit does not converge; ``.result`` holds it."""

    def __init__(self, result: "FitResult") -> None:
        super().__init__(result.message)
        self.result = result

    def __reduce__(self):
        """Pickled (and deep-copied) with its result, so that it crosses process boundaries
        (a worker pool's ``fit(..., throw=True)``): the default would rebuild it from the message."""
        return type(self), (self.result,)


@dataclass
class IterationRecord:
    """One iterate of the fit (iteration 0: the guesses, with the coefficients matched to the data where
    the first reference is built from them).

    Attributes
    ----------
    iteration : int
        Iteration number.
    params : dict of str to Tensor
        Estimated buffers at this iterate (each of its buffer's shape).
    x0 : Tensor ``(n_states,)``
        Initial-state estimate at this iterate: where its linear problem starts, from which the
        update ``alpha`` is measured. It is ``trajectory[0]`` but at iteration 0 of a Kantorovich first
        reference built from the data, which starts at the data's values while ``x0`` holds
        the guesses.
    sse : float
        Weighted sum of squared residuals (values marked exact left out) of this iterate's
        stored trajectory ``trajectory``. Shooting: the model's own solution from this
        iterate's estimates. Kantorovich: the trajectory the previous iterate's linear problem
        predicted for the step taken, ``w_0 + W alpha`` (the reference this iterate is
        linearized about; iteration 0: the first reference, integrated from the guesses or
        built from the data), or after a rejected step the model's solution from the
        estimates that the iterate was re-anchored to. Kantorovich's column is therefore not
        monotone: a step is accepted when it lowers :attr:`merit` or, failing that, the model's
        own sum of squares (:attr:`model_merit`), neither of which is this value, and a
        predicted trajectory is no model solution, so its sum of squares may fall below the
        least-squares optimum and rise back to it as the iteration converges. The last
        iterate's is the model's own at the estimates (``FitResult.sse``).
    alpha : Tensor ``(m,)`` or None
        The update computed from this iterate (None if none was computed).
    alpha_norm : float
        ``max_i |alpha_i| / (|u_i| + s_i)``: the update scaled by the unknowns' magnitudes.
    trajectory : Tensor ``(G, n_states)`` or None
        This iterate's trajectory on ``trajectory_t``.
    trajectory_t : Tensor ``(G,)`` or None
    damping : float
        Levenberg–Marquardt parameter of the step taken from this iterate, relative to the
        largest squared singular value of the scaled least-squares matrix (0: the undamped
        quasilinearization step).
    rejected : int
        Trial steps from this iterate that were rejected (they raised the sum of squares or
        could not be integrated) before one was accepted.
    merit : float
        What the step acceptance compares first: the weighted sum of squares of this iterate's
        particular solution (Kantorovich: the linear problem's trajectory from this iterate's
        estimates without an update; shooting: the model's solution, then equal to ``sse``),
        plus ``1e6`` times the exact values' squared misfit. A step from the previous iterate
        was accepted because this fell, or else because :attr:`model_merit` did. NaN for the
        final evaluation.
    model_merit : float
        The same sum for the model's own solution from this iterate's estimates (integrated at
        a loose tolerance), when the acceptance test needed it; NaN when it did not (the merits
        decided) or the iterate's step was never tested.
    """

    iteration: int
    params: dict[str, torch.Tensor]
    x0: torch.Tensor
    sse: float
    alpha: torch.Tensor | None = None
    alpha_norm: float = float("nan")
    trajectory: torch.Tensor | None = None
    trajectory_t: torch.Tensor | None = None
    damping: float = 0.0
    rejected: int = 0
    merit: float = float("nan")
    model_merit: float = float("nan")


@dataclass
class FitResult:
    """What :func:`torchql.fit` found.

    Attributes
    ----------
    success : bool
        Whether the iteration converged.
    status : Status
        Why it stopped.
    message : str
        ``status.value`` plus details (which unknowns are not identifiable, what the solver said).
    params : dict of str to Tensor
        Estimated buffers (unknown ones at their estimates, others as given), buffer shapes.
    x0 : Tensor ``(n_states,)``
        Estimated initial state at ``t0``.
    t0 : float
        Time of ``x0``.
    unknown_names : list of str
        Names of the estimated quantities, in the order of ``estimates`` and of the columns of
        ``jacobian``: unknown initial states (``"y(t0)"`` style names use the state name), then
        coefficient elements.
    estimates : Tensor ``(m,)``
        The estimated unknowns, in ``unknown_names`` order.
    iterations : int
        Number of updates applied.
    history : list of IterationRecord
        Every iterate, from the first (iteration 0) to the last. The first is the guesses' where the
        iteration starts from the integrated guesses (``initial_trajectory="integrate"``), and the
        coefficients matched to the data where it starts from a reference built from the data.
    sse : float
        Weighted sum of squared residuals ``sum(((y - h(x(t))) / sigma)^2)`` of the fitted model
        (nonlinear solution from ``x0`` with ``params``), over the least-squares observations.
    residuals : Tensor ``(L,)``
        Weighted residuals ``(y - h(x(t))) / sigma`` of the fitted model at every used value
        (time-major order, NaNs skipped), exact ones included. Several experiments: in the order
        of their normalized times ``(t - t0_e) / T_e`` (``T_e`` each one's span), the values of
        one normalized time in experiment order.
    jacobian : Tensor ``(L, m)``
        Weighted sensitivities ``d h(x(t)) / d unknowns / sigma`` at the estimates (the final
        homogeneous solutions at the observation times).
    exact_residual : float
        Largest ``|y - h(x(t))|`` over the values marked exact (0 if none).
    singular_values : Tensor ``(r,)``
        Singular values of the column-scaled weighted Jacobian at the estimates.
    covariance : Tensor ``(m, m)``
        Covariance of ``estimates`` (``unknown_names`` order), from the final Jacobian:
        ``s^2 (J^T J)^{-1}`` restricted to the directions the exact values leave free. All NaN
        when the iteration did not converge (every unsuccessful status but a converged
        ``NOT_IDENTIFIABLE``); NaN rows and columns for the unknowns the data do not determine.
    dof : int
        Degrees of freedom of the residuals, ``L - m`` less the values marked exact that repeat what
        others fix (:func:`torchql.uncertainty.redundant_exact`).
    residual_variance : float
        ``s^2``: ``sse / dof`` when the data's ``sigma`` was neither given nor estimated, else 1.
    sigma_known : bool
        Whether the weights are standard deviations: the data's ``sigma`` given, or estimated with
        the unknowns (``sigma="estimate"``, whose covariance is the expected information's). Then
        ``residual_variance`` is 1 and the Wald intervals take the normal quantile; otherwise
        Student's t with ``dof`` and the estimated residual variance.
    exact_mask : bool Tensor ``(L,)``
        Which used values were met exactly.
    n_observations : int
        Number of values used, ``L``.
    nfev : int
        Right-hand-side evaluations: the number of states the model's ``forward`` (or, for the
        linear system, one term of its series) was evaluated at, a vectorized call over many
        grid intervals counting each of them.
    method : str
        ``"kantorovich"`` or ``"shooting"``.
    model : ODEModel
        A copy of the user's model whose buffers hold the estimates.
    data : Observations or None
        The observations the fit was made to (used by :func:`torchql.profile` and
        :meth:`plot_fit`).
    fit_kwargs : dict
        The keyword arguments :func:`torchql.fit` was called with (``x0``, ``params``,
        ``fixed_x0``, ``t0``, ``method``, tolerances, ``grid``, ...; not ``callback``/``throw``),
        so that a re-fit (a profile) reproduces the fit's settings.
    conditions : list of dict or None
        With several experiments fitted with ``conditions``: each experiment's own coefficient
        values (numbers as tensors, or other coefficients' names); ``predict`` applies them.
    experiment_t0 : list of float or None
        With several experiments (``data`` a list): each one's initial time; ``x0`` is then
        ``(E, n_states)``, one row per experiment, and ``t0`` is 0 (the normalized time of the
        stacked problem that ``history`` trajectories live on).
    lower, upper : Tensor ``(m,)`` or None
        The ``bounds`` of the unknowns, in ``unknown_names`` order (``-inf``/``inf`` where a side
        is open); ``None``: no bounds. Bounded unknowns' intervals are computed in the internal
        variable of :mod:`torchql.bounds` (see :meth:`confidence_intervals`).
    index : int or None
        For one sample of a :func:`torchql.fit_many` batch (``batch[i]``), its position ``i``;
        ``None`` for :func:`torchql.fit`.
    log_scaled : list of str
        The unknowns iterated on a logarithmic scale (``scale=``); their intervals are intervals
        of ``log u`` mapped back.
    moved_guesses : dict of str to (float, float)
        ``{name: (given, used)}`` for every guess that lay on or outside its ``bounds`` and was
        moved strictly inside before the iteration (see :meth:`torchql.bounds.Bounds.move_inside`);
        the guesses used start the iteration (``history[0]`` where it starts from them, see
        :attr:`history`). Empty when none was moved.
    nll : float
        The negative log-likelihood of the data at the estimates (:mod:`torchql.noise`; for
        log-normal noise, of ``y`` itself). AIC and BIC in :meth:`report` follow from it.
    sigma : dict of str to float, or None
        The estimated standard deviations by group (``sigma="estimate"``); ``None`` otherwise.
        The weights, residuals, ``sse`` and covariance are then at these sigmas.
    sigma_stderr : dict of str to float, or None
        The estimated sigmas' standard errors (NaN when the fit did not converge).
    noise : str
        The data's noise distribution, ``"normal"`` or ``"lognormal"``.
    sigma_function : bool
        Whether the data's sigma was a function ``sigma(p)`` of the coefficients
        (:mod:`torchql.sigma_function`): the fit then maximized the likelihood, ``sse`` is the
        weighted sum of squares at the estimates' sigmas, and ``nll`` the objective.
    """

    success: bool
    status: Status
    message: str
    params: dict[str, torch.Tensor]
    x0: torch.Tensor
    t0: float
    unknown_names: list[str]
    estimates: torch.Tensor
    iterations: int
    history: list[IterationRecord]
    sse: float
    residuals: torch.Tensor
    jacobian: torch.Tensor
    exact_residual: float
    singular_values: torch.Tensor
    covariance: torch.Tensor
    dof: int
    residual_variance: float
    sigma_known: bool
    exact_mask: torch.Tensor
    n_observations: int
    nfev: int
    method: str
    model: "ODEModel"
    solver_options: dict = field(default_factory=dict, repr=False)
    data: "Observations | None" = field(default=None, repr=False)
    fit_kwargs: dict = field(default_factory=dict, repr=False)
    experiment_t0: list[float] | None = field(default=None, repr=False)
    conditions: list[dict] | None = field(default=None, repr=False)
    lower: torch.Tensor | None = field(default=None, repr=False)
    upper: torch.Tensor | None = field(default=None, repr=False)
    log_scaled: list[str] = field(default_factory=list, repr=False)
    moved_guesses: dict[str, tuple[float, float]] = field(default_factory=dict, repr=False)
    index: int | None = field(default=None, repr=False)
    nll: float = field(default=math.nan, repr=False)
    sigma: dict[str, float] | None = field(default=None, repr=False)
    sigma_stderr: dict[str, float] | None = field(default=None, repr=False)
    noise: str = field(default="normal", repr=False)
    sigma_function: bool = field(default=False, repr=False)

    @property
    def options(self) -> "FitOptions":
        """The options the fit ran with (:class:`torchql.FitOptions`), to run another one alike."""
        from .options import FitOptions

        return FitOptions.of(self.fit_kwargs)

    @property
    def likelihood(self) -> bool:
        """Whether the fit maximized a likelihood (estimated sigmas, a ``sigma(p)`` function or
        log-normal noise): its objective is then ``nll``, and ``sse`` alone does not rank fits."""
        return self.sigma is not None or self.noise != "normal" or self.sigma_function

    @property
    def objective(self) -> float:
        """What the fit minimized: ``nll`` where it maximized a likelihood, else ``sse``."""
        return self.nll if self.likelihood else self.sse

    @property
    def stderr(self) -> dict[str, float]:
        """Standard error of every unknown, by name (initial states as ``"y(t0)"``).

        NaN when the fit did not converge (see :attr:`covariance`) and for unknowns the data do
        not determine."""
        diag = torch.diagonal(self.covariance).clamp_min(0).sqrt()
        return {name: float(v) for name, v in zip(self.unknown_names, diag)}

    @property
    def correlation(self) -> torch.Tensor:
        """Correlation matrix of the estimates, ``(m, m)`` in ``unknown_names`` order."""
        sd = torch.diagonal(self.covariance).clamp_min(0).sqrt()
        return self.covariance / sd.unsqueeze(-1) / sd.unsqueeze(0)

    def confidence_intervals(self, level: float = 0.95) -> dict[str, tuple[float, float]]:
        """Wald intervals ``estimate -/+ q * stderr`` at confidence ``level``, by name.

        ``q`` is Student's t quantile with ``dof`` degrees of freedom when the residual
        variance was estimated, the normal quantile when ``sigma`` was known. Wald intervals
        rely on the model being close to linear in the unknowns over the interval.

        A bounded unknown's interval is the Wald interval of its internal variable (``log`` of
        the distance to a single bound, ``logit`` of the position between two) mapped back: it
        lies inside the bounds and is asymmetric; on or near a bound it is the Wald interval
        clipped to the bounds, and with bounds far from the estimate the plain Wald interval
        (:func:`torchql.uncertainty.wald_intervals`).
        Both ends are NaN when the fit did not succeed (a ``NOT_IDENTIFIABLE`` fit keeps the
        intervals of the unknowns the data determine) and for unknowns without a standard error.
        """
        return self._intervals(level)[0]

    def _intervals(self, level: float) -> tuple[dict, dict]:
        """:meth:`confidence_intervals`, and each interval's kind by name (``"wald"``, ``"mapped"``
        from the internal variable or the log scale, ``"clipped"`` to the bounds near one)."""
        from .uncertainty import wald_intervals

        valid = self.success or self.status is Status.NOT_IDENTIFIABLE
        kinds: dict = {}
        intervals = wald_intervals(self.unknown_names, self.estimates, self.stderr, self.dof, self.sigma_known, level,
                                   lower=self.lower, upper=self.upper, valid=valid, kinds=kinds,
                                   log=torch.tensor([u in self.log_scaled for u in self.unknown_names],
                                                    dtype=torch.bool))
        return intervals, kinds

    @property
    def condition_number(self) -> float:
        """Condition number of the column-scaled weighted Jacobian at the estimates.

        ``max / min`` of :attr:`singular_values`; ``inf`` when the problem is rank deficient,
        ``nan`` when the Jacobian could not be evaluated (the fit failed).
        """
        from .report import condition_number

        return condition_number(self)

    def report(self, *, level: float = 0.95, min_correlation: float = 0.1, iterations: bool = True,
               print: bool = False) -> str:
        """A text report of the fit (like lmfit's ``fit_report``); see :func:`torchql.report.fit_report`."""
        from .report import fit_report

        return fit_report(self, level=level, min_correlation=min_correlation, iterations=iterations, print=print)

    def plot_fit(self, data=None, ax=None, experiment: int | None = None):
        """Plot the fit against the data, with a residual panel (with several experiments, that of
        ``experiment``, or every one, a column each); see :func:`torchql.plotting.plot_fit`."""
        from .plotting import plot_fit

        return plot_fit(self, data, ax=ax, experiment=experiment)

    def plot_convergence(self, ax=None, *, values: bool = False):
        """Plot the unknowns and the SSE against iteration; see :func:`torchql.plotting.plot_convergence`."""
        from .plotting import plot_convergence

        return plot_convergence(self, ax=ax, values=values)

    def predict(self, t, experiment: int | None = None, inputs=None) -> torch.Tensor:
        """The fitted trajectory: the model with the estimated coefficients, integrated from ``x0``.

        Parameters
        ----------
        t : Tensor ``(T,)``
            Strictly increasing times; times before ``t0`` are integrated backwards.
        experiment : int, optional
            With several experiments, which one (its initial state and time); required then.
        inputs : Inputs, optional
            For a model with inputs: new input signals (default: the fitted data's, of that
            experiment with several).

        Returns
        -------
        Tensor ``(T, n_states)``
        """
        from .integrate import simulate

        if self._experiment_index(experiment) is None:
            return simulate(self.model, self.x0, t, t0=self.t0, inputs=inputs, **self.solver_options)
        if inputs is None and isinstance(self.data, (list, tuple)):
            inputs = self.data[experiment].inputs
        return simulate(self.experiment_model(experiment), self.x0[experiment], t, t0=self.experiment_t0[experiment],
                        inputs=inputs, **self.solver_options)

    def _experiment_index(self, experiment, when: str = "") -> int | None:
        """``experiment`` checked against this fit: None for a fit of one experiment (where it must be
        None), else an index ``0..E-1`` of its ``E`` experiments (required; ``when``: the condition
        under which it is, for the message). ``ValueError`` naming it otherwise."""
        if self.experiment_t0 is None:
            if experiment is not None:
                raise ValueError(f"`experiment` applies only to fits of several experiments; received {experiment!r} "
                                 "for a fit of one")
            return None
        E = len(self.experiment_t0)
        try:
            index = None if isinstance(experiment, bool) else operator.index(experiment)  # (numpy integers too)
        except TypeError:
            index = None
        if index is None or not 0 <= index < E:
            raise ValueError(f"`experiment` must be an index 0..{E - 1} (the fit has {E} experiments){when}; "
                             f"received {experiment!r}")
        return index

    def experiment_model(self, experiment: int) -> "ODEModel":
        """The fitted model as experiment ``experiment`` sees it: :attr:`model` with that
        experiment's ``conditions`` applied (the model itself without conditions)."""
        from .multi import with_condition

        if self.experiment_t0 is None:  # one experiment: 0
            if isinstance(experiment, bool) or experiment != 0:
                raise ValueError(f"`experiment` must be 0 for a fit of one experiment; received {experiment!r}")
            return self.model
        e = self._experiment_index(experiment)
        return with_condition(self.model, self.conditions[e]) if self.conditions else self.model

    def __repr__(self) -> str:
        est = ", ".join(f"{name}={value:.6g}" for name, value in zip(self.unknown_names, self.estimates.tolist()))
        return (
            f"FitResult(success={self.success}, status={self.status.name}, iterations={self.iterations}, "
            f"sse={self.sse:.6g}, {est})"
        )
