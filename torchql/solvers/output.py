"""The output grid of a batched adaptive solver: which node each sample heads for, which nodes its
steps land on exactly, and the values recorded at the nodes.

A grid is shared, ``(G,)``, or each sample's own, ``(S, G)``: a row is non-decreasing, and a
sample whose grid is shorter than ``G`` repeats its last node up to ``G`` (its padding). A sample
is finished at the first node of its final time, which its steps always land on; the padding then
takes its value. Nodes not landed on are filled at the end from the dense output of the steps
that pass them (:mod:`torchql.solvers.steps`).
"""

from __future__ import annotations

import torch

from . import tableau
from .steps import StepRecord, dense_value

__all__ = ["OutputGrid"]


class OutputGrid:
    """Per-sample progress along the output nodes, and the output array ``(S, G, M)``.

    Parameters
    ----------
    grid : Tensor ``(G,)`` or ``(S, G)``
    land : bool Tensor ``(G,)`` or ``(S, G)``, optional
        Nodes the steps land on exactly (default: every node). Each sample's last node is added.
    y0 : Tensor ``(S, M)``
        The values at the first node.
    """

    def __init__(self, grid: torch.Tensor, land: torch.Tensor | None, y0: torch.Tensor) -> None:
        S, M = y0.shape
        G = grid.shape[-1]
        device = y0.device
        self.S, self.G, self.M = S, G, M
        self.per_sample = grid.dim() == 2
        index = torch.arange(G, device=device)
        self.out = y0.new_full((S, G, M), float("nan"))
        self.out[:, 0] = y0
        #: next node to reach, ``(S,)``
        self.node = torch.ones(S, dtype=torch.long, device=device)
        if self.per_sample:
            #: nodes each sample reaches, ``(S,)`` (``None``: all ``G``)
            self.end = (grid < grid[:, -1:]).sum(dim=1) + 1
            landing = (torch.ones(S, G, dtype=torch.bool, device=device) if land is None
                       else land.to(device).expand(S, G).clone())
            landing[torch.arange(S, device=device), self.end - 1] = True
            landing[:, -1] = True
            next_land = torch.where(landing, index, G).flip(-1).cummin(dim=-1).values.flip(-1)
            # flat tables, read at base + node
            self.base = torch.arange(S, device=device) * G
            self._times, self._landing, self._next = grid.reshape(-1), landing.reshape(-1), next_land.reshape(-1)
        else:
            self.end = self.base = None
            landing = torch.ones(G, dtype=torch.bool, device=device) if land is None else land.to(device).clone()
            landing[-1] = True
            next_land = torch.where(landing, index, G).flip(0).cummin(dim=0).values.flip(0)
            self._times, self._landing, self._next = grid, landing, next_land
        #: whether some nodes are filled by dense output
        self.dense = not bool(landing[..., 1:].all())

    def _flat(self, rows: torch.Tensor | None, nodes: torch.Tensor) -> torch.Tensor:
        return nodes if self.base is None else (self.base if rows is None else self.base[rows]) + nodes

    def unfinished(self) -> torch.Tensor:
        """Samples with a node left to reach, ``(S,)`` bool."""
        return self.node < (self.G if self.end is None else self.end)

    def target(self, rows: torch.Tensor | None) -> torch.Tensor:
        """Time of the next node that the samples ``rows`` (``None``: all) land on, ``(A,)``."""
        node = self.node if rows is None else self.node[rows]
        return self._times[self._flat(rows, self._next[self._flat(rows, node)])]

    def passes(self, rows: torch.Tensor | None, t_new: torch.Tensor) -> torch.Tensor:
        """Whether a step of samples ``rows`` (``None``: all) to ``t_new (A,)`` passes a node to interpolate, ``(A,)``."""
        node = (self.node if rows is None else self.node[rows]).clamp(max=self.G - 1)
        flat = self._flat(rows, node)
        return (self._times[flat] < t_new) & ~self._landing[flat]

    def land(self, rows: torch.Tensor, values: torch.Tensor) -> None:
        """Record ``values (R, M)`` at the next node of samples ``rows``, which their steps landed on."""
        self.out[rows, self.node[rows]] = values
        self.node[rows] += 1

    def skip_passed(self, rows: torch.Tensor, t_new: torch.Tensor) -> None:
        """Move samples ``rows`` past the nodes strictly before ``t_new (R,)`` that their steps
        passed without landing (:meth:`fill_between` fills them)."""
        node = self.node[rows]
        times = self._times if self.base is None else self._times.view(self.S, self.G)[rows]
        first = torch.searchsorted(times, t_new.unsqueeze(-1) if self.base is not None else t_new)
        first = first.squeeze(-1) if self.base is not None else first
        limit = self._next[self._flat(rows, node.clamp(max=self.G - 1))]
        self.node[rows] = torch.maximum(node, torch.minimum(first, limit))

    def fill_between(self, steps: StepRecord, tab: tableau.Tensors) -> None:
        """Fill every node not landed on (and before each sample's end) from the dense output
        of the recorded ``steps`` that pass it (``tab``: the method's coefficients)."""
        landing = self._landing.view(-1, self.G).expand(self.S, self.G)
        grid = self._times.view(-1, self.G).expand(self.S, self.G)
        end = torch.full((self.S,), self.G, device=grid.device) if self.end is None else self.end
        index = torch.arange(self.G, device=grid.device)
        fill = ~landing & (index < end.unsqueeze(1)) & (index > 0)
        if not steps.t.shape[0] or not bool(fill.any()):
            return
        where = fill.nonzero(as_tuple=True)
        step, theta = steps.locate(grid)
        step, theta = step[where], theta[where].unsqueeze(-1)
        K = steps.K[:, step]
        y0 = steps.y[step]
        counts, _ = steps.counts(self.S)
        values = dense_value(y0, y0 + tableau.stage_sums(tab.m, K), tableau.stage_sums(tab.dense, K), theta)
        stepped = counts[where[0]] > 0
        self.out[where[0][stepped], where[1][stepped]] = values[stepped]

    def result(self, ok: torch.Tensor) -> torch.Tensor:
        """The output ``(S, G, M)``: each sample's padding repeats its last value; NaN where not ``ok``."""
        out = self.out
        if self.end is not None and bool((self.end < self.G).any()):
            index = torch.arange(self.G, device=out.device)
            last = torch.minimum(index, (self.end - 1).unsqueeze(1))
            out = out.gather(1, last.unsqueeze(-1).expand(self.S, self.G, self.M))
        out[~ok] = float("nan")
        return out
