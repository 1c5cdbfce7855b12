"""The records of a chunk's iterates (``torchql.fit``'s ``history``), kept per sample as the engine
runs: opened at each iterate, annotated as the step is decided, handed to the ``callback``, and
completed by the final pass."""

from __future__ import annotations

import torch

from .budget import deadline, until
from .result import IterationRecord

__all__ = ["Records"]


class Records:
    """The records of the iterates (``torchql.fit``'s ``history``), mixed into
    :class:`torchql.engine.Engine`, whose ``system``, ``grid``, ``history`` (per sample, a list
    of records, or None when not kept), ``callback`` and ``index`` they use."""

    def _record(self, r: int, iteration: int, z0: torch.Tensor, sse: float, traj: torch.Tensor | None = None
                ) -> IterationRecord:
        """Sample ``r``'s record of an iterate: its estimates ``z0 (M,)``, ``sse`` and trajectory ``(G, M)``."""
        n = self.system.n
        origin = self.spec.origin  # (the data's times: the local ones plus the sample's origin)
        origin = origin[self.index[r]] if isinstance(origin, torch.Tensor) else origin
        grid = (self.grid if self.grid.dim() == 1 else self.grid[r]) + origin
        params = {k: v.detach().clone() for k, v in self.system.unpack_params(z0[n:]).items()}
        return IterationRecord(iteration=iteration, params=params, x0=z0[:n].detach().clone(), sse=sse,
                               trajectory=None if traj is None else traj[:, :n].detach().clone(),
                               trajectory_t=None if traj is None else grid)

    def _open(self, rows: torch.Tensor, cur: dict, iterations: torch.Tensor) -> None:
        """Start the records of the iterates ``cur`` of samples ``rows``."""
        if self.history is None:
            return
        for r in rows.tolist():
            record = self._record(r, int(iterations[r]), cur["z0"][r], float(cur["sse"][r]), cur["rz"][r])
            record.merit = float(cur["merit"][r])
            self.history[r].append(record)

    def _annotate(self, rows: torch.Tensor, **values) -> None:
        """Set fields of the open records of samples ``rows`` (per-sample tensors or plain values)."""
        if self.history is None:
            return
        for k, r in enumerate(rows.tolist()):
            record = self.history[r][-1]
            for key, value in values.items():
                if isinstance(value, torch.Tensor):
                    value = value[k].detach().clone() if value.dim() > 1 else value[k].item()
                setattr(record, key, value)

    def _notify(self, rows) -> None:
        """Hand the open records of samples ``rows`` to the callback, under the fit's own time budget
        (the final pass evaluates without one; a callback's own work, a re-fit, keeps to the fit's)."""
        if self.callback is None or self.history is None:
            return
        moment = getattr(self, "deadline", None) if deadline() is None else deadline()
        with until(moment):
            for r in (rows.tolist() if isinstance(rows, torch.Tensor) else [rows]):
                self.callback(int(self.index[r]), self.history[r][-1])
                self.notified[r] = self.history[r][-1]

    def _notify_unsent(self, rows) -> None:
        """Hand the open records of samples ``rows`` to the callback where it has not had them: an
        iterate whose step the time budget cut short is the result's (``MAX_TIME``) though no step
        from it was decided."""
        if self.callback is None or self.history is None:
            return
        for r in (rows.tolist() if isinstance(rows, torch.Tensor) else [rows]):
            if self.history[r] and self.notified.get(r) is not self.history[r][-1]:
                self._notify(r)
