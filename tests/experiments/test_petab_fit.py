"""Bruno_JExpBot2016 (six experiments, per-experiment substrates and rate multipliers, 13 unknowns) fitted
by torchql from a start 20 % off in every parameter returns to the published optimum: its negative
log-likelihood equals the reference to 1e-3 (the tolerance of AMICI's benchmark tests; the fit's own
integration at rtol 1e-8 puts it 4e-6 from the reference, see ``test_petab.py``). ``python
experiments/petab_fit.py`` runs eight such starts (all return). About 20 s with the Boehm check."""

from __future__ import annotations

import pytest
import torch

import torchql
from test_petab import PETAB  # skips this module too without ../shared/petab; puts the repository on the path

from experiments.petab import PROBLEMS, load_problem, nominal_values
from experiments.petab.boehm_fit import boehm_experiment
from experiments.petab.bruno_fit import bruno_experiments, fit_bruno
from experiments.petab.fiedler import steady_state
from experiments.petab.fiedler_fit import TOTALS, fiedler_experiments
from experiments.petab_fit import perturbed
from torchql.model import coefficients
from torchql.multi import check_conditions, with_condition
from torchql.noise import negative_log_likelihood


def test_bruno_returns_to_the_reference_from_a_start_20_percent_off():
    problem = load_problem(PROBLEMS["Bruno_JExpBot2016"], PETAB)
    values = nominal_values(problem)
    start = perturbed(problem, values, seed=0)
    assert all(abs(start[name] / values[name] - 1) > 0.15 for name in problem.estimated)
    result = fit_bruno(problem, start)
    assert result.success, result.message
    assert abs(result.nll - problem.reference_nllh) < 1e-3
    by_name = dict(zip(result.unknown_names, result.estimates.tolist()))
    for name in ("k5", "kb1", "kb2", "kc1", "kc2", "kc4", "szea"):  # near the published values
        assert by_name[name] == pytest.approx(values[name], rel=0.05), name


def test_bruno_problem_has_its_thirteen_unknowns():
    problem = load_problem(PROBLEMS["Bruno_JExpBot2016"], PETAB)
    model, datasets, x0, fixed, conditions, params, bounds = bruno_experiments(problem, nominal_values(problem))
    assert len(datasets) == 6 and x0.shape == (6, 7)
    free = sum(7 - len(f) for f in fixed)
    assert free + len(params) == len(problem.estimated) == 13
    assert sum(int((~torch.isnan(d.y)).sum()) for d in datasets) == len(problem.measurements)


def test_boehm_problem_built_for_torchql_gives_the_reference_likelihood():
    """The data, observables and initial state that ``fit_boehm`` fits, at the nominal parameters and
    the nominal sigmas, give the reference negative log-likelihood (its fit itself, stiff and with
    three sigmas estimated, takes minutes: ``python experiments/petab_fit.py --problem Boehm``)."""
    problem = load_problem(PROBLEMS["Boehm_JProteomeRes2014"], PETAB)
    values = nominal_values(problem)
    model, data, x0 = boehm_experiment(problem, values)
    x = torchql.simulate(model, x0, data.t, solver="rodas5p", rtol=1e-8, atol=1e-10)
    predicted = data.observe(x)
    sigma = torch.tensor([values[f"sd_{name}"] for name in ("pSTAT5A_rel", "pSTAT5B_rel", "rSTAT5A_rel")],
                         dtype=torch.float64).expand_as(data.y)
    present = ~torch.isnan(data.y)
    r = ((data.y - predicted) / sigma)[present]
    nll = negative_log_likelihood((r**2).sum(), torch.log(sigma[present]).sum(), torch.tensor(float(r.numel())))
    assert abs(float(nll) - problem.reference_nllh) < 1e-3
    assert data.sigma_estimated and int(present.sum()) == len(problem.measurements) == 48


def test_fiedler_problem_built_for_torchql_gives_the_reference_likelihood():
    """The data, conditions, observation h(x, p) and noise sigma(p) that ``fit_fiedler`` fits give, at the
    nominal parameters, the reference negative log-likelihood; its 22 unknowns are PEtab's."""
    problem = load_problem(PROBLEMS["Fiedler_BMCSystBiol2016"], PETAB)
    values = nominal_values(problem)
    model, datasets, conditions, params, bounds = fiedler_experiments(problem, values)
    assert sorted(params) == sorted(problem.estimated) and len(params) == 22 == len(bounds)
    assert sum(int((~torch.isnan(d.y)).sum()) for d in datasets) == len(problem.measurements) == 72
    nll = 0.0
    for data, condition in zip(datasets, check_conditions(model, conditions, len(datasets))):
        own = with_condition(model, condition)
        p = coefficients(own)
        x0 = steady_state({**p, **{k: torch.tensor(1.0, dtype=torch.float64) for k in TOTALS}})
        x = torchql.simulate(own, x0, data.t, t0=0.0, rtol=1e-10, atol=1e-12)
        sigma = data.sigma_function(p).expand_as(data.y)
        present = ~torch.isnan(data.y)
        r = ((data.y - torch.stack([data.observe(xi, p) for xi in x])) / sigma)[present]
        nll += float(negative_log_likelihood((r**2).sum(), torch.log(sigma[present]).sum(),
                                             torch.tensor(float(r.numel()))))
    assert abs(nll - problem.reference_nllh) < 1e-3
