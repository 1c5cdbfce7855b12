"""``linear_solver="taylor_quintic"``: Taylor series over quintic Hermite interpolants of ``z`` and ``h f``.

The default propagator (:mod:`.taylor`) stores the reference ``z`` and ``h f`` between grid nodes
as cubic Hermite interpolants of their node values and slopes, whose error, of order ``h^4``,
moves the Kantorovich fixed point off the model's optimum by as much; the final pass then takes
Gauss–Newton steps on the model to remove it. This one also matches their second derivatives at
the nodes, ``z'' = f'`` and ``f'' = A' z' + A f'`` (from the linearization's own ``f'`` and ``A'``:
no extra derivative), which makes both quintic and their error of order ``h^6``; ``h A`` stays
cubic. The series is summed exactly as the default's (:func:`torchql.taylor.series_transfers`),
with a forcing of degree 8 instead of 6.

``f''`` is exact where the model has no explicit time dependence; a component whose ``f'`` is not
``A z'`` to rounding (an explicit ``t``, a measured input) keeps its cubic ``h f`` row. Measured
on noisy nonlinear fits (``experiments/quintic_storage.py``), the Kantorovich fixed point on the
same grid is 20 to 3,500 times closer to the model's optimum than with the cubic storage: the
homogeneous solutions still read the cubic ``h A``, whose error moves the fixed point in
proportion to the residuals, so on noisy data the order stays ``h^4``, with a smaller constant.

Its cost: the forcing's higher degree means at least ten terms per interval instead of eight,
and the second derivatives two more products per node. With the automatic grid, single fits
take about the default's time (median per-problem ratio 1.00 to 1.02 over 15 random problems in
three runs, 0.83 to 0.96 on the Duffing oscillators, where it saves the final pass an integrated
step); in ``fit_many``, 100 Lotka–Volterra datasets 0.94 of it, 1,000 linear oscillators 1.17.
The automatic grid does not yet count on the finer storage (it chooses the cubic storage's
intervals), so this propagator buys accuracy, not speed.
"""

from __future__ import annotations

from ..taylor import taylor_transfers
from ..transfer import _Coefficients
from .taylor import TaylorSeries


class TaylorQuintic(TaylorSeries):
    """The default Taylor-series propagator over quintic Hermite interpolants of ``z`` and ``h f``."""

    name = "taylor_quintic"
    hermite_degree = 5

    def transfers(self, system, *, rtol, atol, solver, max_steps):
        return taylor_transfers(system, rtol=rtol, atol=atol, coefficients=_Coefficients(system, degree=5))
