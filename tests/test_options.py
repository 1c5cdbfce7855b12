"""Tolerances and limits: every default written once, and fit and fit_many resolving them alike."""

import math

import pytest
import torch

import torchql
from testmodels import Decay
from torchql.options import DAMPINGS, Limits, Tolerances, check_damping


def test_float64_defaults():
    tol = Tolerances.resolve(torch.float64)
    assert (tol.rtol, tol.atol, tol.xtol, tol.ftol) == (1e-10, 1e-12, 1e-8, 1e-10)  # ftol: rtol > 1e-12
    assert tol.rcond == pytest.approx(1e-7, rel=1e-12)  # 1e3 rtol > 1e3 eps
    assert Tolerances.resolve(torch.float64, rtol=1e-13).ftol == 1e-12  # never finer than 1e-12


def test_lower_precision_defaults_follow_the_integrator():
    tol = Tolerances.resolve(torch.float32)
    assert (tol.rtol, tol.atol, tol.xtol, tol.ftol) == (1e-6, 1e-8, 1e-4, 1e-6)
    assert tol.rcond == pytest.approx(1e-3)
    loose = Tolerances.resolve(torch.float64, rtol=1e-6)
    assert loose.xtol == pytest.approx(1e-4) and loose.rcond == pytest.approx(1e-3)  # 100 rtol, 1e3 rtol
    assert loose.ftol == 1e-6  # an SSE change below the integration's accuracy is no change


def test_a_loose_rtol_keeps_the_rank_threshold_below_one():
    """``rcond``'s ``1e3 rtol`` is capped at ``sqrt(rtol)``: at ``rtol=1e-3`` (scipy's default) it was 1, and
    a well-conditioned fit (condition number 3.8) ended NOT_IDENTIFIABLE at its guesses. At the default
    and down to ``rtol=1e-6`` nothing changes; an ``rtol`` of 1 or more is no relative tolerance."""
    assert Tolerances.resolve(torch.float64, rtol=1e-3).rcond == pytest.approx(math.sqrt(1e-3))
    assert Tolerances.resolve(torch.float64, rtol=1e-4).rcond == pytest.approx(1e-2)
    with pytest.raises(ValueError, match=r"`rtol` must be below 1 \(a relative tolerance\); received 2"):
        Tolerances.resolve(torch.float64, rtol=2.0)
    for name in ("rtol", "rcond"):  # FitOptions checks them where it is written (rcond = 1: every fit deficient)
        with pytest.raises(ValueError, match=rf"`{name}` must be below 1 \(a relative tolerance\); received 1"):
            torchql.FitOptions(**{name: 1.0})
    with pytest.raises(ValueError, match=r"`rcond` must be below 1"):
        Tolerances.resolve(torch.float64, rcond=1.5)
    from torchql.models import LinearOscillator
    t = torch.arange(14, dtype=torch.float64) * 0.5
    y = torchql.simulate(LinearOscillator(0.1, 3.0), torch.tensor([0.0, 1.0], dtype=torch.float64), t)[:, :1]
    y = y + 0.01 * torch.randn(y.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    data = torchql.Observations(t, y, observe=["y"])
    x0 = torch.tensor([0.5, 0.5], dtype=torch.float64)
    loose, tight = (torchql.fit(LinearOscillator(0.5, 1.0), data, x0, rtol=rtol) for rtol in (1e-3, 1e-10))
    assert loose.status is torchql.Status.CONVERGED, loose.message
    torch.testing.assert_close(loose.estimates, tight.estimates, rtol=1e-2, atol=1e-3)


def test_the_same_number_as_an_int_and_as_a_float_is_given_once():
    """``max_time=10.0`` with ``FitOptions(max_time=10)`` is the same value, not a conflict."""
    data = _decay_data(0.01)
    result = torchql.fit(Decay(0.2), data, X0, max_time=10.0, xtol=1, options=torchql.FitOptions(max_time=10, xtol=1.0))
    assert result.success, result.message
    with pytest.raises(ValueError, match="`max_time` is given twice"):
        torchql.fit(Decay(0.2), data, X0, max_time=11.0, options=torchql.FitOptions(max_time=10))


def test_given_values_are_kept_and_validated():
    tol = Tolerances.resolve(torch.float64, rtol=1e-9, atol=1e-11, xtol=1e-6, ftol=1e-10, rcond=1e-5)
    assert (tol.rtol, tol.atol, tol.xtol, tol.ftol, tol.rcond) == (1e-9, 1e-11, 1e-6, 1e-10, 1e-5)
    for name in ("rtol", "atol", "xtol", "ftol", "rcond"):
        with pytest.raises(ValueError, match=f"`{name}`"):
            Tolerances.resolve(torch.float64, **{name: -1.0})
    assert Limits.resolve() == Limits(50, None, None)
    with pytest.raises((TypeError, ValueError), match="`max_iter`"):
        Limits.resolve(max_iter=-1)
    with pytest.raises((TypeError, ValueError), match="`max_steps`"):
        Limits.resolve(max_steps=0)
    with pytest.raises((TypeError, ValueError), match="`max_time`"):
        Limits.resolve(max_time=math.nan)
    assert [check_damping(d) for d in DAMPINGS] == ["lm", None]
    with pytest.raises(ValueError, match=r"`damping` must be one of \('lm', None\)"):
        check_damping("trust")


def test_fit_and_fit_many_read_the_same_tolerances():
    t = torch.linspace(0, 2, 11, dtype=torch.float64)
    y = (1.5 * torch.exp(-0.7 * t)).unsqueeze(-1)
    data = torchql.Observations(t, y, observe=["y"])
    x0 = torch.tensor([1.0], dtype=torch.float64)
    single = torchql.fit(Decay(0.2), data, x0=x0, rtol=1e-8)
    batch = torchql.fit_many(Decay(0.2), torchql.Observations(t, torch.stack([y, y]), observe=["y"]), x0=x0, rtol=1e-8)
    assert single.fit_kwargs["rtol"] == 1e-8
    assert torch.allclose(batch.estimates[0], single.estimates, rtol=1e-10, atol=0)


def _decay_data(noise=0.0):
    t = torch.linspace(0, 2, 11, dtype=torch.float64)
    y = (1.5 * torch.exp(-0.7 * t)).unsqueeze(-1)
    y = y + noise * torch.randn(y.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    return torchql.Observations(t, y, observe=["y"])


X0 = torch.tensor([1.0], dtype=torch.float64)


def test_fit_options_equal_the_keywords_they_stand_for():
    data = _decay_data(0.01)
    options = torchql.FitOptions(method="shooting", rtol=1e-9, max_iter=30, grid=40)
    by_object = torchql.fit(Decay(0.2), data, X0, options=options)
    by_keywords = torchql.fit(Decay(0.2), data, X0, method="shooting", rtol=1e-9, max_iter=30, grid=40)
    assert by_object.success and torch.equal(by_object.estimates, by_keywords.estimates)
    assert by_object.options == by_keywords.options == options.replace(max_time=None)
    again = torchql.fit(Decay(0.2), data, X0, options=by_object.options)  # a result's options re-run it
    assert torch.equal(again.estimates, by_object.estimates)
    batch = torchql.fit_many(Decay(0.2), [data, data], X0, options=options)
    torch.testing.assert_close(batch.estimates[0], by_object.estimates, rtol=1e-10, atol=0)
    assert batch.options == by_object.options


def test_a_keyword_at_its_default_takes_the_field_and_a_conflict_is_named():
    data = _decay_data()
    options = torchql.FitOptions(rtol=1e-9)
    same = torchql.fit(Decay(0.2), data, X0, rtol=1e-9, options=options)  # the same value both ways: fine
    assert same.fit_kwargs["rtol"] == 1e-9
    with pytest.raises(ValueError, match="`rtol` is given twice, 1e-08 as a keyword and 1e-09 in `options`"):
        torchql.fit(Decay(0.2), data, X0, rtol=1e-8, options=options)
    with pytest.raises(TypeError, match="`options` must be a torchql.FitOptions; received dict"):
        torchql.fit(Decay(0.2), data, X0, options={"rtol": 1e-9})


def test_a_keyword_passed_at_its_default_value_against_options_is_a_conflict_too():
    """Passing ``method="kantorovich"`` (the default) with ``options`` that say shooting is two answers to
    one question: an error, as ``multistart`` and ``profile`` give, not the options' silently; a keyword
    not passed takes the field."""
    data = _decay_data(0.01)
    shooting = torchql.FitOptions(method="shooting")
    with pytest.raises(ValueError, match="`method` is given twice, 'kantorovich' as a keyword and 'shooting' in `options`"):
        torchql.fit(Decay(0.2), data, X0, method="kantorovich", options=shooting)
    with pytest.raises(ValueError, match="`method` is given twice"):
        torchql.fit_many(Decay(0.2), [data, data], X0, method="kantorovich", options=shooting)
    assert torchql.fit(Decay(0.2), data, X0, options=shooting).method == "shooting"


@pytest.mark.parametrize("kwargs, error, match", [
    (dict(method="newton"), ValueError, "`method` must be one of"),
    (dict(rtol=-1.0), ValueError, "`rtol`"),
    (dict(grid=0), ValueError, "`grid`"),
    (dict(solver="rk45"), ValueError, "`solver` must be one of"),
    (dict(linear_solver="magnus"), ValueError, "`linear_solver` must be one of"),
    (dict(max_iter=-1), ValueError, "`max_iter`"),
    (dict(damping="trust"), ValueError, "`damping` must be one of"),
    (dict(method="shooting", initial_trajectory="start"), ValueError, "`initial_trajectory` must be one of"),
])
def test_bad_fit_options_are_named_where_they_are_written(kwargs, error, match):
    with pytest.raises(error, match=match):
        torchql.FitOptions(**kwargs)


def test_profile_multistart_and_gradient_fitting_take_the_options():
    data = _decay_data(0.01)
    result = torchql.fit(Decay(0.2), data, X0)
    loose = torchql.FitOptions(rtol=1e-7)
    by_object = torchql.profile(result, "k", options=loose)
    assert by_object.interval == torchql.profile(result, "k", rtol=1e-7).interval
    with pytest.raises(ValueError, match="`rtol` is given twice"):
        torchql.profile(result, "k", rtol=1e-8, options=loose)
    best = torchql.multistart(Decay(0.2), data, X0, starts=3, options=loose)
    assert best.best.fit_kwargs["rtol"] == 1e-7
    from torchql.baselines import adjoint_fit

    with pytest.raises(ValueError, match="`options.method` = 'shooting' does not apply here"):
        adjoint_fit(Decay(0.2), data, x0=X0, options=torchql.FitOptions(method="shooting"))
    gradient = adjoint_fit(Decay(0.2), data, x0=X0, max_steps=2, options=loose)
    assert gradient.solver_options["rtol"] == 1e-7
    # the field max_steps is the solver's step budget, adjoint_fit's keyword the optimizer's: not read as it
    with pytest.raises(ValueError, match=r"`options.max_steps` = 5 does not apply here \(this function's "
                                         r"`max_steps` is another quantity\)"):
        adjoint_fit(Decay(0.2), data, x0=X0, options=torchql.FitOptions(max_steps=5))
