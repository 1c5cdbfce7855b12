"""Reading a flattened PEtab problem (``<name>.json``) and building each condition's simulation.

The JSON holds the PEtab tables (parameters, conditions, observables, measurements) beside the SBML
model's formulas as text; here only the tables are read. The formulas come from the problem's
hand-written :class:`~.spec.ProblemSpec`, and :func:`load_problem` checks that the two agree on the
states, the model symbols and the observables.

Values of the PEtab parameters travel as a ``dict`` ``name -> float`` on the linear scale
(:func:`nominal_values`, :func:`values_from_scaled`). A model symbol's value in a condition is, in
PEtab v1's order of precedence: the condition's override (a number or a parameter id), else the
parameter of that name, else the SBML model's value (:func:`condition_symbols`).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import torch

import torchql

from .spec import ProblemSpec

__all__ = ["PETAB_DIR", "Parameter", "Observable", "Measurement", "PetabProblem", "ConditionSetup", "load_problem",
           "nominal_values", "values_from_scaled", "resolve_entry", "condition_symbols", "setup_condition"]

#: The shared folder of PEtab problems, beside the repository (``../shared/petab``).
PETAB_DIR = Path(__file__).resolve().parents[2] / ".." / "shared" / "petab"
DTYPE = torch.float64
_SCALES = {"lin": (lambda v: v, lambda v: v), "log10": (lambda v: 10.0 ** v, math.log10),
           "log": (math.exp, math.log)}


@dataclass(frozen=True)
class Parameter:
    """A row of the PEtab parameter table. ``lower``, ``upper`` and ``nominal`` are on the linear scale;
    ``scale`` (``"lin"``, ``"log10"`` or ``"log"``) is the scale an optimizer works on."""

    name: str
    scale: str
    lower: float
    upper: float
    nominal: float
    estimate: bool

    def to_linear(self, value: float) -> float:
        """A value on this parameter's scale, mapped to the linear scale."""
        return _SCALES[self.scale][0](value)

    def to_scale(self, value: float) -> float:
        """A linear value, mapped to this parameter's scale."""
        return _SCALES[self.scale][1](value)


@dataclass(frozen=True)
class Observable:
    """A row of the PEtab observable table: the formulas as text (the code uses the spec's functions),
    ``transformation`` (``"lin"`` or ``"log10"``) and ``distribution`` (``"normal"`` or ``"laplace"``)."""

    formula: str
    noise_formula: str
    transformation: str
    distribution: str


@dataclass(frozen=True)
class Measurement:
    """A row of the PEtab measurement table. ``observable_parameters`` and ``noise_parameters`` give, in
    order, the values of the observable's placeholders ``observableParameter{i}`` / ``noiseParameter{i}``
    for this row: numbers, or ids of PEtab parameters."""

    observable: str
    condition: str
    time: float
    value: float
    observable_parameters: tuple[float | str, ...]
    noise_parameters: tuple[float | str, ...]


@dataclass(frozen=True)
class PetabProblem:
    """A PEtab problem: the tables read from its JSON and the hand-written formulas of its spec.

    Attributes
    ----------
    spec : ProblemSpec
        Model, initial state, observable and noise formulas, integrator settings.
    parameters : dict of str to Parameter
        The parameter table, in its order.
    model_symbols : dict of str to float
        The SBML model's parameters and compartment sizes with their values in the model.
    conditions : dict of str to dict
        Per condition id: overrides of model symbols (or of initial states) by a number or a parameter id.
    observables : dict of str to Observable
    measurements : tuple of Measurement
        Every row, in the table's order.
    reference_nllh : float
        The negative log-likelihood at the nominal parameters that the problem's JSON records.
    raw : dict
        The JSON itself (its formulas as text, for checks against the spec).
    """

    spec: ProblemSpec
    parameters: dict[str, Parameter]
    model_symbols: dict[str, float]
    conditions: dict[str, dict[str, float | str]]
    observables: dict[str, Observable]
    measurements: tuple[Measurement, ...]
    reference_nllh: float
    raw: dict = field(repr=False)

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def estimated(self) -> list[str]:
        """Ids of the estimated parameters, in the table's order."""
        return [name for name, p in self.parameters.items() if p.estimate]


@dataclass(frozen=True)
class ConditionSetup:
    """What one condition simulates.

    Attributes
    ----------
    condition : str
    model : torchql.ODEModel
        The spec's model holding the condition's values of the model symbols.
    x0 : Tensor (n_states,)
        Initial state at ``t0``.
    t0 : float
        Start of the experiment (0 in every problem here).
    times : Tensor (T,)
        The condition's distinct measurement times, increasing (replicates share a time).
    rows : list of int
        Indices into ``problem.measurements`` of the condition's rows.
    time_index : Tensor (len(rows),) of int64
        For each of ``rows``, the index of its time in ``times``.
    symbols : dict of str to Tensor ()
        Values of every model symbol and every PEtab parameter in this condition (linear scale).
    """

    condition: str
    model: torchql.ODEModel
    x0: torch.Tensor
    t0: float
    times: torch.Tensor
    rows: list[int]
    time_index: torch.Tensor
    symbols: dict[str, torch.Tensor]


def load_problem(spec: ProblemSpec, directory: str | Path | None = None) -> PetabProblem:
    """Read ``<directory>/<spec.name>.json`` (default :data:`PETAB_DIR`) and check it against ``spec``.

    Raises
    ------
    FileNotFoundError
        The JSON is not there.
    ValueError
        The JSON's states, model symbols or observables differ from the spec's.
    """
    path = Path(PETAB_DIR if directory is None else directory) / f"{spec.name}.json"
    raw = json.loads(path.read_text())
    if tuple(raw["states"]) != spec.model.state_names:
        raise ValueError(f"{spec.name}: the JSON's states {raw['states']} differ from "
                         f"`{spec.model.__name__}.state_names` {spec.model.state_names}")
    if set(raw["observables"]) != set(spec.observables) or set(spec.noise) != set(spec.observables):
        raise ValueError(f"{spec.name}: the JSON's observables {sorted(raw['observables'])} differ from the spec's "
                         f"{sorted(spec.observables)} (noise: {sorted(spec.noise)})")
    rhs_symbols = {name for name, _ in spec.model().named_buffers()}
    unknown = rhs_symbols - set(raw["model_symbols"])
    if unknown:
        raise ValueError(f"{spec.name}: the model's buffers {sorted(unknown)} are not model symbols of the JSON")
    return PetabProblem(
        spec=spec,
        parameters={p["name"]: Parameter(p["name"], p["scale"], float(p["lower"]), float(p["upper"]),
                                         float(p["nominal"]), bool(p["estimate"])) for p in raw["params"]},
        model_symbols={k: float(v) for k, v in raw["model_symbols"].items()},
        conditions={k: dict(v) for k, v in raw["conditions"].items()},
        observables={k: Observable(o["formula"], o["noise_formula"], o["transformation"], o["noise_distribution"])
                     for k, o in raw["observables"].items()},
        measurements=tuple(Measurement(m["observable"], m["condition"], float(m["time"]), float(m["value"]),
                                       tuple(m["observable_parameters"]), tuple(m["noise_parameters"]))
                           for m in raw["measurements"]),
        reference_nllh=float(raw["reference"]["nllh"]),
        raw=raw,
    )


def nominal_values(problem: PetabProblem) -> dict[str, float]:
    """Every parameter at its nominal value (the published best fit), linear scale."""
    return {name: p.nominal for name, p in problem.parameters.items()}


def values_from_scaled(problem: PetabProblem, theta: Sequence[float]) -> dict[str, float]:
    """Linear-scale values of every parameter from ``theta``, the estimated ones on their own scales
    (in the order of :attr:`PetabProblem.estimated`); the others at their nominal values."""
    names = problem.estimated
    if len(theta) != len(names):
        raise ValueError(f"`theta` must have one entry per estimated parameter ({len(names)}: {names}); "
                         f"received {len(theta)}")
    values = nominal_values(problem)
    values.update((name, problem.parameters[name].to_linear(float(v))) for name, v in zip(names, theta))
    return values


def resolve_entry(entry: float | str, values: Mapping[str, float]) -> float:
    """The value of a table entry: a number, or the id of a parameter (its value in ``values``)."""
    if isinstance(entry, str):
        if entry not in values:
            raise KeyError(f"{entry!r} is neither a number nor a parameter id")
        return float(values[entry])
    return float(entry)


def condition_symbols(problem: PetabProblem, condition: str, values: Mapping[str, float]) -> dict[str, float]:
    """Values in ``condition`` of every model symbol, then of every parameter not a model symbol."""
    overrides = problem.conditions[condition]
    out = {}
    for name, default in problem.model_symbols.items():
        if name in overrides:
            out[name] = resolve_entry(overrides[name], values)
        else:
            out[name] = float(values.get(name, default))
    out.update((name, float(v)) for name, v in values.items() if name not in out)
    return out


def setup_condition(problem: PetabProblem, condition: str, values: Mapping[str, float]) -> ConditionSetup:
    """The model, initial state and measurement times of ``condition`` at the parameter ``values``."""
    symbols = {k: torch.tensor(v, dtype=DTYPE) for k, v in condition_symbols(problem, condition, values).items()}
    spec = problem.spec
    buffers = [name for name, _ in spec.model().named_buffers()]
    model = spec.model(**{name: symbols[name] for name in buffers})
    x0 = spec.initial_state(symbols).to(DTYPE)
    for k, state in enumerate(spec.model.state_names):  # a condition may set an initial state directly
        if state in problem.conditions[condition]:
            x0[k] = resolve_entry(problem.conditions[condition][state], values)
    rows = [i for i, m in enumerate(problem.measurements) if m.condition == condition]
    row_times = torch.tensor([problem.measurements[i].time for i in rows], dtype=DTYPE)
    times, time_index = torch.unique(row_times, sorted=True, return_inverse=True)
    return ConditionSetup(condition, model, x0, 0.0, times, rows, time_index, symbols)
