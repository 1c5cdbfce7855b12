"""``torchql.simulate``: plain forward (and backward) integration of a model."""

import contextlib
import math
import signal

import pytest
import torch

import torchql
from torchql.models import HarmonicOscillator

K = 0.7
X0 = 2.0


class Decay(torchql.ODEModel):
    """``y' = -k y``."""

    state_names = ("y",)

    def __init__(self, k=K, dtype=torch.float64):
        super().__init__()
        self.register_buffer("k", torch.tensor(k, dtype=dtype))

    def forward(self, t, x):
        return -self.k * x


def exact(t, t0=0.0):
    return X0 * torch.exp(-K * (t - t0))


def test_matches_analytic_solution():
    t = torch.linspace(0.0, 3.0, 7, dtype=torch.float64)
    x = torchql.simulate(Decay(), torch.tensor([X0], dtype=torch.float64), t, rtol=1e-11, atol=1e-13)
    assert x.shape == (7, 1) and x.dtype == torch.float64
    assert x[0, 0].item() == X0
    torch.testing.assert_close(x[:, 0], exact(t), rtol=0, atol=1e-9)


def test_default_tolerances_are_tight_in_float64():
    t = torch.linspace(0.0, 3.0, 7, dtype=torch.float64)
    x = torchql.simulate(Decay(), [X0], t)
    torch.testing.assert_close(x[:, 0], exact(t), rtol=0, atol=1e-8)


def test_integrates_backwards_before_t0():
    t = torch.tensor([-1.0, -0.5, 0.0, 0.5, 1.0], dtype=torch.float64)
    x = torchql.simulate(Decay(), torch.tensor([X0], dtype=torch.float64), t, t0=0.0, rtol=1e-11, atol=1e-13)
    assert x.shape == (5, 1)
    assert x[2, 0].item() == X0
    torch.testing.assert_close(x[:, 0], exact(t), rtol=1e-9, atol=0)


def test_all_times_before_t0():
    t = torch.tensor([-2.0, -1.0], dtype=torch.float64)
    x = torchql.simulate(Decay(), torch.tensor([X0], dtype=torch.float64), t, t0=0.5, rtol=1e-11, atol=1e-13)
    torch.testing.assert_close(x[:, 0], exact(t, 0.5), rtol=1e-9, atol=0)


def test_t0_between_output_times():
    t = torch.tensor([0.0, 1.0, 2.0], dtype=torch.float64)
    x = torchql.simulate(Decay(), torch.tensor([X0], dtype=torch.float64), t, t0=0.4, rtol=1e-11, atol=1e-13)
    torch.testing.assert_close(x[:, 0], exact(t, 0.4), rtol=1e-9, atol=0)


def test_two_state_model_and_single_time():
    t = torch.linspace(0.0, 2.0, 5, dtype=torch.float64)
    x = torchql.simulate(HarmonicOscillator(4.0), torch.tensor([1.0, 0.0], dtype=torch.float64), t,
                         rtol=1e-11, atol=1e-13)
    torch.testing.assert_close(x, torch.stack([torch.cos(2 * t), -2 * torch.sin(2 * t)], dim=1), rtol=0, atol=1e-9)
    one = torchql.simulate(HarmonicOscillator(4.0), torch.tensor([1.0, 0.0], dtype=torch.float64), [0.0])
    assert torch.equal(one, torch.tensor([[1.0, 0.0]], dtype=torch.float64))


def test_float32_model_gives_float32():
    x = torchql.simulate(Decay(dtype=torch.float32), [X0], [0.0, 1.0])
    assert x.dtype == torch.float32
    assert x[1, 0].item() == pytest.approx(X0 * math.exp(-K), rel=1e-5)


def test_fixed_step_solver():
    t = torch.linspace(0.0, 1.0, 101, dtype=torch.float64)
    x = torchql.simulate(Decay(), [X0], t, solver="rk4")
    torch.testing.assert_close(x[:, 0], exact(t), rtol=1e-8, atol=0)


def test_model_and_inputs_not_modified():
    model = Decay()
    x0 = torch.tensor([X0], dtype=torch.float64)
    t = torch.tensor([0.0, 1.0], dtype=torch.float64)
    torchql.simulate(model, x0, t)
    assert model.k.item() == K and x0.item() == X0 and torch.equal(t, torch.tensor([0.0, 1.0], dtype=torch.float64))


@pytest.mark.parametrize("solver", ["rk45", "DOPRI5", "scipy_solver", ""])
def test_bad_solver_name_lists_valid_ones(solver):
    with pytest.raises(ValueError, match=r"`solver` must be one of \(.*'dopri5'.*\); received") as info:
        torchql.simulate(Decay(), [X0], [0.0, 1.0], solver=solver)
    for name in torchql.SOLVER_NAMES:
        assert repr(name) in str(info.value)


def test_solver_names():
    assert "dopri5" in torchql.SOLVER_NAMES and "rk4" in torchql.SOLVER_NAMES
    assert "scipy_solver" not in torchql.SOLVER_NAMES


@pytest.mark.parametrize("x0", [[1.0, 2.0], [[1.0]], 1.0, []])
def test_bad_x0_shape(x0):
    with pytest.raises(ValueError, match=r"`x0` must have shape \(n_states,\) = \(1,\)"):
        torchql.simulate(Decay(), x0, [0.0, 1.0])


@pytest.mark.parametrize("t", [[], [[0.0, 1.0]], 0.0])
def test_bad_t_shape(t):
    with pytest.raises(ValueError, match="`t` must be a non-empty one-dimensional tensor"):
        torchql.simulate(Decay(), [X0], t)


@pytest.mark.parametrize("t", [[0.0, 0.0], [1.0, 0.0]])
def test_t_not_increasing(t):
    with pytest.raises(ValueError, match="`t` must be strictly increasing"):
        torchql.simulate(Decay(), [X0], t)


# ------------------------------------------------------------------ validation gaps (see reasons)
@contextlib.contextmanager
def time_limit(seconds):
    """Turn a hang into a TimeoutError (POSIX only)."""

    def handler(signum, frame):
        raise TimeoutError(f"did not return within {seconds} s")

    previous = signal.signal(signal.SIGALRM, handler)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


@pytest.mark.skipif(not hasattr(signal, "SIGALRM"), reason="needs SIGALRM")
def test_infinite_output_time_rejected():
    with time_limit(1.0):
        with pytest.raises(ValueError, match="`t` must be finite"):
            torchql.simulate(Decay(), [X0], [0.0, math.inf])


@pytest.mark.parametrize("t0", [math.nan, math.inf])
def test_non_finite_t0_rejected(t0):
    with pytest.raises(ValueError, match="`t0` must be"):
        torchql.simulate(Decay(), [X0], [0.0, 1.0], t0=t0)


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_non_finite_x0_rejected(bad):
    with pytest.raises(ValueError, match="`x0` must be finite"):
        torchql.simulate(Decay(), [bad], [0.0, 1.0])


@pytest.mark.parametrize("tolerances", [dict(rtol=-1.0), dict(rtol=0.0, atol=0.0), dict(atol=math.nan)])
def test_bad_tolerances_rejected(tolerances):
    with pytest.raises(ValueError, match="`(rtol|atol)` must be a positive finite number"):
        torchql.simulate(Decay(), [X0], [0.0, 1.0], **tolerances)


def test_model_not_an_odemodel():
    with pytest.raises(TypeError, match="`model` must be a torchql.ODEModel"):
        torchql.simulate(torch.nn.Linear(1, 1), [X0], [0.0, 1.0])


# --- the nonlinear model on a grid by multiple shooting (torchql.grid_solve) -----------------

class _Damped(torchql.ODEModel):
    """``y'' + c y' + k y = 0``: closed form, and linear so that one Newton step is exact."""

    state_names = ("y", "v")

    def __init__(self, c=0.1, k=3.0):
        super().__init__()
        self.register_buffer("c", torch.tensor(c, dtype=torch.float64))
        self.register_buffer("k", torch.tensor(k, dtype=torch.float64))

    def forward(self, t, x):
        y, v = x.unbind(-1)
        return torch.stack((v, -self.c * v - self.k * y), dim=-1)


class _Duffing(torchql.ODEModel):
    """A damped Duffing oscillator with a time-dependent forcing (nonlinear, non-autonomous)."""

    state_names = ("y", "v")

    def forward(self, t, x):
        y, v = x.unbind(-1)
        return torch.stack((v, -0.1 * v - 3.0 * y - 4.0 * y**3 + 0.5 * torch.cos(2 * t)), dim=-1)


def _damped_exact(t, c=0.1, k=3.0):
    w = math.sqrt(k - c * c / 4)
    y = torch.exp(-c * t / 2) * torch.sin(w * t) / w  # y(0) = 0, y'(0) = 1
    v = torch.exp(-c * t / 2) * (torch.cos(w * t) - c / (2 * w) * torch.sin(w * t))
    return torch.stack([y, v], dim=-1)


def test_grid_solve_matches_the_closed_form():
    from torchql.grid_solve import solve_on_grid

    grid = torch.linspace(0, 6.5, 651, dtype=torch.float64)
    z0 = torch.tensor([0.0, 1.0], dtype=torch.float64)
    rtol, atol = 1e-10, 1e-12
    X, info = solve_on_grid(_Damped(), z0, grid, rtol=rtol, atol=atol)
    # linear model: the first step lands within the integration error (Newton's matrices are
    # the coarse RK4 steps', not the extrapolated map's derivative); a second leaves a correction
    # at that error, and the third, a chord step, confirms it
    assert info.newton_iterations == 3
    # each interval within rtol / sqrt(N); accumulated over the grid, within sqrt(N) rtol at worst
    err = (X - _damped_exact(grid)).abs().max().item()
    assert err < (650**0.5) * (atol + rtol)
    assert X[0].tolist() == z0.tolist()


def test_grid_solve_agrees_with_dopri5_on_a_nonlinear_model():
    from torchql.grid_solve import solve_on_grid
    from torchql.integrate import solve

    grid = torch.linspace(0, 5, 501, dtype=torch.float64)
    z0 = torch.tensor([0.5, 0.0], dtype=torch.float64)
    model = _Duffing()
    truth = solve(model, z0, grid, solver="dopri8", rtol=1e-13, atol=1e-15)
    dopri5 = solve(model, z0, grid, solver="dopri5", rtol=1e-10, atol=1e-12)
    # a guess near the solution (as a linear prediction would be): quadratic convergence
    guess = truth + 1e-3 * torch.sin(3 * grid).unsqueeze(-1)
    X, info = solve_on_grid(model, z0, grid, rtol=1e-10, atol=1e-12, guess=guess)
    assert info.newton_iterations <= 4
    assert info.max_defect < 1e-12
    err, err5 = (X - truth).abs().max().item(), (dopri5 - truth).abs().max().item()
    assert err < max(10 * err5, 1e-9), (err, err5)


class _DuffingOneState(torchql.ODEModel):
    """:class:`_Duffing` written for one state: its values stacked without an axis, so that a
    batch of states does not broadcast with the batch of times and the call fails."""

    state_names = ("y", "v")

    def forward(self, t, x):
        y, v = x[0], x[1]
        return torch.stack((v, -0.1 * v - 3.0 * y - 4.0 * y**3 + 0.5 * torch.cos(2 * t)))


class _Coupled(torchql.ODEModel):
    """``y' = v``, ``v' = -3 y - 0.1 (y + v)``, the total of the states written ``x.sum(-1)``."""

    state_names = ("y", "v")

    def forward(self, t, x):
        y, v = x.unbind(-1)
        return torch.stack((v, -3.0 * y - 0.1 * x.sum(-1)), dim=-1)


class _CoupledOneState(_Coupled):
    """:class:`_Coupled` with the total written ``x.sum()``: right for one state, and on a batch a
    sum over all of them, values of the right shape but wrong, which the grid solver must notice."""

    def forward(self, t, x):
        y, v = x.unbind(-1)
        return torch.stack((v, -3.0 * y - 0.1 * x.sum()), dim=-1)


def test_grid_solve_calls_a_batch_taking_model_once_and_vmaps_one_that_is_not():
    """A model written for a batch of states (``x.unbind(-1)``) is called once per RK4 stage on every
    interval; one written for a single state is vmapped, whether the batch makes it fail or only
    gives wrong values; each solves its problem to the values of its batch-taking twin."""
    from torchql.grid_solve import _Field, solve_on_grid

    grid = torch.linspace(0, 5, 101, dtype=torch.float64)
    z0 = torch.tensor([0.5, 0.0], dtype=torch.float64)
    t = grid[:-1]
    x = torch.stack([torch.linspace(0.1, 0.5, 100), torch.linspace(-0.3, 0.2, 100)], dim=-1).double()
    pairs = ((_Duffing(), _DuffingOneState()), (_Coupled(), _CoupledOneState()))
    for batch_taking, one_state in pairs:
        for model, direct in ((batch_taking, True), (one_state, False)):
            field = _Field(model)
            values = field.values(t, x)
            assert field.values.direct is direct, type(model).__name__
            torch.testing.assert_close(values, torch.vmap(batch_taking)(t, x), rtol=1e-14, atol=0.0)
            torch.testing.assert_close(field.values(t, x), values, rtol=1e-14, atol=0.0)
        X, _ = solve_on_grid(batch_taking, z0, grid, rtol=1e-10, atol=1e-12)
        X_one, _ = solve_on_grid(one_state, z0, grid, rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(X_one, X, rtol=1e-12, atol=1e-14)


def test_grid_solve_failures():
    from torchql.grid_solve import solve_on_grid
    from torchql.integrate import IntegrationError

    grid = torch.linspace(0, 5, 11, dtype=torch.float64)
    z0 = torch.tensor([0.5, 0.0], dtype=torch.float64)
    with pytest.raises(IntegrationError, match="could not be integrated to the tolerance.*4 RK4 steps"):
        solve_on_grid(_Duffing(), z0, grid, rtol=1e-12, atol=1e-14, max_substeps=4)
    with pytest.raises(IntegrationError, match="did not converge in `max_newton` = 1"):
        solve_on_grid(_Duffing(), z0, torch.linspace(0, 5, 101, dtype=torch.float64), rtol=1e-10, atol=1e-12,
                      max_newton=1)
    with pytest.raises(ValueError, match="power of two"):
        solve_on_grid(_Duffing(), z0, grid, rtol=1e-10, atol=1e-12, max_substeps=3)
