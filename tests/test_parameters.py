"""``parameters=``: one lmfit-like specification (value, vary, min, max, scale) per coefficient or state.

SIR with N = 763 known, only I observed, exact data (beta = 1.66, gamma = 0.44, I0 = 1): the
specification gives the same fit as the keywords it stands for (``params``, ``fixed_x0``, ``x0``,
``bounds``, ``scale``), bit for bit, and the truth to 1e-8; the user's model and its values are
left as they were.
"""

import math
import pytest
import torch

import torchql
from testmodels import SIR
from torchql import Parameter

DT = torch.float64
TRUTH = torch.tensor([1.0, 1.66, 0.44], dtype=DT)


@pytest.fixture(scope="module")
def data():
    t = torch.arange(14, dtype=DT)
    # (by dopri5, as written: the exact data's profile intervals are as wide as their generation's
    # error, about 1e-13, and DOP853's, closer, leaves the truth 2e-14 outside one)
    x = torchql.simulate(SIR(), torch.tensor([762.0, 1.0, 0.0], dtype=DT), t, rtol=1e-12, atol=1e-12, solver="dopri5")
    return torchql.Observations(t, x[:, 1:2], observe=["I"])


SPEC = {"beta": Parameter(3.0, min=0.0, scale="log"), "gamma": Parameter(1.0, min=0.0), "N": Parameter(763.0, vary=False),
        "S": Parameter(762.0, vary=False), "I": Parameter(0.5, min=0.0), "R(t0)": Parameter(0.0, vary=False)}


def test_specification_equals_the_keywords_it_stands_for(data):
    model = SIR(beta=9.0, gamma=9.0)
    spec = torchql.fit(model, data, parameters=SPEC)
    keywords = torchql.fit(SIR(3.0, 1.0), data, torch.tensor([762.0, 0.5, 0.0], dtype=DT), fixed_x0=["S", "R"],
                           bounds={"beta": (0.0, None), "gamma": (0.0, None), "I": (0.0, None)},
                           scale={"beta": "log"})
    assert spec.success, spec.message
    assert spec.unknown_names == keywords.unknown_names == ["I(t0)", "beta", "gamma"]
    assert torch.equal(spec.estimates, keywords.estimates) and spec.iterations == keywords.iterations
    assert torch.allclose(spec.estimates, TRUTH, rtol=1e-8, atol=0)
    assert spec.log_scaled == ["beta"] and spec.lower.tolist() == [0.0, 0.0, 0.0]
    assert model.beta.item() == 9.0 and model.gamma.item() == 9.0  # the user's model keeps its values
    assert spec.fit_kwargs["fixed_x0"] == ["S", "R"] and spec.fit_kwargs["scale"] == {"beta": "log"}
    profile = torchql.profile(spec, "gamma")  # a re-fit from the recorded keywords
    assert profile.interval[0] <= 0.44 <= profile.interval[1]


def test_vary_false_holds_a_coefficient_at_its_value_and_numbers_are_guesses(data):
    r = torchql.fit(SIR(), data, parameters={"gamma": Parameter(0.44, vary=False), "beta": 2.5, "S": Parameter(
        762.0, vary=False), "I": 0.7, "R": Parameter(0.0, vary=False)})
    assert r.success, r.message
    assert r.unknown_names == ["I(t0)", "beta"] and r.params["gamma"].item() == 0.44
    assert torch.allclose(r.estimates, TRUTH[:2], rtol=1e-8, atol=0)
    # vary=True estimates a coefficient that the model lists among its constants (beta held: only beta / N
    # is identifiable)
    r = torchql.fit(SIR(), data, torch.tensor([762.0, 1.0, 0.0], dtype=DT), fixed_x0=["S", "R"],
                    parameters={"N": Parameter(700.0, min=1.0), "beta": Parameter(1.66, vary=False)})
    assert r.unknown_names == ["I(t0)", "gamma", "N"] and r.success, r.message
    assert r.params["N"].item() == pytest.approx(763.0, rel=1e-7)


def test_fit_many_takes_the_specification(data):
    batch = torchql.Observations(data.t, torch.stack([data.y, data.y * 1.02]), observe=["I"])
    many = torchql.fit_many(SIR(), batch, parameters=SPEC)
    for i in range(2):
        one = torchql.fit(SIR(), batch[i], parameters=SPEC)
        assert many[i].log_scaled == ["beta"] and many[i].iterations == one.iterations
        assert torch.allclose(many[i].estimates, one.estimates, rtol=1e-9, atol=0)


def test_several_experiments_share_a_state_specification(data):
    """Two experiments: a state's value and role apply to each one (x0 of shape (E, n) built from them)."""
    r = torchql.fit(SIR(), [data, data], parameters=SPEC)
    assert r.success, r.message
    assert r.unknown_names == ["I[0](t0)", "I[1](t0)", "beta", "gamma"]
    assert torch.allclose(r.params["beta"], torch.tensor(1.66, dtype=DT), rtol=1e-8)
    assert torch.allclose(r.x0[:, 1], torch.ones(2, dtype=DT), rtol=1e-8)
    # fit_many with several experiments per sample, and multistart, build x0 (E, n) as fit does
    many = torchql.fit_many(SIR(), [[data, data]], parameters=SPEC)
    assert many.status[0] is r.status and torch.allclose(many.estimates[0], r.estimates, rtol=1e-9, atol=0)
    best = torchql.multistart(SIR(), [data, data], parameters=SPEC, starts=2).best
    assert best.success and torch.allclose(best.params["beta"], torch.tensor(1.66, dtype=DT), rtol=1e-8)


@pytest.mark.parametrize("parameters, kwargs, error, match", [
    ({"bogus": 1.0}, {}, ValueError, r"`parameters` names 'bogus', which is neither a coefficient nor a state"),
    ({"beta": "x"}, {}, TypeError, r"`parameters\['beta'\]` must be a torchql.Parameter or a number"),
    ({"beta": Parameter(1.0, min=0.0)}, dict(bounds={"beta": (0.0, None)}), ValueError,
     r"`parameters\['beta'\]` gives bounds that `bounds` gives too"),
    ({"beta": Parameter(1.0, scale="log")}, dict(scale={"beta": "log"}), ValueError,
     r"`parameters\['beta'\]` gives a scale that `scale` gives too"),
    ({"S": Parameter(700.0)}, {}, ValueError, r"gives the initial values of \['S'\] but not of \['I', 'R'\]"),
    ({"beta": Parameter(float("nan"))}, {}, ValueError, r"`parameters\['beta'\].value` must be finite"),
    ({"beta": Parameter(torch.ones(2))}, {}, ValueError, r"must be a number or of the coefficient's shape \(\)"),
    ([("beta", 1.0)], {}, TypeError, r"`parameters` must be a dict"),
])
def test_bad_specifications_are_named(data, parameters, kwargs, error, match):
    with pytest.raises(error, match=match):
        torchql.fit(SIR(), data, parameters=parameters, **kwargs)


@pytest.mark.parametrize("kwargs, error, match", [
    (dict(scale="ln"), ValueError, r"`Parameter.scale` must be one of \['lin', 'log', 'log10'\]; received 'ln'"),
    (dict(vary=1), TypeError, r"`Parameter.vary` must be True or False"),
    (dict(min="0"), TypeError, r"`Parameter.min` must be a number or None"),
    (dict(min=float("nan")), ValueError, r"`Parameter.min` must be a number \(or None for no bound\), not NaN"),
    (dict(min=2.0, max=1.0), ValueError, r"`Parameter.min` must be below `Parameter.max`; received min=2.0, max=1.0"),
    (dict(min=1.0, max=1.0), ValueError, r"`Parameter.min` must be below `Parameter.max`"),
    (dict(min=math.inf), ValueError, r"`Parameter.min` must be below inf and `Parameter.max` above -inf"),
    (dict(max=-math.inf), ValueError, r"received min=None, max=-inf"),
])
def test_bad_parameter_fields_are_named(kwargs, error, match):
    with pytest.raises(error, match=match):
        Parameter(1.0, **kwargs)


def _follows(v):
    return v["N"] - v["S"]


@pytest.mark.parametrize("kwargs, match", [
    (dict(expr=_follows, min=0.0), r"`Parameter.expr` makes the state follow the others.*\['min'\] do not apply"),
    (dict(expr=_follows, value=0.7, vary=False), r"\['value', 'vary'\] do not apply with it"),
    (dict(expr=_follows, scale="log"), r"\['scale'\] do not apply with it"),
    (dict(value=5.0, vary=False, min=0.0, max=1.0), r"`Parameter\(vary=False\)` holds a known value, which takes no "
                                                    r"bounds or scale; received \{'min': 0.0, 'max': 1.0\}"),
    (dict(value=0.2, vary=False, scale="log"), r"takes no bounds or scale; received \{'scale': 'log'\}"),
    (dict(value=-0.1, scale="log"), r"`Parameter.scale` = 'log' needs a positive value; received -0.1"),
])
def test_roles_that_exclude_each_other_are_an_error(kwargs, match):
    """What the keywords a specification stands for refuse (``x0_expr`` with ``bounds``, ``bounds`` on a known
    value) was silently dropped from a Parameter: a state following an expression to -1 with ``min=0``, a
    known value held at 5 outside its own bounds [0, 1]."""
    with pytest.raises(ValueError, match=match):
        Parameter(**kwargs)


def test_a_role_that_contradicts_params_or_fixed_x0_is_named(data):
    """A coefficient ``params`` lists as an unknown and ``parameters`` holds fixed, or a state ``fixed_x0``
    fixes and ``parameters`` lets vary, is an error: the two places disagree, and neither may silently win."""
    x0 = torch.tensor([762.0, 0.5, 0.0], dtype=DT)
    with pytest.raises(ValueError, match=r"`parameters\['N'\]` has vary=False, but `params` lists 'N' as an unknown"):
        torchql.fit(SIR(), data, x0, params=["beta", "gamma", "N"], parameters={"N": Parameter(763.0, vary=False)})
    with pytest.raises(ValueError, match=r"`parameters\['S\(t0\)'\]` has vary=True, but `fixed_x0` fixes 'S'"):
        torchql.fit(SIR(), data, x0, fixed_x0=["S", "R"], parameters={"S(t0)": Parameter(762.0)})
    # the same role in both places is no contradiction
    agreed = torchql.fit(SIR(), data, x0, params=["beta", "gamma"], fixed_x0=["S", "R"],
                         parameters={"N": Parameter(763.0, vary=False), "R": Parameter(0.0, vary=False)})
    assert agreed.success and agreed.unknown_names == ["I(t0)", "beta", "gamma"]


def test_parameters_set_an_nn_parameter_coefficient():
    """``parameters=`` for a coefficient registered as an ``nn.Parameter`` raised a bare KeyError (its
    value was looked up among the buffers). It is set like a buffer's, and stays a Parameter."""
    from torch import nn

    class Held(torchql.ODEModel):
        state_names = ("y",)

        def __init__(self):
            super().__init__()
            self.k = nn.Parameter(torch.tensor(0.5, dtype=torch.float64))

        def forward(self, t, x):
            return -self.k * x

    t = torch.linspace(0, 5, 21, dtype=torch.float64)
    data = torchql.Observations(t, torch.exp(-t).unsqueeze(-1), observe=["y"])
    model = Held()
    x0 = torch.tensor([1.0], dtype=torch.float64)
    free = torchql.fit(model, data, x0=x0, fixed_x0=["y"], parameters={"k": torchql.Parameter(0.7, min=0.0)})
    assert free.status is torchql.Status.CONVERGED and float(free.params["k"]) == pytest.approx(1.0, rel=1e-9)
    held = torchql.fit(model, data, x0=x0, parameters={"k": torchql.Parameter(2.0, vary=False)})
    assert held.params["k"].item() == 2.0 and isinstance(held.model.k, nn.Parameter)
    assert model.k.item() == 0.5  # (the user's model untouched)
