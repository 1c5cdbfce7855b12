"""Bruno_JExpBot2016 as one torchql fit: six experiments sharing the rates, each with its own substrate
amount (an unknown initial state) and its own rate multipliers (``conditions``: 0, 1 or the unknown
``szea``), every parameter bounded to ``[1e-5, 1000]`` as the PEtab table bounds it (log10 scale there;
torchql iterates a bounded unknown in a logistic variable).

The measured standard deviations are known per row (PEtab ``noiseParameter1``), the noise Gaussian on
the linear scale, so the fit's negative log-likelihood ``result.nll`` is PEtab's::

    from experiments.petab import PROBLEMS, load_problem, nominal_values
    from experiments.petab.bruno_fit import fit_bruno
    problem = load_problem(PROBLEMS["Bruno_JExpBot2016"])
    result = fit_bruno(problem, nominal_values(problem))
    result.nll                                              # -46.6882 (reference -46.688177)
"""

from __future__ import annotations

from collections.abc import Mapping

import torch

import torchql

from .bruno import MULTIPLIERS, RATES, BrunoCarotenoids
from .problem import DTYPE, PetabProblem, resolve_entry

__all__ = ["BrunoWithActivity", "bruno_experiments", "fit_bruno"]

#: The substrate of each condition: the one state whose initial amount is an unknown.
_SUBSTRATE = {"init_b10": "b10", "init_bcar": "bcar", "init_bcry": "bcry", "init_ohb10": "ohb10", "init_zea": "zea"}
_OBSERVED = {"ob10": "b10", "obcar": "bcar", "obcry": "bcry", "obio": "bio", "oohb10": "ohb10", "ozea": "zea"}


class BrunoWithActivity(BrunoCarotenoids):
    """:class:`~.bruno.BrunoCarotenoids` with ``szea``, the enzyme activity of two experiments, as a
    coefficient of its own (the right-hand side reads it through those experiments' multipliers)."""

    def __init__(self, szea: float = 1.0, **rates) -> None:
        super().__init__(**rates)
        self.register_buffer("szea", torch.tensor(float(szea), dtype=DTYPE))


def bruno_experiments(problem: PetabProblem, values: Mapping[str, float]):
    """The fit's ingredients at the parameter ``values`` (linear scale; the estimated ones are the
    guesses): ``(model, datasets, x0 (E, n), fixed_x0 (per experiment), conditions, params, bounds)``."""
    names = BrunoCarotenoids.state_names
    model = BrunoWithActivity(szea=values["szea"], **{k: values[k] for k in RATES})
    datasets, x0, fixed, conditions = [], [], [], []
    for condition, overrides in problem.conditions.items():
        rows = [m for m in problem.measurements if m.condition == condition]
        times = sorted({m.time for m in rows})
        observables = sorted({m.observable for m in rows})
        y = torch.full((len(times), len(observables)), float("nan"), dtype=DTYPE)
        sigma = torch.ones_like(y)
        for m in rows:
            i, k = times.index(m.time), observables.index(m.observable)
            y[i, k] = m.value
            sigma[i, k] = resolve_entry(m.noise_parameters[0], values)
        datasets.append(torchql.Observations(torch.tensor(times, dtype=DTYPE), y,
                                             observe=[_OBSERVED[o] for o in observables], sigma=sigma))
        state = torch.zeros(len(names), dtype=DTYPE)
        unknown = []
        for symbol, state_name in _SUBSTRATE.items():
            entry = overrides[symbol]
            state[names.index(state_name)] = resolve_entry(entry, values)
            if isinstance(entry, str):
                unknown.append(state_name)
        x0.append(state)
        fixed.append([s for s in names if s not in unknown])
        conditions.append({k: overrides[k] if isinstance(overrides[k], str) else float(overrides[k])
                           for k in MULTIPLIERS})
    params = list(RATES) + ["szea"]
    bounds = {name: (problem.parameters[name].lower, problem.parameters[name].upper) for name in params}
    bounds.update({state: (1e-5, 1e3) for state in _SUBSTRATE.values()})
    return model, datasets, torch.stack(x0), fixed, conditions, params, bounds


def fit_bruno(problem: PetabProblem, values: Mapping[str, float], scale: str = "lin", **options) -> torchql.FitResult:
    """Fit Bruno's 13 unknowns from the guesses ``values`` (linear scale), with the PEtab problem's
    integration tolerances unless ``options`` say otherwise (other ``options`` go to :func:`torchql.fit`).
    ``scale="log10"`` iterates every unknown on the log scale, as the PEtab table estimates them (its
    bounds then bound the logarithm)."""
    model, datasets, x0, fixed, conditions, params, bounds = bruno_experiments(problem, values)
    if scale != "lin":
        options["scale"] = {name: scale for name in bounds}
    options.setdefault("rtol", problem.spec.rtol)
    options.setdefault("atol", problem.spec.atol)
    return torchql.fit(model, datasets, x0=x0, t0=0.0, params=params, fixed_x0=fixed, conditions=conditions,
                       bounds=bounds, **options)
