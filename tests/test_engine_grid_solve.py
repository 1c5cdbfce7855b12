"""The engine's grid solver and its step budget (torchql.engine_grid_solve).

The model is :class:`testmodels.Lag` (``x`` follows a decaying ``y`` with the lag ``1 / k``), measured
from t = 0.1 to 2 with ``k`` fitted by shooting from a guess of 1: the automatic grid is chosen for
that guess, and as ``k`` grows its model outgrows the grid (the grid solver's RK4 steps per
interval). Where the current iterate still fits the grid solver's budget and the next trial does
not, the trial is not a blow-up: it is integrated by the adaptive solver, and so are the sample's
later trials, its final solution and their sensitivities.
"""

import torch

import torchql
from testmodels import Lag, Relaxation, counting, lag_data

DT = torch.float64
X0 = torch.tensor([0.0, 1.0], dtype=DT)
OPTIONS = dict(fixed_x0=["x", "y"], t0=0.0, method="shooting")


def test_a_model_that_outgrows_its_grid_is_fitted_with_sensitivities_integrated_with_its_solution():
    """A lag of 1/100 from a guess of 1: the trials past k = 30 need more RK4 steps than the grid
    solver allows, the iterate before them did not. Those trials were blow-ups, and the damping
    held k at the budget's wall (26 iterations); integrated adaptively, the fit takes 14, and its
    estimates are the optimum that the sensitivities integrated with each solution reach (every
    trial's, ``linear_solver="rodas5p"``), within ``xtol`` (1e-8): the grid's sensitivities,
    0.7 % off at k = 26, stopped Gauss–Newton 2.5e-5 (relative) short of it."""
    data = lag_data(100.0)
    fit = torchql.fit(Lag(1.0, 1.5), data, X0, **OPTIONS)
    joint = torchql.fit(Lag(1.0, 1.5), data, X0, linear_solver="rodas5p", **OPTIONS)
    assert fit.success and joint.success, (fit.message, joint.message)
    assert fit.solver_options["solver"] == "dop853"
    assert torch.allclose(fit.estimates, joint.estimates, rtol=1e-7, atol=0), (fit.estimates, joint.estimates)
    for name, se in joint.stderr.items():  # from the sensitivities integrated with the final solution
        assert abs(fit.stderr[name] - se) <= 1e-6 * se, name
    assert fit.iterations <= 18
    assert "or the model is faster than the grid: an interval needed more steps than the grid solver" in fit.message


def test_shooting_on_auto_follows_a_model_that_becomes_stiff_to_the_stiff_solver():
    """A lag of 1e-4 from a guess of 1: held at the grid solver's wall, the explicit fit crept to
    k = 62 and ended MAX_ITER after 50 iterations. Its trials past the wall integrated adaptively,
    k grows until the model is found stiff along an iterate, and ``"auto"`` fits it again as a
    stiff model: the result is ``solver="rodas5p"``'s."""
    data = lag_data(1e4)
    auto = torchql.fit(Lag(1.0, 1.5), data, X0, **OPTIONS)
    stiff = torchql.fit(Lag(1.0, 1.5), data, X0, solver="rodas5p", **OPTIONS)
    assert stiff.success, stiff.message
    assert auto.status is stiff.status and auto.iterations == stiff.iterations, auto.message
    assert auto.solver_options["solver"] == "rodas5p" and "found the model stiff during the fit" in auto.message
    assert torch.allclose(auto.estimates, stiff.estimates, rtol=1e-12, atol=0)


def _relaxation_data(k: float) -> torchql.Observations:
    t = torch.linspace(0.1, 2.0, 20, dtype=DT)
    x = torchql.simulate(Relaxation(k, 1.0), torch.zeros(1, dtype=DT), torch.cat([torch.zeros(1, dtype=DT), t]),
                         solver="rodas5p", rtol=1e-12, atol=1e-16)[1:]
    noise = 1e-4 * torch.randn(x.shape, generator=torch.Generator().manual_seed(0), dtype=DT)
    return torchql.Observations(t, x + noise, observe=["x"], sigma=1e-4)


def test_shooting_reaches_the_optimum_of_a_relaxation_whose_transient_its_grid_misses():
    """``x(0) = 0`` known, ``k`` and ``A`` fitted from 1 and 1.5 by shooting, true ``k`` 30 and 100.
    The grid chosen for ``k = 1`` misses the transient of width ``1 / k`` after ``t0``; the grid's
    sensitivities, whose forcing ``-(x - A cos t)`` reads the stored trajectory, were off by %:
    at 30 the fit ended CONVERGED_SSE 0.2 standard errors from the optimum (SSE 3.8e-3 above it),
    at 100 MAX_ITER after 50 iterations, crawling 8 % of the way a step. The storage check sees
    the interpolant's defect as a solution of the model, and a sample whose grid misses its model
    takes its sensitivities with its solutions: both end at the optimum of the sensitivities
    integrated with every solution (``linear_solver="rodas5p"``), within ``xtol``."""
    for k in (30.0, 100.0):
        data = _relaxation_data(k)
        options = dict(method="shooting", params=["k", "A"], t0=0.0, fixed_x0=["x"])
        fit = torchql.fit(Relaxation(1.0, 1.5), data, torch.zeros(1, dtype=DT), **options)
        joint = torchql.fit(Relaxation(1.0, 1.5), data, torch.zeros(1, dtype=DT), linear_solver="rodas5p", **options)
        assert fit.status is torchql.Status.CONVERGED and joint.success, (k, fit.message)
        assert torch.allclose(fit.estimates, joint.estimates, rtol=1e-7, atol=0), (k, fit.estimates, joint.estimates)
        # the sums of squares agree to their integration error, 2 sqrt(SSE) |w rtol y| sqrt(20) = 3e-5 (2.5e-6 of it)
        assert abs(fit.sse - joint.sse) <= 2.5e-6 * joint.sse
        assert "misses a change of the model" in fit.message


def test_a_relaxation_whose_decay_holds_the_explicit_steps_takes_rodas5p_sensitivities(monkeypatch):
    """True ``k = 1e3`` over ``[0, 2]``: ``k * span = 2e3``, below the stiff path's 1e4, but DOP853's
    steps at the fit's tolerance are held at ``h k`` of about 1.3, 1,600 of them, each with twelve
    stage Jacobians to differentiate: the sample's shooting trials took 8.1 s of DOP853 sensitivities.
    Once a decay holds most of DOP853's steps in one such solve (``h max(-Re lambda) >= 1``: at
    k = 530, the fourth), the sample's solutions with sensitivities are Rodas5P's (2.9 s in all), at
    the same optimum in as many iterations."""
    import torchql.engine_evaluate as evaluate

    calls = {"explicit": 0, "rodas": 0}
    for name, solver in (("explicit", "explicit_sensitivities"), ("rodas", "rodas5p_sensitivities")):
        monkeypatch.setattr(evaluate, solver, counting(calls, name, getattr(evaluate, solver)))
    data = _relaxation_data(1e3)
    options = dict(method="shooting", params=["k", "A"], t0=0.0, fixed_x0=["x"])
    fit = torchql.fit(Relaxation(1.0, 1.5), data, torch.zeros(1, dtype=DT), **options)
    used = dict(calls)
    joint = torchql.fit(Relaxation(1.0, 1.5), data, torch.zeros(1, dtype=DT), linear_solver="rodas5p", **options)
    assert fit.status is torchql.Status.CONVERGED and joint.success, fit.message
    assert fit.solver_options["solver"] == "dop853"
    assert used["rodas"] >= 6 and used["explicit"] <= 4, used  # (every solve was DOP853's: 10)
    assert fit.iterations == joint.iterations
    assert torch.allclose(fit.estimates, joint.estimates, rtol=1e-7, atol=0), (fit.estimates, joint.estimates)
    assert "by the adaptive solver (Rodas5P's with their sensitivities" in fit.message


def test_fit_many_takes_rodas5p_sensitivities_for_the_samples_whose_decay_holds_dop853_alone():
    """A batch of the relaxation at ``k = 1e3`` (Rodas5P's sensitivities once its decay holds DOP853's
    steps) and at ``k = 30`` (DOP853's): each sample is its own fit."""
    sets = [_relaxation_data(1e3), _relaxation_data(30.0)]
    options = dict(method="shooting", params=["k", "A"], t0=0.0, fixed_x0=["x"])
    batch = torchql.fit_many(Relaxation(1.0, 1.5), sets, torch.zeros(1, dtype=DT), **options)
    for i, data in enumerate(sets):
        alone = torchql.fit(Relaxation(1.0, 1.5), data, torch.zeros(1, dtype=DT), **options)
        assert batch[i].status is alone.status and batch[i].iterations == alone.iterations, i
        assert batch[i].message == alone.message
        torch.testing.assert_close(batch[i].estimates, alone.estimates, rtol=1e-10, atol=0)
    assert "Rodas5P's with their sensitivities" in batch[0].message
    assert "Rodas5P's with their sensitivities" not in batch[1].message
