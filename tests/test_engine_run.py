"""A problem's fit and its second fits (torchql.engine_run): a sample that ``solver="auto"``'s explicit
solver finds stiff during the fit is fitted again as a stiff model, alone, in ``fit`` and ``fit_many``.

The model is :class:`testmodels.Lag`: ``x`` follows a decaying ``y`` with the lag ``1 / k``. Both
are measured from t = 0.1 to 2 (noise 1e-4); ``x(0) = 0`` and ``y(0) = 1`` are known, ``k`` and
``a`` are fitted from ``k = 1``, ``a = 1.5``. At the guesses the model is not stiff (``k * span =
2``), so ``"auto"`` chooses DOP853; a true ``k = 1e4`` makes it stiff (``k * span = 2e4``, above
:data:`torchql.stiffness.STIFF_RATIO`) once the iterates approach it.
"""

import pytest
import torch

import torchql
from testmodels import Lag, lag_data

DT = torch.float64
X0 = torch.tensor([0.0, 1.0], dtype=DT)
OPTIONS = dict(fixed_x0=["x", "y"], t0=0.0)


def test_auto_fits_a_model_its_explicit_solver_finds_stiff_again_as_a_stiff_model():
    """The explicit fit found the model stiff as ``k`` passed about 1e3; the sample is fitted again
    as ``solver="auto"`` fits a model it finds stiff from the start, and that fit is the result,
    the same as ``solver="rodas5p"``'s, its solver recorded and the switch said."""
    data = lag_data(1e4)
    auto = torchql.fit(Lag(1.0, 1.5), data, X0, **OPTIONS)
    stiff = torchql.fit(Lag(1.0, 1.5), data, X0, solver="rodas5p", **OPTIONS)
    assert stiff.success, stiff.message
    assert auto.status is stiff.status and auto.iterations == stiff.iterations, auto.message
    assert auto.solver_options["solver"] == "rodas5p"
    assert 'found the model stiff during the fit' in auto.message and 'solver="rodas5p"' in auto.message
    torch.testing.assert_close(auto.estimates, stiff.estimates, rtol=1e-12, atol=0)
    assert auto.sse == pytest.approx(stiff.sse, rel=1e-12)
    assert auto.covariance is not None and bool(torch.isfinite(auto.covariance).all())


def test_fit_many_fits_again_only_the_samples_found_stiff_each_as_its_own_fit():
    """A batch of a sample that becomes stiff and one that does not: the first is fitted again by
    the stiff solver, the second keeps DOP853's fit, and each is the sample's own ``fit``."""
    sets = [lag_data(1e4), lag_data(3.0, seed=3)]
    batch = torchql.fit_many(Lag(1.0, 1.5), sets, X0, **OPTIONS)
    assert [batch[i].solver_options["solver"] for i in range(2)] == ["rodas5p", "dop853"]
    for i, data in enumerate(sets):
        alone = torchql.fit(Lag(1.0, 1.5), data, X0, **OPTIONS)
        assert alone.success, alone.message
        assert batch[i].status is alone.status and batch[i].iterations == alone.iterations, i
        assert batch[i].message == alone.message
        torch.testing.assert_close(batch[i].estimates, alone.estimates, rtol=1e-10, atol=0)
        assert float(batch[i].sse) == pytest.approx(alone.sse, rel=1e-10)


def test_an_explicit_solver_asked_for_is_not_replaced():
    """``solver="dop853"`` asked for: the sample is not fitted again (the stiffness is the message)."""
    result = torchql.fit(Lag(1.0, 1.5), lag_data(1e4), X0, solver="dop853", max_time=3, **OPTIONS)
    assert result.solver_options["solver"] == "dop853"
    assert "found the model stiff during the fit" not in result.message


def test_an_accepted_iterate_too_fast_for_the_grid_solver_has_its_trials_integrated_adaptively():
    """``k = 1000`` over 2 time units is not stiff for ``"auto"`` (``k * span = 2e3``), but its lag
    (1e-3) is shorter than the storage grid's steps: from the data-built start (``k = 179``) the grid
    solver needed more steps than a trial may take for the current iterate as for every trial, and
    each trial was rejected as a blow-up (STALLED at k = 6036, SSE 17422). The current iterate's own
    need shows the grid too coarse for the model; its trials go to the adaptive solver, and the fit
    reaches the optimum Rodas5P's fit reaches."""
    data = lag_data(1e3)
    result = torchql.fit(Lag(1.0, 1.5), data, X0, solver="dop853", initial_trajectory="data", **OPTIONS)
    stiff = torchql.fit(Lag(1.0, 1.5), data, X0, solver="rodas5p", **OPTIONS)
    assert result.success and stiff.success, (result.message, stiff.message)
    # both at rtol 1e-10: the optima agree to the sensitivity of k (relative 1e-3 per unit of SSE)
    torch.testing.assert_close(result.estimates, stiff.estimates, rtol=1e-6, atol=0)
    assert result.sse == pytest.approx(stiff.sse, rel=1e-7)


def test_a_model_stiff_along_an_accepted_iterate_is_fitted_again_as_stiff():
    """``x' = -k (x - cos t)`` over 10 time units, ``k = 1e4`` fitted from 1: at the fit's tolerance
    DOP853's steps are held at ``h k`` of 1.3 to 3.5, below its stiffness test's bound, and the
    explicit fit crawled to the optimum (12.6 s, where Rodas5P takes 0.7 s). Along an accepted
    iterate the Jacobian's decay rate times the span exceeds 1e4, the test that chooses the stiff
    solver from the data: the sample is fitted again as a stiff model, with Rodas5P's result."""
    from testmodels import Relaxation, relaxation_solution

    t = torch.linspace(0.25, 10.0, 40, dtype=DT)
    y = relaxation_solution(t, 0.0, 1e4).unsqueeze(-1)
    y = y + 1e-4 * torch.randn(y.shape, generator=torch.Generator().manual_seed(0), dtype=DT)
    data = torchql.Observations(t, y, observe=["x"], sigma=1e-4)
    x0 = torch.tensor([0.0], dtype=DT)
    auto = torchql.fit(Relaxation(1.0), data, x0, fixed_x0=["x"], t0=0.0)
    stiff = torchql.fit(Relaxation(1.0), data, x0, fixed_x0=["x"], t0=0.0, solver="rodas5p")
    assert stiff.success and auto.status is stiff.status, auto.message
    assert auto.solver_options["solver"] == "rodas5p"
    torch.testing.assert_close(auto.estimates, stiff.estimates, rtol=1e-12, atol=0)


def test_a_sample_found_stiff_by_its_first_reference_in_a_batch_of_grid_groups_is_fitted_again():
    """Two starts on one dataset (as ``multistart`` batches them): the second's guesses (``k`` =
    3275) make its integrated first reference stiff, and the two samples chose different grids, so
    each group was fitted by an engine of its own, which lost the mark: the second sample ended
    INTEGRATION_FAILED after 0 iterations, where its own ``fit`` converges on Rodas5P."""
    x0 = torch.tensor([1.0, 0.3], dtype=DT)
    t = torch.cat([torch.logspace(-5, -2, 8, dtype=DT), torch.linspace(0.05, 3.0, 15, dtype=DT)])
    x = torchql.simulate(Lag(1e4, 1.0), x0, t, solver="rodas5p", rtol=1e-11, atol=1e-13)
    y = x + 1e-3 * torch.randn(x.shape, generator=torch.Generator().manual_seed(1), dtype=DT)
    data = torchql.Observations(t, y, observe=["x", "y"], sigma=1e-3)
    guesses = torch.tensor([[1.0, 0.5], [3274.68, 14.608]], dtype=DT)
    options = dict(bounds={"k": (0.1, 1e6), "a": (0.01, 100.0)}, initial_trajectory="integrate")
    start = torch.tensor([0.9, 0.25], dtype=DT)
    batch = torchql.fit_many(Lag(1.0, 0.5), [data, data], start, guesses={"k": guesses[:, 0], "a": guesses[:, 1]},
                             **options)
    for i in range(2):
        alone = torchql.fit(Lag(*guesses[i].tolist()), data, start, **options)
        assert alone.success and alone.solver_options["solver"] == "rodas5p", alone.message
        assert batch[i].status is alone.status and batch[i].iterations == alone.iterations, (i, batch[i].message)
        assert batch[i].solver_options == alone.solver_options
        torch.testing.assert_close(batch[i].estimates, alone.estimates, rtol=1e-10, atol=0)


def test_a_callbacks_last_record_is_the_results_when_a_second_fit_loses():
    """Thesis Table 4.5 (two digits), undamped: the fit from the data-built start fails and so does the
    fit from the integrated guesses; the first is kept. The callback received the second fit's records
    last (C = -10.1, where the result has C = -2.6e6); it now receives the kept fit's last record again,
    in ``fit`` and ``fit_many``."""
    from torchql.models import NonlinearOscillator

    times = torch.tensor([0, 1, 2, 3, 4, 5, 6, 6.5], dtype=DT)
    x = torchql.simulate(NonlinearOscillator(), torch.tensor([0.0, 1.0], dtype=DT), times, rtol=1e-13, atol=1e-15)
    data = torchql.Observations(times, torch.round(x[:, :1] * 100) / 100, observe=["y"])
    guess = dict(A=0.5, B=2.0, C=0.5, D=2.0)
    x0 = torch.tensor([0.5, 0.5], dtype=DT)
    records = []
    fit = torchql.fit(NonlinearOscillator(**guess), data, x0=x0, max_steps=200, damping=None, callback=records.append)
    assert not fit.success and "Integrated from the guesses instead" in fit.message
    assert records[-1] is fit.history[-1]
    seen = []
    batch = torchql.fit_many(NonlinearOscillator(**guess), [data], x0[None], max_steps=200, damping=None,
                             callback=lambda sample, record: seen.append((sample, record)))
    assert seen[-1][0] == 0 and seen[-1][1] is batch.history[0][-1]
    assert seen[-1][1].params["C"].item() == batch.params["C"][0].item() == fit.params["C"].item()


def test_a_saddle_left_too_late_for_max_time_is_max_time():
    """Two decays observed as their sum, guessed with equal rates, end on a saddle; where ``max_time`` ran
    out in the fit made from a step off it, the saddle's NOT_IDENTIFIABLE was kept, its advice to fix an
    unknown contradicted by the next sentence. The fit did not finish: MAX_TIME, without covariance."""
    import time

    from test_saddle import TwoDecays, _sum_of_decays

    start = [None]

    def slow(record):  # (the second fit's first record: the budget runs out in it)
        if start[0] is None and record.params["k1"].item() != record.params["k2"].item():
            start[0] = time.monotonic()
            time.sleep(2.1)
    x0 = torch.ones(2, dtype=DT)
    fit = torchql.fit(TwoDecays(0.5, 0.5), _sum_of_decays(), x0=x0, fixed_x0=["x1", "x2"], max_time=2.0,
                      callback=slow)
    assert start[0] is not None and fit.status is torchql.Status.MAX_TIME and not fit.success
    assert "a saddle" in fit.message and "The first fit ended NOT_IDENTIFIABLE" in fit.message
    assert "Fix the named unknowns" not in fit.message and bool(torch.isnan(fit.covariance).all())


def test_a_sample_found_stiff_is_not_fitted_again_once_its_time_is_up():
    """A fit that the explicit solver found stiff and that ran out of ``max_time`` was fitted again by the
    stiff solver with no time left: that fit ended MAX_TIME after 0 iterations at the guesses, and won
    (k = 1, where the explicit fit had reached 3506); a larger budget gave a worse estimate."""
    from types import SimpleNamespace

    from torchql.engine_run import _StiffRefit

    refit = _StiffRefit(SimpleNamespace(stiff_refit=True), max_time=1.0, history=False, callback=None)
    chunk = {"stiff_met": torch.tensor([True, False]), "status": [torchql.Status.MAX_TIME, torchql.Status.MAX_TIME]}
    assert refit(chunk, torch.arange(2)) == [] and refit.spec is None  # (no stiff variant made, nothing fitted)
