"""``linear_solver="rk4_doubling"``: fixed RK4 steps with step doubling (see :mod:`torchql.transfer`)."""

from __future__ import annotations

from ..transfer import interval_transfers, rk4_series
from ._base import LinearPropagator


class RK4Doubling(LinearPropagator):
    """Every interval's transfer by fixed RK4 steps, the error estimated by step doubling and
    only the intervals that need it refined."""

    name = "rk4_doubling"

    def transfers(self, system, *, rtol, atol, solver, max_steps):
        return interval_transfers(system, rtol=rtol, atol=atol)

    def series(self, coefficients, *, rtol, atol, max_substeps):
        out = rk4_series(coefficients, rtol=rtol, atol=atol, max_substeps=max(2, max_substeps))
        return out.Y, out.failed, out.n_evals
