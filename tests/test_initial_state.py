"""Initial states given as expressions of the other values (``x0_expr``): S(t0) = N - I(t0).

SIR in a closed population N = 763 with I(t0) = 3 unknown, so S(t0) = 760 follows it: exact data of I
give the truth to 1e-8, where holding S(t0) at a guessed 762 cannot fit them. The homogeneous
solutions start from ``dz0/du`` (the expressions' derivatives included): the fit's Jacobian equals
finite differences of the model's own residuals, for a linear and for a nonlinear expression.
"""

import pytest
import torch

import torchql
from testmodels import SIR
from torchql import Parameter

DT = torch.float64
T = torch.arange(14, dtype=DT)
SUSCEPTIBLE = {"S": lambda v: v["N"] - v["I"]}
GUESS_X0 = torch.tensor([0.0, 1.0, 0.0], dtype=DT)  # S's entry is ignored: its expression gives it


def _data(x0, noise=0.0, seed=0):
    x = torchql.simulate(SIR(), torch.tensor(x0, dtype=DT), T, rtol=1e-12, atol=1e-12)
    y = x[:, 1:2] * (1 + noise * torch.randn(14, 1, dtype=DT, generator=torch.Generator().manual_seed(seed)))
    return torchql.Observations(T, y, observe=["I"])


@pytest.fixture(scope="module")
def exact():
    return _data([760.0, 3.0, 0.0])


@pytest.mark.parametrize("method", torchql.METHODS)
def test_susceptibles_follow_the_infected_and_the_truth_is_recovered(exact, method):
    r = torchql.fit(SIR(2.0, 0.3), exact, GUESS_X0, fixed_x0=["R"], x0_expr=SUSCEPTIBLE, method=method)
    assert r.success, r.message
    assert r.unknown_names == ["I(t0)", "beta", "gamma"]
    assert torch.allclose(r.estimates, torch.tensor([3.0, 1.66, 0.44], dtype=DT), rtol=1e-8, atol=0)
    assert r.x0[0].item() == pytest.approx(763.0 - r.x0[1].item(), rel=1e-15)
    held = torchql.fit(SIR(2.0, 0.3), exact, torch.tensor([762.0, 1.0, 0.0], dtype=DT), fixed_x0=["S", "R"])
    assert held.sse > 1e6 * max(r.sse, 1e-20)  # S(t0) guessed and held: the exact data are not met


def _numeric_jacobian(result, data, x0_of, h=1e-6):
    """Finite differences of the weighted residuals y - h(x(t)) of the model from the estimates."""
    base = result.estimates.clone()
    columns = []
    for j in range(base.numel()):
        ends = []
        for sign in (1.0, -1.0):
            u = base.clone()
            u[j] += sign * h * max(1.0, abs(float(u[j])))
            model, x0 = x0_of(u)
            x = torchql.simulate(model, x0, data.t, rtol=1e-12, atol=1e-12)
            ends.append(x[:, 1])
        columns.append((ends[0] - ends[1]) / (2 * h * max(1.0, abs(float(base[j])))))
    return torch.stack(columns, dim=1)


@pytest.mark.parametrize("expressions, fixed, states", [
    (SUSCEPTIBLE, ["R"], lambda i0: [763.0 - i0, i0, 0.0]),
    # in order: R from I, then S from I and R
    ({"R": lambda v: 0.1 * v["I"] ** 2, "S": lambda v: v["N"] - v["I"] - v["R"]}, [],
     lambda i0: [763.0 - i0 - 0.1 * i0 ** 2, i0, 0.1 * i0 ** 2]),
], ids=["linear", "nonlinear"])
def test_jacobian_includes_the_expressions_derivatives(expressions, fixed, states):
    """The fit's Jacobian (columns of dh/du, from the homogeneous solutions) equals finite differences
    of the model simulated from the expressions' initial states, to 1e-6 relative."""
    data = _data(states(3.0), noise=0.02)
    r = torchql.fit(SIR(2.0, 0.3), data, GUESS_X0, fixed_x0=fixed, x0_expr=expressions)
    assert r.success, r.message
    assert r.unknown_names == ["I(t0)", "beta", "gamma"]

    def x0_of(u):
        return SIR(float(u[1]), float(u[2])), torch.tensor(states(float(u[0])), dtype=DT)

    numeric = _numeric_jacobian(r, data, x0_of)
    assert torch.allclose(r.jacobian, numeric, rtol=1e-6, atol=1e-6 * numeric.abs().max())


def test_fit_many_equals_fit_per_sample():
    batch = torchql.Observations(T, torch.stack([_data([760.0, 3.0, 0.0], 0.02, s).y for s in range(2)]),
                                 observe=["I"])
    many = torchql.fit_many(SIR(2.0, 0.3), batch, GUESS_X0, fixed_x0=["R"], x0_expr=SUSCEPTIBLE)
    for i in range(2):
        one = torchql.fit(SIR(2.0, 0.3), batch[i], GUESS_X0, fixed_x0=["R"], x0_expr=SUSCEPTIBLE)
        assert many[i].iterations == one.iterations
        assert torch.allclose(many[i].estimates, one.estimates, rtol=1e-9, atol=0)
        assert torch.allclose(many[i].x0, one.x0, rtol=1e-12, atol=0)


def test_several_experiments_each_follow_their_own_values():
    """Two outbreaks of one disease in the same population, I(t0) = 3 and 8: S(t0) = N - I(t0) in each."""
    data = [_data([760.0, 3.0, 0.0]), _data([755.0, 8.0, 0.0])]
    x0 = torch.stack([GUESS_X0, GUESS_X0])
    r = torchql.fit(SIR(2.0, 0.3), data, x0, fixed_x0=["R"], x0_expr=SUSCEPTIBLE)
    assert r.success, r.message
    assert torch.allclose(r.x0, torch.tensor([[760.0, 3.0, 0.0], [755.0, 8.0, 0.0]], dtype=DT), rtol=1e-8)
    assert r.params["beta"].item() == pytest.approx(1.66, rel=1e-8)


def test_parameter_expr_and_profile(exact):
    spec = {"S": Parameter(expr=SUSCEPTIBLE["S"]), "I": Parameter(1.0, min=0.0), "R": Parameter(0.0, vary=False),
            "beta": Parameter(2.0, scale="log"), "gamma": 0.3}
    r = torchql.fit(SIR(), exact, parameters=spec)
    keywords = torchql.fit(SIR(2.0, 0.3), exact, torch.tensor([0.0, 1.0, 0.0], dtype=DT), fixed_x0=["R"],
                           x0_expr=SUSCEPTIBLE, bounds={"I": (0.0, None)}, scale={"beta": "log"})
    assert r.success and torch.equal(r.estimates, keywords.estimates)
    profile = torchql.profile(r, "I(t0)")  # the re-fits keep the expression
    assert profile.interval[0] <= 3.0 <= profile.interval[1]


def _raises(message):
    def expression(v):
        raise RuntimeError(message)
    return expression


@pytest.mark.parametrize("kwargs, error, match", [
    (dict(x0_expr={"Q": lambda v: v["N"]}), ValueError, r"`x0_expr` names unknown state 'Q'"),
    (dict(x0_expr={"S": 760.0}), TypeError, r"`x0_expr\['S'\]` must be callable"),
    (dict(x0_expr=["S"]), TypeError, r"`x0_expr` must be a dict"),
    (dict(x0_expr=SUSCEPTIBLE, fixed_x0=["S", "R"]), ValueError, r"`fixed_x0` fixes it too"),
    (dict(x0_expr={"S": lambda v: torch.ones(2, dtype=DT)}), ValueError, r"must return a scalar; received shape \(2,\)"),
    (dict(x0_expr={"S": lambda v: v["N"] * float("nan")}), ValueError, r"`x0_expr\['S'\]` is nan at the guesses"),
    (dict(x0_expr={"S": _raises("no")}), ValueError, r"`x0_expr\['S'\]` failed on the guesses: RuntimeError: no"),
    (dict(x0_expr={"S": lambda v: "x"}), TypeError, r"must return a scalar tensor; received str"),
    (dict(x0_expr=SUSCEPTIBLE, bounds={"S": (0.0, None)}), ValueError, r"`bounds` names 'S', which is not estimated"),
    (dict(parameters={"beta": Parameter(expr=lambda v: v["gamma"])}), ValueError, r"which applies to initial states"),
    (dict(x0_expr=SUSCEPTIBLE, parameters={"S": Parameter(expr=lambda v: v["N"])}), ValueError,
     r"gives an expression that `x0_expr` gives too"),
    # an expression reading a state that it or a later one sets would read that state's guess at every
    # iterate (a cycle S = N - I, I = N - S held I at its guess), and its derivative would miss the chain
    (dict(x0_expr={"S": lambda v: v["N"] - v["I"], "I": lambda v: v["N"] - v["S"]}, fixed_x0=["R"]), ValueError,
     r"`x0_expr\['S'\]` reads 'I', which `x0_expr` sets after it"),
    (dict(x0_expr={"S": lambda v: v["N"] - v["S"]}), ValueError, r"`x0_expr\['S'\]` reads 'S', which `x0_expr` sets by "
     r"this same expression"),
])
def test_bad_expressions_are_named(exact, kwargs, error, match):
    with pytest.raises(error, match=match):
        torchql.fit(SIR(2.0, 0.3), exact, GUESS_X0, **kwargs)


def test_an_expression_read_before_it_is_set_is_named_in_every_experiment():
    """With several experiments each expression sees its experiment's states by their own names: one
    that reads a state set after it is named as in a single fit."""
    data = [_data([760.0, 3.0, 0.0]), _data([755.0, 8.0, 0.0])]
    backwards = {"S": lambda v: v["N"] - v["I"] - v["R"], "R": lambda v: torch.zeros_like(v["N"])}
    with pytest.raises(ValueError, match=r"`x0_expr\['S\[0\]'\]` reads 'R\[0\]', which `x0_expr` sets after it"):
        torchql.fit(SIR(2.0, 0.3), data, torch.stack([GUESS_X0, GUESS_X0]), x0_expr=backwards)
    forwards = {"R": lambda v: torch.zeros_like(v["N"]), "S": lambda v: v["N"] - v["I"] - v["R"]}
    assert torchql.fit(SIR(2.0, 0.3), data, torch.stack([GUESS_X0, GUESS_X0]), x0_expr=forwards).success


def test_no_x0_is_needed_when_expressions_give_every_state(exact):
    """Every initial state an expression of coefficients (here of N and an I0 coefficient): ``x0`` may be
    left out, for one experiment and for several, and the fit is the one with a placeholder ``x0``."""

    class SeededSIR(SIR):
        def __init__(self, *args, I0=1.0, **kwargs):
            super().__init__(*args, **kwargs)
            self.register_buffer("I0", torch.tensor(float(I0), dtype=DT))

    every = {"S": lambda v: v["N"] - v["I0"], "I": lambda v: v["I0"], "R": lambda v: torch.zeros_like(v["I0"])}
    params = ["beta", "gamma", "I0"]
    without = torchql.fit(SeededSIR(2.0, 0.3), exact, x0_expr=every, params=params, t0=-1.0)
    placeholder = torchql.fit(SeededSIR(2.0, 0.3), exact, torch.zeros(3, dtype=DT), x0_expr=every, params=params,
                              t0=-1.0)
    assert without.success, without.message
    assert torch.equal(without.estimates, placeholder.estimates)
    several = torchql.fit(SeededSIR(2.0, 0.3), [exact, exact], x0_expr=every, params=params, t0=-1.0)
    assert several.success, several.message
    torch.testing.assert_close(several.estimates, without.estimates, rtol=1e-7, atol=0)
