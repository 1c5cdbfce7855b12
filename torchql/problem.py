"""The validated fitting problem: model, data stacked ``(B, T, K)``, unknowns, guesses, bounds, grid.

One class, :class:`Problem`, for one dataset (:func:`torchql.fit`, ``single=True``: its errors
worded for one dataset) and for ``B`` of them (:func:`torchql.fit_many`); the iteration
(:mod:`torchql.engine`) runs on it.
"""

from __future__ import annotations

import copy
import warnings

import torch
from torch.func import vmap

from . import _checks
from ._arrays import float_tensor
from .batch_result import BatchFitResult
from .bounds import Bounds, moved_record
from .data_start import derivation_uses_unknowns, first_reference
from .dopri import dopri_batch
from .grid import AUTO_PROBE, SMOOTH_RTOL, SMOOTH_SAMPLES, make_grid, make_grids, smooth_intervals
from .integrate import check_solver
from .linearize import linearize, load_forward_mode
from .local_time import local_origin, reads_time
from .model import AugmentedSystem, attach_inputs, coefficient_names, model_dtype_device
from .estimated_noise import EstimatedNoise
from .noise import sigma_group_index
from .sigma_function import SigmaFunction
from .observations import LogObservation, ObservationOperator, Observations
from .damping import damping_strategy
from .datasets import check_data, shared_inputs
from .options import Limits, Tolerances, check_scheme
from .solvers import STIFF_SOLVERS
from .stiffness import AUTO, STIFF_SOLVER, choose_solver, linear_solver_for
from .superposition import DEFAULT_LINEAR_SOLVER, check_linear_solver, initial_columns
from .uncertainty import residual_variance
from .initial_state import InitialStateExpressions, check_expressions

__all__ = ["Problem"]


class Problem:
    """The validated problem shared by every chunk: model, data stacked ``(B, T, K)``, guesses, grid.

    Times: ``t_obs (T,)``, ``t0 ()``, ``grid (G,)`` and ``obs_in_grid (T,)`` when the samples share
    them (``grid_size`` is ``None``); else ``t_obs (B, T)``, ``t0 ()`` or ``(B,)``, each sample's
    grid padded ``grid (B, G)`` with its own number of nodes ``grid_size (B,)``, ``obs_in_grid (B, T)``.
    """

    def __init__(self, model, data, x0, params, guesses, fixed_x0, t0, max_iter, rtol, atol, xtol, ftol, rcond,
                 grid, damping, solver, max_steps, bounds=None, linear_solver=None,
                 method="kantorovich", initial_trajectory="auto", single: bool = False, scale=None,
                 x0_expr=None) -> None:
        self.single = single  # torchql.fit's problem: one dataset, errors worded for it
        _checks.model_class(model)
        names = tuple(model.state_names)
        self._options(model, solver, damping, method, initial_trajectory, linear_solver, max_iter, max_steps,
                      rtol, atol, xtol, ftol, rcond)
        self._stack(data, self.dtype, self.device)  # data: (B, T, K)
        user_model = model
        #: ``sigma="estimate"``: the sigmas as unknowns of the fit (:mod:`torchql.estimated_noise`)
        self.estimated_noise = None
        if self.sigma_estimated:
            model, params, guesses, bounds, scale = self._estimated_noise(model, params, guesses, bounds, scale)
        per_sample, p0 = self._coefficients(model, params, guesses)
        system = self.system
        # --- times: t_obs (T,) shared or (B, T) per sample, t0 () shared or (B,) per sample
        self.t_obs = self.t
        self.t0 = self._initial_time(t0)
        #: the fit's local time origin (:meth:`_attach_inputs`); ``t0`` and the inputs in the data's time
        self.origin, self.data_t0, self.data_inputs = 0.0, self.t0, None
        # --- initial states
        self.operator = ObservationOperator(self.observe, names, self.K, self.dtype, self.device).bind(system)
        self.initial = InitialStateExpressions(
            check_expressions(x0_expr, names, None if fixed_x0 is None or isinstance(fixed_x0, str) else fixed_x0),
            system)
        x0 = self._x0_from_data(names) if x0 is None else self._given_x0(x0, len(names))
        self.z0 = torch.cat([x0, p0], dim=1).clone()
        self._noise_model()
        self.sigma_function = (None if self.sigma_callable is None
                               else SigmaFunction(self.sigma_callable, system, self.K))
        free = self._unknowns(fixed_x0, names, per_sample)
        # --- bounds, the same for every sample (guesses on or outside one moved inside, per sample)
        # (the estimated coefficients come first among the per-sample ones, so the zip stops at them)
        self.bounds = Bounds.for_unknowns(bounds, self.unknown_names, len(free), self.params, system.param_sizes,
                                          list(names) + list(coefficient_names(model)), self.dtype, self.device,
                                          scale)
        self._move_guesses_inside()
        if self.initial:
            self.initial.check(self.z0)
            self.z0 = self.initial.complete(self.z0)
        self.breakpoints = self._attach_inputs(model)
        self._check_model(self.z0[0, :system.n])
        if self.inputs is None and not reads_time(system, self.t0, self.t_obs, self.z0[0]):
            self._local_time(per_sample=True)  # (a forward that reads t is given the data's own)
        #: the options as given, for :meth:`stiff_variant`
        self.given = dict(solver=self.solver, grid=grid, linear_solver=linear_solver,
                          initial_trajectory=self.initial_trajectory)
        self._solver_and_grid(grid, linear_solver)
        self._first_references()
        self.model = user_model

    def _first_references(self) -> None:
        """The first reference of the fit (``initial_trajectory``, see
        :func:`~torchql.data_start.first_reference`) and ``"auto"``'s other one, ``start_fallback``."""
        given = self.given["initial_trajectory"]
        t0 = self.t0 if self.t0.dim() == 0 else self.t0[0]

        def choose(stiff: bool) -> str:
            return first_reference(given, self.scheme, self.operator.observed_states, self.mask, stiff=stiff,
                                   max_iter=self.max_iter, derivation_uses_unknowns=lambda measured:
                                   derivation_uses_unknowns(self.system, measured, self.unknown_index, self.z0[0], t0))
        self.initial_trajectory = choose(self.stiff)
        #: ``"auto"``'s other first reference (None: none): a sample whose fit from the chosen one
        #: fails is fitted again from it. The integrated guesses after the data; the data after
        #: the integrated guesses where only the stiffness chose these (the data's values are
        #: the one start that does not depend on how poor the guesses are)
        self.start_fallback = None
        if given == "auto" and self.initial_trajectory == "data":
            self.start_fallback = "integrate"
        elif given == "auto" and self.stiff and choose(False) == "data":
            self.start_fallback = "data"

    @property
    def stiff_refit(self) -> bool:
        """Whether a sample that an explicit pair finds stiff during the fit is fitted again by
        the stiff solver (:meth:`stiff_variant`): ``solver="auto"`` chose the explicit one."""
        return self.given["solver"] == AUTO and not self.stiff

    def stiff_variant(self) -> "Problem":
        """This problem as ``solver="auto"`` would have set it up had it found the model stiff: the
        stiff solver, its linear solver (unless one was given), grid and first references; the
        data, unknowns and guesses shared."""
        other = copy.copy(self)
        other.solver = STIFF_SOLVER
        other._solver_and_grid(self.given["grid"], self.given["linear_solver"])
        other._first_references()
        return other

    def _options(self, model, solver, damping, method, initial_trajectory, linear_solver, max_iter, max_steps,
                 rtol, atol, xtol, ftol, rcond) -> None:
        """The options validated, and the tolerances resolved for the model's dtype."""
        if not isinstance(solver, str):
            raise TypeError(f"`solver` must be a string; received {type(solver).__name__}")
        check_solver(solver, auto=True)
        self.damping, self.solver = damping_strategy(damping), solver
        self.scheme, self.initial_trajectory = check_scheme(method, initial_trajectory)
        self.method = self.scheme.name
        if linear_solver is not None:
            check_linear_solver(linear_solver)
        limits = Limits.resolve(max_iter, max_steps)
        self.max_iter, self.max_steps = limits.max_iter, limits.max_steps
        self.dtype, self.device = dtype, _ = model_dtype_device(model)
        tol = Tolerances.resolve(dtype, rtol, atol, xtol, ftol, rcond)
        self.rtol, self.atol, self.xtol, self.ftol, self.rcond = tol.rtol, tol.atol, tol.xtol, tol.ftol, tol.rcond

    def _estimated_noise(self, model, params, guesses, bounds, scale):
        """``sigma="estimate"``: the model's copy holding the sigmas as coefficients, and ``params``,
        ``guesses``, ``bounds`` and ``scale`` with them added (log scale, bounded below by the floor,
        started from the data's scatter). Arguments of the wrong type are passed on unchanged, for
        their own checks to name."""
        names = tuple(model.state_names)
        labels = ObservationOperator(self.observe, names, self.K, self.dtype, self.device).labels()
        group_names, group = sigma_group_index(self.sigma_groups, self.K, labels)
        self._check_groups_measured(group_names, group, labels)
        noise = self.estimated_noise = EstimatedNoise(group_names, group, list(coefficient_names(model)) + list(names))
        y = self.y
        if self.noise == "lognormal":
            y = torch.log(torch.where(self.mask & (y > 0), y, torch.ones_like(y)))
        self.sigma_callable = noise
        return noise.added(model, params, guesses, bounds, scale, noise.start(self.t, y, self.mask),
                           noise.floor(y, self.mask))

    def _check_groups_measured(self, group_names, group, labels) -> None:
        """``sigma="estimate"``: every sigma group has values in every sample (a ``ValueError`` naming the
        first that has none: nothing would determine its sigma)."""
        present = self.mask.reshape(self.B, -1, self.K).sum(dim=1)  # (B, K)
        for g, name in enumerate(group_names):
            outputs = [k for k in range(self.K) if group[k] == g]
            empty = (present[:, outputs].sum(dim=1) == 0).nonzero().flatten().tolist()
            if empty:
                where = "" if self.single else f" of `data[{empty[0]}]`"
                raise ValueError(f'`sigma="estimate"`: the output(s) {[labels[k] for k in outputs]} of sigma group '
                                 f"{name!r} have no values{where}, so nothing determines their sigma: leave them out "
                                 "of `observe`, or give their `sigma`")

    def _coefficients(self, model, params, guesses) -> tuple[list[str], torch.Tensor]:
        """The estimated coefficients (``self.params``), the augmented system over them and the
        coefficients given per sample (``guesses``); returns the per-sample names and their values
        ``(B, P)`` (the guesses of the estimated ones first)."""
        B, dtype, device = self.B, self.dtype, self.device
        available = [name for name in coefficient_names(model) if name not in getattr(model, "internal_buffers", ())]
        if params is None:
            params = [name for name in available if name not in tuple(model.constants)]
        else:
            params = _checks.distinct_names("params", params, available, "buffer", _checks.coefficients_text(model))
        if guesses is None:
            guesses = {}
        if not isinstance(guesses, dict):
            raise TypeError(f"`guesses` must be a dict {{buffer name: Tensor (B, ...)}}; received {type(guesses).__name__}")
        for name in guesses:
            if name not in available:
                raise ValueError(f"`guesses` names unknown buffer {name!r}; {_checks.coefficients_text(model)}")
        per_sample = list(params) + [name for name in guesses if name not in params]
        self.params = list(params)
        self.system = system = AugmentedSystem(model, per_sample, dtype, device)
        buffers = dict(system.model.named_buffers())
        columns = [self._per_sample_values(name, shape, guesses, buffers)
                   for name, shape in zip(per_sample, system.param_shapes)]
        p0 = torch.cat(columns, dim=1) if columns else torch.zeros(B, 0, dtype=dtype, device=device)
        if not bool(torch.isfinite(p0).all()):
            raise ValueError(f"the guesses of {self.params} (the model's buffers) must be finite")
        return per_sample, p0

    def _per_sample_values(self, name: str, shape, guesses: dict, buffers: dict) -> torch.Tensor:
        """Coefficient ``name``'s value per sample, flattened ``(B, size)``: ``guesses[name]`` or the buffer's."""
        B = self.B
        value = guesses.get(name, buffers[name])
        value = float_tensor(value, f"guesses[{name!r}]", self.dtype, self.device,
                             expected=f"a tensor of shape (B, *{tuple(shape)}) = {(B, *shape)}")
        if value.shape == shape:
            value = value.expand(B, *shape)
        elif value.shape != (B, *shape):
            raise ValueError(f"`guesses[{name!r}]` must have shape (B, *buffer shape) = {(B, *shape)} or the "
                             f"buffer's shape {tuple(shape)}; received shape {tuple(value.shape)}")
        bad = ~torch.isfinite(value.reshape(B, -1)).all(dim=1)
        if bool(bad.any()) and name not in guesses:
            raise ValueError(f"the guesses of [{name!r}] (the model's buffers) must be finite")
        if bool(bad.any()):
            raise ValueError(f"`guesses[{name!r}]` must be finite; samples {bad.nonzero().flatten().tolist()[:10]} "
                             "hold NaN or inf")
        return value.reshape(B, -1)

    def _given_x0(self, x0, n: int) -> torch.Tensor:
        """The given ``x0`` validated, per sample ``(B, n)``."""
        B, single = self.B, self.single
        shapes = f"(n_states,) = ({n},)" if single else f"(B, n_states) = ({B}, {n}) or (n_states,) = ({n},)"
        x0 = float_tensor(x0, "x0", self.dtype, self.device, expected=f"a tensor of shape {shapes}")
        if single and x0.shape != (n,):
            raise ValueError(f"`x0` must have shape (n_states,) = ({n},); received shape {tuple(x0.shape)}")
        if single and not bool(torch.isfinite(x0).all()):
            raise ValueError("`x0` must be finite; received NaN or inf")
        if x0.shape == (n,):
            x0 = x0.expand(B, n)
        elif x0.shape != (B, n):
            raise ValueError(f"`x0` must have shape (B, n_states) = ({B}, {n}) or (n_states,) = ({n},); "
                             f"received shape {tuple(x0.shape)}")
        bad = ~torch.isfinite(x0).all(dim=1)
        if bool(bad.any()):
            raise ValueError(f"`x0` must be finite; rows {bad.nonzero().flatten().tolist()[:10]} hold NaN or inf")
        return x0

    def _unknowns(self, fixed_x0, names: tuple, per_sample: list[str]) -> list[int]:
        """``unknown_index``, ``unknown_names`` and ``m`` (the free initial states, then the estimated
        coefficients' elements), checked against the data; returns the free states' indices."""
        system, n = self.system, len(names)
        fixed_x0 = _checks.distinct_names("fixed_x0", [] if fixed_x0 is None else fixed_x0, names, "state",
                                          f"the model's states are {names}")
        free = [i for i, s in enumerate(names) if s not in fixed_x0 and i not in self.initial.index]
        n_unknown_params = sum(size for name, size in zip(per_sample, system.param_sizes) if name in self.params)
        self.unknown_index = torch.tensor(free + list(range(n, n + n_unknown_params)), dtype=torch.long,
                                          device=self.device)
        self.unknown_names = [f"{names[i]}(t0)" for i in free] + system.element_names[:n_unknown_params]
        self.m = m = self.unknown_index.numel()
        if m == 0:
            raise ValueError("nothing to estimate: every initial state is in `fixed_x0` and `params` is empty")
        short = (self.L < m).nonzero().flatten().tolist()
        if short and self.single:
            raise ValueError(
                f"fewer usable observations ({int(self.L[0])}) than unknowns ({m}: {self.unknown_names}); "
                "add observations, or fix some unknowns with `params=`/`fixed_x0=`")
        if short:
            i = short[0]
            raise ValueError(f"`data[{i}]` has {int(self.L[i])} usable values, fewer than the {m} unknowns "
                             f"{self.unknown_names}" + (f" (samples {short[:10]} alike)" if len(short) > 1 else "")
                             + "; remove it from the batch or fix some unknowns")
        marked = self.exact.flatten(1).sum(dim=1)
        over = (marked > m).nonzero().flatten().tolist()
        if over:
            where = "" if self.single else f"`data[{over[0]}]`: "
            raise ValueError(
                f"{where}more values are marked `exact` ({int(marked[over[0]])}) than there are unknowns ({m}); "
                "at most one exact value per unknown can be met")
        return free

    def _move_guesses_inside(self) -> None:
        """Guesses on or outside their bounds moved inside, per sample (``moved_guesses`` records them)."""
        self.moved_guesses: dict[int, dict[str, tuple[float, float]]] = {}
        if not self.bounds.active:
            return
        given = self.z0[:, self.unknown_index]
        used, moved = self.bounds.move_inside(given)
        for b in moved.any(dim=1).nonzero().flatten().tolist():
            self.moved_guesses[b] = moved_record(self.unknown_names, given[b], used[b], moved[b])
        self._check_positive(used)
        self.z0[:, self.unknown_index] = used

    def _solver_and_grid(self, grid, linear_solver) -> None:
        """The solver (``"auto"``: stiff if some sample's model is stiff along its data; ``fit_many``
        splits a batch that mixes them), the linear
        solver, and the grid: ``(G,)`` shared, or ``(B, G)`` per sample (padded by its last node)."""
        n = self.system.n
        given = None if linear_solver is None else check_linear_solver(linear_solver)
        measured, observed = self.operator.measured_states(self.y)  # log-normal data: exp(log y)
        try:  # "auto": the Jacobians along the data by jacrev under vmap
            #: with solver="auto", the samples found stiff, bool (B,) (fit_many fits a batch that
            #: mixes stiff and non-stiff samples run by run, each sample on the solver its own fit takes)
            self.solver, self.stiff_samples = choose_solver(self.solver, self.system, self.t_obs,
                                        torch.where(self.mask, measured, torch.full_like(measured, float("nan"))),
                                        observed, self.z0[:, :n], self.z0[:, n:],
                                        (self.t_obs[..., -1] - self.t0).expand(self.B),
                                        explicit=None if given is None else given.auto_solver)
        except Exception as exc:  # noqa: BLE001
            raise _checks.not_differentiable(exc) from exc
        self.linear_solver = check_linear_solver(linear_solver_for(self.solver, given, DEFAULT_LINEAR_SOLVER))
        #: whether the fit takes the stiff path (its grids then have geometric early nodes)
        self.stiff = stiff = self.solver in STIFF_SOLVERS
        #: ``grid="auto"`` (the default): the engine chooses each sample's uniform intervals from
        #: its first reference, built on this probe grid (:mod:`torchql.grid`)
        self.auto_grid = grid is None or isinstance(grid, str) and grid == "auto"
        if self.auto_grid:
            grid = AUTO_PROBE
        elif isinstance(grid, str) and grid != "auto":
            grid = self._smooth_grid(grid, stiff)
        elif isinstance(grid, str):
            grid = None
        if self.t_obs.dim() == 1:
            self.grid = make_grid(grid, self.t0, self.t_obs, stiff=stiff, breakpoints=self.breakpoints)
            self.grid_size = None
        else:
            self.grid, self.grid_size = make_grids(grid, self.t0, self.t_obs, stiff=stiff,
                                                    breakpoints=self.breakpoints)
        self.obs_in_grid = torch.searchsorted(self.grid, self.t_obs)

    def _smooth_grid(self, grid: str, stiff: bool) -> int | None:
        """``grid="smooth"``: the uniform intervals that the guesses' trajectories need
        (:func:`torchql.grid.smooth_intervals`; integrated by Dormand–Prince, the nodes from its
        dense output); the default grid for a stiff model."""
        if grid != "smooth":
            raise ValueError(f'`grid` must be a number of intervals, a tensor of times, "auto" or "smooth"; '
                             f'received {grid!r}')
        if stiff:
            return None
        n, u = self.system.n, torch.linspace(0.0, 1.0, SMOOTH_SAMPLES + 1, dtype=self.dtype, device=self.device)
        t0 = self.t0.expand(self.B).unsqueeze(1)
        times = t0 + (self.t_obs[..., -1].expand(self.B).unsqueeze(1) - t0) * u  # (B, G)
        land = torch.zeros_like(u, dtype=torch.bool)
        land[-1] = True
        with torch.no_grad():
            rtol = max(self.rtol, SMOOTH_RTOL)
            traj, ok, _ = dopri_batch(self.system, self.z0, times, rtol=rtol, atol=self.atol * rtol / self.rtol,
                                      land=land)
            if not bool(ok.all()):
                return None
            slopes = vmap(self.system.f)(times.reshape(-1), traj.reshape(-1, self.system.M)).reshape(traj.shape)
        return smooth_intervals(times, traj[..., :n], slopes[..., :n], self.rtol, self.atol)

    def _check_positive(self, guesses: torch.Tensor) -> None:
        """The guesses ``(B, m)`` of the log-scale unknowns are positive (a clear error otherwise)."""
        bad = self.bounds.log & ~(guesses > 0)
        if bool(bad.any()):
            b, i = (int(v) for v in bad.nonzero()[0])
            where = "" if self.single else f" (sample {b})"
            raise ValueError(f"the guess of {self.unknown_names[i]!r} is {float(guesses[b, i]):g}{where}, but it is on "
                             "a log scale (`scale=`), which needs a positive value: give a positive guess, or a lower "
                             "bound 0 to have a guess of 0 moved inside")

    def _initial_time(self, t0) -> torch.Tensor:
        """``t0``: the first observation time (each sample's own, ``(B,)``, when times are per sample)
        or the given time, shared ``()``, not later than any sample's first observation."""
        first = self.t_obs[..., 0]
        if t0 is None:
            if first.dim() == 1 and bool((first == first[0]).all()):
                first = first[0]  # the samples' times differ, not their first: t0 shared
            return first.clone()
        value = torch.as_tensor(_checks.finite_number("t0", t0), dtype=self.dtype, device=self.device)
        late = (value > first).reshape(-1).nonzero().flatten().tolist()
        if late:
            if self.t_obs.dim() == 1:
                raise ValueError(f"`t0` must not be later than the first observation time "
                                 f"{self.t_obs[0].item():g}; received {float(t0):g}")
            alike = f" (samples {late[:10]} alike)" if len(late) > 1 else ""
            raise ValueError(f"`t0` must not be later than the first observation time of any sample; `data[{late[0]}]` "
                             f"starts at {first[late[0]].item():g}{alike}, received t0 = {float(t0):g}")
        return value

    # ------------------------------------------------------------------------------------------
    def _stack(self, data, dtype, device) -> None:
        data = check_data(data)
        if isinstance(data, Observations):
            self.inputs = shared_inputs([data.inputs_of(b) for b in range(data.batch_size)])
            first, y, sigma, exact = data, data.y, data.sigma, data.exact
            t = data.t.to(dtype=dtype, device=device)
            low = [("data", data.y.dtype)] if _coarser(data.y.dtype, dtype) else []
        else:
            first = data[0]
            self.inputs = shared_inputs([d.inputs for d in data])
            t = torch.stack([d.t.to(dtype=dtype, device=device) for d in data])
            exact = torch.stack([d.exact for d in data])
            y = torch.stack([d.y.to(dtype) for d in data])
            sigma = torch.stack([d.sigma.to(dtype) for d in data])
            low = [("data" if self.single else f"data[{i}]", d.y.dtype) for i, d in enumerate(data)
                   if _coarser(d.y.dtype, dtype)]
        self.B = y.shape[0]
        if low:
            warnings.warn(f"`{low[0][0]}` holds {low[0][1]} values but the model computes in {dtype}: the data's own "
                          "rounding limits the fit's accuracy; build the Observations from float64 tensors",
                          UserWarning, stacklevel=4)
        if t.dim() == 2 and bool((t == t[:1]).all()):
            t = t[0]  # every sample at the same times: the shared grid serves them all
        self.t = t  # (T,) or (B, T)
        self.observe = first.observe
        self.K = y.shape[-1]
        self.sigma_known = first.sigma_given
        self.noise, self.sigma_estimated, self.sigma_groups = first.noise, first.sigma_estimated, first.sigma_groups
        self.sigma_callable = first.sigma_function
        if self.sigma_estimated:
            self.sigma_known = True  # the weights at the estimated sigmas are the covariance's
        y = y.to(dtype=dtype, device=device)
        self.mask = ~torch.isnan(y)  # (B, T, K)
        self.exact = exact.to(device) & self.mask  # (B, T, K): values to be met exactly
        self.has_exact = bool(self.exact.any())
        self.y = torch.where(self.mask, y, torch.zeros_like(y))
        self.weights = torch.where(self.mask, 1.0 / sigma.to(dtype=dtype, device=device), torch.zeros_like(y))
        self.L = self.mask.flatten(1).sum(dim=1)  # (B,)

    def _noise_model(self) -> None:
        """For log-normal data, the logarithms: ``y`` becomes ``log y``, the operator ``log h``, and
        ``log_y_sum (B,)`` the likelihood's change of variable."""
        self.log_y_sum = torch.zeros(self.B, dtype=self.dtype, device=self.device)
        if self.noise == "lognormal":
            counted = self.mask & ~self.exact
            log_y = torch.log(torch.where(self.mask, self.y, torch.ones_like(self.y)))
            self.log_y_sum = torch.where(counted, log_y, torch.zeros_like(log_y)).flatten(1).sum(dim=1)
            self.y = log_y
            self.operator = LogObservation(self.operator)

    def weights_at(self, estimates: torch.Tensor) -> torch.Tensor:
        """The values' weights ``1 / sigma (B, T, K)`` with the unknowns at ``estimates (B, m)``: the
        data's own, or with a ``sigma(p)`` function its values there (zero where a value is missing)."""
        if self.sigma_function is None:
            return self.weights
        z0 = self.z0.clone()
        z0[:, self.unknown_index] = torch.where(torch.isfinite(estimates), estimates, z0[:, self.unknown_index])
        sigma, _ = self.sigma_function.evaluate(self.initial.complete(z0))
        return self.weights / sigma.unsqueeze(1)

    def shifted(self, z0: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
        """The augmented initial states ``z0 (S, M)`` with the unknowns moved by ``alpha (S, m)`` and
        the states given by expressions (``x0_expr``) following them (a new tensor)."""
        z = z0.clone()
        z[:, self.unknown_index] = z0[:, self.unknown_index] + alpha
        return self.initial.complete(z)

    def columns(self, z0: torch.Tensor) -> torch.Tensor:
        """``W(t0) = [z0, dz0/du]``, shape ``(S, M, 1 + m)``: the particular solution's and the
        homogeneous solutions' initial values (unit vectors, but for states given by expressions)."""
        if self.initial:
            return self.initial.columns(z0, self.unknown_index)
        return initial_columns(z0, self.unknown_index)

    def _attach_inputs(self, model) -> torch.Tensor | None:
        """The data's inputs checked against the model's ``input_names`` and the data's times, and
        attached to the fit's copy of the model; returns their breakpoints (``None`` without inputs)."""
        names = tuple(getattr(model, "input_names", ()))
        where = "data.inputs" if self.single else "data's inputs"
        if self.inputs is None:
            if names:
                raise ValueError(
                    f"`model` takes inputs {names} (its `input_names`) but `data` carries none: give them as "
                    f"Observations(t, y, observe, inputs=torchql.Inputs(t_u, u, names={list(names)}))")
            return self.system.model.input_nodes()
        if not names:
            raise ValueError(f"`data` carries inputs {list(self.inputs.names)} but `model` declares none: set its "
                             "`input_names` and take them in forward(t, x, u)")
        signals = self.inputs.for_model(names, float(torch.as_tensor(self.t0).min()), float(self.t_obs[..., -1].max()),
                                        self.dtype, self.device, where=where, span="the data's times",
                                        note=" (from t0 to the last observation)")
        self.data_inputs = signals
        signals = signals.shifted(self._local_time())
        attach_inputs(self.system.model, signals, self.origin)
        return signals.nodes

    def _local_time(self, per_sample: bool = False) -> "float | torch.Tensor":
        """Shift the data's times to local time from the earliest ``t0`` (:mod:`torchql.local_time`);
        returns that origin. ``per_sample``: each sample's own ``t0`` where each has its times."""
        self.origin = local_origin(self.t0, self.t_obs, per_sample)
        shift = self.origin.unsqueeze(-1) if isinstance(self.origin, torch.Tensor) else self.origin
        self.t_obs, self.t0 = self.t_obs - shift, self.t0 - self.origin
        return self.origin

    def _x0_from_data(self, names) -> torch.Tensor:
        if len(self.initial.index) == len(names):  # every state given by its expression
            return torch.zeros((self.B, len(names)), dtype=self.dtype, device=self.device)
        early = (self.t0 != self.t_obs[..., 0]).reshape(-1)
        if bool(early.any()):
            where = "" if self.t_obs.dim() == 1 else f" (as in `data[{int(early.nonzero()[0, 0])}]`)"
            raise ValueError(f"`x0` is required when `t0` precedes the first observation{where}")
        x0 = torch.full((self.B, len(names)), float("nan"), dtype=self.dtype, device=self.device)
        for k, i in enumerate(self.operator.observed_states):
            if i is not None:
                x0[:, i] = torch.where(self.mask[:, 0, k], self.y[:, 0, k], x0[:, i])
        x0[:, self.initial.index] = 0.0  # given by their expressions
        missing = torch.isnan(x0)
        if bool(missing.any()):
            b = int(missing.any(dim=1).nonzero()[0, 0])
            states = [names[i] for i in range(len(names)) if bool(missing[b, i])]
            if self.single:
                raise ValueError(f"`x0` is required: the states {states} are not observed directly at t0")
            raise ValueError(f"`x0` is required: in `data[{b}]` the states {states} are not observed directly at t0")
        return x0

    def _check_model(self, x0: torch.Tensor) -> None:
        """The forward on sample 0's guesses (in-place updates, shape, dtype, finite; differentiable
        with torch.func), then finite on every sample's guesses, vectorized."""
        system = self.system
        t0 = self.t0.expand(self.B)

        def check(b: int, sample: str = "") -> None:
            p = self.z0[b, system.n:]
            _checks.model_forward(lambda t, x: system.rhs(t, x, p), t0[b], self.z0[b, :system.n],
                                  system.state_names, dict(zip(system.element_names, p.tolist())), self.dtype,
                                  sample)

        check(0)
        load_forward_mode()
        try:  # every sample's guesses under vmap (which .item(), float() and branching on values fail),
            # then one node's linearization as the engine takes it for this model
            with torch.no_grad():
                finite = torch.isfinite(vmap(system.f)(t0, self.z0)).all(dim=1)
            linearize(system, t0[:1], self.z0[:1])
        except Warning:  # a warning turned error (-W error) is the warning's, not a fault of the model's
            raise
        except Exception as exc:  # noqa: BLE001
            raise _checks.not_differentiable(exc) from exc
        bad = (~finite).nonzero().flatten().tolist()
        if bad:
            check(bad[0], f" of `data[{bad[0]}]`" + (f" (samples {bad[:10]} alike)" if len(bad) > 1 else ""))
        base = getattr(self.operator, "inner", self.operator)
        self.operator.check(x0, base._params(self.z0[0]) if base.takes_params else None)
        if self.sigma_function is not None:
            if self.has_exact and self.estimated_noise is not None:
                raise ValueError("`exact` values cannot be combined with sigma='estimate': give the data a "
                                 "fixed sigma, or drop `exact`")
            if self.has_exact:
                raise ValueError("`exact` values cannot be combined with a `sigma` function of the coefficients: "
                                 "give the exact values' experiment a fixed sigma, or drop `exact`")
            self.sigma_function.check(self.z0[0])

    # ------------------------------------------------------------------------------------------
    def result(self, z0, out, statuses, messages, nfev) -> BatchFitResult:
        system, n, B = self.system, self.system.n, self.B
        model = system.user_model()
        if self.data_inputs is not None:  # the data's own times, not the fit's local ones
            attach_inputs(model, self.data_inputs)
        params = self._params_of(z0)
        dof = self.L - self.m - out["redundant_exact"].round().long()  # (exact values that fix nothing more)
        variance = residual_variance(out["sse"], dof, self.sigma_known)
        return BatchFitResult(
            success=torch.tensor([s.success for s in statuses], dtype=torch.bool, device=self.device),
            status=statuses, message=messages, params=params, x0=z0[:, :n].clone(),
            t0=float(self.data_t0) if self.data_t0.dim() == 0 else self.data_t0.clone(),
            unknown_names=list(self.unknown_names), estimates=z0[:, self.unknown_index].clone(),
            iterations=out["iterations"], sse=out["sse"], covariance=out["cov"], n_observations=self.L.clone(),
            dof=dof, residual_variance=variance, sigma_known=self.sigma_known, nfev=nfev,
            model=model, residuals=out["residuals"], jacobian=out["jacobian"],
            used=self.mask.reshape(B, -1).clone(), singular_values=out["singular_values"],
            exact=self.exact.reshape(B, -1).clone(), exact_residual=out["exact_residual"],
            start_params=self._params_of(out["z0_start"]), start_x0=out["z0_start"][:, :n].clone(),
            sse_start=out["sse_start"], sse_end=out["sse_end"],
            solver_options={"solver": self.solver, "rtol": self.rtol, "atol": self.atol},
            lower=self.bounds.lower.clone() if self._bounded else None,
            upper=self.bounds.upper.clone() if self._bounded else None,
            log_scaled=[name for name, log in zip(self.unknown_names, self.bounds.log.tolist()) if log],
            moved_guesses={b: dict(moved) for b, moved in self.moved_guesses.items()})


    @property
    def _bounded(self) -> bool:
        """Whether some unknown has a finite bound."""
        return bool((self.bounds.has_lower | self.bounds.has_upper).any())

    def _params_of(self, z0: torch.Tensor) -> dict[str, torch.Tensor]:
        """Every float buffer per sample ``(B, *shape)`` for augmented states ``z0 (B, M)``."""
        system, B = self.system, self.B
        per_sample, start = {}, system.n
        for name, shape, size in zip(system.param_names, system.param_shapes, system.param_sizes):
            per_sample[name] = z0[:, start:start + size].reshape(B, *shape)
            start += size
        params = {}
        for name, value in system.model.named_buffers():
            if value.is_floating_point():
                params[name] = (per_sample[name] if name in per_sample else value.expand(B, *value.shape)).clone()
        return params


def _coarser(data_dtype: torch.dtype, dtype: torch.dtype) -> bool:
    """Whether data of ``data_dtype`` are rounded more coarsely than the computation's ``dtype``."""
    return torch.finfo(data_dtype).eps > torch.finfo(dtype).eps
