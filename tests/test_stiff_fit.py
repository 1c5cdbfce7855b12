"""Stiff fits: Robertson kinetics through ``fit`` and ``fit_many`` on the stiff path.

The stiff path is ``solver="rodas5p"`` (every nonlinear pass by the implicit Rosenbrock solver)
with ``linear_solver="radau"`` (Radau IIA transfers) and the grid's early geometric nodes. The
explicit defaults cannot fit this model at all (``simulate`` with dopri5 to t = 1e3 does not
finish in 30 s; benchmarks/stiff_simulate.py).
"""

import math

import pytest
import torch

import torchql
from testmodels import Relaxation, relaxation_solution
from torchql.models import Robertson

DT = torch.float64
TRUTH = {"k1": 0.04, "k2": 3e7, "k3": 1e4}
STIFF = dict(solver="rodas5p", linear_solver="radau", rtol=1e-8, atol=1e-14)


@pytest.fixture(scope="module")
def robertson_data():
    """All three states at 12 log-spaced times from 1e-4 to 1e5, exact (simulated at rtol 1e-10)."""
    t = torch.logspace(-4, 5, 12, dtype=DT)
    x0 = torch.tensor([1.0, 0.0, 0.0], dtype=DT)
    x = torchql.simulate(Robertson(), x0, torch.cat([torch.zeros(1, dtype=DT), t]), solver="rodas5p", rtol=1e-10,
                         atol=1e-16)[1:]
    return torchql.Observations(t, x, observe=["y1", "y2", "y3"], sigma=0.01 * x), x0


def _fit(data, x0, guess, stiff=STIFF, **options):
    return torchql.fit(Robertson(**guess), data, x0, fixed_x0=["y1", "y2", "y3"], t0=0.0,
                       bounds={k: (0.0, None) for k in TRUTH}, **stiff, **options)


@pytest.mark.slow
def test_robertson_rates_from_guesses_2x_off_by_shooting(robertson_data):
    """Exact data (relative weights 1 %): shooting reaches the truth to 1e-6 relative, the
    integration tolerance's reach on these weights (rtol 1e-8 over values down to 1e-9 of y1)."""
    data, x0 = robertson_data
    r = _fit(data, x0, {"k1": 0.08, "k2": 1.5e7, "k3": 2e4}, method="shooting")
    assert r.success, r.message
    assert max(abs(r.params[k].item() - v) / v for k, v in TRUTH.items()) < 1e-6
    assert r.solver_options["solver"] == "rodas5p"
    # the fitted model predicts on the stiff path too
    assert torch.allclose(r.predict(data.t), torchql.simulate(Robertson(), x0, data.t, t0=0.0, solver="rodas5p",
                                                             rtol=1e-10, atol=1e-16), rtol=1e-5, atol=1e-12)


@pytest.mark.slow
def test_robertson_kantorovich_fit_and_fit_many_agree(robertson_data):
    """Kantorovich converges to within 1e-5 of the truth (measured 4e-8, as shooting: its fixed
    point on the storage grid lies up to 6e-6 from the model's optimum, and the final pass's
    Gauss–Newton step on the model takes that out); fit_many over two starts gives
    the first start the result of fit from it, and the second the same optimum. Both with the
    default ``solver="auto"``, which finds the model stiff along the data and takes the stiff path."""
    data, x0 = robertson_data
    guesses = [{"k1": 0.08, "k2": 1.5e7, "k3": 2e4}, {"k1": 0.02, "k2": 6e7, "k3": 5e3}]
    tolerances = dict(rtol=1e-8, atol=1e-14)
    single = _fit(data, x0, guesses[0], stiff=tolerances)
    assert single.solver_options["solver"] == "rodas5p" and single.fit_kwargs["solver"] == "auto"
    per_sample = {k: torch.tensor([g[k] for g in guesses], dtype=DT) for k in TRUTH}
    batch = torchql.fit_many(Robertson(), [data, data], x0, guesses=per_sample, fixed_x0=["y1", "y2", "y3"], t0=0.0,
                             bounds={k: (0.0, None) for k in TRUTH}, **tolerances)
    assert batch.solver_options["solver"] == "rodas5p"
    assert single.success and batch.success.all(), (single.message, batch.message)
    assert max(abs(single.params[k].item() - v) / v for k, v in TRUTH.items()) < 1e-5
    for b in range(2):
        assert torch.allclose(batch[b].estimates, single.estimates, rtol=1e-6, atol=0)


@pytest.mark.parametrize("guess", [TRUTH, {"k1": 0.044, "k2": 3.3e7, "k3": 1.1e4}], ids=["at-truth", "10%-off"])
def test_robertson_kantorovich_on_exact_data_with_unit_weights_reaches_the_truth(guess):
    """Exact values of all three states at 30 log-spaced times over [1e-5, 1e4], unit weights, the
    defaults (the stiff path by ``solver="auto"``). The sums of squares to be told apart are then
    those of the storage's errors, so the Kantorovich references must be accurate: the first one
    and a re-anchoring are integrated at the fit's tolerance. From loose (1e-6) ones, whose error
    the slopes ``f(z)`` multiply by the stiffness (``h |lambda|`` up to 1e5), the first particular
    solution missed the model's own by 1.5e-3; a fit started at the true rates walked away from
    them (DIVERGED, k2 14x too small) and one 10 % off ended MAX_ITER with k2 26 % off. Measured
    now: estimates within 2e-8 of the truth (the data's own simulation error), SSE below 1e-18."""
    t = torch.logspace(-5, 4, 30, dtype=DT)
    x0 = torch.tensor([1.0, 0.0, 0.0], dtype=DT)
    x = torchql.simulate(Robertson(), x0, torch.cat([torch.zeros(1, dtype=DT), t]), solver="rodas5p", rtol=1e-12,
                         atol=1e-18)[1:]
    r = torchql.fit(Robertson(**guess), torchql.Observations(t, x, observe=["y1", "y2", "y3"]), x0,
                    fixed_x0=["y1", "y2", "y3"], t0=0.0, bounds={k: (0.0, None) for k in TRUTH})
    assert r.success, r.message
    assert r.solver_options["solver"] == "rodas5p"
    assert max(abs(r.params[k].item() - v) / v for k, v in TRUTH.items()) < 1e-6
    assert r.sse < 1e-16


def test_auto_finds_robertson_stiff_and_an_oscillator_not(robertson_data):
    """The stiffness ratio along the data: Robertson's measured y2 (~4e-5) gives -2 k2 y2 ~ -2e3
    over a span of 1e5 (2e8, far above the 1e4 threshold), though its Jacobian at the initial
    state (1, 0, 0) is mild (0.04 * 1e5 = 4e3); a damped oscillator over 6.5 s stays near 1."""
    from torchql.model import AugmentedSystem
    from torchql.models import LinearOscillator
    from torchql.stiffness import STIFF_RATIO, states_from_data, stiffness_ratio

    data, x0 = robertson_data
    system = AugmentedSystem(Robertson(), [], DT, torch.device("cpu"))
    p = torch.zeros(1, 0, dtype=DT)
    along_data = stiffness_ratio(system, data.t, states_from_data(data.y, [0, 1, 2], x0).unsqueeze(0), p,
                                 data.t[-1])
    at_start = stiffness_ratio(system, data.t, x0.expand(1, 12, 3), p, data.t[-1])
    assert float(along_data) > 1e8 and float(at_start) < STIFF_RATIO
    t = torch.arange(14, dtype=DT) * 0.5
    y = torchql.simulate(LinearOscillator(), torch.tensor([0.0, 1.0], dtype=DT), t)
    oscillator = torchql.fit(LinearOscillator(A=0.5, B=1.0), torchql.Observations(t, y[:, :1], observe=["y"]),
                             torch.tensor([0.5, 0.5], dtype=DT), grid=50)
    assert oscillator.success and oscillator.solver_options["solver"] == "dop853"
    # with a propagator that integrates by torchdiffeq, the explicit solver is torchdiffeq's
    by_torchdiffeq = torchql.fit(LinearOscillator(A=0.5, B=1.0), torchql.Observations(t, y[:, :1], observe=["y"]),
                                 torch.tensor([0.5, 0.5], dtype=DT), grid=50, linear_solver="torchdiffeq")
    assert by_torchdiffeq.success and by_torchdiffeq.solver_options["solver"] == "dopri5"


def test_auto_finds_robertson_stiff_along_log_normal_data_too(robertson_data):
    """Log-normal data are fitted on ``log y``; the stiffness test reads the states they measure,
    ``exp(log y)``, as it reads normal data (it saw only the guesses (1, 0, 0), chose the explicit
    solver and crawled through the first iteration)."""
    data, x0 = robertson_data
    logs = torchql.Observations(data.t, data.y, observe=["y1", "y2", "y3"], noise="lognormal", sigma=0.01)
    result = torchql.fit(Robertson(), logs, x0, fixed_x0=["y1", "y2", "y3"], t0=0.0, max_iter=1)
    assert result.solver_options["solver"] == "rodas5p"


def test_sensitivities_integrated_with_the_solution_give_the_grid_transfers_optimum():
    """``linear_solver="rodas5p"`` (shooting's sensitivities integrated with each solution by
    Rodas5P on its own steps) reaches the optimum that ``"radau"``'s grid transfers reach, to
    1e-6 relative (rtol 1e-6; measured 3e-8, and 4e-9 from the truth), with the same status;
    ``fit_many``'s first sample equals its own fit (1e-8; measured bit-identical), the second,
    from another guess, the same optimum (1e-7; measured 9e-10). The model relaxes fast (``k = 50``) onto a driven
    trajectory; the data are exact, x0 and k unknown."""
    t = torch.logspace(-2, 0, 8, dtype=DT)
    x0, k = torch.tensor(2.0, dtype=DT), torch.tensor(50.0, dtype=DT)
    data = torchql.Observations(t, relaxation_solution(t, x0, k).unsqueeze(-1), observe=["x"])
    options = dict(t0=0.0, method="shooting", solver="rodas5p", rtol=1e-6, atol=1e-10)
    guess = torch.tensor([1.5], dtype=DT)
    grid = torchql.fit(Relaxation(k=80.0), data, guess, linear_solver="radau", **options)
    joint = torchql.fit(Relaxation(k=80.0), data, guess, linear_solver="rodas5p", **options)
    assert grid.success and joint.success, (grid.message, joint.message)
    assert torch.allclose(joint.estimates, torch.tensor([2.0, 50.0], dtype=DT), rtol=1e-6, atol=0)
    assert torch.allclose(joint.estimates, grid.estimates, rtol=1e-6, atol=0)
    batch = torchql.fit_many(Relaxation(), [data, data], guess, guesses={"k": torch.tensor([80.0, 30.0], dtype=DT)},
                             linear_solver="rodas5p", **options)
    assert batch.success.all(), batch.message
    assert torch.allclose(batch[0].estimates, joint.estimates, rtol=1e-8, atol=0)
    assert batch.iterations[0] == joint.iterations
    assert torch.allclose(batch[1].estimates, joint.estimates, rtol=1e-7, atol=0)


@pytest.mark.slow
def test_van_der_pol_from_a_third_of_mu_reaches_the_truth_from_the_data():
    """Van der Pol with mu = 1000, y exact at 20 times over (0, 700] (the slow drift before the
    first jump at t = 807). Integrated from mu = 300 the model jumps three times inside the window
    (the sum of squares has spurious minima at mu ~ 290-410, where scipy's least_squares stops);
    the first reference built from the data does not depend on the guess, and the fit reaches
    the truth to 1e-6 (the integration's reach at rtol 1e-8; measured 5e-12, in 2 iterations)."""
    from torchql.models import VanDerPol

    t = torch.linspace(35.0, 700.0, 20, dtype=DT)
    x0 = torch.tensor([2.0, 0.0], dtype=DT)
    y = torchql.simulate(VanDerPol(1000.0), x0, torch.cat([torch.zeros(1, dtype=DT), t]), solver="rodas5p",
                         rtol=1e-11, atol=1e-13)[1:, :1]
    data = torchql.Observations(t, y, observe=["y"], sigma=0.01)
    r = torchql.fit(VanDerPol(300.0), data, x0, params=["mu"], fixed_x0=["y", "v"], t0=0.0,
                    bounds={"mu": (0.0, None)}, initial_trajectory="data", rtol=1e-8, atol=1e-10)
    assert r.success, r.message
    assert r.solver_options["solver"] == "rodas5p"
    assert abs(float(r.params["mu"]) - 1000.0) / 1000.0 < 1e-6


def _van_der_pol(t: torch.Tensor, noise_seed: int | None = None) -> tuple:
    """Van der Pol with mu = 1000 from (2, 0): y at times ``t`` (noise 0.01 from ``noise_seed``, or
    exact), its start and the options that fit mu alone (positive) at rtol 1e-8: ``(data, x0, options)``."""
    from torchql.models import VanDerPol

    x0 = torch.tensor([2.0, 0.0], dtype=DT)
    y = torchql.simulate(VanDerPol(1000.0), x0, torch.cat([torch.zeros(1, dtype=DT), t]), solver="rodas5p",
                         rtol=1e-11, atol=1e-13)[1:, :1]
    if noise_seed is not None:
        y = y + 0.01 * torch.randn(y.shape, generator=torch.Generator().manual_seed(noise_seed), dtype=DT)
    data = torchql.Observations(t, y, observe=["y"], sigma=0.01)
    options = dict(params=["mu"], fixed_x0=["y", "v"], t0=0.0, bounds={"mu": (0.0, None)}, rtol=1e-8, atol=1e-10)
    return data, x0, options


@pytest.mark.slow
def test_a_rejected_trials_model_solution_stops_once_it_cannot_beat_the_current_one(monkeypatch):
    """Van der Pol with mu = 1000 from mu = 3000 at the defaults: the first Gauss–Newton steps land
    near mu = 265, whose solution jumps inside the window; the second opinion on such a trial
    stops integrating once its sum of squares over the data passed exceeds the current
    iterate's. The fit is the same, step for step, as with every trial integrated to the end
    (a rejected trial's value is only compared), with fewer right-hand-side evaluations
    (measured 8,600 against 12,600); fit_many's batched solver stops its samples alike."""
    import torchql.engine_evaluate as engine_evaluate
    from torchql.models import VanDerPol

    data, x0, options = _van_der_pol(torch.linspace(35.0, 700.0, 20, dtype=DT))
    stopping = torchql.fit(VanDerPol(3000.0), data, x0, **options)
    assert stopping.success, stopping.message
    # the case in question: the undamped step rejected, its retry at damping 1 accepted (the raises
    # to 1e-3, 1e-2 and 0.1, which shorten a one-parameter step by 0.1 %, 1 % and 9 %, skipped)
    assert (stopping.history[0].damping, stopping.history[0].rejected) == (1.0, 1)
    assert abs(float(stopping.params["mu"]) - 1000.0) / 1000.0 < 1e-6
    guesses = {"mu": torch.tensor([3000.0, 1400.0], dtype=DT)}
    batch = torchql.fit_many(VanDerPol(3000.0), [data, data], x0, guesses=guesses, **options)
    assert batch.status[0] == stopping.status and batch.iterations[0] == stopping.iterations
    assert float(batch.params["mu"][0]) == pytest.approx(float(stopping.params["mu"]), rel=1e-8, abs=0)
    assert bool(batch.success.all())
    monkeypatch.setattr(engine_evaluate, "STOP_EARLY", False)  # integrate every trial whole
    whole = torchql.fit(VanDerPol(3000.0), data, x0, **options)
    assert torch.equal(whole.estimates, stopping.estimates) and whole.iterations == stopping.iterations
    assert [(r.damping, r.rejected) for r in whole.history] == [(r.damping, r.rejected) for r in stopping.history]
    assert stopping.nfev < 0.9 * whole.nfev


def test_a_start_built_from_the_data_races_its_first_trial(monkeypatch):
    """Van der Pol with mu = 1000 from noisy data, the start built from the data (mu = 839, whose
    first jump falls inside the window): neither it nor its first trial (mu = 1022) has a model
    solution yet. Both are integrated together; the trial's finishes first and the start's stops
    once its sum of squares over the data passed exceeds the trial's, so that the start's own
    objective stays unknown (NaN in the history). The fit is the one with both integrated whole,
    estimates to the bit and step for step, with fewer evaluations (measured 7,700 against
    9,700); fit_many's samples alike."""
    import torchql.engine_evaluate as engine_evaluate
    from torchql.models import VanDerPol

    data, x0, options = _van_der_pol(torch.linspace(17.5, 700.0, 40, dtype=DT), noise_seed=1)
    options["initial_trajectory"] = "data"
    raced = torchql.fit(VanDerPol(1400.0), data, x0, **options)
    assert raced.success, raced.message
    start, first = raced.history[0], raced.history[1]
    assert 800 < float(start.params["mu"]) < 900 and 1000 < float(first.params["mu"]) < 1100
    assert math.isnan(start.model_merit) and math.isfinite(first.model_merit)  # the start's not needed whole
    guesses = {"mu": torch.tensor([1400.0, 3000.0], dtype=DT)}
    batch = torchql.fit_many(VanDerPol(1400.0), [data, data], x0, guesses=guesses, **options)
    torch.testing.assert_close(batch.params["mu"], raced.params["mu"].expand(2), rtol=1e-10, atol=0)
    monkeypatch.setattr(engine_evaluate, "STOP_EARLY", False)  # both integrated whole
    whole = torchql.fit(VanDerPol(1400.0), data, x0, **options)
    assert torch.equal(whole.estimates, raced.estimates) and whole.iterations == raced.iterations
    assert [(r.damping, r.rejected) for r in whole.history] == [(r.damping, r.rejected) for r in raced.history]
    assert whole.history[0].model_merit > 100 * first.model_merit  # what the race spared: the jump inside
    assert raced.nfev < 0.85 * whole.nfev
    batch_whole = torchql.fit_many(VanDerPol(1400.0), [data, data], x0, guesses=guesses, **options)
    assert batch.nfev < 0.85 * batch_whole.nfev


def test_auto_refits_from_the_data_where_the_integrated_start_of_a_stiff_model_fails():
    """``initial_trajectory="auto"`` takes the integrated guesses for a stiff model; where that fit
    fails (van der Pol from mu = 400: its solution's jumps fall inside the window, and the fit
    ends STALLED), the sample is fitted again from the data, the one start that does not depend
    on the guess, and the better fit is kept, its message saying what the other gave. The second
    fit is the data-started one, bit for bit; in fit_many only the sample that needs it is
    fitted again."""
    from torchql.models import VanDerPol

    data, x0, options = _van_der_pol(torch.linspace(35.0, 700.0, 20, dtype=DT))
    auto = torchql.fit(VanDerPol(400.0), data, x0, **options)
    assert auto.success and abs(float(auto.params["mu"]) - 1000.0) < 1e-6 * 1000.0, auto.message
    assert "Integrated from the guesses the fit ended STALLED" in auto.message
    assert auto.message.endswith("this fit's first reference was built from the data.")
    from_data = torchql.fit(VanDerPol(400.0), data, x0, initial_trajectory="data", **options)
    assert torch.equal(auto.estimates, from_data.estimates) and auto.iterations == from_data.iterations
    batch = torchql.fit_many(VanDerPol(400.0), [data, data], x0, guesses={"mu": torch.tensor([400.0, 1400.0], dtype=DT)},
                             **options)
    assert bool(batch.success.all())
    assert "built from the data" in batch[0].message and "built from the data" not in batch[1].message
    torch.testing.assert_close(batch.params["mu"], torch.full((2,), float(auto.params["mu"]), dtype=DT),
                               rtol=1e-8, atol=0)


class _BlowUp(torchql.ODEModel):
    """``x' = p x^2``: from ``x(0) = 1`` with ``p = 1`` it blows up at ``t = 1``."""

    state_names = ("x",)

    def __init__(self, p: float) -> None:
        super().__init__()
        self.register_buffer("p", torch.tensor(p, dtype=DT))

    def forward(self, t, x):
        return self.p * x**2


def test_a_stiff_solvers_start_that_blows_up_from_every_guess_is_refitted_from_the_data():
    """With ``solver="rodas5p"`` the integrated start of ``x' = p x^2`` from ``p = 1`` fails for every
    sample (it blows up at t = 1, inside the data's span): INTEGRATION_FAILED, and the fit from the
    data reaches the truth ``p = -1`` (data ``1 / (1 + t)``). Keeping the model's solution of no
    sample raised a reshape error."""
    t = torch.linspace(0, 10, 50, dtype=DT)
    data = torchql.Observations(t, (1 / (1 + t)).unsqueeze(1), observe=["x"])
    x0 = torch.tensor([1.0], dtype=DT)
    result = torchql.fit(_BlowUp(1.0), data, x0, solver="rodas5p")
    assert result.success, result.message
    assert "Integrated from the guesses the fit ended INTEGRATION_FAILED" in result.message
    assert float(result.params["p"]) == pytest.approx(-1.0, rel=1e-9)
    integrated = torchql.fit(_BlowUp(1.0), data, x0, solver="rodas5p", initial_trajectory="integrate")
    assert integrated.status is torchql.Status.INTEGRATION_FAILED and "t = 1" in integrated.message


@pytest.mark.parametrize("linear_solver", ["radau", "rodas5p"])
def test_max_steps_counts_the_stiff_solvers_steps_per_grid_interval(linear_solver):
    """``max_steps`` is a budget per grid interval on the stiff path too, as ``fit`` documents it
    and torchdiffeq counts it: the relaxation fit below takes more than 20 Rodas5P steps over its
    whole span but at most 3 between two nodes, so ``max_steps=10`` changes nothing (it failed at
    the guesses while Rodas5P counted the whole span), and ``max_steps=1`` fails in words."""
    t = torch.logspace(-2, 0, 8, dtype=DT)
    data = torchql.Observations(t, relaxation_solution(t, torch.tensor(2.0, dtype=DT), torch.tensor(50.0, dtype=DT))
                                .unsqueeze(-1), observe=["x"])
    options = dict(t0=0.0, method="shooting", solver="rodas5p", rtol=1e-6, atol=1e-10, linear_solver=linear_solver)
    guess = torch.tensor([1.5], dtype=DT)
    free = torchql.fit(Relaxation(k=80.0), data, guess, **options)
    budgeted = torchql.fit(Relaxation(k=80.0), data, guess, max_steps=10, **options)
    assert free.success and budgeted.status is free.status and budgeted.iterations == free.iterations
    assert torch.equal(budgeted.estimates, free.estimates)
    starved = torchql.fit(Relaxation(k=80.0), data, guess, max_steps=1, **options)
    assert starved.status is torchql.Status.INTEGRATION_FAILED
    assert "max_steps = 1 steps between two grid nodes ran out" in starved.message, starved.message


@pytest.mark.parametrize("linear_solver", ["taylor", "radau"])
def test_a_stiff_fit_that_fails_with_an_explicit_propagator_names_it(linear_solver):
    """A fit of a stiff model (``solver="rodas5p"``) that does not succeed (here ``max_iter=1``)
    with an explicit ``linear_solver`` names it and the stiff default in its message: on Robertson
    kinetics from guesses twice off, ``"taylor"`` and ``"rk4_doubling"`` stalled at rates 1e4
    times off, and the message spoke only of guesses, where ``"radau"`` converges in 2 s. A
    stable propagator's failure does not name it."""
    t = torch.logspace(-2, 0, 8, dtype=DT)
    data = torchql.Observations(t, relaxation_solution(t, torch.tensor(2.0, dtype=DT), torch.tensor(50.0, dtype=DT))
                                .unsqueeze(-1), observe=["x"])
    result = torchql.fit(Relaxation(k=80.0), data, torch.tensor([1.5], dtype=DT), t0=0.0, solver="rodas5p",
                         linear_solver=linear_solver, max_iter=1)
    assert result.status is torchql.Status.MAX_ITER
    named = f"linear_solver='{linear_solver}' propagates explicitly" in result.message
    assert named == (linear_solver == "taylor"), result.message
    assert ("linear_solver='radau', suits them" in result.message) == named


def test_a_batch_mixing_stiff_and_non_stiff_samples_fits_each_on_its_own_solver():
    """``solver="auto"`` took the stiff solver for a whole batch where one sample was stiff: a van der
    Pol sample of mu = 2 beside one of mu = 1000 was fitted by Rodas5P in 5 iterations, where its
    own fit takes DOP853 and 13 (SSE 6e-8 apart). Samples alike in stiffness are fitted run by run,
    each as its own fit, and each result names its solver."""
    from torchql.models import VanDerPol

    t = torch.linspace(1.0, 20.0, 20, dtype=DT)
    x0 = torch.tensor([2.0, 0.0], dtype=DT)
    sets = []
    for s, mu in enumerate([2.0, 1000.0, 3.0]):
        y = torchql.simulate(VanDerPol(mu), x0, torch.cat([torch.zeros(1, dtype=DT), t]), solver="rodas5p",
                             rtol=1e-11, atol=1e-13)[1:, :1]
        y = y + 0.01 * torch.randn(y.shape, generator=torch.Generator().manual_seed(s), dtype=DT)
        sets.append(torchql.Observations(t, y, observe=["y"], sigma=0.01))
    guess = torch.tensor([2.3, 1100.0, 2.8], dtype=DT)
    options = dict(params=["mu"], fixed_x0=["y", "v"], t0=0.0, bounds={"mu": (0.0, None)}, rtol=1e-8, atol=1e-10)
    batch = torchql.fit_many(VanDerPol(1000.0), sets, x0, guesses={"mu": guess}, **options)
    for i, data in enumerate(sets):
        alone = torchql.fit(VanDerPol(float(guess[i])), data, x0, **options)
        assert batch[i].status is alone.status and batch[i].iterations == alone.iterations, i
        assert batch[i].solver_options == alone.solver_options
        torch.testing.assert_close(batch[i].estimates, alone.estimates, rtol=1e-10, atol=0)
        assert float(batch[i].sse) == pytest.approx(alone.sse, rel=1e-10)
    assert [batch[i].solver_options["solver"] for i in range(3)] == ["dop853", "rodas5p", "dop853"]


def test_an_explicit_solver_asked_for_on_a_stiff_model_says_so_at_once():
    """``solver="dop853"`` on Robertson's kinetics: the explicit pair's stiffness test ends the
    integration after about a thousand steps (it ran 100,000, 54 s, to the step budget), and the
    fit's message says the problem is stiff and which solver integrates it."""
    t = torch.tensor([0.0, 0.4, 4.0, 40.0, 400.0], dtype=DT)
    x = torchql.simulate(Robertson(), torch.tensor([1.0, 0.0, 0.0], dtype=DT), t, solver="rodas5p")
    data = torchql.Observations(t, x[:, [0, 2]], observe=["y1", "y3"])
    result = torchql.fit(Robertson(k1=0.05), data, torch.tensor([1.0, 0.0, 0.0], dtype=DT),
                         params=["k1"], fixed_x0=["y1", "y2", "y3"], solver="dop853")
    assert result.status is torchql.Status.INTEGRATION_FAILED
    assert "became stiff" in result.message and 'solver="rodas5p"' in result.message
    assert result.nfev < 100_000
