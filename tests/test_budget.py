"""The wall-clock budget ``max_time``: fits end with Status.MAX_TIME instead of running on."""

import math
import time

import pytest
import torch

import torchql
from testmodels import Decay
from torchql.budget import TimeBudgetExceeded, check_time, deadline, no_time_budget, time_budget, time_left, until

DT = torch.float64
T = torch.linspace(0, 2, 11, dtype=DT)
INTEGRATE = dict(initial_trajectory="integrate")
Y = (1.5 * torch.exp(-0.7 * T)).unsqueeze(-1)


class SlowDecay(Decay):
    """``y' = -k y`` whose every right-hand-side evaluation takes 20 ms: an unbudgeted fit takes minutes
    (integrated from the guesses, ``INTEGRATE``; from the data it converges before the budget ends)."""

    def forward(self, t, x):
        time.sleep(0.02)
        return super().forward(t, x)


def test_budget_context_nests_to_the_earlier_deadline_and_can_be_lifted():
    assert time_left() == math.inf
    check_time()  # no budget: never raises
    with time_budget(100.0):
        assert 99.0 < time_left() <= 100.0
        with time_budget(1000.0):  # an inner budget never extends the outer one
            assert time_left() <= 100.0
        with time_budget(0.0):
            time.sleep(0.001)
            with pytest.raises(TimeBudgetExceeded):
                check_time()
            with no_time_budget():
                check_time()
                assert time_left() == math.inf
        assert time_left() > 99.0
        moment = deadline()
        with no_time_budget(), until(moment):  # an optional phase keeps the lifted deadline
            assert deadline() == moment and 99.0 < time_left() <= 100.0
        with until(None):
            assert time_left() == math.inf
    assert time_left() == math.inf and deadline() is None


def test_fit_stops_at_max_time_with_its_own_status():
    data = torchql.Observations(T, Y, observe=["y"])
    start = time.perf_counter()
    result = torchql.fit(SlowDecay(k=0.2), data, x0=torch.tensor([1.0], dtype=DT), max_time=0.5, **INTEGRATE)
    elapsed = time.perf_counter() - start
    assert result.status is torchql.Status.MAX_TIME
    assert not result.success
    assert "max_time = 0.5 s" in result.message and "Increase `max_time`" in result.message
    assert math.isnan(result.sse) and torch.isnan(result.covariance).all()
    assert torch.isfinite(result.estimates).all()
    # without the budget this fit runs for minutes (thousands of 20 ms evaluations); the budget is
    # checked at every evaluation, so it ends within a few evaluations of 0.5 s (generous bound: a busy machine)
    assert elapsed < 10.0


def test_a_fit_without_a_budget_inside_one_with_it_stops_at_the_enclosing_one():
    """A fit run from another's callback (a diagnostic re-fit of each iterate), with no ``max_time``
    of its own: the enclosing fit's deadline stops it, MAX_TIME, saying whose budget (its message
    formatted ``max_time = None`` and raised a TypeError)."""
    data = torchql.Observations(T, Y, observe=["y"])
    inner = []

    def refit(record):
        inner.append(torchql.fit(SlowDecay(k=0.2), data, x0=torch.tensor([1.0], dtype=DT), **INTEGRATE))

    outer = torchql.fit(Decay(k=0.2), data, x0=torch.tensor([1.0], dtype=DT), max_time=1.0, callback=refit,
                        **INTEGRATE)
    assert outer.status is torchql.Status.MAX_TIME and inner
    assert inner[-1].status is torchql.Status.MAX_TIME
    assert "max_time = an enclosing fit's" in inner[-1].message


def test_fit_within_its_budget_is_unchanged():
    data = torchql.Observations(T, Y, observe=["y"])
    x0 = torch.tensor([1.0], dtype=DT)
    free = torchql.fit(Decay(k=0.2), data, x0=x0)
    budgeted = torchql.fit(Decay(k=0.2), data, x0=x0, max_time=600.0)
    assert budgeted.status is free.status is torchql.Status.CONVERGED
    assert torch.equal(budgeted.estimates, free.estimates)
    assert budgeted.iterations == free.iterations
    assert abs(float(budgeted.params["k"]) - 0.7) < 1e-8


def test_fit_many_stops_every_running_and_unstarted_sample_at_max_time():
    data = torchql.Observations(T, torch.stack([Y, 1.1 * Y, 0.9 * Y]), observe=["y"])
    start = time.perf_counter()
    result = torchql.fit_many(SlowDecay(k=0.2), data, x0=torch.tensor([1.0], dtype=DT), max_time=0.5, **INTEGRATE,
                              chunk_size=1)
    assert time.perf_counter() - start < 10.0
    assert [s.name for s in result.status] == ["MAX_TIME"] * 3
    assert not bool(result.success.any())
    assert all("max_time = 0.5 s" in m for m in result.message)
    assert torch.isnan(result.sse).all()
    # the samples of the chunks that never started keep their guesses
    assert float(result.params["k"][2]) == pytest.approx(0.2, abs=0.0)


def test_fit_many_within_its_budget_is_unchanged():
    data = torchql.Observations(T, torch.stack([Y, 1.1 * Y]), observe=["y"])
    x0 = torch.tensor([1.0], dtype=DT)
    free = torchql.fit_many(Decay(k=0.2), data, x0=x0)
    budgeted = torchql.fit_many(Decay(k=0.2), data, x0=x0, max_time=600.0)
    assert [s.name for s in budgeted.status] == [s.name for s in free.status] == ["CONVERGED"] * 2
    assert torch.equal(budgeted.estimates, free.estimates)


@pytest.mark.parametrize("value", [0, -1.0, math.nan, "1"])
def test_max_time_must_be_a_positive_number(value):
    data = torchql.Observations(T, Y, observe=["y"])
    with pytest.raises((TypeError, ValueError), match="max_time"):
        torchql.fit(Decay(), data, x0=torch.tensor([1.0], dtype=DT), max_time=value)
    with pytest.raises((TypeError, ValueError), match="max_time"):
        torchql.fit_many(Decay(), [data, data], x0=torch.tensor([1.0], dtype=DT), max_time=value)


def test_a_fit_estimating_sigma_that_runs_out_of_time_says_so():
    data = torchql.Observations(T, Y, observe=["y"], sigma="estimate")
    result = torchql.fit(SlowDecay(k=0.2), data, x0=torch.tensor([1.0], dtype=DT), max_time=0.5, **INTEGRATE)
    assert result.status is torchql.Status.MAX_TIME and not result.success
    # the sigma of the last iterate, as its coefficients, without error bars or a likelihood (no final pass)
    assert set(result.sigma) == {"y"} and result.sigma["y"] > 0 and math.isnan(result.sigma_stderr["y"])
    assert math.isnan(result.nll)


@pytest.mark.parametrize("batched", [False, True])
def test_max_time_counts_from_the_call_the_problems_set_up_too(monkeypatch, batched):
    """The budget starts when ``fit`` or ``fit_many`` is called: the problem's set-up (the stiffness
    test over every sample's data, 2.4 s for 400 samples of 5,000 times) is spent from it. Here the
    set-up takes longer than the whole budget, and a fit that converges in milliseconds ends
    MAX_TIME (it converged, unbudgeted, after the set-up)."""
    import torchql.problem as problem

    original = problem.choose_solver

    def slow(*args, **kwargs):
        time.sleep(0.3)
        return original(*args, **kwargs)

    monkeypatch.setattr(problem, "choose_solver", slow)
    data = torchql.Observations(T, Y, observe=["y"])
    x0 = torch.tensor([1.0], dtype=DT)
    run = (lambda **kw: torchql.fit_many(Decay(k=0.2), [data, data], x0=x0, **kw)[0]) if batched else (
        lambda **kw: torchql.fit(Decay(k=0.2), data, x0=x0, **kw))
    assert run().status is torchql.Status.CONVERGED
    cut = run(max_time=0.2)
    assert cut.status is torchql.Status.MAX_TIME and "max_time = 0.2 s" in cut.message


def test_runs_of_a_batch_share_the_budget_counted_from_the_call():
    """``fit_many`` fits samples that differ in their inputs or stiffness run by run; the runs share
    the budget counted from the ``fit_many`` call (the set-up that found the runs, a stiffness test
    over every sample, is spent from it too): with the budget spent before the first run, every
    sample ends MAX_TIME."""
    from torchql.batch import _fit_runs

    data = torchql.Observations(T, torch.stack([Y, 1.1 * Y, 0.9 * Y]), observe=["y"])
    x0 = torch.tensor([1.0], dtype=DT)
    runs = [(0, 1), (1, 3)]
    fresh = _fit_runs(runs, Decay(k=0.2), data, x0, guesses=None, max_time=600.0, progress=False, callback=None,
                      started=time.monotonic())
    assert [s.name for s in fresh.status] == ["CONVERGED"] * 3
    spent = _fit_runs(runs, Decay(k=0.2), data, x0, guesses=None, max_time=1.0, progress=False, callback=None,
                      started=time.monotonic() - 2.0)
    assert [s.name for s in spent.status] == ["MAX_TIME"] * 3


def test_the_callback_receives_the_iterate_a_fit_stopped_at_when_its_time_ran_out(monkeypatch):
    """The time budget ran out while a step from the third iterate was being made: the fit's result
    is that iterate (``MAX_TIME``), and ``history`` ends with its record, which the callback had
    not been handed (no step from it was decided). It is handed over as the fit stops."""
    from torchql.engine import Engine

    real, calls = Engine._propose, []

    def propose(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise TimeBudgetExceeded("time's up")
        return real(self, *args, **kwargs)

    monkeypatch.setattr(Engine, "_propose", propose)
    seen = []
    data = torchql.Observations(T, Y, observe=["y"])
    result = torchql.fit(Decay(k=0.2), data, x0=torch.tensor([1.0], dtype=DT), callback=seen.append, max_time=60.0,
                         **INTEGRATE)
    assert result.status is torchql.Status.MAX_TIME
    assert len(result.history) >= 3
    assert [id(r) for r in seen] == [id(r) for r in result.history]


def test_the_callback_receives_the_guesses_of_a_fit_stopped_before_its_first_step():
    """A budget spent before the first step: ``history`` holds the guesses' record (the result's
    estimates, unevaluated), and the callback gets it too, under the fit's budget (the final pass
    that hands it over evaluates without one)."""
    seen = []
    data = torchql.Observations(T, Y, observe=["y"])
    result = torchql.fit(Decay(k=0.2), data, x0=torch.tensor([1.0], dtype=DT), callback=seen.append, max_time=1e-9,
                         **INTEGRATE)
    assert result.status is torchql.Status.MAX_TIME and result.iterations == 0
    assert result.history and [id(r) for r in seen] == [id(r) for r in result.history]
