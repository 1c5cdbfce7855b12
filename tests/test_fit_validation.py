"""``torchql.fit``: argument validation at the entry point, and small behavioural checks."""

import math

import numpy as np
import pytest
import torch

import torchql
from testmodels import Decay
from torchql.models import LinearOscillator

GRID = 10  # a coarse Kantorovich storage grid keeps these tiny fits fast


class Custom(Decay):
    """A decay model whose ``forward`` is replaced by ``fn(self, t, x)``."""

    def __init__(self, fn):
        super().__init__(0.5)
        self.fn = fn

    def forward(self, t, x):
        return self.fn(self, t, x)


T = torch.linspace(0.0, 2.0, 6, dtype=torch.float64)
Y = 2.0 * torch.exp(-0.7 * T)


def decay_data(**kwargs):
    return torchql.Observations(T, Y, ["y"], **kwargs)


def oscillator_data(observe=("y",), t=None):
    t = torch.linspace(0.0, 3.0, 7, dtype=torch.float64) if t is None else t
    x = torchql.simulate(LinearOscillator(0.3, 2.0), torch.tensor([1.0, 0.0], dtype=torch.float64), t)
    columns = [LinearOscillator.state_names.index(name) for name in observe]
    return torchql.Observations(t, x[:, columns], list(observe))


# ================================================================== argument validation
def test_model_not_an_odemodel():
    with pytest.raises(TypeError, match="`model` must be a torchql.ODEModel; received Linear"):
        torchql.fit(torch.nn.Linear(1, 1), decay_data())


def test_model_with_bad_state_names():
    class NoStates(Decay):
        state_names = ()

    with pytest.raises(ValueError, match="`model.state_names`"):
        torchql.fit(NoStates(), decay_data())


def test_a_state_and_a_coefficient_with_one_name():
    """``bounds={"y": ...}`` silently bounded the coefficient ``y`` and not the state's initial value
    (its guess outside the bounds left there). A fit refuses the model; a simulation takes it."""
    class Clash(Decay):
        def __init__(self):
            super().__init__()
            self.register_buffer("y", torch.tensor(0.1, dtype=torch.float64))

    with pytest.raises(ValueError, match="`model` has a state and a coefficient both named 'y'.*rename one"):
        torchql.fit(Clash(), decay_data(), bounds={"y": (0.0, 1.5)})
    assert torchql.simulate(Clash(), torch.tensor([1.0], dtype=torch.float64), T).shape == (T.numel(), 1)


def test_data_not_observations():
    with pytest.raises(TypeError, match="`data` must be a torchql.Observations or a list of them; received dict"):
        torchql.fit(Decay(), {"t": T, "y": Y})


def test_data_list_of_observations_takes_x0_from_each_experiment():
    result = torchql.fit(Decay(0.3), [decay_data(), decay_data()], grid=GRID)
    assert result.success and result.x0.shape == (2, 1)


def test_unknown_method_lists_valid_ones():
    with pytest.raises(ValueError, match=r"`method` must be one of \('kantorovich', 'shooting'\); received 'newton'"):
        torchql.fit(Decay(), decay_data(), method="newton")


def test_unknown_solver_lists_valid_ones():
    with pytest.raises(ValueError, match=r"`solver` must be one of \(.*'dopri5'.*'rk4'.*\); received 'rk45'") as info:
        torchql.fit(Decay(), decay_data(), solver="rk45")
    for name in torchql.SOLVER_NAMES:
        assert repr(name) in str(info.value)


def test_unknown_param_name():
    with pytest.raises(ValueError, match=r"`params` names unknown buffer 'kk'; the model's float buffers are \('k',\)"):
        torchql.fit(Decay(), decay_data(), params=["kk"])


def test_params_bare_string():
    with pytest.raises(TypeError, match=r"`params` must be a sequence of buffer names, not a string; use \['k'\]"):
        torchql.fit(Decay(), decay_data(), params="k")


def test_params_duplicate():
    with pytest.raises(ValueError, match="`params` lists a buffer twice"):
        torchql.fit(Decay(), decay_data(), params=["k", "k"])


def test_unknown_state_in_fixed_x0():
    with pytest.raises(ValueError, match=r"`fixed_x0` names unknown state 'z'; the model's states are \('y',\)"):
        torchql.fit(Decay(), decay_data(), torch.tensor([2.0]), fixed_x0=["z"])


def test_fixed_x0_bare_string():
    with pytest.raises(TypeError, match="`fixed_x0` must be a sequence of state names, not a string"):
        torchql.fit(Decay(), decay_data(), torch.tensor([2.0]), fixed_x0="y")


def test_unknown_state_in_observe_names():
    data = torchql.Observations(T, Y, ["z"])
    with pytest.raises(ValueError, match=r"`observe` names unknown state 'z'; the model's states are \('y',\)"):
        torchql.fit(Decay(), data, torch.tensor([2.0]))


def test_observe_matrix_wrong_number_of_states():
    data = torchql.Observations(T, Y, torch.ones(1, 2, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"`observe` matrix must have shape \(K, n_states\) = \(1, 1\)"):
        torchql.fit(Decay(), data, torch.tensor([2.0]))


def test_observe_callable_wrong_output_shape():
    data = torchql.Observations(T, Y, lambda x: torch.cat([x, x]))
    with pytest.raises(ValueError, match=r"`observe` callable must return shape \(K,\) = \(1,\)"):
        torchql.fit(Decay(), data, torch.tensor([2.0]))


def test_observe_callable_of_one_output_may_return_a_scalar():
    """With one output, ``h(x, p) = p["scale"] * x[1] + p["offset"]`` (the README's example, a
    scalar) is that output: a two-state oscillator's velocity measured with a gain and an offset
    gives back the truth (the scalar was refused: the callable had to return shape (1,))."""

    class Measured(LinearOscillator):
        def __init__(self, A=0.1, B=3.0, scale=1.0, offset=0.0):
            super().__init__(A, B)
            self.register_buffer("scale", torch.tensor(scale, dtype=torch.float64))
            self.register_buffer("offset", torch.tensor(offset, dtype=torch.float64))

    t = torch.linspace(0, 6.5, 14, dtype=torch.float64)
    x = torchql.simulate(LinearOscillator(0.1, 3.0), torch.tensor([0.0, 1.0], dtype=torch.float64), t)
    data = torchql.Observations(t, 2.0 * x[:, 1:2] + 0.3, observe=lambda x, p: p["scale"] * x[1] + p["offset"])
    result = torchql.fit(Measured(0.5, 1.0, 1.5, 0.0), data, torch.tensor([0.0, 1.0], dtype=torch.float64),
                         fixed_x0=["y", "v"])
    assert result.success, result.message
    for name, truth in dict(A=0.1, B=3.0, scale=2.0, offset=0.3).items():
        assert float(result.params[name]) == pytest.approx(truth, rel=1e-7, abs=1e-9)


@pytest.mark.parametrize("x0", [torch.tensor([1.0, 0.0]), torch.tensor(1.0), torch.ones(1, 1)])
def test_x0_wrong_shape(x0):
    with pytest.raises(ValueError, match=r"`x0` must have shape \(n_states,\) = \(1,\)"):
        torchql.fit(Decay(), decay_data(), x0)


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_x0_non_finite(bad):
    with pytest.raises(ValueError, match="`x0` must be finite"):
        torchql.fit(Decay(), decay_data(), torch.tensor([bad]))


def test_x0_not_numeric():
    with pytest.raises(TypeError, match="`x0` must be a tensor"):
        torchql.fit(Decay(), decay_data(), "2.0")


def test_x0_missing_for_unobserved_state():
    with pytest.raises(ValueError, match=r"`x0` is required: the states \['v'\] are not observed directly at t0"):
        torchql.fit(LinearOscillator(), oscillator_data(("y",)))


def test_x0_missing_when_observation_at_t0_is_nan():
    y = Y.clone()
    y[0] = math.nan
    with pytest.raises(ValueError, match=r"`x0` is required: the states \['y'\]"):
        torchql.fit(Decay(), torchql.Observations(T, y, ["y"]))


def test_x0_missing_when_t0_precedes_data():
    with pytest.raises(ValueError, match="`x0` is required when `t0` precedes the first observation"):
        torchql.fit(Decay(), decay_data(), t0=-1.0)


def test_t0_after_first_observation():
    with pytest.raises(ValueError, match=r"`t0` must not be later than the first observation time 0; received 0.5"):
        torchql.fit(Decay(), decay_data(), torch.tensor([2.0]), t0=0.5)


@pytest.mark.parametrize("t0", [math.nan, math.inf, "0"])
def test_t0_not_a_finite_number(t0):
    with pytest.raises(ValueError, match="`t0` must be a finite number"):
        torchql.fit(Decay(), decay_data(), torch.tensor([2.0]), t0=t0)


def test_forward_wrong_shape():
    model = Custom(lambda self, t, x: torch.cat([x, x]))
    with pytest.raises(ValueError, match=r"`model` forward must return dx/dt of the state's shape \(1,\).*received shape \(2,\)"):
        torchql.fit(model, decay_data())


def test_forward_wrong_dtype():
    model = Custom(lambda self, t, x: (-self.k * x).to(torch.float32))
    with pytest.raises(TypeError, match=r"`model` forward must return dtype torch.float64 .*received torch.float32"):
        torchql.fit(model, decay_data())


def test_forward_not_a_tensor():
    model = Custom(lambda self, t, x: [0.0])
    with pytest.raises(TypeError, match="`model` forward must return a Tensor; received list"):
        torchql.fit(model, decay_data())


def test_forward_raises():
    def boom(self, t, x):
        raise RuntimeError("boom")

    with pytest.raises(ValueError, match=r"`model` forward\(t, x\) failed for x of shape \(1,\): boom") as info:
        torchql.fit(Custom(boom), decay_data())
    assert isinstance(info.value.__cause__, RuntimeError)


@pytest.mark.parametrize("forward", [
    lambda self, t, x: -float(self.k) * x,  # .item()-style code breaks torch.func transforms
    lambda self, t, x: -self.k * x if bool(x.sum() > 0) else self.k * x,  # branching on a value
    lambda self, t, x: -self.k * torch.as_tensor(x.detach().numpy()),  # leaving torch
], ids=["float", "branch", "numpy"])
def test_forward_not_differentiable(forward):
    """Each would give autograd a silently wrong (zero) derivative or fail inside the fit; the
    check names it at the entry point, for fit and fit_many alike."""
    with pytest.raises(ValueError, match=r"`model` forward could not be differentiated with torch.func \(jacrev and jvp under vmap\)"):
        torchql.fit(Custom(forward), decay_data())
    with pytest.raises(ValueError, match=r"`model` forward could not be differentiated with torch.func"):
        torchql.fit_many(Custom(forward), [decay_data(), decay_data()])


def test_fewer_usable_observations_than_unknowns():
    y = Y.clone()
    y[1:] = math.nan  # one value left, two unknowns (y(t0), k)
    with pytest.raises(ValueError, match=r"fewer usable observations \(1\) than unknowns \(2: \['y\(t0\)', 'k'\]\).*`params=`/`fixed_x0=`"):
        torchql.fit(Decay(), torchql.Observations(T, y, ["y"]), torch.tensor([2.0]))


def test_more_exact_values_than_unknowns():
    exact = torch.tensor([True, True, True, False, False, False])
    with pytest.raises(ValueError, match=r"more values are marked `exact` \(3\) than there are unknowns \(2\)"):
        torchql.fit(Decay(), decay_data(exact=exact))


@pytest.mark.parametrize("max_iter", [-1, True, 2.0, "3"])
def test_max_iter_invalid(max_iter):
    with pytest.raises(ValueError, match=r"`max_iter` must be a non-negative integer"):
        torchql.fit(Decay(), decay_data(), max_iter=max_iter)


@pytest.mark.parametrize("name", ["rtol", "atol"])
@pytest.mark.parametrize("value", [0.0, -1e-8, math.nan, math.inf])
def test_tolerances_invalid(name, value):
    with pytest.raises(ValueError, match=f"`{name}` must be a positive finite number"):
        torchql.fit(Decay(), decay_data(), **{name: value})


@pytest.mark.parametrize("name", ["xtol", "ftol", "rcond"])
def test_convergence_tolerances_invalid(name):
    with pytest.raises(ValueError, match=f"`{name}` must be a positive finite number"):
        torchql.fit(Decay(), decay_data(), **{name: -1.0})


def test_bounds_must_be_a_dict():
    with pytest.raises(TypeError, match="`bounds` must be a dict"):
        torchql.fit(Decay(), decay_data(), bounds=[(0.0, 1.0)])


def test_initial_trajectory_invalid():
    with pytest.raises(ValueError, match=r"`initial_trajectory` must be one of \('auto', 'integrate', 'data'\); received 'zeros'"):
        torchql.fit(Decay(), decay_data(), initial_trajectory="zeros")


def test_initial_trajectory_data_with_shooting_is_accepted():
    result = torchql.fit(Decay(), decay_data(), method="shooting", initial_trajectory="data")
    assert result.fit_kwargs["initial_trajectory"] == "data" and result.fit_kwargs["method"] == "shooting"


@pytest.mark.parametrize("max_steps", [0, -5, 1.5])
def test_max_steps_invalid(max_steps):
    with pytest.raises(ValueError, match="`max_steps` must be a positive integer"):
        torchql.fit(Decay(), decay_data(), max_steps=max_steps)


@pytest.mark.parametrize("grid", [0, -3, True, 2.5])
def test_grid_invalid(grid):
    with pytest.raises(ValueError, match="`grid` must be a positive number of intervals"):
        torchql.fit(Decay(), decay_data(), grid=grid)


def test_nothing_to_estimate():
    with pytest.raises(ValueError, match="nothing to estimate: every initial state is in `fixed_x0` and `params` is empty"):
        torchql.fit(Decay(), decay_data(), torch.tensor([2.0]), params=[], fixed_x0=["y"])


def test_non_finite_buffer_guess():
    with pytest.raises(ValueError, match=r"the guesses of \['k'\]"):
        torchql.fit(Decay(math.nan), decay_data())



def test_max_steps_bool_rejected():
    with pytest.raises(ValueError, match="`max_steps` must be a positive integer"):
        torchql.fit(Decay(), decay_data(), max_steps=True, grid=GRID)


@pytest.mark.parametrize("t0", [np.float32(0.0), np.int64(0)])
def test_t0_numpy_scalar_accepted(t0):
    result = torchql.fit(Decay(0.3), decay_data(), torch.tensor([1.5]), t0=t0, grid=GRID, max_iter=0)
    assert result.t0 == 0.0


def test_callback_not_callable():
    with pytest.raises(TypeError, match="`callback` must be callable"):
        torchql.fit(Decay(), decay_data(), callback=3, grid=GRID)


# ================================================================== behaviour
@pytest.mark.parametrize("method", ["kantorovich", "shooting"])
def test_user_model_and_x0_unchanged_and_result_model_is_a_copy(method):
    model = Decay(0.3)
    k_before = model.k.clone()
    x0 = torch.tensor([1.5], dtype=torch.float64)
    x0_before = x0.clone()
    result = torchql.fit(model, decay_data(), x0, method=method, grid=GRID)
    assert result.success, result.message
    assert torch.equal(model.k, k_before)
    assert torch.equal(x0, x0_before)
    assert result.model is not model
    assert isinstance(result.model, Decay)
    assert result.model.k.item() == pytest.approx(0.7, rel=1e-8)
    assert result.params["k"].item() == pytest.approx(0.7, rel=1e-8)
    assert result.x0.item() == pytest.approx(2.0, rel=1e-8)
    assert result.unknown_names == ["y(t0)", "k"]
    # the result's tensors are not views of the user's objects
    result.model.k.add_(1.0)
    result.x0.add_(1.0)
    assert torch.equal(model.k, k_before) and torch.equal(x0, x0_before)


@pytest.mark.parametrize("method", ["kantorovich", "shooting"])
def test_fixed_x0_is_kept_bitwise(method):
    # v(t0) fixed to a value that is deliberately not a "round" one; y(t0), A, B estimated
    v0 = 0.1 + 0.2  # 0.30000000000000004
    x0 = torch.tensor([0.8, v0], dtype=torch.float64)
    t = torch.linspace(0.0, 3.0, 7, dtype=torch.float64)
    truth = torchql.simulate(LinearOscillator(0.3, 2.0), torch.tensor([1.0, v0], dtype=torch.float64), t)
    data = torchql.Observations(t, truth, ["y", "v"])
    result = torchql.fit(LinearOscillator(0.2, 2.5), data, x0, fixed_x0=["v"], method=method, grid=GRID, max_iter=20)
    assert result.unknown_names == ["y(t0)", "A", "B"]
    assert result.x0[1].item() == v0
    assert len(result.history) >= 2
    for record in result.history:
        assert record.x0[1].item() == v0
    assert result.success, result.message
    torch.testing.assert_close(result.estimates, torch.tensor([1.0, 0.3, 2.0], dtype=torch.float64),
                               rtol=1e-6, atol=1e-6)


def test_throw_raises_fit_error_with_result():
    with pytest.raises(torchql.FitError) as info:
        torchql.fit(Decay(0.05), decay_data(), torch.tensor([1.0]), max_iter=1, throw=True, grid=GRID)
    result = info.value.result
    assert isinstance(result, torchql.FitResult)
    assert not result.success
    assert result.status is torchql.Status.MAX_ITER
    assert str(info.value) == result.message
    # it crosses process boundaries (a worker pool's fit raising it) with its result
    import copy
    import pickle

    for again in (pickle.loads(pickle.dumps(info.value)), copy.deepcopy(info.value)):
        assert isinstance(again, torchql.FitError) and str(again) == result.message
        assert again.result.status is torchql.Status.MAX_ITER
        torch.testing.assert_close(again.result.estimates, result.estimates, rtol=0, atol=0)


def test_no_throw_returns_unsuccessful_result():
    result = torchql.fit(Decay(0.05), decay_data(), torch.tensor([1.0]), max_iter=1, grid=GRID)
    assert result.success is False
    assert result.status is torchql.Status.MAX_ITER
    assert result.message == result.status.value
    assert result.iterations == 1


def test_max_iter_zero_returns_guess():
    result = torchql.fit(Decay(0.3), decay_data(), torch.tensor([1.5]), max_iter=0, grid=GRID)
    assert result.status is torchql.Status.MAX_ITER and result.iterations == 0
    assert result.x0.item() == 1.5 and result.params["k"].item() == 0.3
    assert len(result.history) == 1


@pytest.mark.parametrize("method", ["kantorovich", "shooting"])
def test_callback_called_once_per_record(method):
    seen = []
    result = torchql.fit(Decay(0.3), decay_data(), torch.tensor([1.5]), method=method, grid=GRID, callback=seen.append)
    assert result.success
    assert len(seen) == len(result.history) == result.iterations + 1
    for got, record in zip(seen, result.history):
        assert got is record
    assert [r.iteration for r in seen] == list(range(len(seen)))


@pytest.mark.parametrize("method", ["kantorovich", "shooting"])
def test_float32_model_gives_float32_results(method):
    model = Decay(0.3, dtype=torch.float32)
    data = torchql.Observations(T.float(), Y.float(), ["y"])
    result = torchql.fit(model, data, torch.tensor([1.5]), method=method, grid=GRID)
    assert result.success, result.message
    for tensor in (result.x0, result.estimates, result.residuals, result.jacobian, result.singular_values,
                   result.params["k"], result.model.k, result.history[-1].x0, result.history[-1].params["k"]):
        assert tensor.dtype == torch.float32
    assert result.model.k.item() == pytest.approx(0.7, rel=1e-4)
    assert model.k.dtype == torch.float32 and model.k.item() == pytest.approx(0.3)


def noisy_decay(n=9):
    t = torch.linspace(0.0, 2.0, n, dtype=torch.float64)
    return t, 2.0 * torch.exp(-0.7 * t) + 0.01 * torch.sin(7.0 * t + 1.0)


@pytest.mark.parametrize("method", ["kantorovich", "shooting"])
def test_nan_values_are_skipped(method):
    t, y = noisy_decay()
    y_nan = y.clone()
    drop = torch.tensor([2, 5])
    y_nan[drop] = math.nan
    keep = torch.ones(9, dtype=torch.bool)
    keep[drop] = False
    # grid=8 puts a node on every time of t (0.25 apart), so both fits use the same grid and
    # differ only in the rows that the NaNs remove
    kwargs = dict(method=method, grid=8)
    with_nan = torchql.fit(Decay(0.3), torchql.Observations(t, y_nan, ["y"]), torch.tensor([1.5]), **kwargs)
    dropped = torchql.fit(Decay(0.3), torchql.Observations(t[keep], y[keep], ["y"]), torch.tensor([1.5]), **kwargs)
    assert with_nan.success and dropped.success
    assert with_nan.n_observations == dropped.n_observations == 7
    torch.testing.assert_close(with_nan.estimates, dropped.estimates, rtol=0, atol=1e-10)
    assert with_nan.sse == pytest.approx(dropped.sse, rel=1e-8)
    assert with_nan.sse > 1e-6  # the noise makes this a genuine least-squares problem
    assert torch.isfinite(with_nan.residuals).all() and with_nan.residuals.shape == (7,)
    torch.testing.assert_close(with_nan.residuals, dropped.residuals, rtol=0, atol=1e-10)


def _decay_least_squares(t, y):
    """The exact minimizer of sum((x0 exp(-k t) - y)^2), by Newton on the analytic gradient."""
    sse = lambda p: ((p[0] * torch.exp(-p[1] * t) - y) ** 2).sum()  # noqa: E731
    gradient = torch.func.grad(sse)
    sol = torchql.newton_raphson(gradient, torch.tensor([1.5, 0.3], dtype=torch.float64),
                                 jacobian=torch.func.jacrev(gradient))
    assert sol.success
    return sol.x


@pytest.mark.parametrize("method", ["kantorovich", "shooting"])
def test_estimates_are_the_least_squares_minimizer_on_a_coarse_grid(method):
    # with noisy data, inexact sensitivities would move the converged point off the minimizer
    t, y = noisy_decay()
    keep = torch.tensor([0, 1, 3, 4, 6, 7, 8])  # non-uniform times; grid nodes every 0.2 plus these
    t, y = t[keep], y[keep]
    result = torchql.fit(Decay(0.3), torchql.Observations(t, y, ["y"]), torch.tensor([1.5]), method=method, grid=GRID)
    assert result.success, result.message
    torch.testing.assert_close(result.estimates, _decay_least_squares(t, y), rtol=0, atol=1e-9)


@pytest.mark.parametrize("method", ["kantorovich", "shooting"])
def test_reported_jacobian_matches_analytic_sensitivities(method):
    # the sensitivities use the grid's interpolation of A(t): their error falls as h^4
    result = torchql.fit(Decay(0.3), decay_data(), torch.tensor([1.5]), method=method, grid=40)
    assert result.success, result.message
    x0, k = result.x0[0], result.model.k
    expected = torch.stack([torch.exp(-k * T), -T * x0 * torch.exp(-k * T)], dim=1)  # d y / d (x0, k)
    torch.testing.assert_close(result.jacobian, expected, rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize("method", ["kantorovich", "shooting"])
def test_t0_before_first_observation(method):
    t = torch.linspace(0.5, 2.5, 6, dtype=torch.float64)
    y = 2.0 * torch.exp(-0.7 * t)  # x(0) = 2
    result = torchql.fit(Decay(0.3), torchql.Observations(t, y, ["y"]), torch.tensor([1.5]), t0=0.0,
                         method=method, grid=GRID)
    assert result.success, result.message
    assert result.t0 == 0.0
    assert result.x0.item() == pytest.approx(2.0, rel=1e-7)
    assert result.model.k.item() == pytest.approx(0.7, rel=1e-7)
    torch.testing.assert_close(result.predict(t)[:, 0], y, rtol=1e-7, atol=1e-9)


def test_fixed_x0_listed_twice():
    with pytest.raises(ValueError, match="`fixed_x0` lists a state twice"):
        torchql.fit(Decay(), decay_data(), torch.tensor([1.0], dtype=torch.float64), params=["k"],
                    fixed_x0=["y", "y"], grid=GRID)


@pytest.mark.parametrize("name", ["rtol", "atol", "xtol", "t0"])
def test_bool_is_not_a_number(name):
    with pytest.raises(ValueError, match=f"`{name}` must be"):
        torchql.fit(Decay(), decay_data(), torch.tensor([1.0], dtype=torch.float64), grid=GRID, **{name: True})
