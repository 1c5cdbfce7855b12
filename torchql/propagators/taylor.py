"""``linear_solver="taylor"``: each interval's Taylor series (see :mod:`torchql.taylor`)."""

from __future__ import annotations

from ..taylor import series_transfers, taylor_transfers
from ._base import LinearPropagator


class TaylorSeries(LinearPropagator):
    """Every interval's transfer from its Taylor series, exact for the interpolated (polynomial)
    coefficients and summed to a truncation error bounded by Gronwall's inequality, in substeps
    where the interval is long against the dynamics. The default."""

    name = "taylor"

    def transfers(self, system, *, rtol, atol, solver, max_steps):
        return taylor_transfers(system, rtol=rtol, atol=atol)

    def series(self, coefficients, *, rtol, atol, max_substeps):
        out = series_transfers(coefficients, rtol=rtol, atol=atol, max_substeps=max_substeps)
        return out.Y, out.failed, out.points
