"""Truthful statuses for fits that do not reach an optimum: diverged is not "not identifiable"."""

import math

import pytest
import torch

import torchql
from testmodels import MichaelisMenten
from torchql.diagnosis import (RUNAWAY_FACTOR, SSE_GROWTH, WEAK_RUNAWAY_FACTOR, final_status, negligible_columns,
                               null_detail, ran_away)
from torchql.status import Status

DT = torch.float64
NULL = " Unknowns the data cannot separate: {V, Km}."


NAMES = ["V", "Km"]
SCALE = torch.ones(2, dtype=DT)


def rules(status, deficient=False, growth=(1.0, 1.0), sse=1.0, sse_start=1.0):
    """``final_status`` for estimates ``growth`` times their typical magnitude (1)."""
    return final_status(status, rank_deficient=deficient, null_text=NULL if deficient else "",
                        estimates=torch.tensor(growth, dtype=DT), scale=SCALE, unknown_names=NAMES, sse=sse,
                        sse_start=sse_start)


WEAK = (2 * WEAK_RUNAWAY_FACTOR, 1.0)  # beyond the factor for weakly determined directions only
STRONG = (2 * RUNAWAY_FACTOR, 1.0)


def test_null_detail_names_each_group_once():
    v = torch.tensor([[0.7, 0.7], [0.7, 0.7], [0.0, 0.0]], dtype=DT)
    assert null_detail(v, ["V", "Km", "S(t0)"]) == NULL


def test_ran_away_compares_with_the_typical_magnitude():
    scale = torch.tensor([1.0, 1e-3, 2.0], dtype=DT)
    u = torch.tensor([-2e6, 5e2, math.nan], dtype=DT)
    assert ran_away(u, scale, ["a", "b", "c"]) == ["a", "c"]
    assert ran_away(torch.tensor([RUNAWAY_FACTOR], dtype=DT), torch.ones(1, dtype=DT), ["a"]) == []


@pytest.mark.parametrize("status", [Status.CONVERGED, Status.CONVERGED_SSE])
def test_converged(status):
    assert rules(status) == (status, "")
    assert rules(status, deficient=True) == (Status.NOT_IDENTIFIABLE, NULL)
    # a full-rank optimum far from the guesses is an optimum
    assert rules(status, growth=STRONG) == (status, "")
    # converged only relative to estimates that ran away along a direction the data barely determine
    code, detail = rules(status, deficient=True, growth=(2 * WEAK_RUNAWAY_FACTOR, -3 * WEAK_RUNAWAY_FACTOR))
    assert code is Status.DIVERGED and "['V', 'Km'] ran away" in detail and "{V, Km}" in detail
    # a non-identifiable direction's minimal-norm steps stay near the guesses
    assert rules(status, deficient=True, growth=(0.5 * WEAK_RUNAWAY_FACTOR, 1.0))[0] is Status.NOT_IDENTIFIABLE


@pytest.mark.parametrize("status", [Status.MAX_ITER, Status.STALLED])
def test_unconverged(status):
    assert rules(status) == (status, "")
    code, detail = rules(status, deficient=True)
    assert code is Status.NOT_IDENTIFIABLE and detail.startswith(NULL) and status.name in detail
    code, detail = rules(status, growth=STRONG)
    assert code is Status.DIVERGED and "['V'] ran away" in detail and status.name in detail
    assert rules(status, growth=WEAK) == (status, "")  # full rank: far, but perhaps on its way
    code, detail = rules(status, deficient=True, growth=WEAK)
    assert code is Status.DIVERGED and "barely determine" in detail
    code, detail = rules(status, sse=2 * SSE_GROWTH, sse_start=1.0)
    assert code is Status.DIVERGED and "grew from 1 at the guesses to 2000" in detail
    # no start from the model's own solution (a data-built first trajectory): no comparison
    assert rules(status, sse=1e300, sse_start=None) == (status, "")


@pytest.mark.parametrize("status", [Status.INTEGRATION_FAILED, Status.DIVERGED, Status.EXACT_INFEASIBLE,
                                    Status.MAX_TIME])
def test_other_statuses_stand(status):
    assert rules(status, deficient=True, growth=STRONG, sse=1e9) == (status, "")


T = torch.linspace(0, 10, 21, dtype=DT)


def michaelis_menten_data():
    """Exact S at 21 times over [0, 10] from V = 1, Km = 0.5, S(0) = 5: values ``(21, 1)`` and Observations."""
    y = torchql.simulate(MichaelisMenten(), torch.tensor([5.0], dtype=DT), T)
    return y, torchql.Observations(T, y, observe=["S"])


def test_a_runaway_along_a_weak_direction_is_diverged_not_unidentifiable():
    """From V = 0.3, Km = 0.15 the integrated start descends into the valley ``V, Km -> inf`` with ``V / Km``
    fixed (sum of squares 2.17 at infinity, 0 at the truth). The Jacobian there is nearly rank deficient,
    but the problem is well conditioned at its optimum (column-scaled condition number 38): the honest
    status is DIVERGED, naming the runaway, in fit and in fit_many alike."""
    y, data = michaelis_menten_data()
    result = torchql.fit(MichaelisMenten(0.3, 0.15), data, x0=torch.tensor([5.0], dtype=DT),
                         initial_trajectory="integrate")
    assert result.status is Status.DIVERGED, result.message
    assert "['V', 'Km'] ran away" in result.message
    assert abs(float(result.params["V"])) > WEAK_RUNAWAY_FACTOR * 0.3
    batch = torchql.fit_many(MichaelisMenten(0.3, 0.15), torchql.Observations(T, torch.stack([y, y]), observe=["S"]),
                             x0=torch.tensor([5.0], dtype=DT), initial_trajectory="integrate")
    assert [s.name for s in batch.status] == ["DIVERGED", "DIVERGED"], batch.message
    assert all("ran away" in m for m in batch.message)


def test_the_same_data_from_the_data_built_start_reach_the_truth():
    y, data = michaelis_menten_data()
    result = torchql.fit(MichaelisMenten(0.3, 0.15), data, x0=torch.tensor([5.0], dtype=DT),
                         initial_trajectory="data")
    assert result.success, result.message
    # exact data, rtol 1e-10: the estimates to the integrator's accuracy times the conditioning (38)
    assert abs(float(result.params["V"]) - 1.0) < 1e-7 and abs(float(result.params["Km"]) - 0.5) < 1e-7


def test_a_step_far_from_solving_the_model_is_judged_by_the_model():
    """From the true V, Km but S(t0) guessed 2 (truth 5), the second undamped Kantorovich step goes to
    V = -3.3, Km = -5.1: its linear problem's misfit falls (6.7 -> 6.1), but the trajectory is far from
    solving the model (model_defect 83: the model is singular where Km + S = 0). Judged by its linear
    misfit the step was taken and the iteration ran away to V, Km ~ -1e6; judged by the model it is
    rejected, the step damped, and the fit converges to the truth, through fit and fit_many alike."""
    y, data = michaelis_menten_data()
    result = torchql.fit(MichaelisMenten(1.0, 0.5), data, x0=torch.tensor([2.0], dtype=DT),
                         initial_trajectory="integrate")
    assert result.success, result.message
    assert abs(float(result.params["V"]) - 1.0) < 1e-7 and abs(float(result.params["Km"]) - 0.5) < 1e-7
    assert abs(float(result.x0[0]) - 5.0) < 1e-7
    assert any(record.rejected for record in result.history)
    batch = torchql.fit_many(MichaelisMenten(1.0, 0.5), torchql.Observations(T, torch.stack([y, y]), observe=["S"]),
                             x0=torch.tensor([2.0], dtype=DT))
    assert bool(batch.success.all()), batch.message
    assert torch.allclose(batch.estimates[0], result.estimates, rtol=1e-8, atol=0)


def test_a_coefficient_the_data_start_puts_near_zero_is_not_a_runaway():
    """x'' = -xi x seen at t = 0, 0.5, 1 as cos(pi t) = 1, 0, -1: every xi fits (with its own x'(0)),
    so the problem is not identifiable. The data-built start fits xi ~ 1e-13 to the straight line's
    slopes; the fit ends at xi = 8.38, far above that but not above the guess 1: NOT_IDENTIFIABLE."""
    from torchql.models import HarmonicOscillator

    t = torch.tensor([0.0, 0.5, 1.0], dtype=DT)
    data = torchql.Observations(t, torch.cos(math.pi * t), observe=["x"])
    result = torchql.fit(HarmonicOscillator(1.0), data, x0=torch.tensor((1.0, 1.0), dtype=DT),
                         initial_trajectory="data")
    assert abs(float(result.history[0].params["xi"])) < 1e-6
    assert result.status is Status.NOT_IDENTIFIABLE, result.message
    assert "{u(t0), xi}" in result.message


def test_rank_deficient_far_from_a_stationary_point_is_not_called_not_identifiable():
    """NOT_IDENTIFIABLE after MAX_ITER or STALLED needs a (near-)stationary iterate: the
    minimal-norm Gauss-Newton step there moves no unknown by more than STATIONARY_STEP of its
    typical magnitude. Far from one, the rank deficiency may be the iterate's, not the optimum's:
    the status stands, and the message names the unknowns."""
    from torchql.diagnosis import STATIONARY_STEP

    common = dict(rank_deficient=True, null_text=" Unknowns the data cannot separate: {a, b}.",
                  estimates=torch.tensor([1.0, 2.0], dtype=torch.float64), scale=torch.ones(2, dtype=torch.float64),
                  unknown_names=["a", "b"], sse=1.0, sse_start=None)
    far = final_status(Status.MAX_ITER, step=torch.tensor([0.5, 0.0], dtype=torch.float64), **common)
    assert far[0] is Status.MAX_ITER and "not near a stationary point" in far[1] and "{a, b}" in far[1]
    near = final_status(Status.STALLED, step=torch.tensor([0.1 * STATIONARY_STEP, 0.0], dtype=torch.float64), **common)
    assert near[0] is Status.NOT_IDENTIFIABLE and "{a, b}" in near[1]
    assert final_status(Status.MAX_ITER, **common)[0] is Status.NOT_IDENTIFIABLE  # no step given: as before


def test_negligible_columns_compare_effects_over_the_unknowns_magnitudes():
    """Column j times max(|estimate_j|, scale_j) against max(L, m) eps times the largest such product."""
    tol = 10 * torch.finfo(DT).eps  # L = 10 rows, m = 5 unknowns
    J = torch.zeros(10, 5, dtype=DT)
    J[0, 0], J[1, 1], J[2, 2], J[3, 3] = 1.0, 0.5 * tol, 2.0 * tol, 1e-25
    estimates = torch.zeros(5, dtype=DT)
    scale = torch.tensor([1.0, 1.0, 1.0, 1e25, 1.0], dtype=DT)  # unknown 3 in units 1e25 times too small
    assert negligible_columns(J, estimates, scale).tolist() == [False, True, False, False, True]
    # an estimate above its typical magnitude counts: 4 * 0.5 tol is above the threshold
    assert not negligible_columns(J, torch.tensor([0.0, 4.0, 0.0, 0.0, 0.0], dtype=DT), scale)[1]
    batch = torch.stack([J, torch.zeros_like(J)])  # with every column zero, every unknown is undetermined
    assert negligible_columns(batch, estimates, scale).tolist() == [[False, True, False, False, True], [True] * 5]


def _at_rest_fit(kind):
    """The linear oscillator seen at rest, y = 0 at 14 times, fitted from A = 0.5, B = 1 and (y, v) = (0.2, 0.8)."""
    from torchql.models import LinearOscillator

    t = torch.arange(14, dtype=DT) * 0.5
    y = torch.zeros(14, 1, dtype=DT)
    if kind == "fit":
        return torchql.fit(LinearOscillator(0.5, 1.0), torchql.Observations(t, y, observe=["y"]),
                           torch.tensor([0.2, 0.8], dtype=DT))
    batch = torchql.fit_many(LinearOscillator(0.5, 1.0), torchql.Observations(t, torch.stack([y, y]), observe=["y"]),
                             torch.tensor([0.2, 0.8], dtype=DT))
    return batch[0]


@pytest.mark.parametrize("kind", ["fit", "fit_many"])
def test_data_that_carry_no_information_about_the_parameters_are_not_identifiable(kind):
    """At rest the trajectory is 0 and so are its sensitivities to A and B (~1e-32, from the estimates'
    rounding, or exactly 0), while those to y(t0), v(t0) are of order 1. Scaled to unit norm the columns
    looked well conditioned (singular values 1.35 to 0.31) and the fit CONVERGED with A and B at their
    guesses, +/- 0.5. Over their magnitudes (0.5, 1) their effects are 1e-31 of the others' or nothing:
    not identifiable, A and B named and without error bars; the initial states, determined as 0, keep theirs."""
    result = _at_rest_fit(kind)
    assert result.status is Status.NOT_IDENTIFIABLE and not result.success, result.message
    assert "{B}; {A}" in result.message
    se = result.stderr
    assert math.isnan(se["A"]) and math.isnan(se["B"])
    # residuals of 1e-31 at most (SSE below 4e-62) and unit sensitivities: the states are 0 to within 1e-30
    for name in ("y(t0)", "v(t0)"):
        assert 0 <= se[name] < 1e-30 and abs(float(result.estimates[result.unknown_names.index(name)])) < 1e-30


def test_a_tiny_initial_state_in_its_own_units_is_no_negligible_column():
    """Data of scale 1e-20: the raw sensitivity to k (1.6e-20) is 1e-20 of that to y(t0) (1.8), but over
    the unknowns' magnitudes (1e-20 and 0.7) the two effects are alike. The fit is that of the same data
    in units 1e20 times larger: k and its standard error the same to the integration's accuracy."""
    from testmodels import Decay

    times = torch.linspace(0, 5, 20, dtype=DT)
    noise = 1e-3 * torch.randn(20, generator=torch.Generator().manual_seed(1), dtype=DT)
    fits = [torchql.fit(Decay(1.0), torchql.Observations(times, (s * torch.exp(-0.7 * times) * (1 + noise))[:, None],
                                                         observe=["y"]), torch.tensor([2 * s], dtype=DT))
            for s in (1.0, 1e-20)]
    assert all(f.status is Status.CONVERGED for f in fits), [f.message for f in fits]
    assert fits[1].stderr["k"] == pytest.approx(fits[0].stderr["k"], rel=1e-5)
    assert fits[1].stderr["y(t0)"] == pytest.approx(1e-20 * fits[0].stderr["y(t0)"], rel=1e-5)


def test_an_unconverged_fit_that_misses_the_data_by_orders_of_magnitude_diverged():
    """A fit ending MAX_ITER or STALLED whose sum of squares exceeds SSE_GROWTH times the data's own
    (a model predicting zero) diverged, whatever its Jacobian's rank: an undamped fit from a guess
    whose model blows up ended at 3.8e72 with data of order 1, and was called NOT_IDENTIFIABLE. At
    the factor itself, or for a converged fit, the status stands."""
    common = dict(rank_deficient=True, null_text=NULL, estimates=torch.ones(2, dtype=DT), scale=SCALE,
                  unknown_names=NAMES, sse_start=None)
    far = final_status(Status.MAX_ITER, sse=2 * SSE_GROWTH * 5.0, sse_data=5.0, **common)
    assert far[0] is Status.DIVERGED and "misses the data by orders of magnitude" in far[1]
    assert final_status(Status.STALLED, sse=SSE_GROWTH * 5.0, sse_data=5.0, **common)[0] is Status.NOT_IDENTIFIABLE
    assert final_status(Status.CONVERGED, sse=2 * SSE_GROWTH * 5.0, sse_data=5.0, **common)[0] is \
        Status.NOT_IDENTIFIABLE


def test_rounding_spread_is_the_largest_value_change_of_rounding_the_estimates():
    """``eps sum_j |J_ij| |u_j|``, the largest over the rows; zero estimates contribute nothing."""
    from torchql.diagnosis import rounding_spread

    J = torch.tensor([[1.0, 2.0], [-3.0, 4.0]], dtype=torch.float64)
    u = torch.tensor([2.0, -0.5], dtype=torch.float64)
    eps = torch.finfo(torch.float64).eps
    assert float(rounding_spread(J, u)) == pytest.approx(eps * (3.0 * 2.0 + 4.0 * 0.5), rel=1e-15)
    assert float(rounding_spread(J, torch.zeros(2, dtype=torch.float64))) == 0.0


def test_a_rounding_spread_above_the_data_makes_any_status_diverged():
    """Above the data's root mean square the fit diverged, converged or stalled, rank deficient or not;
    below it (or with data all zero, which have no magnitude to compare) the other rules decide."""
    common = dict(null_text=" {a}.", estimates=torch.ones(2, dtype=torch.float64),
                  scale=torch.ones(2, dtype=torch.float64), unknown_names=["a", "b"], sse=1.0, sse_start=2.0,
                  sse_data=4.0, n_values=4)
    for status in (Status.CONVERGED, Status.STALLED):
        for deficient in (False, True):
            code, text = final_status(status, rank_deficient=deficient, rounding=1.5, **common)
            assert code is Status.DIVERGED and "root mean square (1)" in text
    assert final_status(Status.CONVERGED, rank_deficient=False, rounding=0.5, **common)[0] is Status.CONVERGED
    common["sse_data"] = 0.0
    assert final_status(Status.CONVERGED, rank_deficient=False, rounding=1.5, **common)[0] is Status.CONVERGED
