"""``linear_solver="taylor_quintic"``: Taylor series over quintic Hermite interpolants of ``z``, ``h f`` and ``h A``.

The default propagator (:mod:`.taylor`) stores the reference ``z``, ``h f`` and ``h A`` between grid
nodes as cubic Hermite interpolants of their node values and slopes, whose error, of order ``h^4``,
moves the Kantorovich fixed point off the model's optimum and the homogeneous solutions (the
sensitivities, hence the standard errors) off the model's by as much. This one also matches
their second derivatives at the nodes, which makes all three quintic and their error of order
``h^6``:

* ``z'' = f'`` and ``f'' = A' z' + A f'``, from the linearization's own ``f'`` and ``A'``; ``f''`` is
  exact where the model has no explicit time dependence, and a component whose ``f'`` is not
  ``A z'`` to rounding (an explicit ``t``, a measured input) keeps its cubic ``h f`` row;
* ``A''``, the second time derivative of the Jacobian along the reference with ``z'' = f'``, which
  the engine's linearization gives for this propagator (:class:`torchql.linearize.SecondLinearization`:
  one more backward pass per state by autograd, a second forward-mode tangent otherwise), with its
  explicit time terms.

The series is summed exactly as the default's (:func:`torchql.taylor.series_transfers`), with
``h A`` of degree 5 and a forcing of degree 10 instead of 6, so at least 12 terms per interval
instead of 8; and ``grid="auto"`` counts the intervals by the quintic's error bound
(:func:`torchql.grid.needed_intervals`), for the same interpolation error as the cubic storage's.

Measured (``benchmarks/grid_tradeoff.py``, torch on one thread): 1,000 noisy linear oscillators
choose 25 or 40 intervals where the cubic storage chooses 100 or 200, and take 0.62 of the
default's time, with the estimates and standard errors of a 1,000-interval grid within 5.3e-9 and
1.2e-7 (the default's: 8.7e-10 and 2.6e-7); 1,000 coasting cars, on 20 intervals either way,
take 1.19 times as long, within 2.5e-10 and 1.7e-10 (the default's: 7.4e-8 and 4e-7), one
iteration fewer. Single fits, whose cost is the number of operations rather than of intervals,
take 1.10 to 1.35 times the default's time on ``benchmarks/fit_speed.py``'s problems and 1.09 to
1.80 (median 1.16) on ``experiments/quintic_storage.py``'s, where the fixed points on 50 to 200
intervals are 60 to 370,000 times closer to the optimum; hence not the default.
"""

from __future__ import annotations

from ..taylor import taylor_transfers
from ..transfer import _Coefficients
from .taylor import TaylorSeries


class TaylorQuintic(TaylorSeries):
    """The default Taylor-series propagator over quintic Hermite interpolants of ``z``, ``h f`` and ``h A``."""

    name = "taylor_quintic"
    hermite_degree = 5
    jacobian_degree = 5

    def transfers(self, system, *, rtol, atol, solver, max_steps):
        return taylor_transfers(system, rtol=rtol, atol=atol, coefficients=_Coefficients(system, degree=5))
