"""Boehm_JProteomeRes2014 as one torchql fit: six rate constants and the three observables' noise
sigmas (``sigma="estimate"``, one per observable, by maximum likelihood), the model stiff (the solver
``"auto"`` detects it and integrates by Rodas5P), the initial state known (the fixed ``ratio``), the
observables rational functions of the states, every rate bounded to ``[1e-5, 1e5]`` as the PEtab
table bounds it.

The fit's negative log-likelihood ``result.nll`` is PEtab's, at the sigmas' maximum-likelihood values.
The problem as built here gives the reference likelihood at the nominal parameters
(``tests/experiments/test_petab_fit.py``). The fit shoots, its sensitivities integrated with each
solution (``linear_solver="rodas5p"``, :mod:`torchql.solvers.sensitivity`): an iteration takes 5 to
10 s on one thread. The sigmas are unknowns of the fit with the rates
(:mod:`torchql.estimated_noise`). From the nominal values perturbed by 1.2 (seed 0 of
``experiments/petab_fit.py``'s ``perturbed``), with torchql's defaults, it converges in 19
iterations (162 s) to NLL 138.221980 against the reference 138.221997;
``python experiments/petab_fit.py --problem Boehm`` runs such starts::

    from experiments.petab import PROBLEMS, load_problem, nominal_values
    from experiments.petab.boehm_fit import fit_boehm
    problem = load_problem(PROBLEMS["Boehm_JProteomeRes2014"])
    fit_boehm(problem, nominal_values(problem), max_time=3600)
"""

from __future__ import annotations

from collections.abc import Mapping

import torch

import torchql

from .boehm import BoehmSTAT5, initial_state, p_stat5a_rel, p_stat5b_rel, r_stat5a_rel
from .problem import DTYPE, PetabProblem, condition_symbols

__all__ = ["boehm_experiment", "fit_boehm"]

RATES = ("Epo_degradation_BaF3", "k_exp_hetero", "k_exp_homo", "k_imp_hetero", "k_imp_homo", "k_phos")
_OBSERVABLES = {"pSTAT5A_rel": p_stat5a_rel, "pSTAT5B_rel": p_stat5b_rel, "rSTAT5A_rel": r_stat5a_rel}


def boehm_experiment(problem: PetabProblem, values: Mapping[str, float]):
    """``(model, data, x0)`` at the parameter ``values`` (linear scale; the rates are the guesses)."""
    (condition,) = problem.conditions
    symbols = {k: torch.tensor(v, dtype=DTYPE) for k, v in condition_symbols(problem, condition, values).items()}
    model = BoehmSTAT5(**{name: float(symbols[name]) for name, _ in BoehmSTAT5().named_buffers()})
    names = BoehmSTAT5.state_names
    observables = list(_OBSERVABLES)
    times = sorted({m.time for m in problem.measurements})
    y = torch.full((len(times), len(observables)), float("nan"), dtype=DTYPE)
    for m in problem.measurements:
        y[times.index(m.time), observables.index(m.observable)] = m.value

    def observe(x: torch.Tensor) -> torch.Tensor:
        states = dict(zip(names, x.unbind(-1)))
        return torch.stack([f(states, symbols, ()) for f in _OBSERVABLES.values()], dim=-1)

    data = torchql.Observations(torch.tensor(times, dtype=DTYPE), y, observe=observe, sigma="estimate")
    return model, data, initial_state(symbols).to(DTYPE)


def fit_boehm(problem: PetabProblem, values: Mapping[str, float], scale: str = "lin",
              **options) -> torchql.FitResult:
    """Fit Boehm's rates and noise sigmas from the guesses ``values`` (linear scale), by shooting with
    ``linear_solver="rodas5p"`` and the problem's integration tolerances unless ``options`` say
    otherwise (other ``options`` go to :func:`torchql.fit`). ``scale="log10"`` iterates the rates on
    the log scale, as the PEtab table estimates them (the sigmas always are)."""
    model, data, x0 = boehm_experiment(problem, values)
    # shooting with the sensitivities integrated with each solution (linear_solver="rodas5p"): the
    # stiff grid's Radau transfers need many substeps on this model's intermediate stiffness
    options.setdefault("method", "shooting")
    options.setdefault("linear_solver", "rodas5p")
    options.setdefault("rtol", problem.spec.rtol)
    options.setdefault("atol", problem.spec.atol)
    bounds = {name: (problem.parameters[name].lower, problem.parameters[name].upper) for name in RATES}
    if scale != "lin":
        options["scale"] = {name: scale for name in RATES}
    return torchql.fit(model, data, x0=x0, params=list(RATES), fixed_x0=list(BoehmSTAT5.state_names), bounds=bounds,
                       **options)
