"""The three PEtab benchmark problems written by hand in ``experiments/petab/`` reproduce the
problems' own formulas and their reference likelihood.

* The negative log-likelihood at the nominal parameters (the published best fits) equals
  ``reference.nllh`` of each problem's JSON to 1e-3 absolute, the tolerance of AMICI's benchmark
  tests. Each problem is simulated with its spec's settings, ``rtol = 1e-8``, ``atol = 1e-10``
  (Boehm: ``rodas5p``, stiff; Bruno, Fiedler: ``dopri5``). Measured: these settings are within 2e-7 of
  the values converged at ``rtol = 1e-12``, and those differ from the references by 8e-7 (Boehm),
  4e-6 (Bruno) and 3e-5 (Fiedler, as scipy's LSODA at 1e-10 also finds: the reference's own
  integration error), so the test passes with a margin of more than 30x. Loosening to ``rtol = 1e-5``
  would still stay within 1e-4. About 1.5 s in all.
* The hand-written right-hand sides, initial states, observables and noise formulas equal the JSON's
  expressions (evaluated by a restricted evaluator: arithmetic, ``exp`` and ``sqrt`` on torch
  tensors, nothing else) at random states, in every condition, to rounding.

The problems live in ``../shared/petab`` beside the repository; without it these tests skip.
"""

from __future__ import annotations

import ast
import math
import re
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[2]
PETAB = ROOT / ".." / "shared" / "petab"
if not PETAB.is_dir():
    pytest.skip(f"the PEtab problems are not there ({PETAB.resolve()}: expected ../shared/petab beside the "
                "repository)", allow_module_level=True)
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from experiments.petab import (PROBLEMS, condition_symbols, load_problem, negative_log_likelihood,  # noqa: E402
                               nominal_values, row_terms, setup_condition, values_from_scaled)

DT = torch.float64
NAMES = sorted(PROBLEMS)


@pytest.fixture(scope="module", params=NAMES)
def problem(request):
    return load_problem(PROBLEMS[request.param], PETAB)


# --- a restricted evaluator of the JSON's expressions (arithmetic, exp, sqrt) --------------------------------
_NODES = (ast.Expression, ast.BinOp, ast.UnaryOp, ast.Name, ast.Load, ast.Constant, ast.Call, ast.Add, ast.Sub,
          ast.Mult, ast.Div, ast.Pow, ast.USub, ast.UAdd)
_FUNCTIONS = {"exp": torch.exp, "sqrt": torch.sqrt}


def evaluate(expression: str, names: dict[str, torch.Tensor]) -> torch.Tensor:
    """The value of ``expression`` with ``names`` bound; anything beyond arithmetic on names and numbers and
    calls of ``exp``/``sqrt`` is refused."""
    tree = ast.parse(expression, mode="eval")
    for node in ast.walk(tree):
        if not isinstance(node, _NODES):
            raise ValueError(f"{type(node).__name__} is not allowed in {expression!r}")
        if isinstance(node, ast.Constant) and type(node.value) not in (int, float):
            raise ValueError(f"constant {node.value!r} is not a number in {expression!r}")
        if isinstance(node, ast.Call) and (node.keywords or not isinstance(node.func, ast.Name)
                                           or node.func.id not in _FUNCTIONS):
            raise ValueError(f"only exp(x) and sqrt(x) may be called in {expression!r}")
        if isinstance(node, ast.Name) and node.id not in names and node.id not in _FUNCTIONS:
            raise KeyError(f"{node.id!r} of {expression!r} has no value")
    return torch.as_tensor(eval(compile(tree, "<petab>", "eval"), {"__builtins__": {}}, {**_FUNCTIONS, **names}),
                           dtype=DT)


def test_evaluator_refuses_anything_but_arithmetic():
    x = {"x": torch.tensor(2.0, dtype=DT)}
    assert float(evaluate("sqrt(x)*exp(-x/2) + x**2 - 1", x)) == pytest.approx(math.sqrt(2) * math.exp(-1) + 3)
    for bad in ("__import__('os')", "x.real", "[x]", "log(x)", "'a'", "x if x else x"):
        with pytest.raises((ValueError, KeyError)):
            evaluate(bad, x)


# --- the likelihood --------------------------------------------------------------------------------------------
def test_nominal_negative_log_likelihood_matches_reference(problem):
    value = negative_log_likelihood(problem, nominal_values(problem))
    assert math.isfinite(value)
    assert abs(value - problem.reference_nllh) < 1e-3, (problem.name, value, problem.reference_nllh)


def test_row_terms_are_negative_log_densities():
    """The three PEtab v1 formulas against torch's distributions (lin normal, lin Laplace, and the normal
    in log10 m, whose density in m carries the Jacobian ``1 / (m ln 10)``)."""
    g = torch.Generator().manual_seed(0)
    m, y, s = (torch.rand(6, generator=g, dtype=DT) * 2 + 0.1 for _ in range(3))
    torch.testing.assert_close(row_terms(m, y, s, "lin", "normal"),
                               -torch.distributions.Normal(y, s).log_prob(m))
    torch.testing.assert_close(row_terms(m, y, s, "lin", "laplace"),
                               -torch.distributions.Laplace(y, s).log_prob(m))
    torch.testing.assert_close(row_terms(m, y, s, "log10", "normal"),
                               -torch.distributions.Normal(torch.log10(y), s).log_prob(torch.log10(m))
                               + torch.log(m * math.log(10)))
    with pytest.raises(ValueError, match="laplace"):
        row_terms(m, y, s, "log10", "laplace")


def test_parameter_scales_and_condition_precedence():
    """A condition's override beats the parameter table, which beats the SBML model's value."""
    bruno = load_problem(PROBLEMS["Bruno_JExpBot2016"], PETAB)
    scaled = [bruno.parameters[n].to_scale(bruno.parameters[n].nominal) for n in bruno.estimated]
    values = values_from_scaled(bruno, scaled)
    assert values == pytest.approx(nominal_values(bruno), rel=1e-14)
    assert all(bruno.parameters[n].scale == "log10" for n in bruno.estimated)
    s3 = condition_symbols(bruno, "model1_data3", values)
    assert s3["kb1_multiplier"] == pytest.approx(values["szea"]) and s3["init_bcar"] == pytest.approx(3.30171980495163)
    assert s3["init_b10"] == 0.0
    with pytest.raises(ValueError, match="one entry per estimated parameter"):
        values_from_scaled(bruno, scaled[:-1])
    boehm = load_problem(PROBLEMS["Boehm_JProteomeRes2014"], PETAB)
    s = condition_symbols(boehm, "model1_data1", nominal_values(boehm))
    assert s["k_imp_homo"] == boehm.parameters["k_imp_homo"].nominal != boehm.model_symbols["k_imp_homo"]
    assert s["nuc"] == boehm.model_symbols["nuc"] == 0.45


# --- the hand-written formulas against the JSON's ------------------------------------------------------------
def _setups(problem):
    values = nominal_values(problem)
    return [setup_condition(problem, c, values) for c in problem.conditions]


def _random_states(problem, setup, g, k=5):
    scale = max(float(setup.x0.abs().max()), 1.0)
    return torch.rand(k, len(problem.spec.model.state_names), generator=g, dtype=DT) * scale + 1e-3


def test_right_hand_side_matches_json(problem):
    g = torch.Generator().manual_seed(1)
    states = problem.spec.model.state_names
    for setup in _setups(problem):
        x, t = _random_states(problem, setup, g), torch.rand(5, generator=g, dtype=DT) * 10
        mine = setup.model(t, x)
        names = {**setup.symbols, **dict(zip(states, x.unbind(-1))), "t": t}
        json_rhs = torch.stack([evaluate(problem.raw["ode_rhs"][s], names).expand(5) for s in states], dim=-1)
        torch.testing.assert_close(mine, json_rhs, rtol=1e-10, atol=1e-12 * float(mine.abs().max()))


def test_initial_state_matches_json(problem):
    states = problem.spec.model.state_names
    for setup in _setups(problem):
        json_x0 = torch.stack([evaluate(problem.raw["initial_state"][s], setup.symbols) for s in states])
        torch.testing.assert_close(setup.x0, json_x0, rtol=1e-9, atol=1e-14)


def _placeholder_values(expression, obs_id, kind, g):
    """Random positive values for the placeholders ``<kind>Parameter{i}_<obs_id>`` of ``expression``."""
    found = re.findall(rf"\b{kind}Parameter(\d+)_{obs_id}\b", expression)
    count = max((int(i) for i in found), default=0)
    return [torch.rand(5, generator=g, dtype=DT) + 0.5 for _ in range(count)]


def test_observables_and_noise_match_json(problem):
    g = torch.Generator().manual_seed(2)
    states = problem.spec.model.state_names
    for setup in _setups(problem):
        x = dict(zip(states, _random_states(problem, setup, g).unbind(-1)))
        for obs_id, observable in problem.observables.items():
            for kind, text, mine in (("observable", observable.formula, problem.spec.observables[obs_id]),
                                     ("noise", observable.noise_formula, problem.spec.noise[obs_id])):
                p = _placeholder_values(text, obs_id, kind, g)
                names = {**setup.symbols, **x, **{f"{kind}Parameter{i + 1}_{obs_id}": v for i, v in enumerate(p)}}
                torch.testing.assert_close(mine(x, setup.symbols, p).expand(5), evaluate(text, names).expand(5),
                                           rtol=1e-12, atol=0.0, msg=f"{problem.name} {obs_id} {kind}")


# --- the script's scipy column and stiffness measure (cheap parts, on Bruno) ---------------------------------
def _script():
    import importlib.util

    pytest.importorskip("scipy")
    spec = importlib.util.spec_from_file_location("petab_nllh", ROOT / "experiments" / "petab_nllh.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_script_scipy_column_and_stiffness():
    script = _script()
    bruno = load_problem(PROBLEMS["Bruno_JExpBot2016"], PETAB)
    values = nominal_values(bruno)
    scipy_value = negative_log_likelihood(bruno, values, script.scipy_simulator("RK45", 1e-8, 1e-10))
    assert abs(scipy_value - bruno.reference_nllh) < 1e-3
    ratio, where = script.stiffness(bruno, points=41)
    assert 1.0 < ratio < 10.0 and "model1_data" in where  # first-order rates ~1e-2 /min over 180 min: not stiff
    text = script.report([dict(name="P", reference=1.0, torchql=1.0 + 2e-3, solver="dopri5", seconds=0.1, scipy=1.0,
                               scipy_method="RK45", scipy_seconds=0.1, stiffness=3.0, where="c", data=2, conditions=1)])
    assert "| P | 1 | 2 | 1.000000 | 1.002000 | 2.0e-03 | dopri5 |" in text and "Further than 1e-3" in text
