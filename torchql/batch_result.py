"""The result of :func:`torchql.fit_many`: per-sample estimates, statuses and statistics.

``batch[i]`` is sample ``i``'s :class:`torchql.FitResult`, with everything a result of
:func:`torchql.fit` has (report, intervals, prediction, profiles), so that one result type serves
every fit.
"""

from __future__ import annotations

import math
import operator
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import torch

from .result import FitError, FitResult, IterationRecord, Status

if TYPE_CHECKING:  # pragma: no cover
    from .model import ODEModel
    from .options import FitOptions

__all__ = ["BatchFitError", "BatchFitResult", "SampleResult", "concatenate"]


#: One sample of a :class:`BatchFitResult` is a :class:`torchql.FitResult` (the former name of its type).
SampleResult = FitResult


@dataclass
class BatchFitResult:
    """What :func:`torchql.fit_many` found for each of ``B`` independent datasets.

    Attributes
    ----------
    success : bool Tensor ``(B,)``
        Whether each sample converged.
    status : list of Status
        Why each sample stopped (the same statuses as :class:`torchql.FitResult`).
    message : list of str
        Each sample's ``status.value`` plus details.
    params : dict of str to Tensor ``(B, *shape)``
        Every floating-point buffer per sample (estimated ones at their estimates).
    x0 : Tensor ``(B, n_states)``
        Estimated (or fixed) initial states at ``t0``.
    t0 : float or Tensor ``(B,)``
        Time of ``x0``: a float when the samples share it, else each sample's own (with
        per-sample observation times and ``t0`` not given, each sample's first time).
    unknown_names : list of str
        Names of the ``m`` unknowns, in the order of ``estimates``' last axis.
    estimates : Tensor ``(B, m)``
        The estimated unknowns.
    iterations : Tensor ``(B,)`` of int
        Updates applied to each sample (a converged sample stops iterating).
    sse : Tensor ``(B,)``
        Weighted sum of squared residuals of each fitted model (NaN where it failed).
    covariance : Tensor ``(B, m, m)``
        Covariance of each sample's estimates: NaN rows/columns for undetermined unknowns, all
        NaN for a sample whose iteration did not converge (as :attr:`torchql.FitResult.covariance`).
    n_observations : Tensor ``(B,)`` of int
        Values used per sample (NaNs skipped).
    dof : Tensor ``(B,)`` of int
        ``n_observations - m``.
    residual_variance : Tensor ``(B,)``
        ``sse / dof`` when ``sigma`` was not given, else 1.
    sigma_known : bool
        Whether the data's ``sigma`` was given.
    nfev : int
        Right-hand-side evaluations (points of the batched calls, all samples together).
    model : ODEModel
        A copy of the user's model holding the guesses (sample ``i``'s fitted model:
        :meth:`model_of`).
    residuals : Tensor ``(B, R)`` or None
        Weighted residuals of each fitted model at every value slot, ``R = T K`` in time-major
        order (NaN in the slots ``used`` marks missing, and for samples without a final
        evaluation).
    jacobian : Tensor ``(B, R, m)`` or None
        Weighted sensitivities at the estimates, rows as ``residuals`` (zero rows for missing values).
    used : bool Tensor ``(B, R)`` or None
        Which value slots each sample used (its values that are not NaN).
    singular_values : Tensor ``(B, m)`` or None
        Singular values of each column-scaled weighted Jacobian (NaN where not evaluated).
    start_params, start_x0, sse_start
        Each sample's first iterate (``{name: (B, *shape)}``, ``(B, n_states)``) and its sum of
        squares ``(B,)``: the first record of ``batch[i].history``. Integrated from the guesses, the
        first iterate is the guesses; built from the data, its coefficients are those fitted to
        the data's slopes.
    sse_end : Tensor ``(B,)`` or None
        The value of each sample's last record (``batch[i].history[-1].sse``): ``sse``, and where
        the fit maximized a likelihood, its objective ``sse + 2 sum log sigma``, as ``sse_start``
        and :func:`torchql.fit`'s records have it (NaN where the final pass did not evaluate).
    solver_options : dict
        ``solver``, ``rtol``, ``atol`` of the fits (used by ``batch[i].predict``).
    sample_solver_options : list of dict or None
        Each sample's, where they differ (``solver="auto"`` on a batch mixing stiff and non-stiff
        samples: each on the solver its own fit takes); ``batch[i].solver_options`` is sample
        ``i``'s. None where ``solver_options`` is every sample's.
    data : Observations or list of Observations or None
        The datasets fitted (``batch[i].data`` is sample ``i``'s).
    fit_kwargs : dict
        The options :func:`torchql.fit_many` was called with that a re-fit of one sample by
        :func:`torchql.fit` takes (for :func:`torchql.profile` of ``batch[i]``).
    lower, upper : Tensor ``(m,)`` or None
        The ``bounds`` of the unknowns (every sample's), as :attr:`torchql.FitResult.lower`;
        ``None``: no bounds.
    log_scaled : list of str
        The unknowns iterated on a logarithmic scale, as :attr:`torchql.FitResult.log_scaled`.
    moved_guesses : dict of int to dict
        ``{sample: {name: (given, used)}}`` for the samples whose guesses lay on or outside a
        bound and were moved inside (``batch[i].moved_guesses``).
    exact : bool Tensor ``(B, R)`` or None
        The value slots each sample marked ``exact`` (met exactly, left out of ``sse``).
    exact_residual : Tensor ``(B,)`` or None
        Each sample's largest absolute residual over its exact values (0 without any).
    history : list of list of IterationRecord, or None
        Every sample's iterates, when they were kept (:func:`torchql.fit` keeps them; a batch
        keeps only the guesses and the estimates, see :meth:`sample`).
    nll : Tensor ``(B,)`` or None
        Each sample's negative log-likelihood at its estimates (:mod:`torchql.noise`).
    sigma : Tensor ``(B, G)`` or None
        The estimated standard deviations (``sigma="estimate"``), one per group ``sigma_names``.
    sigma_stderr : Tensor ``(B, G)`` or None
        Their standard errors, from the expected information (``sigma / sqrt(2 n_g)`` for a group
        of ``n_g`` values; NaN where the fit did not converge).
    noise : str
        The data's noise distribution.
    sigma_function : bool
        Whether the data's sigma was a function ``sigma(p)`` of the coefficients (the weights,
        residuals and Jacobian are then at its values at each sample's estimates).
    experiment_t0, conditions : list or None
        With several experiments per sample: their initial times and checked ``conditions``
        (shared by the samples, as :class:`torchql.FitResult` has them); ``x0`` is then ``(B, E, n)``.
    """

    success: torch.Tensor
    status: list[Status]
    message: list[str]
    params: dict[str, torch.Tensor]
    x0: torch.Tensor
    t0: float | torch.Tensor
    unknown_names: list[str]
    estimates: torch.Tensor
    iterations: torch.Tensor
    sse: torch.Tensor
    covariance: torch.Tensor
    n_observations: torch.Tensor
    dof: torch.Tensor
    residual_variance: torch.Tensor
    sigma_known: bool
    nfev: int
    model: "ODEModel" = field(repr=False)
    residuals: torch.Tensor | None = field(default=None, repr=False)
    jacobian: torch.Tensor | None = field(default=None, repr=False)
    used: torch.Tensor | None = field(default=None, repr=False)
    singular_values: torch.Tensor | None = field(default=None, repr=False)
    start_params: dict[str, torch.Tensor] | None = field(default=None, repr=False)
    start_x0: torch.Tensor | None = field(default=None, repr=False)
    sse_start: torch.Tensor | None = field(default=None, repr=False)
    sse_end: torch.Tensor | None = field(default=None, repr=False)
    solver_options: dict = field(default_factory=dict, repr=False)
    sample_solver_options: list | None = field(default=None, repr=False)
    data: object = field(default=None, repr=False)
    fit_kwargs: dict = field(default_factory=dict, repr=False)
    lower: torch.Tensor | None = field(default=None, repr=False)
    upper: torch.Tensor | None = field(default=None, repr=False)
    log_scaled: list[str] = field(default_factory=list, repr=False)
    moved_guesses: dict[int, dict[str, tuple[float, float]]] = field(default_factory=dict, repr=False)
    exact: torch.Tensor | None = field(default=None, repr=False)
    exact_residual: torch.Tensor | None = field(default=None, repr=False)
    history: list[list[IterationRecord]] | None = field(default=None, repr=False)
    nll: torch.Tensor | None = field(default=None, repr=False)
    sigma: torch.Tensor | None = field(default=None, repr=False)
    sigma_names: list[str] | None = field(default=None, repr=False)
    sigma_stderr: torch.Tensor | None = field(default=None, repr=False)
    noise: str = field(default="normal", repr=False)
    sigma_function: bool = field(default=False, repr=False)
    experiment_t0: list[float] | None = field(default=None, repr=False)
    conditions: list[dict] | None = field(default=None, repr=False)

    @property
    def options(self) -> "FitOptions":
        """The options the fit ran with (:class:`torchql.FitOptions`), to run another one alike."""
        from .options import FitOptions

        return FitOptions.of(self.fit_kwargs)

    def __len__(self) -> int:
        return int(self.success.shape[0])

    def _index(self, i) -> int:
        """Sample index ``i`` in ``[0, B)``: anything an index may be (an int, a NumPy integer, a
        one-element integer tensor; not a bool), negative counting from the end."""
        B = len(self)
        if isinstance(i, bool) or isinstance(i, torch.Tensor) and (i.dtype == torch.bool or i.numel() != 1):
            raise TypeError(f"a sample index must be an integer; received {_describe(i)}")
        try:
            i = operator.index(i)
        except TypeError:
            raise TypeError(f"a sample index must be an integer; received {_describe(i)}") from None
        if not -B <= i < B:
            raise IndexError(f"sample index {i} is out of range for a batch of {B}")
        return i % B

    def sample(self, i: int) -> FitResult:
        """Sample ``i``'s :class:`torchql.FitResult` (negative indices count from the end).

        As a result of :func:`torchql.fit` on that dataset alone, except: ``history`` holds two
        records (without a ``callback``: ``fit_many`` keeps no iterates in between), the first
        iterate as ``fit``'s first record has it (``start_params``: the guesses integrated, or
        built from the data) and the estimates; ``nfev`` counts the whole batch's evaluations;
        ``index`` is ``i``.
        """
        i = self._index(i)
        nan = float("nan")
        t0 = float(self.t0[i]) if isinstance(self.t0, torch.Tensor) else self.t0
        m = len(self.unknown_names)
        if self.used is not None:
            used = self.used[i]
            residuals, jacobian = self.residuals[i][used].clone(), self.jacobian[i][used].clone()
            singular_values = self.singular_values[i].clone()
        else:  # a result assembled without them (older parts)
            L = int(self.n_observations[i])
            residuals = self.x0.new_full((L,), nan)
            jacobian, singular_values = self.x0.new_full((L, m), nan), self.x0.new_full((m,), nan)
        if not bool(torch.isfinite(singular_values).all()):
            singular_values = singular_values[:0]
        params = {k: v[i].clone() for k, v in self.params.items()}
        history = []
        if self.history is not None:
            history = list(self.history[i])
        elif self.start_params is not None:
            history.append(IterationRecord(iteration=0, params={k: v[i].clone() for k, v in self.start_params.items()},
                                           x0=self.start_x0[i].clone(), sse=float(self.sse_start[i])))
        iterations = int(self.iterations[i])
        if self.history is None:
            last = self.sse if self.sse_end is None else self.sse_end
            history.append(IterationRecord(iteration=iterations, params={k: v.clone() for k, v in params.items()},
                                           x0=self.x0[i].clone(), sse=float(last[i])))
        exact = (self.exact[i][self.used[i]].clone() if self.exact is not None and self.used is not None
                 else torch.zeros(residuals.shape[0], dtype=torch.bool, device=residuals.device))
        exact_residual = (float(self.exact_residual[i]) if self.exact_residual is not None
                          else 0.0 if math.isfinite(float(self.sse[i])) else nan)
        data = self.data
        if data is not None:
            data = data[i]
        return FitResult(
            success=bool(self.success[i]), status=self.status[i], message=self.message[i], params=params,
            x0=self.x0[i].clone(), t0=t0, unknown_names=list(self.unknown_names),
            estimates=self.estimates[i].clone(), iterations=iterations, history=history, sse=float(self.sse[i]),
            residuals=residuals, jacobian=jacobian, exact_residual=exact_residual,
            singular_values=singular_values, covariance=self.covariance[i].clone(), dof=int(self.dof[i]),
            residual_variance=float(self.residual_variance[i]), sigma_known=self.sigma_known,
            exact_mask=exact,
            n_observations=int(self.n_observations[i]), nfev=int(self.nfev),
            method=self._method_name(),
            model=self.model_of(i), data=data,
            solver_options=dict(self.solver_options if self.sample_solver_options is None
                                else self.sample_solver_options[i]),
            fit_kwargs=dict(self.fit_kwargs), index=i,
            lower=None if self.lower is None else self.lower.clone(),
            upper=None if self.upper is None else self.upper.clone(),
            log_scaled=list(self.log_scaled),
            moved_guesses=dict(self.moved_guesses.get(i, {})),
            nll=math.nan if self.nll is None else float(self.nll[i]),
            sigma=None if self.sigma is None else dict(zip(self.sigma_names, self.sigma[i].tolist())),
            sigma_stderr=(None if self.sigma_stderr is None
                          else dict(zip(self.sigma_names, self.sigma_stderr[i].tolist()))),
            noise=self.noise, sigma_function=self.sigma_function,
            experiment_t0=None if self.experiment_t0 is None else list(self.experiment_t0),
            conditions=self.conditions)

    def _method_name(self) -> str:
        """The scheme's name (``method=`` may have been a :class:`torchql.schemes.Scheme`), as ``fit`` reports it."""
        method = self.fit_kwargs.get("method", "kantorovich")
        return method if isinstance(method, str) else method.name

    def __getitem__(self, i: int) -> FitResult:
        return self.sample(i)

    def __iter__(self):
        return (self.sample(i) for i in range(len(self)))

    @property
    def stderr(self) -> torch.Tensor:
        """Standard errors ``(B, m)`` of the estimates (NaN where undetermined)."""
        return torch.diagonal(self.covariance, dim1=-2, dim2=-1).clamp_min(0).sqrt()

    def model_of(self, i: int) -> "ODEModel":
        """A copy of the model whose buffers hold sample ``i``'s estimates."""
        import copy

        from .model import _set_buffer, attach_inputs

        i = self._index(i)
        fitted = copy.deepcopy(self.model)
        for name, value in self.params.items():
            _set_buffer(fitted, name, value[i].clone())
        inputs = self._inputs_of(i)
        if inputs is not None and getattr(fitted, "input_names", ()):  # sample i's own inputs
            dtype, device = self.x0.dtype, self.x0.device
            attach_inputs(fitted, inputs.select(fitted.input_names).to(dtype, device))
        return fitted

    def _inputs_of(self, i: int):
        """Sample ``i``'s measured inputs from the fitted data, or ``None``."""
        data = self.data
        if isinstance(data, (list, tuple)):
            own = data[i]
            return None if isinstance(own, (list, tuple)) else own.inputs  # several experiments: each its own
        return data.inputs_of(i) if data is not None else None

    def summary(self) -> str:
        """A short text summary: statuses counted, iterations, and the spread of the estimates."""
        B = len(self)
        ok = self.success
        lines = [f"fit_many: {B} samples, {int(ok.sum())} converged, {B - int(ok.sum())} not"]
        for status, count in Counter(s.name for s in self.status).most_common():
            lines.append(f"  {status:<18} {count}")
        it = self.iterations.to(torch.float64)
        lines.append(f"iterations: min {int(it.min())}, median {float(it.median()):g}, max {int(it.max())}")
        if bool(ok.any()):
            est = self.estimates[ok]
            lines.append(f"{'unknown':<14} {'mean':>13} {'std':>13} {'min':>13} {'max':>13}  (converged samples)")
            for k, name in enumerate(self.unknown_names):
                col = est[:, k]
                std = float(col.std()) if col.numel() > 1 else math.nan
                lines.append(f"{name:<14} {float(col.mean()):13.6g} {std:13.6g} {float(col.min()):13.6g} "
                             f"{float(col.max()):13.6g}")
        failed = [i for i in range(B) if not bool(ok[i])]
        if failed:
            shown = ", ".join(f"{i} ({self.status[i].name})" for i in failed[:10])
            lines.append(f"not converged: {shown}" + (" ..." if len(failed) > 10 else ""))
        return "\n".join(lines)

    def __repr__(self) -> str:
        return (f"BatchFitResult(B={len(self)}, converged={int(self.success.sum())}, "
                f"unknowns={self.unknown_names})")


class BatchFitError(FitError):
    """Raised by ``fit_many(..., throw=True)`` when some sample does not converge: ``.result``
    holds the whole :class:`BatchFitResult`, ``.failed`` the indices of the samples that failed.
    A :class:`torchql.FitError`, so that one ``except`` serves ``fit`` and ``fit_many``."""

    def __init__(self, result: BatchFitResult) -> None:
        failed = [i for i, ok in enumerate(result.success.tolist()) if not ok]
        shown = "; ".join(f"sample {i}: {result.message[i]}" for i in failed[:3])
        RuntimeError.__init__(self, f"{len(failed)} of {len(result)} samples did not converge ({shown}"
                                    + ("; ...)" if len(failed) > 3 else ")"))
        self.result = result
        self.failed = failed


def _initial_times(parts: Sequence[BatchFitResult]) -> float | torch.Tensor:
    """The parts' ``t0``: a float when every sample of every part shares it, else one per sample ``(B,)``."""
    if all(not isinstance(p.t0, torch.Tensor) for p in parts) and len({p.t0 for p in parts}) == 1:
        return parts[0].t0
    return torch.cat([p.t0 if isinstance(p.t0, torch.Tensor)
                      else torch.full((len(p.status),), p.t0, dtype=p.x0.dtype, device=p.x0.device) for p in parts])


def concatenate(parts: Sequence[BatchFitResult]) -> BatchFitResult:
    """One :class:`BatchFitResult` from consecutive parts (same model, unknowns and settings), in order."""
    first = parts[0]
    return BatchFitResult(
        success=torch.cat([p.success for p in parts]),
        status=[s for p in parts for s in p.status],
        message=[m for p in parts for m in p.message],
        params={name: torch.cat([p.params[name] for p in parts]) for name in first.params},
        x0=torch.cat([p.x0 for p in parts]),
        t0=_initial_times(parts),
        unknown_names=list(first.unknown_names),
        estimates=torch.cat([p.estimates for p in parts]),
        iterations=torch.cat([p.iterations for p in parts]),
        sse=torch.cat([p.sse for p in parts]),
        covariance=torch.cat([p.covariance for p in parts]),
        n_observations=torch.cat([p.n_observations for p in parts]),
        dof=torch.cat([p.dof for p in parts]),
        residual_variance=torch.cat([p.residual_variance for p in parts]),
        sigma_known=first.sigma_known,
        nfev=int(math.fsum(p.nfev for p in parts)),
        model=first.model,
        **_joined_evaluations(parts),
        solver_options=dict(first.solver_options),
        sample_solver_options=_joined_solver_options(parts),
        fit_kwargs=dict(first.fit_kwargs),
        lower=first.lower,
        upper=first.upper,
        log_scaled=list(first.log_scaled),
        moved_guesses=_joined_moves(parts),
        nll=None if any(p.nll is None for p in parts) else torch.cat([p.nll for p in parts]),
        sigma=None if any(p.sigma is None for p in parts) else torch.cat([p.sigma for p in parts]),
        sigma_names=first.sigma_names,
        sigma_stderr=(None if any(p.sigma_stderr is None for p in parts)
                      else torch.cat([p.sigma_stderr for p in parts])),
        noise=first.noise,
        sigma_function=first.sigma_function,
        history=None if any(p.history is None for p in parts) else [h for p in parts for h in p.history],
        experiment_t0=first.experiment_t0,
        conditions=first.conditions,
    )


def _joined_solver_options(parts: Sequence[BatchFitResult]) -> list | None:
    """Each sample's solver options where the parts' differ (else None: the first part's are all's)."""
    per_sample = [dict(p.solver_options if p.sample_solver_options is None else p.sample_solver_options[i])
                  for p in parts for i in range(len(p.status))]
    return None if all(options == per_sample[0] for options in per_sample) else per_sample


def _joined_moves(parts: Sequence[BatchFitResult]) -> dict:
    """The parts' moved guesses, keyed by each sample's index in the joined batch."""
    out, offset = {}, 0
    for p in parts:
        out.update({offset + b: moved for b, moved in p.moved_guesses.items()})
        offset += len(p)
    return out


def _joined_evaluations(parts: Sequence[BatchFitResult]) -> dict:
    """The parts' per-sample final evaluations and starts, joined (``None`` unless every part has them)."""
    out = {}
    for key in ("residuals", "jacobian", "used", "singular_values", "start_x0", "sse_start", "sse_end", "exact",
                "exact_residual"):
        values = [getattr(p, key) for p in parts]
        out[key] = torch.cat(values) if all(v is not None for v in values) else None
    starts = [p.start_params for p in parts]
    out["start_params"] = ({name: torch.cat([s[name] for s in starts]) for name in starts[0]}
                           if all(s is not None for s in starts) else None)
    return out


def _describe(i) -> str:
    """A rejected index, as an error message names it: its type, and a tensor's shape and dtype."""
    if isinstance(i, torch.Tensor):
        return f"a tensor of shape {tuple(i.shape)} and dtype {i.dtype}"
    return type(i).__name__
