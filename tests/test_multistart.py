"""Multi-start: reproducible draws within the range or bounds, the best fit, distinct optima."""

import importlib
import math

import pytest
import torch

import torchql
from testmodels import Decay, counting
from torchql.models import HarmonicOscillator, LinearOscillator

#: The module (``torchql.multistart`` the attribute is the function of the same name).
multistart_module = importlib.import_module("torchql.multistart")

DT = torch.float64


@pytest.fixture(scope="module")
def decay_data():
    t = torch.linspace(0, 2, 11, dtype=DT)
    return torchql.Observations(t, (1.5 * torch.exp(-0.7 * t)).unsqueeze(-1), observe=["y"])


def test_every_start_finds_the_single_optimum(decay_data):
    ms = torchql.multistart(Decay(0.3), decay_data, torch.tensor([1.0], dtype=DT), starts=5, seed=1, grid=50)
    assert len(ms.results) == 5 and ms.n_converged == 5
    assert len(ms.optima) == 1 and ms.fraction_best == 1.0
    assert abs(ms.best.params["k"].item() - 0.7) < 1e-8
    g = ms.guesses[:, 0]
    assert g[0].item() == pytest.approx(0.3)  # the model's own guess first
    assert bool(((g >= 0.03) & (g <= 3.0)).all()) and len(set(g.tolist())) == 5
    assert "5 starts, 5 converged, 1 distinct optima" in ms.summary()


def test_each_start_begins_at_its_own_guesses(decay_data):
    """With ``y`` measured, ``fit``'s default first reference is built from the data, the same for every
    start: the draws made no difference (every start's first iterate was one point). multistart
    integrates each start from its guesses unless told otherwise."""
    ms = torchql.multistart(Decay(0.3), decay_data, torch.tensor([1.0], dtype=DT), starts=4, seed=1)
    first = [r.history[0].params["k"].item() for r in ms.results]
    assert first == pytest.approx(ms.guesses[:, 0].tolist(), rel=1e-12)
    assert ms.best.fit_kwargs["initial_trajectory"] == "integrate"
    auto = torchql.multistart(Decay(0.3), decay_data, torch.tensor([1.0], dtype=DT), starts=4, seed=1,
                              initial_trajectory="auto")
    assert len({round(r.history[0].params["k"].item(), 12) for r in auto.results}) == 1  # the data's, as asked


def test_draws_are_reproducible_and_respect_bounds(decay_data):
    kwargs = dict(starts=4, seed=7, grid=50, bounds={"k": (0.5, 2.0)}, max_iter=0)
    a = torchql.multistart(Decay(1.0), decay_data, torch.tensor([1.0], dtype=DT), **kwargs)
    b = torchql.multistart(Decay(1.0), decay_data, torch.tensor([1.0], dtype=DT), **kwargs)
    assert torch.equal(a.guesses, b.guesses)
    assert bool(((a.guesses > 0.5) & (a.guesses < 2.0)).all())
    assert a.n_converged == 0 and not a.best.success and a.optima == [] and a.fraction_best == 0.0


def test_distinct_optima_are_separated_and_best_is_the_lowest():
    """x = cos(w t) sampled coarsely: aliasing makes several frequencies fit locally."""
    t = torch.linspace(0, 10, 21, dtype=DT)
    data = torchql.Observations(t, torch.cos(1.3 * t).unsqueeze(-1), observe=["x"])
    ms = torchql.multistart(HarmonicOscillator(1.0), data, torch.tensor([1.0, 0.0], dtype=DT), starts=8, spread=4.0,
                            seed=0, fixed_x0=["x", "u"], grid=200)
    sses = [r.sse for r in ms.results if r.success]
    first = ms.optima[0].starts[0]  # the start with the smallest SSE; best is its fit
    assert ms.results[first].sse == min(sses)
    assert torch.allclose(ms.best.estimates, ms.results[first].estimates, rtol=1e-8, atol=0)
    assert ms.best.params["xi"].item() == pytest.approx(1.69, rel=1e-8)
    assert [o.sse for o in ms.optima] == sorted(o.sse for o in ms.optima)
    assert sum(len(o.starts) for o in ms.optima) == ms.n_converged
    if len(ms.optima) > 1:
        assert ms.optima[1].sse > ms.optima[0].sse * (1 + 1e-6) or not math.isclose(
            ms.optima[1].estimates[0].item(), ms.optima[0].estimates[0].item(), rel_tol=1e-4)


@pytest.mark.parametrize("kwargs, error, match", [
    (dict(starts=0), ValueError, "starts"),
    (dict(spread=0.5), ValueError, "spread"),
    (dict(throw=True), TypeError, "throw"),
    (dict(callback=3), TypeError, "callback"),
    (dict(foo=1), TypeError, r"multistart\(\) got unexpected keyword argument\(s\) \['foo'\]"),
])
def test_bad_arguments(decay_data, kwargs, error, match):
    with pytest.raises(error, match=match):
        torchql.multistart(Decay(0.3), decay_data, torch.tensor([1.0], dtype=DT), **kwargs)


def test_callback_sees_every_fit(decay_data):
    seen = []
    torchql.multistart(Decay(0.3), decay_data, torch.tensor([1.0], dtype=DT),
                       starts=3, grid=50, callback=lambda k, r: seen.append((k, r.success)))
    assert [k for k, _ in seen] == [0, 1, 2]


def test_batched_path_gives_the_loop_best_and_optima(monkeypatch):
    """Kantorovich fits with options fit_many supports: all starts in one fit_many call, and the
    result is the loop's (best estimates to 1e-8, the same optima reached by the same starts);
    the best is a full FitResult, fitted once more with torchql.fit from its start."""
    t = torch.linspace(0, 10, 21, dtype=DT)
    noise = 0.01 * torch.randn(21, generator=torch.Generator().manual_seed(2), dtype=DT)
    data = torchql.Observations(t, (torch.cos(1.3 * t) + noise).unsqueeze(-1), observe=["x"])
    args = (HarmonicOscillator(1.0), data, torch.tensor([1.0, 0.0], dtype=DT))
    kwargs = dict(starts=6, spread=4.0, seed=3, grid=100, max_iter=12, method="kantorovich")  # 2 starts: MAX_ITER

    calls = {"fit_many": 0, "fit": 0}
    monkeypatch.setattr(multistart_module, "fit_many", counting(calls, "fit_many", multistart_module.fit_many))
    monkeypatch.setattr(multistart_module, "fit", counting(calls, "fit", multistart_module.fit))
    batched = torchql.multistart(*args, **kwargs)
    assert batched.batched and calls == {"fit_many": 1, "fit": 1}  # one batch, then the best's full fit
    assert isinstance(batched.best, torchql.FitResult) and batched.best.success

    monkeypatch.setattr(multistart_module, "_fit_many_serves", lambda *a: False)
    loop = torchql.multistart(*args, **kwargs)
    assert not loop.batched and calls == {"fit_many": 1, "fit": 7}

    assert torch.allclose(batched.best.estimates, loop.best.estimates, rtol=1e-8, atol=0)
    assert batched.best.sse == pytest.approx(loop.best.sse, rel=1e-8)
    assert batched.best.iterations == loop.best.iterations
    assert [s.name for s in (r.status for r in batched.results)] == [r.status.name for r in loop.results]
    assert [sorted(o.starts) for o in batched.optima] == [sorted(o.starts) for o in loop.optima]
    for ours, theirs in zip(batched.optima, loop.optima):
        assert torch.allclose(ours.estimates, theirs.estimates, rtol=1e-8, atol=0)


@pytest.mark.parametrize("kwargs", [dict(linear_solver="torchdiffeq"), dict(max_time=60.0)])
def test_options_fit_many_lacks_keep_the_loop(decay_data, kwargs):
    """A propagator without a batched form; a ``max_time``, which is each start's in a loop and would
    be the whole batch's."""
    ms = torchql.multistart(Decay(0.3), decay_data, torch.tensor([1.0], dtype=DT), starts=2, grid=50, max_iter=2,
                            **kwargs)
    assert not ms.batched and all(isinstance(r, torchql.FitResult) for r in ms.results)


@pytest.mark.parametrize("options", [dict(method="kantorovich"), dict(method="shooting"),
                                     dict(initial_trajectory="data")])
def test_starts_with_bounds_are_batched_and_match_the_loop(decay_data, monkeypatch, options):
    """``fit_many`` takes ``bounds``, ``method`` and ``initial_trajectory``: the starts are one
    batch, each the fit of the loop."""
    args = (Decay(0.3), decay_data, torch.tensor([1.0], dtype=DT))
    kwargs = dict(starts=3, grid=50, bounds={"k": (0.01, 5.0)}, **options)
    batched = torchql.multistart(*args, **kwargs)
    monkeypatch.setattr(multistart_module, "_fit_many_serves", lambda *a: False)
    loop = torchql.multistart(*args, **kwargs)
    assert batched.batched and not loop.batched
    assert all(isinstance(r, torchql.FitResult) for r in batched.results)
    assert [r.status for r in batched.results] == [r.status for r in loop.results]
    for ours, theirs in zip(batched.results, loop.results):
        assert torch.allclose(ours.estimates, theirs.estimates, rtol=1e-8, atol=0)
        assert torch.equal(ours.lower, theirs.lower)


def _two_decays():
    """``y' = -k y`` in two experiments (1 % noise); the first's initial value 1.5 is known and
    measured exactly."""
    gen = torch.Generator().manual_seed(4)
    t = torch.linspace(0, 2, 11, dtype=DT)
    out = []
    for y0 in (1.5, 0.8):
        y = (y0 * torch.exp(-0.7 * t) * (1 + 0.01 * torch.randn(11, generator=gen, dtype=DT))).unsqueeze(-1)
        y[0] = y0 if y0 == 1.5 else y[0]
        exact = torch.zeros(11, 1, dtype=torch.bool)
        exact[0] = y0 == 1.5
        out.append(torchql.Observations(t, y, observe=["y"], sigma=0.01 * y0, exact=exact))
    return out


@pytest.mark.parametrize("options", [dict(), dict(scale={"k": "log"}, method="shooting")])
def test_starts_of_several_experiments_with_exact_values_are_batched_and_match_the_loop(monkeypatch, options):
    """``fit_many`` fits each sample as ``fit`` does, experiments and exact values included: the
    starts are one batch, each start's fit the loop's (statuses, iterations, estimates)."""
    args = (Decay(0.3), _two_decays(), torch.tensor([[1.5], [1.0]], dtype=DT))
    kwargs = dict(starts=4, seed=2, **options)
    batched = torchql.multistart(*args, **kwargs)
    monkeypatch.setattr(multistart_module, "_fit_many_serves", lambda *a: False)
    loop = torchql.multistart(*args, **kwargs)
    assert batched.batched and not loop.batched
    assert [r.status for r in batched.results] == [r.status for r in loop.results]
    assert [r.iterations for r in batched.results] == [r.iterations for r in loop.results]
    for ours, theirs in zip(batched.results, loop.results):
        torch.testing.assert_close(ours.estimates, theirs.estimates, rtol=1e-8, atol=0)
    assert batched.best.success and batched.best.x0[0, 0].item() == 1.5  # the exact value met
    assert batched.best.params["k"].item() == pytest.approx(0.7, rel=0.02)


def test_a_batch_of_datasets_is_rejected(decay_data):
    batch = torchql.Observations(decay_data.t, torch.stack([decay_data.y, decay_data.y]), observe=["y"])
    with pytest.raises(ValueError, match=r"`data` holds a batch of 2 independent datasets.*torchql.fit_many"):
        torchql.multistart(Decay(0.3), batch, torch.tensor([1.0], dtype=DT), starts=2)


def test_bounds_given_in_a_parameter_specification_bound_the_draws_alike():
    """``parameters={"B": Parameter(1.0, min=0.5, max=10.0), ...}`` stands for ``bounds={"B": (0.5, 10.0)}``
    in the draws too: the same starts from the same seed, inside the bounds (they were drawn as if
    unbounded, below the lower bound), and the same best fit."""
    P = torchql.Parameter
    t = torch.linspace(0, 10, 41, dtype=torch.float64)
    x = torchql.simulate(LinearOscillator(0.1, 3.0), torch.tensor([0.0, 1.0], dtype=torch.float64), t)
    noise = 0.01 * torch.randn(41, 1, generator=torch.Generator().manual_seed(12), dtype=torch.float64)
    data = torchql.Observations(t, x[:, :1] + noise, observe=["y"])
    by_keywords = torchql.multistart(LinearOscillator(0.5, 1.0), data, torch.tensor([0.5, 0.5], dtype=torch.float64),
                                     starts=4, bounds={"A": (0.0, 1.0), "B": (0.5, 10.0)})
    by_specification = torchql.multistart(LinearOscillator(0.5, 1.0), data, starts=4, parameters={
        "A": P(0.5, min=0.0, max=1.0), "B": P(1.0, min=0.5, max=10.0), "y": P(0.5), "v": P(0.5)})
    assert torch.equal(by_specification.guesses, by_keywords.guesses)
    assert bool((by_specification.guesses[:, 1] > 0.5).all())
    torch.testing.assert_close(by_specification.best.estimates, by_keywords.best.estimates, rtol=1e-12, atol=0)


def test_with_estimated_sigma_the_likelihood_ranks_the_optima():
    """With ``sigma="estimate"`` each fit's ``sse`` is at its own sigmas, the number of values at every
    optimum: ranked by it, a spurious optimum of the frequency (B = 0.64, NLL 43.1) came first and was
    ``best``, where the true one (B = 3.0) has NLL -64.9. The negative log-likelihood, which the fits
    minimize, ranks them now (:attr:`torchql.FitResult.objective`), and ``summary`` shows it."""
    t = torch.linspace(0, 15, 40, dtype=DT)
    truth = torchql.simulate(LinearOscillator(0.1, 3.0), torch.tensor([1.0, 0.0], dtype=DT), t)
    y = truth[:, :1] + 0.05 * torch.randn(40, 1, generator=torch.Generator().manual_seed(0), dtype=DT)
    data = torchql.Observations(t, y, observe=["y"], sigma="estimate")
    ms = torchql.multistart(LinearOscillator(0.1, 1.0), data, torch.tensor([1.0, 0.0], dtype=DT), starts=8,
                            spread=5.0, params=["B"], fixed_x0=["y", "v"])
    converged = [r for r in ms.results if r.success]
    assert len({round(float(r.params["B"]), 3) for r in converged}) > 1  # more than one optimum reached
    assert ms.best.nll == min(r.nll for r in converged)
    assert float(ms.best.params["B"]) == pytest.approx(3.0, rel=0.01)
    assert [opt.nll for opt in ms.optima] == sorted(opt.nll for opt in ms.optima)
    assert "NLL" in ms.summary().splitlines()[1]
    assert f"best_nll={ms.best.nll:.6g})" in repr(ms)  # (its sse is the number of values, 40)


def test_the_summary_names_starts_that_did_not_converge_below_the_best_optimum():
    """A harmonic oscillator (xi = 9) whose sum of squares has a local minimum every few units of xi,
    with large residuals there: Gauss–Newton steps there overshoot, the damped ones are too short to
    matter, and the starts' iterations stall near a minimum. The summary counted only the converged
    ones, and said nothing of stalled starts at a lower sum of squares (39.7 beside a converged
    41.6); it now names the lowest of them, with or without a converged optimum.

    The final pass finds each start at its local minimum as far as the integration resolves it
    (the Gauss–Newton step on the model promises 1e-8 of a sum of squares of 41, about the
    integration's error): CONVERGED_SSE, five local optima. The summary's words are tested on the
    same results with the statuses set: none converged, then only the highest."""
    from dataclasses import replace

    from torchql.multistart import MultiStartResult, _cluster

    t = torch.linspace(0, 20, 81, dtype=torch.float64)
    y = torchql.simulate(HarmonicOscillator(9.0), torch.tensor([1.0, 0.0], dtype=torch.float64), t)[:, 0]
    y = y + 0.05 * torch.randn(81, generator=torch.Generator().manual_seed(11), dtype=torch.float64)
    data = torchql.Observations(t, y[:, None], observe=["x"])
    ms = torchql.multistart(HarmonicOscillator(3.0), data, x0=torch.tensor([0.5, 0.5], dtype=torch.float64),
                            starts=5, seed=1)
    assert all(r.status is torchql.Status.CONVERGED_SSE and "below what the integration's error lets it resolve"
               in r.message for r in ms.results)
    stalled = [replace(r, status=torchql.Status.STALLED, success=False) for r in ms.results]
    lowest = min(stalled, key=lambda r: r.sse)
    none = MultiStartResult(best=lowest, results=stalled, guesses=ms.guesses, param_names=ms.param_names,
                            optima=_cluster(stalled, 1e-4, 1e-8), batched=ms.batched)
    assert not none.optima
    assert f"No start converged; the lowest (STALLED) ended at SSE {lowest.sse:.6g}" in none.summary()
    highest = max(range(5), key=lambda k: stalled[k].sse)  # pretend the highest converged
    results = list(stalled)
    results[highest] = replace(results[highest], status=torchql.Status.CONVERGED, success=True)
    pretended = MultiStartResult(best=results[highest], results=results, guesses=ms.guesses,
                                 param_names=ms.param_names, optima=_cluster(results, 1e-4, 1e-8), batched=ms.batched)
    below = sum(r.sse < results[highest].sse for r in results)
    assert f"{below} start(s) that did not converge (STALLED) ended below the best optimum, the lowest at SSE " \
           f"{lowest.sse:.6g}" in pretended.summary()
    assert "below" not in torchql.multistart(Decay(k=0.5), torchql.Observations(
        t[:20], torch.exp(-0.7 * t[:20])[:, None], observe=["y"]), x0=torch.tensor([1.0], dtype=torch.float64),
        starts=3).summary()


def test_fits_a_hundredth_of_a_standard_error_apart_are_one_optimum(decay_data):
    """Fits whose estimates differ by 1e-3 of their standard errors are one optimum, though 100 times
    ``x_rtol`` apart (a flat optimum's fits, each converged on the sum of squares, stop so far apart,
    and were listed as optima of their own); fits a standard error apart are two."""
    from dataclasses import replace

    from torchql.multistart import _cluster

    fit = torchql.fit(Decay(0.3), decay_data, torch.tensor([1.0], dtype=DT))
    stderr = torch.tensor(list(fit.stderr.values()), dtype=DT)
    assert fit.success and bool(torch.isfinite(stderr).all()) and bool((stderr > 0).all())
    near = replace(fit, estimates=fit.estimates + 1e-3 * stderr, sse=fit.sse * (1 + 1e-12))
    far = replace(fit, estimates=fit.estimates + stderr, sse=fit.sse * 1.5)
    x_rtol = 1e-5 * float((stderr / fit.estimates.abs()).min())  # far below 1e-3 standard errors
    optima = _cluster([fit, near, far], x_rtol, 0.0)
    assert [o.starts for o in optima] == [[0, 1], [2]]


def test_a_coefficient_every_condition_sets_is_not_drawn():
    """Two experiments whose conditions set ``s`` in both (1, and the unknown ``s2``): ``fit`` leaves ``s``
    out of its unknowns, and ``multistart`` drew and estimated it too. Nothing reads it, so every start
    ended NOT_IDENTIFIABLE and the result listed no optimum, though each reached the fit's."""

    class Scaled(torchql.ODEModel):
        state_names = ("y",)

        def __init__(self):
            super().__init__()
            for name in ("k", "s", "s2"):
                self.register_buffer(name, torch.tensor(1.0, dtype=torch.float64))

        def forward(self, t, x):
            return -self.k * self.s * x

    g = torch.Generator().manual_seed(0)
    t = torch.linspace(0.2, 4, 12, dtype=torch.float64)
    data = [torchql.Observations(t, torch.exp(-0.7 * s * t).unsqueeze(-1) + 0.01 * torch.randn(12, 1, generator=g,
                                                                                                   dtype=torch.float64),
                                 observe=["y"], sigma=0.01) for s in (1.0, 2.5)]
    kw = dict(conditions=[{"s": 1.0}, {"s": "s2"}], t0=[0.0, 0.0])
    x0 = torch.ones(2, 1, dtype=torch.float64)
    single = torchql.fit(Scaled(), data, x0=x0, **kw)
    result = torchql.multistart(Scaled(), data, x0, starts=4, **kw)
    assert result.best.unknown_names == single.unknown_names and "s" not in single.unknown_names
    assert all(r.status is torchql.Status.CONVERGED for r in result.results) and len(result.optima) == 1
    assert result.best.sse == pytest.approx(single.sse, rel=1e-9)
