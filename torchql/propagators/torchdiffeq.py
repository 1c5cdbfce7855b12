"""``linear_solver="torchdiffeq"``: one adaptive torchdiffeq call over all intervals."""

from __future__ import annotations

import torch

from ..integrate import CountedField, solve
from ..solvers import MAX_COMPONENTS, STIFF_SOLVERS
from ..transfer import Transfers
from ._base import LinearPropagator


class Torchdiffeq(LinearPropagator):
    """All intervals' transfers in one torchdiffeq call with ``fit``'s ``solver`` (max-norm error
    control, so that no interval dilutes another's error; first step the whole interval, since the
    intervals are short against the dynamics). ``fit`` then integrates every nonlinear pass with
    ``solver`` too, instead of solving it on the grid. ``solver="auto"`` takes torchdiffeq's
    ``"dopri5"`` with it for a model that is not stiff; torchql's own ``"dop853"``, when given,
    integrates the transfers alike (:func:`torchql.integrate.solve`)."""

    name = "torchdiffeq"
    grid_solver = False
    auto_solver = "dopri5"

    def transfers(self, system, *, rtol, atol, solver, max_steps):
        Y0 = system.initial()
        intervals, M = Y0.shape[0], Y0.shape[1]
        if solver in STIFF_SOLVERS and Y0.numel() > MAX_COMPONENTS:
            raise ValueError(
                f"`linear_solver='torchdiffeq'` integrates the {intervals} grid intervals' transfers as one system of "
                f"{Y0.numel()} components with the fit's solver {solver!r}, an implicit solver that factorises it "
                f"densely and takes at most {MAX_COMPONENTS}: for a stiff model use the default `linear_solver` "
                "(\"radau\"), or a `grid` of fewer intervals")
        s = torch.tensor([0.0, 1.0], dtype=Y0.dtype, device=Y0.device)
        Y = solve(CountedField(system), Y0, s, solver=solver, rtol=rtol, atol=atol, max_steps=max_steps,
                  norm=_max_norm, first_step=1.0)[-1]
        T = torch.zeros(intervals, M + 1, M + 1, dtype=Y.dtype, device=Y.device)
        T[:, :M] = Y
        T[:, M, M] = 1.0
        return Transfers.from_full(T), system.n_evals


def _max_norm(x: torch.Tensor) -> torch.Tensor:
    return x.abs().max()
