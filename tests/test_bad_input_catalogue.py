"""Every bad input and every failure a user can provoke, in one catalogue.

Each case either raises at the public entry point (TypeError/ValueError naming the argument,
what was expected and what was received) or returns an unsuccessful FitResult whose status and
message say what happened and what to do. Nothing crashes with anything else.
"""

import math

import pytest
import torch

import torchql
from testmodels import Decay, Product
from torchql.baselines import adjoint_fit

DT = torch.float64
T = torch.linspace(0, 2, 11, dtype=DT)
Y = (1.5 * torch.exp(-0.7 * T)).unsqueeze(-1)


def data(**kwargs):
    return torchql.Observations(T, Y, observe=["y"], **kwargs)


class NaNAfterOne(torchql.ODEModel):
    """``y' = -k y`` that returns NaN for t > 1 (a model failing mid-integration)."""

    state_names = ("y",)

    def __init__(self, k=0.5):
        super().__init__()
        self.register_buffer("k", torch.tensor(k, dtype=DT))

    def forward(self, t, x):
        return torch.where(t > 1.0, torch.full_like(x, math.nan), -self.k * x)


class ScaledInPlace(torchql.ODEModel):
    """``y' = -k y`` written with an in-place update of its input ``x``."""

    state_names = ("y",)

    def __init__(self, k=0.3):
        super().__init__()
        self.register_buffer("k", torch.tensor(k, dtype=DT))

    def forward(self, t, x):
        return -self.k * x.mul_(1.0)


class ShiftedInPlace(ScaledInPlace):
    """The same, updating one component of ``x`` in place."""

    def forward(self, t, x):
        x[..., 0] += 0.0
        return -self.k * x


class NaNAtStart(ScaledInPlace):
    """``y' = -k sqrt(y)``: NaN for a negative state."""

    def forward(self, t, x):
        return -self.k * torch.sqrt(x)


class InfAtStart(ScaledInPlace):
    """``y' = -k / y``: inf at ``y = 0``."""

    def forward(self, t, x):
        return -self.k / x


class ParameterDecay(torchql.ODEModel):
    """``y' = -k y`` with ``k`` registered as an ``nn.Parameter`` (not a buffer)."""

    state_names = ("y",)

    def __init__(self, k=0.3, constants=()):
        super().__init__()
        self.k = torch.nn.Parameter(torch.tensor(k, dtype=DT))
        self.constants = constants

    def forward(self, t, x):
        return -self.k * x


class _TwoStatesNamedByAString(torchql.ODEModel):
    """Two states named ``"xv"``: a string, which would read as the states 'x' and 'v'."""

    state_names = "xv"

    def forward(self, t, x):
        return -x


def batch(samples=3):
    return torchql.Observations(T, Y.expand(samples, -1, -1), observe=["y"])


HALF = r"`model` computes in torch.{}.*model.double\(\)"
IN_PLACE = r"`model` forward updates its input `x` in place.*build a new tensor instead"
X0 = torch.tensor([1.0], dtype=DT)
RAISES = [
    ("NaN time", lambda: torchql.Observations(T.clone().index_fill_(0, torch.tensor([3]), math.nan), Y, observe=["y"]),
     ValueError, r"`t`"),
    ("inf value", lambda: torchql.Observations(T, Y.clone().index_fill_(0, torch.tensor([3]), math.inf), observe=["y"]),
     ValueError, r"`y`"),
    ("unsorted times", lambda: torchql.Observations(T.flip(0), Y, observe=["y"]), ValueError, r"`t`"),
    ("sigma zero", lambda: data(sigma=0.0), ValueError, r"`sigma`"),
    ("sigma negative", lambda: data(sigma=-1.0), ValueError, r"`sigma`"),
    ("NaN in x0", lambda: torchql.fit(Decay(0.3), data(), torch.tensor([math.nan], dtype=DT)), ValueError, r"`x0`"),
    ("inf in x0", lambda: torchql.fit(Decay(0.3), data(), torch.tensor([math.inf], dtype=DT)), ValueError, r"`x0`"),
    ("NaN guess of a coefficient", lambda: torchql.fit(Decay(math.nan), data(), X0), ValueError, r"guesses of \['k'\]"),
    ("x0 of the wrong shape", lambda: torchql.fit(Decay(0.3), data(), torch.zeros(2, dtype=DT)), ValueError, r"`x0`"),
    ("data not Observations", lambda: torchql.fit(Decay(0.3), (T, Y), X0), TypeError, r"`data"),
    ("bounds lower >= upper", lambda: torchql.fit(Decay(0.3), data(), X0, bounds={"k": (1.0, 0.1)}), ValueError,
     r"`bounds\['k'\]` needs lower < upper"),
    ("bounds lower == upper", lambda: torchql.fit(Decay(0.3), data(), X0, bounds={"k": (0.5, 0.5)}), ValueError,
     r"`bounds\['k'\]` needs lower < upper; received \(0.5, 0.5\), a fixed value: fix it instead .*`params=`"),
    ("NaN bound", lambda: torchql.fit(Decay(0.3), data(), X0, bounds={"k": (math.nan, None)}), ValueError,
     r"`bounds\['k'\]` lower bound is NaN"),
    ("bound on an unknown name", lambda: torchql.fit(Decay(0.3), data(), X0, bounds={"q": (0, 1)}), ValueError,
     r"`bounds` names unknown 'q'"),
    ("more exact values than unknowns",
     lambda: torchql.fit(Decay(0.3), data(exact=torch.ones(11, dtype=torch.bool)), X0), ValueError, r"`exact`"),
    ("fewer observations than unknowns",
     lambda: torchql.fit(Decay(0.3), torchql.Observations(T[:1], Y[:1], observe=["y"]), X0), ValueError,
     r"fewer usable observations"),
    ("negative rtol", lambda: torchql.fit(Decay(0.3), data(), X0, rtol=-1e-8), ValueError, r"`rtol`"),
    ("unknown method", lambda: torchql.fit(Decay(0.3), data(), X0, method="newton"), ValueError, r"`method`"),
    ("unknown solver", lambda: torchql.fit(Decay(0.3), data(), X0, solver="rk45"), ValueError, r"`solver`"),
    ("unknown linear solver", lambda: torchql.fit(Decay(0.3), data(), X0, linear_solver="magic"), ValueError,
     r"`linear_solver`"),
    ("unknown damping", lambda: torchql.fit(Decay(0.3), data(), X0, damping="trust"), ValueError, r"`damping`"),
    ("empty list of experiments", lambda: torchql.fit(Decay(0.3), [], X0), ValueError, r"`data`"),
    ("a batch of datasets given to fit",
     lambda: torchql.fit(Decay(0.3), torchql.Observations(T, Y.expand(3, -1, -1), observe=["y"]), X0), ValueError,
     r"`data` holds a batch of 3 .*torchql.fit_many"),
    ("a batch among experiments",
     lambda: torchql.fit(Decay(0.3), [data(), torchql.Observations(T, Y.expand(2, -1, -1), observe=["y"])], X0),
     ValueError, r"`data\[1\]` holds a batch"),
    ("a batch of datasets given to adjoint_fit",
     lambda: adjoint_fit(Decay(0.3), torchql.Observations(T, Y.expand(3, -1, -1), observe=["y"]), x0=X0), ValueError,
     r"`data` holds a batch.*torchql.fit_many"),
    ("bfloat16 model in fit", lambda: torchql.fit(Decay(0.3, dtype=torch.bfloat16), data(), X0), TypeError,
     HALF.format("bfloat16")),
    ("bfloat16 model in fit_many", lambda: torchql.fit_many(Decay(0.3, dtype=torch.bfloat16), batch(), X0), TypeError,
     HALF.format("bfloat16")),
    ("bfloat16 model in simulate", lambda: torchql.simulate(Decay(0.3, dtype=torch.bfloat16), X0, T), TypeError,
     HALF.format("bfloat16")),
    ("float16 model in fit", lambda: torchql.fit(Decay(0.3, dtype=torch.float16), data(), X0), TypeError,
     HALF.format("float16")),
    ("float16 model in fit_many", lambda: torchql.fit_many(Decay(0.3, dtype=torch.float16), batch(), X0), TypeError,
     HALF.format("float16")),
    ("float16 model in simulate", lambda: torchql.simulate(Decay(0.3, dtype=torch.float16), X0, T), TypeError,
     HALF.format("float16")),
    ("forward updates x in place (mul_) in fit", lambda: torchql.fit(ScaledInPlace(), data(), X0), ValueError,
     IN_PLACE),
    ("forward updates x in place (mul_) in fit_many", lambda: torchql.fit_many(ScaledInPlace(), batch(), X0),
     ValueError, IN_PLACE),
    ("forward updates x in place (mul_) in simulate", lambda: torchql.simulate(ScaledInPlace(), X0, T), ValueError,
     IN_PLACE),
    ("forward updates a component of x in place in fit", lambda: torchql.fit(ShiftedInPlace(), data(), X0),
     ValueError, IN_PLACE),
    ("forward updates a component of x in place in fit_many",
     lambda: torchql.fit_many(ShiftedInPlace(), batch(), X0), ValueError, IN_PLACE),
    ("forward NaN at the guesses in fit", lambda: torchql.fit(NaNAtStart(), data(), -X0), ValueError,
     r"`model` forward is not finite at the guesses: dy/dt = nan at t0 = 0, x0 = \(y = -1\), k = 0.3\..*x0"),
    ("forward inf at the guesses in fit", lambda: torchql.fit(InfAtStart(), data(), 0 * X0), ValueError,
     r"`model` forward is not finite at the guesses: dy/dt = -inf at t0 = 0, x0 = \(y = 0\), k = 0.3"),
    ("forward NaN at the guesses in fit_many", lambda: torchql.fit_many(NaNAtStart(), batch(), -X0), ValueError,
     r"`model` forward is not finite at the guesses: dy/dt = nan at t0 = 0, x0 = \(y = -1\), k = 0.3"),
    ("forward NaN at one sample's guesses in fit_many",
     lambda: torchql.fit_many(NaNAtStart(), batch(), torch.tensor([[1.0], [1.0], [-1.0]], dtype=DT)), ValueError,
     r"`model` forward is not finite at the guesses of `data\[2\]`: dy/dt = nan .*x0 = \(y = -1\)"),
    ("a list of experiments given to adjoint_fit", lambda: adjoint_fit(Decay(0.3), [data(), data()], x0=X0), TypeError,
     r"`data` must be one torchql.Observations: .*received a list of 2 .*torchql.fit"),
    ("simulate: times as a string", lambda: torchql.simulate(Decay(0.3), X0, "abc"), TypeError,
     r"`t` must be a one-dimensional tensor of times; received str"),
    ("simulate: ragged x0", lambda: torchql.simulate(Decay(0.3), [[1.0], [1.0, 2.0]], T), TypeError,
     r"`x0` must be a tensor of shape \(n_states,\) = \(1,\); received list"),
    ("simulate: complex times", lambda: torchql.simulate(Decay(0.3), X0, T + 5j), TypeError,
     r"`t` must be real-valued; received dtype torch.complex128"),
    ("simulate: complex x0", lambda: torchql.simulate(Decay(0.3), torch.tensor([1 + 3j]), T), TypeError,
     r"`x0` must be real-valued"),
    ("predict: times as a string", lambda: torchql.fit(Decay(0.3), data(), X0, max_iter=0).predict("abc"), TypeError,
     r"`t` must be a one-dimensional tensor of times; received str"),
    ("fit: complex x0", lambda: torchql.fit(Decay(0.3), data(), torch.tensor([1 + 3j])), TypeError,
     r"`x0` must be real-valued"),
    ("fit_many: x0 as a string", lambda: torchql.fit_many(Decay(0.3), batch(), "a"), TypeError,
     r"`x0` must be a tensor of shape \(B, n_states\) = \(3, 1\) or \(n_states,\) = \(1,\); received str"),
    ("fit_many: complex guesses", lambda: torchql.fit_many(Decay(0.3), batch(), X0, guesses={"k": [1j, 2j, 3j]}),
     TypeError, r"`guesses\['k'\]` must be real-valued"),
    ("sigma as a bool", lambda: data(sigma=True), TypeError, r"`sigma` must be real-valued; received dtype torch.bool"),
    ("y as strings", lambda: torchql.Observations(T, ["a"] * 11, observe=["y"]), TypeError,
     r"`y` must be a tensor or array of real numbers; received list"),
    ("exact marks a missing value",
     lambda: torchql.Observations(T, Y.clone().index_fill_(0, torch.tensor([2]), math.nan), observe=["y"],
                                  exact=torch.arange(11).eq(2).unsqueeze(-1)), ValueError,
     r"`exact` marks values that are missing \(NaN\), at index \(2, 0\)"),
    ("grid times of NaN in FitOptions", lambda: torchql.FitOptions(grid=torch.tensor([math.nan])), ValueError,
     r"`grid` times must be finite"),
    ("grid times as a matrix", lambda: torchql.fit(Decay(0.3), data(), X0, grid=torch.tensor([[0.5, 1.5]])),
     ValueError, r"`grid` given as times must be a one-dimensional tensor .*received shape \(1, 2\)"),
    ("unknown name in params of a model with a Parameter",
     lambda: torchql.fit(ParameterDecay(), data(), X0, params=["kk"]), ValueError,
     r"`params` names unknown buffer 'kk'; .* float parameters \('k',\)"),
    ("multistart: unknown name in params", lambda: torchql.multistart(Decay(0.3), data(), X0, params=["q"], starts=2),
     ValueError, r"`params` names unknown buffer 'q'; the model's float buffers are \('k',\)"),
    ("multistart: seed as a string", lambda: torchql.multistart(Decay(0.3), data(), X0, seed="a", starts=2),
     ValueError, r"`seed` must be a non-negative integer; received 'a'"),
    ("multistart: negative x_rtol", lambda: torchql.multistart(Decay(0.3), data(), X0, x_rtol=-1.0, starts=2),
     ValueError, r"`x_rtol` must be a non-negative finite number; received -1.0"),
    ("multistart: x0 of the wrong shape",
     lambda: torchql.multistart(Decay(0.3), data(), torch.zeros(3, dtype=DT), starts=2), ValueError,
     r"`x0` must have shape \(n_states,\) = \(1,\); received shape \(3,\)"),
    ("several experiments: the stacking's buffer in params",
     lambda: torchql.fit(Decay(0.3), [data(), data()], torch.stack([X0, X0]), params=["k", "_span"]), ValueError,
     r"`params` names unknown buffer '_span'; the model's float buffers are \('k',\)$"),
    ("fit_many of several experiments: per-sample x0 of the wrong number of experiments",
     lambda: torchql.fit_many(Decay(0.3), [[data(), data()]] * 2, torch.ones(2, 3, 1, dtype=DT)), ValueError,
     r"`x0` must have shape \(E, n_states\) \(shared\) or \(B, E, n_states\) with B = 2 samples of E = 2 "
     r"experiments and n_states = 1; received shape \(2, 3, 1\)"),
    ("parameters varying a coefficient that params leaves out",
     lambda: torchql.fit(Product(1.0, 1.0), data(), X0, params=["a"], parameters={"b": 1.0}), ValueError,
     r"`parameters\['b'\]` varies \(vary=True, the default\), but `params` = \['a'\] does not list 'b'"),
    ("multistart: bounds lower above upper", lambda: torchql.multistart(Decay(0.3), data(), X0, starts=2,
                                                                      bounds={"k": (1.0, 0.0)}), ValueError,
     r"`bounds\['k'\]` needs lower < upper; received \(1, 0\)"),
    ("multistart: include_guess as a string",
     lambda: torchql.multistart(Decay(0.3), data(), X0, starts=2, include_guess="no"), TypeError,
     r"`include_guess` must be True or False; received 'no'"),
    ("report: iterations as a string", lambda: torchql.fit(Decay(0.3), data(), X0).report(iterations="no"),
     TypeError, r"`iterations` must be True or False; received 'no'"),
    ("experiment_model of an experiment the fit does not have",
     lambda: torchql.fit(Decay(0.3), data(), X0).experiment_model(5), ValueError,
     r"`experiment` must be 0 for a fit of one experiment; received 5"),
    ("experiment_model of several experiments, index out of range",
     lambda: torchql.fit(Decay(0.3), [data(), data()], torch.stack([X0, X0])).experiment_model(-1), ValueError,
     r"`experiment` must be an index 0..1 \(the fit has 2 experiments\); received -1"),
    ("plot_fit: data not Observations", lambda: torchql.fit(Decay(0.3), data(), X0).plot_fit(data=5), TypeError,
     r"`data` must be a torchql.Observations \(one experiment's\); received int"),
    ("state_names as one string", lambda: torchql.simulate(_TwoStatesNamedByAString(), torch.ones(2, dtype=DT), T),
     ValueError, r"`model.state_names` must be a non-empty tuple of distinct strings; received 'xv'"),
    ("FitOptions: grid as a list", lambda: torchql.FitOptions(grid=[1, 2]), ValueError,
     r'`grid` must be a number of intervals, a tensor of times, "auto" or "smooth"; received \[1, 2\]'),
    ("fit: x0 on the meta device", lambda: torchql.fit(Decay(0.3), data(), torch.ones(1, device="meta")), TypeError,
     r"`x0` must be a tensor of shape \(n_states,\) = \(1,\) with values; received a tensor on the meta device"),
    ("profile: an unknown keyword", lambda: torchql.profile(torchql.fit(Decay(0.3), data(), X0), "k", foo=1),
     TypeError, r"profile\(\) got unexpected keyword argument\(s\) \['foo'\]"),
]


@pytest.mark.parametrize("case, call, error, match", RAISES, ids=[c[0] for c in RAISES])
def test_bad_input_raises_naming_the_argument(case, call, error, match):
    with pytest.raises(error, match=match):
        call()


def _contradictory_exact():
    """The same state measured twice at t0, both values exact and different: no iterate meets both."""
    y = torch.stack([Y[:, 0], Y[:, 0]], dim=1)
    y[0, 1] += 0.1
    exact = torch.zeros(11, 2, dtype=torch.bool)
    exact[0] = True
    return torchql.fit(Decay(0.3), torchql.Observations(T, y, observe=["y", "y"], exact=exact), X0)


FAILS = [
    ("exact values that contradict each other", _contradictory_exact, torchql.Status.EXACT_INFEASIBLE, r"exact"),
    ("model returns NaN mid-integration", lambda: torchql.fit(NaNAfterOne(), data(), X0),
     torchql.Status.INTEGRATION_FAILED, r"ODE solver failed"),
    ("integrator exceeds its step budget", lambda: torchql.fit(Decay(0.3), data(), X0, max_steps=1, grid=1),
     torchql.Status.INTEGRATION_FAILED, r"max_num_steps|step"),
    ("iteration budget exhausted", lambda: torchql.fit(Decay(0.3), data(), X0, max_iter=1),
     torchql.Status.MAX_ITER, r"Increase `max_iter`"),
]


@pytest.mark.parametrize("case, call, status, match", FAILS, ids=[c[0] for c in FAILS])
def test_failure_is_a_status_with_an_actionable_message(case, call, status, match):
    result = call()
    assert not result.success
    assert result.status is status, result.message
    assert __import__("re").search(match, result.message), result.message
    with pytest.raises(torchql.FitError):
        raise torchql.FitError(result)


# --- inputs accepted as they are: requires_grad tensors are read (copied), nn.Parameter coefficients
K_TRUE, Y0_TRUE = 0.7, 1.5


def _assert_exact_decay(result):
    assert result.success, result.message
    assert abs(float(result.params["k"]) - K_TRUE) < 1e-8
    assert abs(float(result.x0[0]) - Y0_TRUE) < 1e-8


def _assert_exact_batch(result):
    assert bool(result.success.all()), result.message
    assert float((result.params["k"] - K_TRUE).abs().max()) < 1e-8
    assert float((result.x0[:, 0] - Y0_TRUE).abs().max()) < 1e-8


def test_x0_that_requires_grad_is_read_not_differentiated():
    x0 = X0.clone().requires_grad_(True)
    _assert_exact_decay(torchql.fit(Decay(0.3), data(), x0))
    _assert_exact_batch(torchql.fit_many(Decay(0.3), batch(), x0))
    assert x0.requires_grad and float(x0.detach()) == 1.0
    x = torchql.simulate(Decay(K_TRUE), torch.tensor([Y0_TRUE], dtype=DT, requires_grad=True), T)
    assert torch.allclose(x, Y, rtol=1e-8, atol=0)


def test_observations_of_tensors_that_require_grad_are_copies():
    t, y = T.clone().requires_grad_(True), Y.clone().requires_grad_(True)
    sigma = torch.ones(11, 1, dtype=DT, requires_grad=True)
    obs = torchql.Observations(t, y, observe=["y"], sigma=sigma)
    assert not (obs.t.requires_grad or obs.y.requires_grad or obs.sigma.requires_grad)
    assert torch.equal(obs.t, T) and torch.equal(obs.y, Y)
    assert t.requires_grad and y.requires_grad and sigma.requires_grad
    assert torch.equal(t.detach(), T) and torch.equal(y.detach(), Y)
    _assert_exact_decay(torchql.fit(Decay(0.3), obs, X0))
    many = torchql.Observations(t, y.expand(3, -1, -1), observe=["y"])
    assert not many.y.requires_grad
    _assert_exact_batch(torchql.fit_many(Decay(0.3), many, X0))
    _assert_exact_batch(torchql.fit_many(Decay(0.3), [obs, obs], X0))


@pytest.mark.parametrize("params", [None, ["k"]], ids=["default params", "params=['k']"])
def test_parameter_coefficient_is_fitted_like_a_buffer(params):
    model = ParameterDecay(0.3)
    result = torchql.fit(model, data(), X0, params=params)
    _assert_exact_decay(result)
    assert result.unknown_names == ["y(t0)", "k"]
    assert not result.params["k"].requires_grad
    fitted = result.model.k
    assert isinstance(fitted, torch.nn.Parameter) and fitted.requires_grad
    assert abs(float(fitted.detach()) - K_TRUE) < 1e-8 and dict(result.model.named_buffers()) == {}
    assert isinstance(model.k, torch.nn.Parameter) and model.k.requires_grad and float(model.k.detach()) == 0.3
    assert torch.allclose(result.predict(T), Y, rtol=1e-8, atol=0)

    many = torchql.fit_many(model, batch(), X0, params=params)
    _assert_exact_batch(many)
    sample = many.model_of(1).k
    assert isinstance(sample, torch.nn.Parameter) and abs(float(sample.detach()) - K_TRUE) < 1e-8
    assert float(model.k.detach()) == 0.3 and model.k.requires_grad

    experiments = torchql.fit(model, [data(), data()], torch.stack([X0, X0]), params=params)
    assert experiments.success, experiments.message
    assert abs(float(experiments.model.k.detach()) - K_TRUE) < 1e-8 and isinstance(experiments.model.k, torch.nn.Parameter)
    assert float(model.k.detach()) == 0.3


def test_parameter_listed_in_constants_is_not_estimated():
    model = ParameterDecay(K_TRUE, constants=("k",))
    result = torchql.fit(model, data(), X0)
    assert result.success, result.message
    assert result.unknown_names == ["y(t0)"]
    assert abs(float(result.x0[0]) - Y0_TRUE) < 1e-8 and float(result.model.k.detach()) == K_TRUE
    many = torchql.fit_many(model, batch(), X0)
    assert many.unknown_names == ["y(t0)"] and bool(many.success.all())


def test_adjoint_fit_of_a_parameter_coefficient():
    model = ParameterDecay(0.6)
    result = adjoint_fit(model, data(), x0=torch.tensor([1.4], dtype=DT), optimizer="lbfgs", adjoint=False)
    assert abs(float(result.params["k"]) - K_TRUE) < 1e-4, result.message
    assert isinstance(result.model.k, torch.nn.Parameter) and float(model.k.detach()) == 0.6
