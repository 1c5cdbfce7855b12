"""A fitted model against data it was not fitted to: the fit percentage (NRMSE) per output.

:func:`compare` simulates the fitted model with the validation experiment's own inputs, from the
fit's initial state (or a given one), and measures each output by the normalized root-mean-square
error fit of system identification (MATLAB's ``compare``, ``goodnessOfFit(..., 'NRMSE')``):

    fit_k = 100 (1 - ||y_k - yhat_k|| / ||y_k - mean(y_k)||)   (percent),

over the values present (NaN skipped). 100 is a perfect prediction, 0 no better than the
measured mean, and it is negative for a worse one.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import torch

from ._checks import finite_number
from .integrate import simulate
from .model import coefficients
from .observations import ObservationOperator, Observations
from .result import FitResult

__all__ = ["Comparison", "compare", "fit_percent"]


def fit_percent(y: torch.Tensor, predicted: torch.Tensor) -> torch.Tensor:
    """NRMSE fit in percent per column of ``y (T, K)`` against ``predicted (T, K)``; NaN values of
    ``y`` are skipped. A column with no spread about its mean gives NaN."""
    present = ~torch.isnan(y)
    count = present.sum(dim=0).clamp(min=1)
    zero = torch.zeros_like(y)
    mean = torch.where(present, y, zero).sum(dim=0) / count
    error = torch.where(present, y - predicted, zero).norm(dim=0)
    spread = torch.where(present, y - mean, zero).norm(dim=0)
    return torch.where(spread > 0, 100.0 * (1.0 - error / spread.clamp(min=torch.finfo(y.dtype).tiny)),
                       torch.full_like(spread, float("nan")))


@dataclass
class Comparison:
    """The result of :func:`compare`.

    Attributes
    ----------
    fit_percent : Tensor ``(K,)``
        NRMSE fit of each output, in percent (see :mod:`torchql.compare`).
    t : Tensor ``(T,)``
        The validation data's times.
    y : Tensor ``(T, K)``
        Its measured values (NaN where missing).
    predicted : Tensor ``(T, K)``
        The fitted model's outputs at those times.
    states : Tensor ``(T, n_states)``
        The simulated states.
    output_names : list of str
        A label per output (the observed state names, else ``"y[k]"``).
    """

    fit_percent: torch.Tensor
    t: torch.Tensor
    y: torch.Tensor
    predicted: torch.Tensor
    states: torch.Tensor
    output_names: list[str] = field(default_factory=list)
    #: the fitted model's outputs at any times ``(Q,) -> (Q, K)`` in the data's span (for plots)
    curve: Callable[[torch.Tensor], torch.Tensor] | None = field(default=None, repr=False)

    def plot(self, ax=None):
        """Measured and simulated outputs with their fit percentages; see
        :func:`torchql.plotting.plot_comparison`."""
        from .plotting import plot_comparison

        return plot_comparison(self, ax=ax)

    def __repr__(self) -> str:
        fits = ", ".join(f"{name}: {value:.2f}%" for name, value in zip(self.output_names, self.fit_percent.tolist()))
        return f"Comparison({fits})"


def compare(result: "FitResult", data: Observations, *, x0=None, t0: float | None = None,
            experiment: int | None = None) -> Comparison:
    """Simulate a fitted model on validation data and give each output's fit percentage (NRMSE).

    Parameters
    ----------
    result : FitResult
        A fit (its ``model`` holds the estimates).
    data : Observations
        One validation experiment: its times, values and ``observe``, and for a model with inputs
        its own :class:`~torchql.Inputs`.
    x0 : Tensor ``(n_states,)``, optional
        The validation experiment's initial state at ``t0``. Default: the fit's estimated
        ``x0`` at the fit's ``t0`` (the same initial condition; with several experiments, that of
        ``experiment``).
    t0 : float, optional
        Time of ``x0``; default the data's first time when ``x0`` is given, else the fit's ``t0``.
    experiment : int, optional
        With a fit of several experiments, whose initial state is the default ``x0`` and whose
        ``conditions`` (coefficient values) apply: required where ``x0`` is not given, or where
        the fit's ``conditions`` give its experiments their own coefficients.

    Returns
    -------
    Comparison
        ``fit_percent (K,)``, the measured and predicted outputs, and ``plot()``.

    Examples
    --------
    >>> comparison = torchql.compare(result, validation)   # doctest: +SKIP
    >>> comparison.fit_percent                              # doctest: +SKIP
    tensor([97.31])
    """
    if not isinstance(result, FitResult):
        what = " (compare one fit of it: `result[i]`)" if type(result).__name__ == "BatchFitResult" else ""
        raise TypeError(f"`result` must be a torchql.FitResult{what}; received {type(result).__name__}")
    if not isinstance(data, Observations) or data.batch_size is not None:
        received = type(data).__name__ if not isinstance(data, Observations) else f"a batch of {data.batch_size}"
        raise TypeError(f"`data` must be one torchql.Observations (a validation experiment); received {received}")
    if result.experiment_t0 is None:
        result._experiment_index(experiment)  # (None: a fit of one experiment takes none)
    model = result.model
    dtype = result.estimates.dtype
    device = result.estimates.device
    if x0 is None:
        if result._experiment_index(experiment, " when `x0` is not given") is not None:
            x0, start = result.x0[experiment], result.experiment_t0[experiment]
            model = result.experiment_model(experiment)
        else:
            x0, start = result.x0, result.t0
        if t0 is not None:
            start = finite_number("t0", t0)
    else:
        start = float(data.t[0]) if t0 is None else finite_number("t0", t0)
        if result.experiment_t0 is not None and (experiment is not None or any(result.conditions or ())):
            model = result.experiment_model(result._experiment_index(
                experiment, " when its `conditions` give the experiments their own coefficients"))
    takes = tuple(getattr(model, "input_names", ()))
    if takes and data.inputs is None:  # the fitted model still holds the training signal: never use it here
        raise ValueError(f"`model` takes inputs {takes} (its `input_names`) but `data` carries none: give the "
                         f"validation experiment its own, Observations(t, y, observe, inputs=torchql.Inputs(t_u, u, "
                         f"names={list(takes)}))")
    t = data.t.to(dtype=dtype, device=device)
    names = list(model.state_names)
    operator = ObservationOperator(data.observe, names, data.n_outputs, dtype, device)

    curve = _Outputs(model, x0, float(start), data.inputs, dict(result.solver_options), operator)
    states, predicted = curve.with_states(t)
    y = data.y.to(dtype=dtype, device=device)
    return Comparison(fit_percent=fit_percent(y, predicted), t=t, y=y, predicted=predicted, states=states,
                      output_names=operator.labels(), curve=curve)


class _Outputs:
    """The fitted model's outputs at any times, ``(Q,) -> (Q, K)``: a :class:`Comparison`'s ``curve``
    (an object, not a closure, so that the comparison pickles)."""

    def __init__(self, model, x0, start: float, inputs, solver_options: dict, operator: ObservationOperator) -> None:
        self.model, self.x0, self.start, self.inputs = model, x0, start, inputs
        self.solver_options, self.operator = solver_options, operator

    def with_states(self, times: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The simulated states ``(Q, n_states)`` and outputs ``(Q, K)`` at ``times``."""
        states = simulate(self.model, self.x0, times, t0=self.start, inputs=self.inputs, **self.solver_options)
        return states, self.operator.values(states, coefficients(self.model)).detach()

    def __call__(self, times: torch.Tensor) -> torch.Tensor:
        return self.with_states(times)[1]
