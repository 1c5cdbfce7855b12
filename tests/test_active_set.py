"""The bounded update: unknowns held on their bounds, and let go where the data pull them inside.

An unknown that the unconstrained solution pushes onto its bound is held there while the others
are re-solved; held on the strength of that first solve alone, it can be held wrongly (the others'
free moves pushed it out), and at an unknown one rounding inside its bound the bound became a
false stationary point that the iteration reported as converged. These tests check the update
against scipy's bounded linear least squares, and fits that start at or reach such a point
against scipy's bounded nonlinear least squares over ``solve_ivp``.
"""

import math

import numpy as np
import pytest
import torch

import torchql
from testmodels import Decay, LotkaVolterra, MichaelisMenten
from torchql.active_set import bounded_update
from torchql.bounds import Bounds
from torchql.lstsq import solve_update_batch

scipy_optimize = pytest.importorskip("scipy.optimize")
solve_ivp = pytest.importorskip("scipy.integrate").solve_ivp

DT = torch.float64


def _solve(rows, C, d, w):
    alpha = solve_update_batch(C, d, w, 1e-12, None)[0]
    return alpha, torch.zeros(alpha.shape[0], dtype=torch.bool), torch.zeros(alpha.shape[0], dtype=DT)


def test_an_unknown_pushed_out_only_by_the_others_free_move_is_let_go():
    """``min |C v - b|`` over the box ``[0, 1]^2`` from ``u`` 1e-12 below the upper bounds, the
    unconstrained minimum at ``(2, 1.2)`` and the columns anti-correlated: the unconstrained step
    pushes both unknowns out of their upper bounds, but with the first held on its bound the
    second's best value is 0.2 (scipy's bounded solution holds only the first). The update holds
    the first toward its bound and moves the second down by a capped step (a factor 1000 in its
    distance to the bound), which :meth:`Bounds.leaving` reports: no such step is converged."""
    C = torch.tensor([[1.0, -1.0], [1.0, -0.9], [0.0, 0.3]], dtype=DT)
    u = torch.full((2,), 1.0 - 1e-12, dtype=DT)
    b = C @ torch.tensor([2.0, 1.2], dtype=DT)
    d = b - C @ u  # the misfit at u
    reference = scipy_optimize.lsq_linear(C.numpy(), b.numpy(), bounds=(0.0, 1.0))
    assert reference.active_mask.tolist() == [1, 0]  # only the first unknown on its (upper) bound
    assert reference.x[1] == pytest.approx(0.2, abs=1e-9)
    names = ["p", "q"]
    bounds = Bounds({"p": (0.0, 1.0), "q": (0.0, 1.0)}, names, {}, names, DT, torch.device("cpu"))
    alpha, capped, infeasible, _ = bounded_update(bounds, _solve, C[None], d[None], torch.ones(1, 3, dtype=DT),
                                                  u[None])
    assert not bool(infeasible.any())
    assert float(alpha[0, 0]) >= 0.0  # held toward its bound
    assert 1.0 - float(u[1] + alpha[0, 1]) == pytest.approx(1e-9, rel=1e-3)  # let go: 1000 times as far
    assert capped[0].tolist() == [True, True]
    assert bool(bounds.leaving(u[None], alpha, capped))

def _scipy_bounded(rhs, t, y, u0, lower, upper, n):
    """scipy ``least_squares`` (trf) over ``solve_ivp`` (DOP853, rtol 1e-11): initial states, then coefficients."""
    def residuals(u):
        sol = solve_ivp(rhs, (t[0], t[-1]), u[:n], t_eval=t, args=(u[n:],), rtol=1e-11, atol=1e-13, method="DOP853")
        return (sol.y.T - y).ravel()
    out = scipy_optimize.least_squares(residuals, u0, bounds=(lower, upper), x_scale="jac", xtol=1e-14,
                                       ftol=1e-14, gtol=1e-14)
    return out.x, 2 * out.cost


def test_a_guess_one_rounding_below_its_bound_climbs_out_to_the_interior_optimum():
    """``y = 2 exp(-0.5 t)`` with noise, ``k`` in ``(0, 1)`` guessed at the largest double below 1:
    the fit was CONVERGED at k = 0.818 (SSE 573 times the optimum's) on capped steps each far
    below ``xtol``. It reaches the optimum that a guess of 1.0 (moved inside) reaches."""
    t = torch.linspace(0, 5, 21, dtype=DT)
    noise = 0.01 * torch.randn(21, dtype=DT, generator=torch.Generator().manual_seed(0))
    data = torchql.Observations(t, (2 * torch.exp(-0.5 * t) + noise).unsqueeze(-1), observe=["y"])
    x, sse = _scipy_bounded(lambda _, s, p: -p[0] * s, t.numpy(), data.y.numpy(), [2.0, 0.5], [-np.inf, 0.0],
                            [np.inf, 1.0], 1)
    for method in ("kantorovich", "shooting"):
        result = torchql.fit(Decay(k=math.nextafter(1.0, 0.0)), data, x0=torch.tensor([2.0], dtype=DT),
                             bounds={"k": (0.0, 1.0)}, method=method, initial_trajectory="integrate")
        assert result.status is torchql.Status.CONVERGED, result.message
        assert float(result.params["k"]) == pytest.approx(x[1], rel=1e-7)
        assert result.sse == pytest.approx(sse, rel=1e-9)


@pytest.fixture(scope="module")
def predators():
    t = torch.linspace(0, 10, 41, dtype=DT)
    x = torchql.simulate(LotkaVolterra(), torch.tensor([2.0, 1.0], dtype=DT), t)
    y = x + 0.02 * torch.randn(x.shape, dtype=DT, generator=torch.Generator().manual_seed(3))
    return torchql.Observations(t, y, observe=["x", "y"])


def test_a_rate_the_data_pull_inside_is_not_held_on_its_bound(predators):
    """Lotka–Volterra with ``a <= 0.9`` (truth 1.0) and ``d >= 0.35`` (truth 0.3): at the bounded
    optimum only ``d`` lies on its bound. The data-built start leaves ``a`` 1e-8 below its bound,
    where the unconstrained step pushed it (with ``d``) outward: held there, it ended CONVERGED at
    ``a = 0.9`` with the sum of squares 42 % above the optimum, and named ``a`` at its bound though
    the gradient there points inside. Now it reaches scipy's bounded optimum (trf over DOP853)."""
    def rhs(_, z, p):
        a, b, c, d = p
        return [a * z[0] - b * z[0] * z[1], -c * z[1] + d * z[0] * z[1]]
    lower, upper = [-np.inf, -np.inf, 0.0, -np.inf, -np.inf, 0.35], [np.inf, np.inf, 0.9, np.inf, np.inf, np.inf]
    x, sse = _scipy_bounded(rhs, predators.t.numpy(), predators.y.numpy(), [2.0, 1.0, 0.8, 0.4, 1.2, 0.4],
                            lower, upper, 2)
    result = torchql.fit(LotkaVolterra(0.8, 0.4, 1.2, 0.4), predators, x0=torch.tensor([2.0, 1.0], dtype=DT),
                         bounds={"a": (0, 0.9), "d": (0.35, None)})
    assert result.status is torchql.Status.CONVERGED, result.message
    assert result.sse == pytest.approx(sse, rel=1e-9)
    assert result.estimates.numpy() == pytest.approx(x, rel=1e-6)
    assert "['d']" in result.message  # only d named at its bound


def test_an_optimum_on_two_bounds_is_converged_with_its_standard_errors():
    """Michaelis–Menten by shooting with ``V <= 0.5`` and ``Km >= 0`` both active at the optimum
    (scipy's active mask): the estimates equal scipy's, and the fit, STALLED with NaN standard
    errors before, is CONVERGED with finite ones and names both unknowns at their bounds."""
    t = torch.linspace(0, 6, 25, dtype=DT)
    x = torchql.simulate(MichaelisMenten(1.0, 2.0), torch.tensor([5.0], dtype=DT), t)
    data = torchql.Observations(t, x + 0.02 * torch.randn(x.shape, dtype=DT, generator=torch.Generator().manual_seed(3)),
                                observe=["S"])
    ref, sse = _scipy_bounded(lambda _, s, p: [-p[0] * s[0] / (p[1] + s[0])], t.numpy(), data.y.numpy(),
                              [4.0, 0.3, 1.0], [-np.inf, 0.0, 0.0], [np.inf, 0.5, np.inf], 1)
    result = torchql.fit(MichaelisMenten(0.3, 1.0), data, x0=torch.tensor([4.0], dtype=DT),
                         bounds={"V": (0, 0.5), "Km": (0, None)}, method="shooting")
    assert result.status is torchql.Status.CONVERGED, result.message
    assert result.sse == pytest.approx(sse, rel=1e-9)
    assert float(result.x0[0]) == pytest.approx(ref[0], rel=1e-8)
    # (approached a decade a step, MAX_TOWARD_STEP: the last step below xtol leaves a tenth of it)
    assert float(result.params["V"]) == pytest.approx(0.5, rel=1e-11)
    assert float(result.params["Km"]) < 1e-10
    assert all(math.isfinite(v) for v in result.stderr.values())
    assert "['V', 'Km']" in result.message


def test_the_final_pass_measures_stationarity_by_the_bounded_step():
    """At estimates on a bound the unconstrained Gauss–Newton step points outside, and a stalled
    fit there was never found stationary (NaN errors at a bounded optimum). The final pass's step
    is the bounded one: zero for an unknown the data pull outside its bound, with the others
    re-solved; NaN where the data pull one inside (no optimum)."""
    from types import SimpleNamespace

    from torchql.engine_final import FinalPass

    names = ["p", "q"]
    bounds = Bounds({"p": (0.0, 1.0)}, names, {}, names, DT, torch.device("cpu"))
    final = SimpleNamespace(spec=SimpleNamespace(bounds=bounds, rcond=1e-12))
    J = torch.tensor([[[1.0, 0.0], [0.0, 1.0], [1.0, 0.0]]], dtype=DT)  # orthogonal columns
    u = torch.tensor([[math.nextafter(1.0, 0.0), 0.3]], dtype=DT)  # p on its upper bound
    for pull, expected in ((1.0, "held"), (-1.0, "left")):
        rw = J @ torch.tensor([pull, 0.0], dtype=DT)  # the unconstrained step: p by `pull`, q by 0
        step = FinalPass._bounded(final, J, rw[0][None], u, None)
        if expected == "held":  # pulled outside: p stays, q re-solved with p held (still 0)
            assert float(step[0, 0]) == 0.0 and abs(float(step[0, 1])) < 1e-15
        else:  # pulled inside: the bound is no optimum
            assert bool(torch.isnan(step).all())
