"""Tolerances and limits: every default written once, and fit and fit_many resolving them alike."""

import math

import pytest
import torch

import torchql
from testmodels import Decay
from torchql.options import DAMPINGS, Limits, Tolerances, check_damping


def test_float64_defaults():
    tol = Tolerances.resolve(torch.float64)
    assert (tol.rtol, tol.atol, tol.xtol, tol.ftol) == (1e-10, 1e-12, 1e-8, 1e-12)
    assert tol.rcond == pytest.approx(1e-7, rel=1e-12)  # 1e3 rtol > 1e3 eps


def test_lower_precision_defaults_follow_the_integrator():
    tol = Tolerances.resolve(torch.float32)
    assert (tol.rtol, tol.atol, tol.xtol, tol.ftol) == (1e-6, 1e-8, 1e-4, 1e-6)
    assert tol.rcond == pytest.approx(1e-3)
    loose = Tolerances.resolve(torch.float64, rtol=1e-6)
    assert loose.xtol == pytest.approx(1e-4) and loose.rcond == pytest.approx(1e-3)  # 100 rtol, 1e3 rtol


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
