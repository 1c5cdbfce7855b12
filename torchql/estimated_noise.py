"""Estimated noise: ``sigma="estimate"`` fitted jointly with the model's unknowns.

Each group of outputs (``Observations(..., sigma_groups=...)``) has one standard deviation
``sigma_g``. The fit treats the G sigmas as unknowns of its own: coefficients held by the model's
copy inside the fit (never by the user's model), iterated on the log scale, that the model's
right-hand side does not read and the outputs' standard deviations do, ``sigma_k = sigma_{g(k)}``.
The iteration then minimizes the negative log-likelihood through the rows of
:mod:`torchql.sigma_function` (a function ``sigma(p)`` of the unknowns): Gauss–Newton on the
coefficients and the sigmas together, whose fixed point is the maximum-likelihood estimate. (The
alternative, re-fitting by weighted least squares at the sigmas of the last fit until they settle,
converges only linearly, and each round is a whole fit.)

The result holds the sigmas apart from the coefficients (:meth:`EstimatedNoise.split`): ``sigma``
``(B, G)`` and ``sigma_stderr`` ``(B, G)``, the unknowns, their covariance and the Jacobian over
the model's unknowns alone. (The expected information of the Gaussian is block diagonal between
the mean's unknowns and ``log sigma``, so dropping the sigmas leaves the coefficients' covariance
as it is.) While the fit runs, the iteration records a ``callback`` receives hold the sigmas among
the coefficients, as ``sigma_<group>``; the result's ``history`` does not.

**Start.** Each group's first sigma comes from the data alone: the scatter of every value about the
straight line through its two neighbours in time (:func:`scatter_sigma`), which smooth noise-free
data keep small. An overestimate costs a few iterations; the log-scale step moves it by a factor of
about ``e`` per iteration at most.

**Floor.** A group the model meets exactly has no maximum of the likelihood (it grows without
bound as its sigma goes to zero), so each sigma is bounded below by :data:`SIGMA_FLOOR` times the
largest absolute value of the data (at least 1): the fit then converges with that sigma at its bound,
and the message says so.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence

import torch

from .lstsq import solve_update_batch
from .model import coefficient_names

__all__ = ["EstimatedNoise", "SIGMA_FLOOR", "scatter_sigma"]

#: The sigmas' lower bound relative to the data's largest absolute value (see the module's notes).
SIGMA_FLOOR = 1e-12


class EstimatedNoise:
    """The G estimated sigmas of a fit as coefficients of the model's copy.

    Parameters
    ----------
    group_names : sequence of str
        The groups' names (``result.sigma``'s keys), G of them.
    group : sequence of int
        Each of the K outputs' group.
    taken : sequence of str
        The model's coefficient names, which the sigmas' own names avoid.
    """

    def __init__(self, group_names: Sequence[str], group: Sequence[int], taken: Sequence[str]) -> None:
        self.group_names = list(group_names)
        self.group = list(group)
        self.names = _coefficient_names(self.group_names, set(taken))

    @property
    def G(self) -> int:
        """The number of sigmas."""
        return len(self.names)

    def attach(self, model):
        """A deep copy of ``model`` with one scalar buffer per sigma (value 1; the fit's guesses
        are given per sample)."""
        holder = copy.deepcopy(model)
        dtype = next((b.dtype for b in holder.buffers() if b.is_floating_point()), torch.float64)
        for name in self.names:
            holder.register_buffer(name, torch.ones((), dtype=dtype))
        return holder

    def added(self, model, params, guesses, bounds, scale, start: torch.Tensor, floor: float):
        """The fit's arguments with the sigmas added: the model's copy holding them (:meth:`attach`),
        ``params`` naming them after the coefficients (all but the model's ``constants`` when
        ``None``), ``guesses`` starting them at ``start (B, G)``, ``bounds`` from ``floor`` up, and
        ``scale`` logarithmic. Arguments of the wrong type are passed on unchanged, for the fit's
        checks to name."""
        if params is None:
            params = [name for name in coefficient_names(model) if name not in tuple(model.constants)]
        if isinstance(params, (list, tuple)):
            params = list(params) + self.names
        if guesses is None or isinstance(guesses, dict):
            guesses = {**(guesses or {}), **{name: start[:, g] for g, name in enumerate(self.names)}}
        if bounds is None or isinstance(bounds, Mapping):
            bounds = {**(bounds or {}), **{name: (floor, None) for name in self.names}}
        if scale is None or isinstance(scale, Mapping):
            scale = {**(scale or {}), **{name: "log" for name in self.names}}
        return self.attach(model), params, guesses, bounds, scale

    def __call__(self, p: dict) -> torch.Tensor:
        """Every output's standard deviation ``(K,)`` from the coefficients ``p`` by name."""
        return torch.stack([p[self.names[g]] for g in self.group])

    def start(self, t: torch.Tensor, y: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """The sigmas' first values ``(B, G)`` from the data ``y (B, T, K)`` (``mask`` the values
        present) at increasing times ``t (T,)`` or ``(B, T)``: :func:`scatter_sigma` pooled over each
        group, and where a group has fewer than three values in every output, the RMS of its values
        (1 where that is zero); floored at :meth:`floor`."""
        B, T, K = y.shape
        times = (t.expand(B, T) if t.dim() == 1 else t).unsqueeze(-1).expand(B, T, K)
        square, count = scatter_sigma(times, y, mask)  # (B, K) each
        one_hot = torch.nn.functional.one_hot(torch.tensor(self.group, device=y.device), self.G).to(y.dtype)
        sums, counts = square @ one_hot, count.to(y.dtype) @ one_hot
        present = mask.to(y.dtype)
        rms_sum = (torch.where(mask, y, torch.zeros_like(y)) ** 2).sum(dim=1) @ one_hot
        rms = (rms_sum / (present.sum(dim=1) @ one_hot).clamp(min=1)).sqrt()
        scatter = (sums / counts.clamp(min=1)).sqrt()
        sigma = torch.where(counts > 0, scatter, torch.where(rms > 0, rms, torch.ones_like(rms)))
        return sigma.clamp(min=self.floor(y, mask))

    @staticmethod
    def floor(y: torch.Tensor, mask: torch.Tensor) -> float:
        """The sigmas' lower bound: :data:`SIGMA_FLOOR` times ``max(1, max |y|)`` over every sample."""
        present = torch.where(mask, y.abs(), torch.zeros_like(y))
        return SIGMA_FLOOR * max(1.0, float(present.max())) if present.numel() else SIGMA_FLOOR

    def split(self, result, m: int) -> None:
        """Move the sigmas, the last G of the ``m`` unknowns of ``result`` (a
        :class:`torchql.BatchFitResult`, modified in place), out of its unknowns into ``sigma`` and
        ``sigma_stderr``."""
        G, keep = self.G, m - self.G
        names = set(self.names)
        est = result.estimates
        result.sigma = est[:, keep:].clone()
        variance = torch.diagonal(result.covariance, dim1=1, dim2=2)[:, keep:]
        result.sigma_stderr = variance.clamp(min=0).sqrt()
        result.sigma_names = list(self.group_names)
        result.estimates = est[:, :keep].clone()
        result.covariance = result.covariance[:, :keep, :keep].clone()
        result.unknown_names = result.unknown_names[:keep]
        for params in [result.params, result.start_params] + [r.params for h in result.history or [] for r in h]:
            if params is not None:
                for name in self.names:
                    params.pop(name, None)
        if result.jacobian is not None:
            result.jacobian = result.jacobian[..., :keep].clone()
            result.singular_values = _scaled_singular_values(result.jacobian, result.singular_values[:, :keep])
        if result.lower is not None:
            lower, upper = result.lower[:keep].clone(), result.upper[:keep].clone()
            bounded = bool((torch.isfinite(lower) | torch.isfinite(upper)).any())
            result.lower, result.upper = (lower, upper) if bounded else (None, None)
        result.log_scaled = [name for name in result.log_scaled if name not in names]
        result.moved_guesses = {b: {k: v for k, v in moved.items() if k not in names}
                                for b, moved in result.moved_guesses.items()}
        result.moved_guesses = {b: moved for b, moved in result.moved_guesses.items() if moved}
        result.dof = result.dof + G  # as with known sigmas: values less the model's unknowns
        for name in self.names:  # registered on the copy's top module by attach
            del result.model._buffers[name]


def scatter_sigma(t: torch.Tensor, y: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(sum, count)``, each ``(B, K)``, of the variance estimates of white noise on the columns of
    ``y (B, T, K)`` at increasing times ``t (B, T, K)``, over the values ``mask`` marks present.

    Each present value with a present neighbour on either side deviates from the line through those
    neighbours by ``e_i``, of variance ``sigma^2 (1 + a_i^2 + b_i^2)`` (``a_i``, ``b_i`` the
    neighbours' weights) when the signal is locally straight, so ``e_i^2 / (1 + a_i^2 + b_i^2)``
    estimates ``sigma^2`` (a curved signal makes it larger).
    """
    B, T, K = y.shape
    position = torch.arange(T, device=y.device).reshape(1, T, 1).expand(B, T, K)
    before = torch.where(mask, position, torch.full_like(position, -1)).cummax(dim=1).values
    previous = torch.cat([torch.full_like(before[:, :1], -1), before[:, :-1]], dim=1)
    after = torch.where(mask, position, torch.full_like(position, T)).flip(1).cummin(dim=1).values.flip(1)
    following = torch.cat([after[:, 1:], torch.full_like(after[:, :1], T)], dim=1)
    inner = mask & (previous >= 0) & (following < T)
    i0, i2 = previous.clamp(0, T - 1), following.clamp(0, T - 1)
    t0, t2, y0, y2 = t.gather(1, i0), t.gather(1, i2), y.gather(1, i0), y.gather(1, i2)
    span = (t2 - t0).clamp(min=torch.finfo(t.dtype).tiny)
    a, b = (t2 - t) / span, (t - t0) / span
    estimate = (y - (a * y0 + b * y2)) ** 2 / (1 + a ** 2 + b ** 2)
    return torch.where(inner, estimate, torch.zeros_like(estimate)).sum(dim=1), inner.sum(dim=1)


def _coefficient_names(group_names: Sequence[str], taken: set[str]) -> list[str]:
    """A buffer name per group: ``"sigma_<group>"`` where the group's name is an identifier, else
    ``"sigma_<index>"``, with trailing underscores until no coefficient has it."""
    names = []
    for g, group in enumerate(group_names):
        name = f"sigma_{group}" if str(group).isidentifier() else f"sigma_{g}"
        while name in taken or name in names:
            name += "_"
        names.append(name)
    return names


def _scaled_singular_values(J: torch.Tensor, fallback: torch.Tensor) -> torch.Tensor:
    """The singular values ``(B, m)`` of each column-scaled Jacobian ``J (B, R, m)`` (unused rows
    zero), as the engine's final pass computes them (:func:`torchql.lstsq.solve_update_batch`);
    ``fallback`` where a sample's Jacobian is not finite (not evaluated)."""
    rows = J.new_ones(J.shape[:2])
    _, _, values = solve_update_batch(J, J.new_zeros(J.shape[:2]), rows, 1.0, None)
    finite = torch.isfinite(J).flatten(1).all(dim=1)
    return torch.where(finite.unsqueeze(1), values, fallback)
