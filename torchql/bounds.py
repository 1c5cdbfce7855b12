"""Lower and upper bounds on the unknowns, honoured by a smooth change of variables.

Each bounded unknown ``u`` is written through an unbounded internal variable ``q``:

* lower bound only: ``u = lo + exp(q)`` (a positive rate constant is fitted in its logarithm,
  which also makes the step scale-free);
* upper bound only: ``u = hi - exp(q)``;
* both: ``u = lo + (hi - lo) / (1 + exp(-q))``.

The least-squares update is solved for ``q`` (the sensitivity columns multiplied by
``du/dq``) and mapped back, so every iterate lies strictly inside its bounds and the stored
trajectory is updated by the actual change of ``u``. One step moves ``q`` by at most
:data:`MAX_INTERNAL_STEP` (``log 1000``): near a bound ``du/dq`` is tiny, and the linearized
step in ``q`` that a far-away ``u`` asks for is huge (``exp`` of it overflows); capped, the
distance to a bound grows by at most a factor 1000 per step and shrinks by at most a factor 10
(:data:`MAX_TOWARD_STEP`), and the unknowns whose step was capped are held at their capped move
while the others are re-solved. Everything a user sees (estimates,
covariance, reports) is in ``u``, the user's units.

A guess on a bound, or outside it, has no internal value (``log 0``), so it is moved strictly
inside first (as scipy's ``least_squares`` does with ``make_strictly_feasible``) by
:meth:`Bounds.move_inside`, to the point one capped step (:data:`MAX_INTERNAL_STEP`) away from
the unknown's natural scale in ``q``:

* one bound ``b``: ``b + START_OFFSET * max(1, |b|)`` (or ``b - ...`` for an upper bound),
  so one capped step takes the distance to the bound from ``1e-3 max(1, |b|)`` to
  ``max(1, |b|)``: a rate guessed 0 starts at ``1e-3``, one capped step below a unit rate
  (and a rate of ``5e-5`` lies within one step below it);
* two bounds: ``START_OFFSET`` of the width from the nearer bound, ``q = logit(1e-3)``, one
  capped step from the middle.

With :data:`START_OFFSET` ``= 1e-3`` rates guessed 0 cost 3 to 5 iterations more than guesses
inside (``experiments/bound_start.py``); a point ``1e-10`` above the bound would cost several
capped steps to climb out (from there 4 of the 6 fits of that script stalled or ran out of
iterations). Guesses strictly inside are kept as given, however close to a bound.

An unknown on a logarithmic scale (``scale={"k": "log"}``, or ``"log10"``, the same iteration)
is iterated in ``s = log u``, and its bounds bound ``s`` (``log lo``, ``log hi``; a lower bound 0
leaves ``s`` open below): ``u = exp(q)`` without bounds, ``u = exp(log lo + exp(q))`` with a
lower bound, ``u = exp(log lo + (log hi - log lo) / (1 + exp(-q)))`` with both. A rate known only
to lie between ``1e-5`` and ``1e5`` is then iterated evenly over its ten decades, not squeezed
against the lower bound of a linear logistic, and its intervals are intervals of ``log u``.
Its values must be positive.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping, Sequence

import torch

__all__ = ["Bounds", "MAX_INTERNAL_STEP", "MAX_TOWARD_STEP", "SCALES", "START_OFFSET", "at_bound_note", "bound_pair",
           "moved_guesses_note", "moved_record"]

#: Largest move of a bounded unknown's internal variable ``q`` in one step (a factor 1000 in
#: its distance to a bound).
MAX_INTERNAL_STEP = math.log(1000.0)
#: ... toward its nearer bound (a factor 10). A linearization that asks to cross the bound asks
#: for an infinite move in ``q``; capped at a factor 1000, one step took an SIR fit's rates from
#: 0.65 to 6.5e-4, into a flat stretch of its sum of squares where nothing spreads, and further
#: capped steps flipped them between 1.7e-5 and 1.7e-8 (shooting: 42 iterations and 23 s where
#: scipy took 17 evaluations; ``tests/test_bounds.py``). A tenfold approach reaches an estimate on
#: the bound as well, in a step per decade.
MAX_TOWARD_STEP = math.log(10.0)

#: Where :meth:`Bounds.move_inside` puts a guess that is not strictly inside its bounds: this
#: fraction of ``max(1, |bound|)`` from a one-sided bound, of the width from the nearer of two.
#: It equals ``exp(-MAX_INTERNAL_STEP)``: one capped step from the unknown's scale.
START_OFFSET = 1e-3

#: A bound farther than this many times ``max(|s|, 1)`` from the iterated value ``s`` is open to the
#: change of variables at that iterate: ``u = lo + exp(q)`` resolves ``u`` only to ``eps |u - lo|``
#: (bounds of +-1e15 around a rate of 0.05 resolved it to 0.2, and the fit "converged" at 0 with
#: its interval (0, 0)); there the unknown steps in its own units, and a step that would cross
#: such a bound goes nine tenths of the way to it (:meth:`Bounds.step`), where the bound is near.
FAR_BOUND = 1e6

#: The scales an unknown may be iterated on (``"log"`` and ``"log10"`` give the same iteration).
SCALES = ("lin", "log", "log10")


class Bounds:
    """Bounds of the ``m`` unknowns, parsed from the ``bounds=`` argument of :func:`torchql.fit`.

    Parameters
    ----------
    bounds : dict or None
        ``{name: (lower, upper)}``; ``None`` (or an infinity) leaves a side open. A name is an
        unknown's name (``"A"``, ``"W[0,1]"``, ``"y(t0)"``), a state's name (its initial value),
        or a vector/matrix buffer's name (every element).
    unknown_names : list of str
        Names of the unknowns, in order (``"x(t0)"`` for initial states).
    groups : dict of str to list of int
        Further accepted names: a buffer's name -> the indices of its elements among the
        unknowns.
    all_names : sequence of str
        Every state and coefficient name of the model, to tell a known-but-fixed name (error:
        it is not estimated) from a typo.
    """

    def __init__(self, bounds: Mapping | None, unknown_names: Sequence[str], groups: Mapping[str, list[int]],
                 all_names: Sequence[str], dtype: torch.dtype, device: torch.device,
                 scale: Mapping | None = None) -> None:
        m = len(unknown_names)
        lower = [-math.inf] * m
        upper = [math.inf] * m
        index = {name: [i] for i, name in enumerate(unknown_names)}
        index.update({name[:-4]: [i] for i, name in enumerate(unknown_names) if name.endswith("(t0)")})
        index.update({k: list(v) for k, v in groups.items()})
        if bounds is not None:
            if not isinstance(bounds, Mapping):
                raise TypeError(
                    f"`bounds` must be a dict {{name: (lower, upper)}}; received {type(bounds).__name__}")
            given: dict[int, str] = {}
            for name, pair in bounds.items():
                lo, hi = bound_pair(name, pair)
                for i in _named(index, "bounds", name, all_names, unknown_names):
                    _once("bounds", given, i, name, unknown_names)
                    lower[i], upper[i] = lo, hi
        log = [False] * m
        if scale is not None:
            if not isinstance(scale, Mapping):
                raise TypeError(f"`scale` must be a dict {{name: 'lin' | 'log' | 'log10'}}; received "
                                f"{type(scale).__name__}")
            scaled: dict[int, str] = {}
            for name, kind in scale.items():
                if kind not in SCALES:
                    raise ValueError(f"`scale[{name!r}]` must be one of {list(SCALES)}; received {kind!r}")
                for i in _named(index, "scale", name, all_names, unknown_names):
                    _once("scale", scaled, i, name, unknown_names)
                    log[i] = kind != "lin"
                    if log[i] and (-math.inf < lower[i] < 0 or upper[i] <= 0):
                        raise ValueError(f"`scale[{name!r}]` is {kind!r}, so {unknown_names[i]} is positive; its "
                                         f"bounds must lie in [0, inf), received ({lower[i]:g}, {upper[i]:g})")
        self.lower = torch.tensor(lower, dtype=dtype, device=device)
        self.upper = torch.tensor(upper, dtype=dtype, device=device)
        self.log = torch.tensor(log, dtype=torch.bool, device=device)
        self.names = list(unknown_names)
        self._derive()

    def _derive(self) -> None:
        """The bounds' masks, and their values on the iterated scale ``s`` (``log u`` where :attr:`log`)."""
        self.has_lower = torch.isfinite(self.lower)
        self.has_upper = torch.isfinite(self.upper)
        with torch.no_grad():
            positive = self.lower > 0
            self._lo = torch.where(self.log, torch.where(positive, self.lower.clamp_min(1e-300).log(),
                                                         torch.full_like(self.lower, -math.inf)), self.lower)
            self._hi = torch.where(self.log, self.upper.log(), self.upper)
        self._has_lo, self._has_hi = torch.isfinite(self._lo), torch.isfinite(self._hi)
        self.transformed = self._has_lo | self._has_hi | self.log
        self.active = bool(self.transformed.any())

    @classmethod
    def for_unknowns(cls, bounds: Mapping | None, unknown_names: Sequence[str], n_states: int,
                     param_names: Sequence[str], param_sizes: Sequence[int], all_names: Sequence[str],
                     dtype: torch.dtype, device: torch.device, scale: Mapping | None = None) -> "Bounds":
        """Bounds of a fit's unknowns: ``n_states`` initial states, then the elements of the
        coefficients ``param_names`` (``param_sizes`` elements each) in order, a coefficient's
        name bounding all of its elements (the ``groups`` of the constructor)."""
        groups, k = {}, n_states
        for name, size in zip(param_names, param_sizes):
            groups[name] = list(range(k, k + size))
            k += size
        return cls(bounds, unknown_names, groups, all_names, dtype, device, scale)

    @classmethod
    def of(cls, lower: torch.Tensor, upper: torch.Tensor, names: Sequence[str],
           log: torch.Tensor | None = None) -> "Bounds":
        """Bounds from their values ``lower``, ``upper`` ``(m,)`` (infinite where a side is open) and
        the log-scale mask ``log (m,)``, as a :class:`torchql.FitResult` stores them, for the change
        of variables they define."""
        bounds = cls(None, names, {}, names, lower.dtype, lower.device)
        bounds.lower, bounds.upper = lower.clone(), upper.clone()
        if log is not None:
            bounds.log = log.to(device=lower.device, dtype=torch.bool).clone()
        bounds._derive()
        return bounds

    def move_inside(self, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The guesses ``u (m,)`` with those not strictly inside their bounds moved inside.

        A guess on a bound or beyond it goes to ``bound ± START_OFFSET * max(1, |bound|)``
        (one-sided) or to ``START_OFFSET`` of the width inside the nearer bound (two-sided);
        see the module's description. For an unknown on a log scale with positive bounds the rule
        applies to ``log u`` and ``log`` of its bounds (``[1e-5, 1e3]``: ``1e-5 * 1e8^0.001``).
        Guesses strictly inside are returned unchanged.

        Returns
        -------
        used : Tensor ``(m,)``
            A new tensor (``u`` is not modified).
        moved : bool Tensor ``(m,)``
            Which guesses were moved.
        """
        low = self.has_lower & ~(u > self.lower)  # on or below the lower bound (lower < upper: not both)
        moved = low | (self.has_upper & ~(u < self.upper))
        if not bool(moved.any()):
            return u.clone(), moved
        lo = torch.where(self.has_lower, self.lower, torch.zeros_like(u))
        hi = torch.where(self.has_upper, self.upper, torch.zeros_like(u))
        used = self._moved(u, lo, hi, low, moved)
        # on a log scale (positive bounds) the step inside is taken in log u, as the iteration sees it
        logged = self.log & moved & ~(self.has_lower & (lo <= 0))
        if bool(logged.any()):
            def log(v):
                return torch.log(torch.where(logged, v, torch.ones_like(v)))
            in_log = torch.exp(self._moved(log(u.clamp_min(torch.finfo(u.dtype).tiny)), log(lo), log(hi), low, moved))
            used = torch.where(logged, in_log, used)
        return used, moved

    def _moved(self, u, lo, hi, low, moved) -> torch.Tensor:
        """:meth:`move_inside`'s rule on values ``u`` with bounds ``lo``, ``hi`` (0 where absent)."""
        both = self.has_lower & self.has_upper
        width = START_OFFSET * hi - START_OFFSET * lo  # START_OFFSET * (hi - lo), which cannot overflow
        up = torch.where(both, width, START_OFFSET * torch.maximum(lo.abs(), torch.ones_like(u)))
        down = torch.where(both, width, START_OFFSET * torch.maximum(hi.abs(), torch.ones_like(u)))
        inf = torch.full_like(u, math.inf)
        inside_lo, inside_hi = torch.nextafter(lo, inf), torch.nextafter(hi, -inf)  # where the offset rounds away
        used = torch.where(low, torch.maximum(lo + up, inside_lo), u)
        return torch.where(moved & ~low, torch.minimum(hi - down, inside_hi), used)

    def _iterated(self, u: torch.Tensor) -> torch.Tensor:
        """``s``: ``log u`` for the log-scale unknowns, ``u`` for the others."""
        return torch.where(self.log, torch.log(u.clamp_min(torch.finfo(u.dtype).tiny)), u)

    def _sides(self, u: torch.Tensor):
        """The change of variables at the iterate ``u (..., m)``: ``(both, lo_only, hi_only, lo, hi)``,
        the bounds it uses (those within :data:`FAR_BOUND` of the iterated value) and their values
        on the iterated scale (0 and 1 where unused)."""
        s = self._iterated(u)
        reach = FAR_BOUND * torch.maximum(s.abs(), torch.ones_like(s))
        has_lo = self._has_lo & ~(s - self._lo > reach)
        has_hi = self._has_hi & ~(self._hi - s > reach)
        lo = torch.where(has_lo, self._lo, torch.zeros_like(s))
        hi = torch.where(has_hi, self._hi, torch.ones_like(s))
        return has_lo & has_hi, has_lo & ~has_hi, has_hi & ~has_lo, lo, hi

    def transformed_at(self, u: torch.Tensor) -> torch.Tensor:
        """Bool ``(..., m)``: the unknowns iterated through a change of variables at ``u`` (a near
        bound, or a log scale)."""
        both, lo_only, hi_only, _, _ = self._sides(u)
        return both | lo_only | hi_only | self.log

    def internal(self, u: torch.Tensor) -> torch.Tensor:
        """``q(u)``: shape ``(..., m)``."""
        s = self._iterated(u)
        both, lo_only, hi_only, lo, hi = self._sides(u)
        tiny = torch.finfo(u.dtype).tiny
        q = torch.where(lo_only, torch.log((s - lo).clamp_min(tiny)), s)
        q = torch.where(hi_only, torch.log((hi - s).clamp_min(tiny)), q)
        frac = ((s - lo) / (hi - lo)).clamp(tiny, 1 - torch.finfo(u.dtype).eps)
        return torch.where(both, torch.log(frac) - torch.log1p(-frac), q)

    def external(self, q: torch.Tensor, at: torch.Tensor) -> torch.Tensor:
        """``u(q)`` in the change of variables at the iterate ``at``: shape ``(..., m)``."""
        both, lo_only, hi_only, lo, hi = self._sides(at)
        s = torch.where(lo_only, lo + torch.exp(q), q)
        s = torch.where(hi_only, hi - torch.exp(q), s)
        s = torch.where(both, lo + (hi - lo) * torch.sigmoid(q), s)
        return torch.where(self.log, torch.exp(s), s)

    def derivative(self, u: torch.Tensor) -> torch.Tensor:
        """``du/dq`` at ``u``: shape ``(..., m)`` (ones where neither bounded nor on a log scale)."""
        s = self._iterated(u)
        both, lo_only, hi_only, lo, hi = self._sides(u)
        d = torch.ones_like(s)
        d = torch.where(lo_only, s - lo, d)
        d = torch.where(hi_only, s - hi, d)
        d = torch.where(both, (s - lo) * (hi - s) / (hi - lo), d)
        return torch.where(self.log, d * u, d)

    def internal_columns(self, C: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Least-squares columns ``C (S, R, m)`` of the unknowns at ``u (S, m)`` as columns of the
        internal variables, ``C du/dq`` (``C`` itself where no bound is active)."""
        return C * self.derivative(u).unsqueeze(1) if self.active else C

    def step(self, u: torch.Tensor, alpha_q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The change of ``u`` when ``q`` moves by ``alpha_q``; the result stays strictly inside.

        Where rounding would put ``u + change`` on a bound, the iterate moves to the nearest
        representable number inside it.

        Returns
        -------
        change : Tensor ``(m,)``
        blocked : bool Tensor ``(m,)``
            Unknowns that the step pushed onto their bound (already at it in all but
            rounding), or whose step was capped (:meth:`_limit`): the caller
            re-solves with them held at their move, so the others' step is consistent.
        """
        if not self.active:
            return alpha_q, torch.zeros_like(alpha_q, dtype=torch.bool)
        limit = self._limit(u, alpha_q)
        capped = self._capped(alpha_q, u)
        alpha_q = torch.where(capped, torch.maximum(torch.minimum(alpha_q.nan_to_num(0.0), limit), -limit), alpha_q)
        u_new = self.external(self.internal(u) + alpha_q, u)
        inf = torch.full_like(u, math.inf)
        low = self.has_lower & (u_new <= self.lower)
        high = self.has_upper & (u_new >= self.upper)
        # past a bound too far for the change of variables: nine tenths of the way to it
        u_new = torch.where(low, torch.maximum(u + 0.9 * (self.lower - u), torch.nextafter(self.lower, inf)), u_new)
        u_new = torch.where(high, torch.minimum(u + 0.9 * (self.upper - u), torch.nextafter(self.upper, -inf)), u_new)
        u_new = torch.where(self.log & (u_new <= 0), torch.full_like(u, torch.finfo(u.dtype).tiny), u_new)
        return torch.where(self.transformed, u_new - u, alpha_q), low | high | capped

    def capped(self, alpha_q: torch.Tensor, u: torch.Tensor) -> bool:
        """Whether :meth:`step` caps some transformed unknown's internal step ``alpha_q (m,)`` at
        ``u``: the linearization then asked for a move beyond where it can be trusted."""
        return self.active and bool(self._capped(alpha_q, u).any())

    def leaving(self, u: torch.Tensor, change: torch.Tensor, capped: torch.Tensor) -> torch.Tensor:
        """Bool ``(S,)``: the samples some of whose unknowns at ``u (S, m)`` take a ``capped (S, m)``
        step ``change (S, m)`` away from their nearer bound (or from the edge 0 of an open log
        scale). The linearization asked to leave the bound by more than a factor 1000 in distance:
        the data pull the unknown inside, however small its move in ``u`` (a guess one rounding
        inside a bound climbs out by capped steps, each far below ``xtol``), so no such step is
        converged. A capped step toward the bound is the approach to an estimate on it."""
        if not self.active:  # (every step of an unbounded fit asks)
            return torch.zeros(u.shape[0], dtype=torch.bool, device=u.device)
        return (capped & self.away(u, change)).any(dim=1)

    def away(self, u: torch.Tensor, direction: torch.Tensor) -> torch.Tensor:
        """Bool ``(S, m)``: the transformed unknowns at ``u (S, m)`` that ``direction (S, m)`` moves
        away from their nearer bound (from the edge 0 of a log scale without a lower bound)."""
        both = self.has_lower & self.has_upper
        near_lo = torch.where(both, (u - self.lower) <= (self.upper - u), ~self.has_upper)
        return self.transformed_at(u) & torch.where(near_lo, direction > 0, direction < 0)

    def _capped(self, alpha_q: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Transformed unknowns whose internal step exceeds its limit (NaN counts as capped)."""
        return self.transformed_at(u) & ~(alpha_q.abs() <= self._limit(u, alpha_q))

    def _limit(self, u: torch.Tensor, alpha_q: torch.Tensor) -> torch.Tensor:
        """The largest internal step of each unknown at ``u`` in the direction of ``alpha_q``:
        :data:`MAX_INTERNAL_STEP` away from its nearer bound, :data:`MAX_TOWARD_STEP` toward it; for
        a log-scale unknown whose ``s = log u`` moves faster than ``q`` (bounded in ``s``) the step
        that moves ``s`` by about that much (a factor 1000 or 10 in ``u``)."""
        limit = torch.full_like(u, MAX_INTERNAL_STEP)
        if bool(self.log.any()):
            rate = (self.derivative(u) / u).abs()  # ds/dq on the log scale
            limit = torch.where(self.log & (rate > 1), MAX_INTERNAL_STEP / rate, limit)
        toward = ~self.away(u, alpha_q * self.derivative(u))  # (du/dq < 0 below an upper bound)
        return torch.where(toward, limit * (MAX_TOWARD_STEP / MAX_INTERNAL_STEP), limit)

    def at_bound(self, u: torch.Tensor, rel: float = 1e-6, stderr: torch.Tensor | None = None) -> list[str]:
        """Names of the unknowns within ``rel`` of a bound, relative to ``max(|u|, |bound|, unit)``,
        ``unit`` the smaller of 1 and the unknown's standard error where ``stderr (m,)`` gives a
        finite one (an estimate of 5e-7 that the data determine to 5e-9 is 100 standard errors inside
        a bound at 0, whatever the units), else 1; and, given ``stderr``, the log-scaled ones without
        a positive lower bound below ``rel`` times theirs: at the edge 0 of the log scale, where data
        that want them negative leave them (a small estimate that the data determine is not named)."""
        unit = torch.ones_like(u)
        if stderr is not None:
            unit = torch.where(torch.isfinite(stderr) & (stderr > 0), torch.minimum(stderr, unit), unit)
        scale = torch.maximum(u.abs(), unit)
        near_lo = self.has_lower & ((u - self.lower).abs() <= rel * torch.maximum(scale, self.lower.abs().nan_to_num(0)))
        near_hi = self.has_upper & ((self.upper - u).abs() <= rel * torch.maximum(scale, self.upper.abs().nan_to_num(0)))
        if stderr is not None:
            near_lo = near_lo | (self.log & ~(self.lower > 0) & (u <= rel * stderr))
        return [self.names[i] for i in torch.nonzero(near_lo | near_hi).flatten().tolist()]


def _named(index: Mapping[str, list[int]], argument: str, name, all_names: Sequence[str],
           unknown_names: Sequence[str]) -> list[int]:
    """The unknowns that ``name`` (a key of ``bounds`` or ``scale``) stands for; a clear error for a
    name that is not estimated or not known."""
    if name in index:
        return index[name]
    if name in all_names or (isinstance(name, str) and name.removesuffix("(t0)") in all_names):
        raise ValueError(f"`{argument}` names {name!r}, which is not estimated in this fit (add it to `params=`, "
                         "or remove it from `fixed_x0=`)")
    raise ValueError(f"`{argument}` names unknown {name!r}; the unknowns are {list(unknown_names)}")


def moved_record(names: Sequence[str], given: torch.Tensor, used: torch.Tensor,
                 moved: torch.Tensor) -> dict[str, tuple[float, float]]:
    """``{name: (given, used)}`` of the guesses ``given (m,)`` that :meth:`Bounds.move_inside` moved
    (``moved (m,)``) to ``used (m,)``, as ``FitResult.moved_guesses`` records them."""
    return {names[i]: (float(given[i]), float(used[i])) for i in torch.nonzero(moved).flatten().tolist()}


def at_bound_note(names: Sequence[str]) -> str:
    """The sentence of a fit's message that names the estimates lying at their bounds (empty if none)."""
    if not names:
        return ""
    return (f" The estimates of {list(names)} lie at their bounds: the data pull them outside, and "
            "their standard errors and intervals assume an interior optimum.")


def moved_guesses_note(moved: Mapping[str, tuple[float, float]]) -> str:
    """The sentence of a fit's message that names the guesses :meth:`Bounds.move_inside` moved.

    ``moved``: ``{name: (given, used)}``, as ``FitResult.moved_guesses``.
    """
    if not moved:
        return ""
    return ("The guesses of " + str(list(moved)) + " lay on or outside their bounds and were moved inside: "
            + ", ".join(f"{name} = {given:g} -> {used:.6g}" for name, (given, used) in moved.items()) + ".")


def _once(argument: str, given: dict, i: int, name, unknown_names: Sequence[str]) -> None:
    """Record that key ``name`` of ``argument`` (``bounds`` or ``scale``) sets unknown ``i``; a ``ValueError``
    where another key set it already (a state under its two names, ``"v"`` and ``"v(t0)"``, or a
    buffer and one of its entries), rather than the later key silently winning."""
    if i in given:
        raise ValueError(f"`{argument}` gives {unknown_names[i]} twice, under {given[i]!r} and {name!r}: give it once")
    given[i] = name


def bound_pair(name: str, pair) -> tuple[float, float]:
    """``(lower, upper)`` as floats (``None`` -> infinite), validated."""
    if isinstance(pair, (str, bytes)) or not isinstance(pair, (tuple, list)) or len(pair) != 2:
        raise TypeError(f"`bounds[{name!r}]` must be a pair (lower, upper); received {pair!r}")
    out = []
    for side, value, open_value in (("lower", pair[0], -math.inf), ("upper", pair[1], math.inf)):
        if value is None:
            out.append(open_value)
            continue
        if isinstance(value, bool) or not isinstance(value, numbers.Real) and not (
                isinstance(value, torch.Tensor) and value.numel() == 1):
            raise TypeError(f"`bounds[{name!r}]` {side} bound must be a number or None; received {value!r}")
        value = float(value)
        if math.isnan(value):
            raise ValueError(f"`bounds[{name!r}]` {side} bound is NaN")
        if value == -open_value:
            beyond = "above" if side == "lower" else "below"
            raise ValueError(f"`bounds[{name!r}]` {side} bound is {value:g}: no value lies {beyond} it; give a "
                             f"finite bound, or None (or {open_value:g}) for an open side")
        out.append(value)
    if out[0] == out[1]:
        raise ValueError(
            f"`bounds[{name!r}]` needs lower < upper; received ({out[0]:g}, {out[1]:g}), a fixed value: fix it "
            "instead (leave a coefficient out of `params=`, its buffer holding the value; list an initial state "
            "in `fixed_x0=`, its value in `x0`)")
    if not out[0] < out[1]:
        raise ValueError(f"`bounds[{name!r}]` needs lower < upper; received ({out[0]:g}, {out[1]:g})")
    return out[0], out[1]
