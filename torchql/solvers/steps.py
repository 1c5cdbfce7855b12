"""The accepted steps of a batched Rodas5P integration, and values between them.

The solver keeps its accepted steps (their starts, sizes and stage increments) where an output
node lies inside a step, and fills those nodes at the end, all at once, from the steps' dense
output (instead of one node per sample per call as the steps are taken); the sensitivities
(:mod:`torchql.solvers.sensitivity`) are computed from the same steps.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from . import tableau

__all__ = ["StepRecord", "dense_value"]


@dataclass
class StepRecord:
    """The accepted steps (of non-zero length) of ``S`` samples, each sample's in order of time.

    Attributes
    ----------
    sample : long Tensor ``(N,)``
        The sample each step belongs to (non-decreasing).
    t, h, end : Tensor ``(N,)``
        Its start, its size, and the time it reached (``t + h`` up to rounding; a node's time
        exactly where the step landed on one).
    y : Tensor ``(N, M)``
        The state at its start.
    K : Tensor ``(8, N, M)``
        Its stage increments (:mod:`torchql.solvers.tableau`): ``y + sum_i M_i K_i`` is its end.
    """

    sample: torch.Tensor
    t: torch.Tensor
    h: torch.Tensor
    end: torch.Tensor
    y: torch.Tensor
    K: torch.Tensor

    @classmethod
    def join(cls, parts: list, like: torch.Tensor) -> "StepRecord":
        """The record of ``parts`` (``(sample, t, h, end, y, K)`` tuples of the solver's rounds,
        in order), sorted by sample (stably, so each sample's steps stay in order of time);
        ``like (S, M)`` gives the dtype, device and width of an empty record."""
        if not parts:
            M = like.shape[1]
            empty = like.new_empty(0)
            return cls(torch.zeros(0, dtype=torch.long, device=like.device), empty, empty, empty,
                       like.new_empty(0, M), like.new_empty(tableau.STAGES, 0, M))
        sample, t, h, end, y, K = (torch.cat(column, dim=1 if k == 5 else 0) for k, column in enumerate(zip(*parts)))
        order = torch.sort(sample, stable=True).indices
        return cls(sample[order], t[order], h[order], end[order], y[order], K[:, order])

    def counts(self, S: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Each sample's number of steps and the index of its first, ``(S,)`` each."""
        counts = torch.bincount(self.sample, minlength=S)
        return counts, counts.cumsum(0) - counts

    def locate(self, grid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """For each node of ``grid (S, G)``: the step that reaches or passes it (an index into the
        record, ``(S, G)``; meaningless for a sample without steps) and the node's place in it,
        ``theta (S, G)`` in ``[0, 1]`` (1: at or beyond its end)."""
        S, N = grid.shape[0], self.t.shape[0]
        counts, offsets = self.counts(S)
        if not N:
            return torch.zeros(grid.shape, dtype=torch.long, device=grid.device), torch.ones_like(grid)
        position = torch.arange(N, device=grid.device) - offsets[self.sample]
        ends = torch.full((S, max(int(counts.max()), 1)), float("inf"), dtype=grid.dtype, device=grid.device)
        ends[self.sample, position] = self.end
        k = torch.searchsorted(ends, grid.contiguous())
        k = torch.minimum(k, (counts - 1).clamp(min=0).unsqueeze(1))
        step = (offsets.unsqueeze(1) + k).clamp(max=N - 1)
        inside = ((grid - self.t[step]) / self.h[step]).clamp(0, 1)
        theta = torch.where(grid >= self.end[step], torch.ones_like(grid), inside)
        return step, theta


def dense_value(y0: torch.Tensor, y1: torch.Tensor, q: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """Rodas5P's dense output ``(1 - theta) y0 + theta (y1 + (1 - theta) (q1 + theta (q2 + theta q3)))``
    from a step's start ``y0``, end ``y1``, its vectors ``q = DENSE @ K`` (``(3, *y0.shape)``) and
    ``theta`` broadcastable against ``y0``."""
    return (1 - theta) * y0 + theta * (y1 + (1 - theta) * (q[0] + theta * (q[1] + theta * q[2])))
