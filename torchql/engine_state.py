"""The state of one chunk's iteration between the engine's phases, sample by sample: the loop's
state (:class:`LoopState`), the samples' rows (:func:`put_samples`, :func:`_pick`) and the
acceptance test's comparison of merits (:func:`not_above`)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from .linearize import map_fields
from .status import Status

if TYPE_CHECKING:
    from .engine import Engine

__all__ = ["LoopState", "RUNNING", "TRIAL_ONLY", "put_samples", "by_level", "shifted_report", "not_above", "bound_of",
           "members"]

_STATUSES = list(Status)
#: The status code of a sample still iterating.
RUNNING = -1

#: Entries of a trial iterate that only decide its acceptance and are not kept.
TRIAL_ONLY = ("failed", "defect", "by_model")
#: A trial step is accepted when its merit exceeds the current one by at most ``_MERIT_SLACK`` times
#: its magnitude (rounding of the sums of squares must not reject a converging step).
_MERIT_SLACK = 1e-10


def not_above(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a <= b`` up to :data:`_MERIT_SLACK` relative to ``|b|`` (an objective with a ``sigma(p)``
    function may be negative; for ``b >= 0`` this is ``a <= b (1 + _MERIT_SLACK)``)."""
    return a <= bound_of(b)


def bound_of(b: torch.Tensor) -> torch.Tensor:
    """The largest value that :func:`not_above` takes as not above ``b``."""
    return torch.where(b >= 0, b * (1 + _MERIT_SLACK), b * (1 - _MERIT_SLACK))


def members(samples: set, idx: torch.Tensor) -> torch.Tensor:
    """Whether each of the chunk's samples ``idx (S,)`` is in ``samples`` (one of the engine's sets of
    chunk rows: ``coarse_grid``, ``fast_decay``), bool ``(S,)``."""
    return torch.tensor([int(i) in samples for i in idx.tolist()], dtype=torch.bool, device=idx.device)


def shifted_report(report, offset: int):
    """``report`` for a part of the samples, the first ``offset`` before it: a count of the part's
    samples stopped is reported as ``offset`` more; a phase's name passes as it is."""
    return lambda count: report(count if isinstance(count, str) else offset + count)


def put_samples(cur: dict, target: torch.Tensor, new: dict, rows: torch.Tensor) -> None:
    """Copy samples ``rows`` of ``new`` into samples ``target`` of ``cur`` (sorted, distinct indices).

    When ``target`` is every sample of ``cur`` and ``rows`` every sample of ``new``, ``cur`` takes
    ``new``'s arrays instead of copying them (``new`` is not used after), each with storage of its
    own: two of ``new``'s arrays that share one (a re-anchored iterate's reference is its model
    solution) would otherwise stay one, and a later copy of some samples into either would write
    the other (the model solution's NaN into the reference: a batch's trials then failed).
    """
    if target.numel() == cur["z0"].shape[0] and rows.numel() == new["z0"].shape[0]:
        seen: set[int] = set()

        def own(value):
            if value is None:
                return None
            pointer = value.untyped_storage().data_ptr()
            fresh = value.clone() if pointer in seen else value
            seen.add(pointer)
            return fresh
        for key, value in new.items():
            if key not in TRIAL_ONLY:
                cur[key] = _each(own, key, value)
        return
    for key, value in new.items():
        if key not in TRIAL_ONLY:
            for old, fresh in _pairs(key, cur[key], value):
                old[target] = fresh[rows]


def _each(fn, key: str, value):
    """``fn`` applied to an iterate's entry ``key``: to each field of its linearization (``"lin"``),
    else to the array itself."""
    return map_fields(value, fn) if key == "lin" else fn(value)


def _pairs(key: str, a, b):
    """The arrays of two iterates' entries ``key``, side by side (field by field for ``"lin"``)."""
    return zip(a, b) if key == "lin" else ((a, b),)


class LoopState:
    """The mutable state of one chunk's iteration: per sample ``status`` (the position of a
    ``Status``, :data:`RUNNING` while iterating) and ``detail``, ``iterations``, ``damping`` and
    the previous iterate's ``last_damping``, ``fresh`` (at the start of an iteration),
    ``rejected`` trials at this iterate, ``sse_prev``, the estimates ``z0 (S, M)``, the current
    iterate ``cur``, ``final_guess (S, G, M)``, a prediction of the final trajectory, and which
    samples the final pass may ``polish``."""

    def __init__(self, engine: "Engine", report) -> None:
        S, dev, dtype = engine.S, engine.spec.device, engine.spec.dtype
        self.report = report
        self.status = torch.full((S,), RUNNING, dtype=torch.long, device=dev)
        self.detail = [""] * S
        self.iterations = torch.zeros(S, dtype=torch.long, device=dev)
        self.damping = torch.zeros(S, dtype=dtype, device=dev)
        self.last_damping = torch.zeros(S, dtype=dtype, device=dev)
        self.fresh = torch.ones(S, dtype=torch.bool, device=dev)
        self.rejected = torch.zeros(S, dtype=torch.long, device=dev)
        self.sse_prev = torch.full((S,), float("nan"), dtype=dtype, device=dev)
        self.z0 = engine.z0_guess.clone()
        #: the estimates of each sample's previous iterate (restored where the current one's model
        #: turns out not to integrate: :meth:`~torchql.engine_steps.StepTests._restore_lost`)
        self.prev_z0 = engine.z0_guess.clone()
        #: samples whose next trial is judged by the model's own sum of squares, not its merit (their
        #: iterate was lost and restored)
        self.distrust = torch.zeros(S, dtype=torch.bool, device=dev)
        self.all_idx = torch.arange(S, device=dev)
        self.cur: dict = {}
        self.final_guess: torch.Tensor | None = None
        self.scaled: torch.Tensor | None = None
        #: of the samples stepping, those whose step leaves a bound by a capped move (Bounds.leaving)
        self.leaving: torch.Tensor | None = None
        #: samples stopped by a convergence test on an undamped step (their estimates may be polished)
        self.undamped_stop = torch.zeros(S, dtype=torch.bool, device=dev)
        #: those of them that stopped within the time budget (set when the iteration ends)
        self.polish = torch.zeros(S, dtype=torch.bool, device=dev)

    def stop(self, rows: torch.Tensor, code: Status, text: str = "") -> None:
        """Samples ``rows`` end with ``code`` and the detail ``text``."""
        self.status[rows] = _STATUSES.index(code)
        for r in rows.tolist():
            self.detail[r] = text
        self.report_stopped()

    def report_stopped(self) -> None:
        self.report(int((self.status != RUNNING).sum()))


def _pick(x: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``x[index]`` for sorted, distinct sample indices; ``x`` itself (no copy) when they are all of them.

    Most iterations keep every sample of a chunk running, and the gathers of its largest arrays
    (the propagated columns, the linearization) would copy them whole. The result may be ``x``:
    callers only read it.
    """
    return x if index.numel() == x.shape[0] else x[index]


def by_level(levels: torch.Tensor, run, at) -> tuple[dict, torch.Tensor]:
    """The trials of samples ``(S,)`` made in groups of equal ``levels (S,)`` (a tolerance): within
    ``at(level)`` (a context), ``run(positions (R,))`` returns a group's ``(trial, ok)`` (``ok`` may be
    None); their rows are put back in the samples' order, one ``(trial, ok)`` over all (a single
    group's as it is)."""
    parts = []
    for level in levels.unique().tolist():
        pos = (levels == level).nonzero().flatten()
        with at(level):
            parts.append((pos, *run(pos)))
    if len(parts) == 1:
        return parts[0][1], parts[0][2]
    S = levels.numel()

    def empty(v):
        return None if v is None else v.new_empty((S, *v.shape[1:]))
    trial = {k: _each(empty, k, v) for k, v in parts[0][1].items()}
    ok = None if parts[0][2] is None else parts[0][2].new_empty(S)
    for pos, part, good in parts:
        if ok is not None:
            ok[pos] = good
        for key, value in part.items():
            for out, fresh in _pairs(key, trial[key], value):
                if fresh is not None:
                    out[pos] = fresh
    return trial, ok
