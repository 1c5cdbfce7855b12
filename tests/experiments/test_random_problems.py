"""`experiments/random_problems.py` on a CI-sized subset: its generator draws identifiable problems
that scipy solves to the truth on exact data, torchql never claims a convergence it did not reach,
and torchql reaches the best SSE wherever it does today (the cases where it does not are strict
xfails that name the failure, so they flip when it is fixed).

The subset is the full study's own problems (``--seed 0``): seeds 5-9 are its noise-1e-3 problems,
one per family, and seed 0 its first exact-data problem.
"""

import importlib
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import torchql

pytest.importorskip("scipy")

SCRIPT_DIR = Path(__file__).resolve().parents[2] / "experiments"
#: Per-fit budget here: a fit that reaches the optimum takes a few seconds; a failing one stops early.
MAX_TIME = 20.0
#: Exact data, one problem per family: the study's seeds 0-4, except Lotka-Volterra seed 18 for seed 3,
#: from whose guess scipy integrates ever stiffer trajectories until the study's 120 s budget runs out
#: (a poor start, not a flaw of the problem: torchql fits it).
EXACT = (("linear", 0, 0.0), ("oscillator", 1, 0.0), ("logistic", 2, 0.0), ("lotka_volterra", 18, 0.0),
         ("michaelis_menten", 4, 0.0))
NOISY = (("linear", 5, 1e-3), ("oscillator", 6, 1e-3), ("logistic", 7, 1e-3), ("lotka_volterra", 8, 1e-3),
         ("michaelis_menten", 9, 1e-3))
FITTED = NOISY + EXACT[:1]
#: Cases where torchql does not reach the best SSE today, with how it fails.
FAILING: dict[tuple, str] = {}


def _ids(cases):
    return [f"{family}-{seed}-noise{noise:g}" for family, seed, noise in cases]


@pytest.fixture(scope="module")
def rp():
    """The script, imported by name from experiments/ (as the other experiment tests do)."""
    sys.path.insert(0, str(SCRIPT_DIR))
    try:
        yield importlib.import_module("random_problems")
    finally:
        sys.path.remove(str(SCRIPT_DIR))


_RECORDS: dict[tuple, dict] = {}


def _record(rp, case) -> dict:
    """Both fits of one case, run once per session (two tests read each)."""
    if case not in _RECORDS:
        _RECORDS[case] = rp.run_problem((*case, MAX_TIME))
    return _RECORDS[case]


@pytest.mark.parametrize("case", EXACT + NOISY, ids=_ids(EXACT + NOISY))
def test_generated_problem_is_identifiable_and_its_models_agree(rp, case):
    problem = rp.make_problem(*case)
    rj = problem.residuals_and_jacobian(problem.truth)
    assert rj is not None
    rank, cond = rp.scaled_condition(rj[1])
    assert rank == len(problem.truth) and cond < rp.MAX_COND
    # the torchql model and the numpy right-hand side are one model
    x = torchql_simulate(problem)
    np.testing.assert_allclose(x, problem.trajectory(problem.truth), rtol=0, atol=1e-7 * problem.scale.max())
    # guesses: coefficients within the drawn factors of the truth; observed initial states from the data
    factors = problem.guess_p / problem.truth_p
    assert np.all((factors >= rp.GUESS_LOW) & (factors <= rp.GUESS_HIGH))
    np.testing.assert_array_equal(problem.guess_x0[problem.observed], problem.y[0])
    # the same seed draws the same problem
    again = rp.make_problem(*case)
    np.testing.assert_array_equal(again.y, problem.y)
    np.testing.assert_array_equal(again.guess, problem.guess)


def torchql_simulate(problem):
    import torchql

    model = problem.make_model(problem.truth_p)
    return torchql.simulate(model, torch.tensor(problem.truth_x0), torch.tensor(problem.t)).numpy()


@pytest.mark.parametrize("case", EXACT, ids=_ids(EXACT))
def test_scipy_reaches_the_truth_on_exact_data(rp, case):
    problem = rp.make_problem(*case)
    result = rp.run_scipy(problem, MAX_TIME)
    assert result["success"], result
    np.testing.assert_allclose(result["estimates"], problem.truth, rtol=1e-6, atol=1e-8)
    assert problem.sse(result["estimates"]) <= problem.floor


@pytest.mark.slow
@pytest.mark.parametrize("case", FITTED, ids=_ids(FITTED))
def test_torchql_claims_no_convergence_it_did_not_reach(rp, case):
    record = _record(rp, case)
    tq = record["torchql"]
    assert math.isfinite(record["best"])
    assert tq["reached"] or not tq["success"], (tq["status"], tq["sse_eval"], record["best"])


@pytest.mark.slow
@pytest.mark.parametrize("case", [
    pytest.param(case, marks=pytest.mark.xfail(strict=True, reason=FAILING[case])) if case in FAILING else case
    for case in FITTED], ids=_ids(FITTED))
def test_torchql_reaches_the_best_sse(rp, case):
    record = _record(rp, case)
    tq = record["torchql"]
    assert tq["reached"], (tq["status"], tq["sse_eval"], record["best"], tq["message"])
    assert tq["success"], tq["message"]
    assert record["wrong"] is None, record["wrong"]


def test_lightly_damped_progress_along_a_curved_valley_is_not_taken_for_a_creep(rp):
    """Linear seed 105 (noise 1e-3) crosses a curved valley: every iteration's undamped step is
    rejected and one damped 1e-5 is taken, lowering the sum of squares by about 4e-6 of it. With
    ``ftol=1e-5`` those steps are below ``ftol``, but lightly damped: progress, not a creep (which
    would stop the fit STALLED 1.2e-4 above the optimum). The fit ends as the ``ftol`` test says,
    CONVERGED_SSE (measured: 35 iterations, 1.0e-4 relative above scipy's optimum; the default
    ``ftol`` reaches the optimum in 104)."""
    problem = rp.make_problem("linear", 105, 1e-3)
    result = torchql.fit(problem.make_model(problem.guess_p), problem.data(),
                         x0=torch.tensor(problem.guess_x0, dtype=torch.float64), ftol=1e-5)
    assert result.status is torchql.Status.CONVERGED_SSE, result.message
    assert max(record.damping for record in result.history) <= 1e-3


@pytest.mark.parametrize("option", [["--n", "0"], ["--n", "-3"], ["--workers", "0"]])
def test_counts_below_one_are_refused_by_name(rp, option, capsys):
    """(``--n 0`` once ended in numpy's "argmax of an empty sequence".)"""
    with pytest.raises(SystemExit) as stop:
        rp.main(option)
    assert stop.value.code == 2
    assert f"argument {option[0]}: must be at least 1" in capsys.readouterr().err
