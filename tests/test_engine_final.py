"""The final pass's Gauss–Newton steps on the model itself (torchql/engine_final.py).

On a coarse storage grid Kantorovich's fixed point carries the grid's interpolation error; the
final pass takes the model's own Gauss–Newton step from there, so the estimates are the model's
optimum on any grid. Without those steps (``POLISH_STEPS = 0``) the same fit of the thesis' nonlinear
oscillator stops about 1e-5 off. (A model linear in its states has exact Kantorovich fixed points on any
grid: its linearization about the interpolated reference is exact where the coefficients agree.)
"""

from __future__ import annotations

import pytest
import torch

import torchql
import torchql.budget as budget
import torchql.engine_final as engine_final
from testmodels import LotkaVolterra
from torchql.models import NonlinearOscillator
from torchql.options import Tolerances

DT = torch.float64
TRUTH = torch.tensor([0.0, 1.0, 0.1, 3.0, 0.2, 4.0], dtype=DT)
XTOL = Tolerances.resolve(DT).xtol


def _exact_fit(**options):
    t = torch.linspace(0, 6.5, 27, dtype=DT)
    x = torchql.simulate(NonlinearOscillator(0.1, 3.0, 0.2, 4.0), torch.tensor([0.0, 1.0], dtype=DT), t,
                         rtol=1e-13, atol=1e-15)
    data = torchql.Observations(t, x[:, :1], observe=["y"])
    return torchql.fit(NonlinearOscillator(0.12, 2.8, 0.25, 3.7), data, torch.tensor([0.0, 1.0], dtype=DT), **options)


def test_a_coarse_grid_fit_ends_at_the_model_optimum(monkeypatch):
    polished = _exact_fit(grid=50)
    assert polished.success
    assert float((polished.estimates - TRUTH).abs().max()) < 1e-10
    steps = [r for r in polished.history if r.alpha is not None and r.alpha_norm > XTOL]
    assert steps, "the grid's fixed point needed a step on the model"
    assert polished.iterations == polished.history[-1].iteration
    monkeypatch.setattr(engine_final, "POLISH_STEPS", 0)
    fixed_point = _exact_fit(grid=50)
    assert fixed_point.success
    assert float((fixed_point.estimates - TRUTH).abs().max()) > 1e-6  # the grid's own error
    assert fixed_point.iterations < polished.iterations


def test_the_steps_on_the_model_respect_max_iter():
    free = _exact_fit(grid=50)
    capped = _exact_fit(grid=50, max_iter=free.iterations - 1)
    assert capped.iterations <= free.iterations - 1


def test_on_a_fine_grid_no_step_is_taken():
    fine = _exact_fit(grid=1000)
    assert fine.success
    assert float((fine.estimates - TRUTH).abs().max()) < 1e-9
    last = fine.history[-2]  # the iterate before the final evaluation: the iteration's own last step
    assert last.alpha_norm <= XTOL


class _Friction(torchql.ODEModel):
    """``x' = v``, ``v' = -2 x - b v - a tanh(50 v)``: a friction that switches over ``|v| < 0.02``,
    a change the automatic grid's fourth-derivative estimate does not see."""

    state_names = ("x", "v")

    def __init__(self, a: float = 0.3, b: float = 0.1) -> None:
        super().__init__()
        self.register_buffer("a", torch.tensor(a, dtype=DT))
        self.register_buffer("b", torch.tensor(b, dtype=DT))

    def forward(self, t, x):
        p, v = x.unbind(-1)
        return torch.stack((v, -self.b * v - self.a * torch.tanh(50.0 * v) - 2.0 * p), -1)


def test_where_the_grid_misses_a_fast_change_the_final_pass_still_reaches_the_optimum():
    """The Kantorovich fixed point on the automatic grid (200 intervals) is 0.2 standard errors off, and
    so were the grid's sensitivities: Gauss-Newton with them stopped at a point whose SSE is 1e-3 above
    the optimum, and said CONVERGED. A second step on the model takes the sensitivities integrated
    with the solution, and the fit ends at the optimum that shooting reaches (SSE to 1e-9 relative,
    the estimates within 1e-4 of a standard error), for either storage."""
    t = torch.linspace(0, 10, 41, dtype=DT)
    x = torchql.simulate(_Friction(), torch.tensor([1.0, 0.0], dtype=DT), t)
    noise = 0.01 * torch.randn(41, 1, generator=torch.Generator().manual_seed(5), dtype=DT)
    data = torchql.Observations(t, x[:, :1] + noise, observe=["x"])
    x0 = torch.tensor([1.0, 0.0], dtype=DT)
    optimum = torchql.fit(_Friction(0.2, 0.2), data, x0, method="shooting")
    se = torch.tensor(list(optimum.stderr.values()), dtype=DT)
    for options in ({}, {"linear_solver": "taylor_quintic"}):
        result = torchql.fit(_Friction(0.2, 0.2), data, x0, **options)
        assert result.status is torchql.Status.CONVERGED, result.message
        assert abs(result.sse - optimum.sse) <= 1e-9 * optimum.sse
        assert float(((result.estimates - optimum.estimates) / se).abs().max()) < 1e-4


def test_fit_many_steps_to_the_optimum_as_each_fit_does():
    """The final pass's steps with sensitivities integrated alongside are each sample's own: two noisy
    friction datasets fitted together end where each fits alone (estimates 1e-8, the same status
    and iterations)."""
    t = torch.linspace(0, 10, 41, dtype=DT)
    x = torchql.simulate(_Friction(), torch.tensor([1.0, 0.0], dtype=DT), t)
    sets = [torchql.Observations(t, x[:, :1] + 0.01 * torch.randn(41, 1, generator=torch.Generator().manual_seed(s),
                                                                  dtype=DT), observe=["x"]) for s in (5, 6)]
    x0 = torch.tensor([1.0, 0.0], dtype=DT)
    batch = torchql.fit_many(_Friction(0.2, 0.2), sets, x0)
    for i, data in enumerate(sets):
        alone = torchql.fit(_Friction(0.2, 0.2), data, x0)
        assert batch[i].status is alone.status and batch[i].iterations == alone.iterations
        torch.testing.assert_close(batch[i].estimates, alone.estimates, rtol=1e-8, atol=1e-10)


def test_where_the_storage_misses_the_model_shooting_on_either_storage_reaches_the_optimum():
    """Shooting's Gauss–Newton steps take the grid's sensitivities, which miss ``tanh(50 v)``'s switch
    as the grid does: with the quintic storage (its grid coarser) they stopped at CONVERGED_SSE 0.06
    standard errors from the optimum, 1e-4 of SSE above it. The final pass's check of the storage
    against the model (torchql.storage_check) gives such a sample the sensitivities integrated with
    its solution, and says so; the fit ends at the optimum of the adaptive linear solver's fit."""
    t = torch.linspace(0, 10, 41, dtype=DT)
    x = torchql.simulate(_Friction(), torch.tensor([1.0, 0.0], dtype=DT), t)
    noise = 0.01 * torch.randn(41, 1, generator=torch.Generator().manual_seed(5), dtype=DT)
    data = torchql.Observations(t, x[:, :1] + noise, observe=["x"])
    x0 = torch.tensor([1.0, 0.0], dtype=DT)
    optimum = torchql.fit(_Friction(0.2, 0.2), data, x0, method="shooting", linear_solver="torchdiffeq")
    se = torch.tensor(list(optimum.stderr.values()), dtype=DT)
    for linear_solver in ("taylor", "taylor_quintic"):
        result = torchql.fit(_Friction(0.2, 0.2), data, x0, method="shooting", linear_solver=linear_solver)
        assert result.success, result.message
        if linear_solver == "taylor_quintic":  # (the cubic storage's grid for shooting resolves it)
            assert "storage grid misses a change of the model" in result.message
        assert abs(result.sse - optimum.sse) <= 1e-9 * optimum.sse
        assert float(((result.estimates - optimum.estimates) / se).abs().max()) < 1e-4


def test_a_fit_that_wanders_along_an_exactly_undetermined_direction_says_so():
    """Predators alone observed: ``(x(t0), d) -> (s x(t0), d / s)`` leaves them unchanged, exactly.
    The storage grid's sensitivities measure that direction's singular value at 1.8e-7 of the
    largest (scipy's central differences: 3e-10), above ``rcond``; the iteration moved along it
    until ``max_iter``. A fit that does not converge is tested at the sensitivities' accuracy
    (``sqrt(rtol)``): NOT_IDENTIFIABLE, naming the pair, the product ``x(t0) d`` at the truth's."""
    t = torch.linspace(0.0, 8.0, 40, dtype=DT)
    y = torchql.simulate(LotkaVolterra(1.0, 0.4, 1.2, 0.3), torch.tensor([2.0, 1.0], dtype=DT), t,
                         rtol=1e-12, atol=1e-14)[:, 1:]
    result = torchql.fit(LotkaVolterra(0.8, 0.5, 1.0, 0.25), torchql.Observations(t, y, observe=["y"]),
                         x0=torch.tensor([1.5, 1.0], dtype=DT), max_iter=15)
    assert result.status is torchql.Status.NOT_IDENTIFIABLE, result.message
    assert "{x(t0), d}" in result.message and "(MAX_ITER)" in result.message
    assert float(result.x0[0] * result.params["d"]) == pytest.approx(0.6, rel=1e-5)


def test_a_fit_that_stalls_at_the_exact_truth_from_rates_guessed_near_zero_is_converged():
    """Shooting from rates 1e-10 (2e6 times below the truth, inside (0, None) bounds) reaches exact
    data to an SSE of 1e-24, where rounding decides every trial step and the damping runs out
    (STALLED). The Gauss–Newton step on the model there is 1e-15 of the estimates: converged. It
    was reported DIVERGED, its rates having "run away" from the tiny guesses."""
    from torchql.models import FirstOrderReactions

    truth = dict(k1=5e-5, k2=2e-4)
    x0 = torch.tensor([100.0, 0.0, 0.0], dtype=DT)
    t = torch.arange(21, dtype=DT) * 500.0
    data = torchql.Observations(t, torchql.simulate(FirstOrderReactions(**truth), x0, t, rtol=1e-13, atol=1e-15),
                                observe=["A", "B", "C"])
    result = torchql.fit(FirstOrderReactions(k1=1e-10, k2=1e-10), data, x0, method="shooting",
                         bounds={"k1": (0.0, None), "k2": (0.0, None)})
    assert result.status is torchql.Status.CONVERGED and result.success, result.message
    assert "Found on the model itself" in result.message
    for name, value in truth.items():  # exact data: the truth to the integration's accuracy
        assert float(result.params[name]) == pytest.approx(value, rel=1e-10)
    assert result.sse < 1e-20
    assert bool(torch.isfinite(result.covariance).all())  # a converged fit's error bars


def test_the_steps_on_the_model_keep_to_the_time_budget(monkeypatch):
    """The polishing steps are optional, so they run under the fit's own deadline (the rest of the
    final pass runs without one: every sample that finished in time gets its evaluation). A stalled
    SIR fit with ``max_time=20`` spent 48 s there integrating one trial. Here each trial integration
    of the steps finds its deadline spent: the fit keeps the iteration's fixed point, evaluated on
    the model, and says MAX_TIME without error bars; without a budget nothing changes."""
    seen = []
    original = engine_final.FinalPass._model_at

    def spent(self, *args, **kwargs):
        seen.append(budget.deadline())
        if budget.deadline() is not None:  # a polishing trial, under the fit's deadline: spent by now
            raise budget.TimeBudgetExceeded
        return original(self, *args, **kwargs)

    monkeypatch.setattr(engine_final.FinalPass, "_model_at", spent)
    free = _exact_fit(grid=50)
    assert free.success and seen and all(d is None for d in seen)
    seen.clear()
    cut = _exact_fit(grid=50, max_time=600.0)
    assert any(d is not None for d in seen), "a polishing trial ran under the budget"
    assert cut.status is torchql.Status.MAX_TIME and not cut.success
    assert "stopped by the time budget (max_time = 600 s)" in cut.message and "had converged" in cut.message
    assert cut.iterations < free.iterations
    assert float((cut.estimates - TRUTH).abs().max()) > 1e-6  # the grid's fixed point, not polished
    assert torch.isfinite(torch.tensor(cut.sse)) and torch.isnan(cut.covariance).all()


def test_a_long_polishing_step_is_shortened_to_the_unknowns_scale(monkeypatch):
    """A Gauss–Newton step on the model longer than ``POLISH_MAX_STEP`` of the unknowns' scale is taken
    that long, along its direction (a stalled fit's rank-deficient step reached 1e15 of the scale,
    whose model took 10^5 explicit steps to fail). With the bound far below the grid's error the
    steps are each that long, and run out before reaching the optimum: STALLED (``max_iter`` was not
    reached; the final pass's own limit is no user's), saying so."""
    monkeypatch.setattr(engine_final, "POLISH_MAX_STEP", 1e-9)
    short = _exact_fit(grid=50)
    polishing = short.history[-4:-1]  # (the last record is the final evaluation's)
    assert all(r.alpha_norm == pytest.approx(1e-9, rel=1e-12) for r in polishing)
    assert all(b.sse < a.sse for a, b in zip(polishing, polishing[1:]))  # each kept, lowering the SSE
    assert short.status is torchql.Status.STALLED and "stopped before converging" in short.message
    assert short.iterations < short.options.max_iter


def test_estimates_run_away_stop_the_steps_on_the_model(monkeypatch):
    """The final pass takes no step on the model from estimates beyond ``RUNAWAY_FACTOR`` times their
    typical magnitudes: the diagnosis calls them a divergence whatever a further step does. (A fit whose
    optimum lies at infinity doubled an initial state from 1e6 to 4e11 in 20 such steps, at one sum of
    squares, each a solve with sensitivities: 34 of its 124 s.) With the factor set below the estimates'
    own ratio to their guesses, the grid's fixed point is kept, not converged on the model: STALLED,
    saying why."""
    polished = _exact_fit(grid=50)
    monkeypatch.setattr(engine_final, "RUNAWAY_FACTOR", 0.5)
    stopped = _exact_fit(grid=50)
    assert stopped.status is torchql.Status.STALLED and not stopped.success
    assert "were stopped with the estimates beyond 0.5 times their typical magnitudes" in stopped.message
    assert stopped.iterations < polished.iterations
    assert float((stopped.estimates - TRUTH).abs().max()) > 1e-6  # the grid's own error, unpolished
