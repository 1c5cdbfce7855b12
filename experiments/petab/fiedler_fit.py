"""Fiedler_BMCSystBiol2016 as one torchql fit: three experiments (control, Sorafenib, UO126) sharing the
cascade's rates, each starting from the unstimulated steady state (an expression of the rates), the
inhibitors' doses constants per experiment (``conditions``).

pMEK and pERK are read on four gels (two dates, two gels each); each gel has its own scaling ``s``
(an unknown), and the noise is proportional to it, ``sigma = s * sigma_<observable>``. Each
experiment's data have four columns, one per observable and date; the column's gel is the
experiment's (gel 1 for the control, gel 2 for the inhibitors), so the model carries four
*slots* (``s_erk_a``, ``s_erk_b``, ``s_mek_a``, ``s_mek_b``: observable, date) that each
experiment's ``conditions`` point at its gels' scalings. The observation ``h(x, p)`` and the noise
``sigma(p)`` read them; the fit maximizes the likelihood (:mod:`torchql.sigma_function`), so its
``result.nll`` is PEtab's::

    from experiments.petab import PROBLEMS, load_problem, nominal_values
    from experiments.petab.fiedler_fit import fit_fiedler
    problem = load_problem(PROBLEMS["Fiedler_BMCSystBiol2016"])
    result = fit_fiedler(problem, nominal_values(problem))
    result.nll                                              # reference -58.583902

The 22 unknowns are those of the PEtab table: 12 rates and constants, 8 gel scalings, 2 noise
levels, iterated on its log10 scale within its bounds.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch

import torchql

from .fiedler import FiedlerMAPK, steady_state
from .problem import DTYPE, PetabProblem

__all__ = ["FiedlerWithGels", "fiedler_experiments", "fit_fiedler"]

#: The cascade's estimated coefficients (the rest of the estimated parameters are gels and noise).
RATES = ("K_1", "K_2", "K_3", "k10", "k11", "k2", "k3", "k4", "k5", "k6", "tau1", "tau2")
#: The data columns of every experiment: (observable, date) and the slot that holds its gel's scaling.
COLUMNS = (("pErk", "20140430", "s_erk_a"), ("pErk", "20140505", "s_erk_b"),
           ("pMek", "20140430", "s_mek_a"), ("pMek", "20140505", "s_mek_b"))
_SLOTS = tuple(slot for _, _, slot in COLUMNS)
TOTALS = ("RAF_total", "MEK_total", "ERK_total")


class FiedlerWithGels(FiedlerMAPK):
    """:class:`~.fiedler.FiedlerMAPK` with the observation's coefficients: the eight gels' scalings
    ``s_<observable>_<date>_<gel>``, the noise levels ``sigma_pErk`` and ``sigma_pMek`` (none of which
    the right-hand side reads), and the four column slots, constants set per experiment."""

    constants = FiedlerMAPK.constants + _SLOTS

    def __init__(self, gels: Mapping[str, float], sigma_pErk: float, sigma_pMek: float, **rates) -> None:
        super().__init__(**rates)
        for name, value in {**gels, "sigma_pErk": sigma_pErk, "sigma_pMek": sigma_pMek,
                            **dict.fromkeys(_SLOTS, 1.0)}.items():
            self.register_buffer(name, torch.tensor(float(value), dtype=DTYPE))


def observe(x: torch.Tensor, p: dict) -> torch.Tensor:
    """The four columns: each gel's scaling times pERK or pMEK, ``(4,)``."""
    erk, mek = x[5], x[3]
    return torch.stack((p["s_erk_a"] * erk, p["s_erk_b"] * erk, p["s_mek_a"] * mek, p["s_mek_b"] * mek))


def sigma(p: dict) -> torch.Tensor:
    """The four columns' standard deviations: the gel's scaling times the observable's noise level, ``(4,)``."""
    return torch.stack((p["s_erk_a"] * p["sigma_pErk"], p["s_erk_b"] * p["sigma_pErk"],
                        p["s_mek_a"] * p["sigma_pMek"], p["s_mek_b"] * p["sigma_pMek"]))


def _steady_state_expressions() -> dict:
    """``x0_expr``: every state at the unstimulated steady state of the coefficients (totals 1)."""
    def state(i: int):
        def expression(v: dict) -> torch.Tensor:
            one = torch.ones((), dtype=v["k2"].dtype, device=v["k2"].device)
            return steady_state({**v, **dict.fromkeys(TOTALS, one)})[i]
        return expression
    return {name: state(i) for i, name in enumerate(FiedlerMAPK.state_names)}


def fiedler_experiments(problem: PetabProblem, values: Mapping[str, float]):
    """The fit's ingredients at the parameter ``values`` (linear scale; the estimated ones are the
    guesses): ``(model, datasets, conditions, params, bounds)``."""
    gels = {name: values[name] for name in problem.parameters if name.startswith("s_")}
    model = FiedlerWithGels(gels, values["sigma_pErk"], values["sigma_pMek"], **{k: values[k] for k in RATES})
    datasets, conditions = [], []
    for condition, overrides in problem.conditions.items():
        rows = [m for m in problem.measurements if m.condition == condition]
        times = sorted({m.time for m in rows})
        y = torch.full((len(times), len(COLUMNS)), float("nan"), dtype=DTYPE)
        slots: dict[str, str] = {}
        for m in rows:
            gel = str(m.observable_parameters[0])  # s_<observable>_<date>_<gel>
            k = next(k for k, (obs, date, _) in enumerate(COLUMNS) if obs == m.observable and f"_{date}_" in gel)
            y[times.index(m.time), k] = m.value
            slots[COLUMNS[k][2]] = gel
        datasets.append(torchql.Observations(torch.tensor(times, dtype=DTYPE), y, observe=observe, sigma=sigma))
        conditions.append({**{k: float(v) for k, v in overrides.items()}, **slots})
    params = problem.estimated
    bounds = {name: (problem.parameters[name].lower, problem.parameters[name].upper) for name in params}
    return model, datasets, conditions, params, bounds


def fit_fiedler(problem: PetabProblem, values: Mapping[str, float], scale: str = "log10",
                **options) -> torchql.FitResult:
    """Fit Fiedler's 22 unknowns from the guesses ``values`` (linear scale), on PEtab's log10 scale
    within its bounds (``scale="lin"``: on the linear scale), with the problem's integration
    tolerances unless ``options`` say otherwise (other ``options`` go to :func:`torchql.fit`)."""
    model, datasets, conditions, params, bounds = fiedler_experiments(problem, values)
    if scale != "lin":
        options["scale"] = {name: scale for name in params}
    options.setdefault("rtol", problem.spec.rtol)
    options.setdefault("atol", problem.spec.atol)
    return torchql.fit(model, datasets, t0=0.0, params=params, x0_expr=_steady_state_expressions(),
                       conditions=conditions, bounds=bounds, **options)
