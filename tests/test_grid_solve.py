"""``torchql.grid_solve``: the nonlinear model on a grid by multiple shooting, every sample its own Newton."""

import math

import pytest
import torch

import torchql
from torchql.grid_solve import _Field, solve_on_grid_batch
from torchql.integrate import solve
from torchql.model import AugmentedSystem

DT = torch.float64


class _Damped(torchql.ODEModel):
    """``y'' + c y' + k y = 0``: closed form, and linear so that one Newton step is exact."""

    state_names = ("y", "v")

    def __init__(self, c=0.1, k=3.0):
        super().__init__()
        self.register_buffer("c", torch.tensor(c, dtype=DT))
        self.register_buffer("k", torch.tensor(k, dtype=DT))

    def forward(self, t, x):
        y, v = x.unbind(-1)
        return torch.stack((v, -self.c * v - self.k * y), dim=-1)


class _Duffing(torchql.ODEModel):
    """A damped Duffing oscillator with a time-dependent forcing (nonlinear, non-autonomous)."""

    state_names = ("y", "v")

    def forward(self, t, x):
        y, v = x.unbind(-1)
        return torch.stack((v, -0.1 * v - 3.0 * y - 4.0 * y**3 + 0.5 * torch.cos(2 * t)), dim=-1)


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


def _damped_exact(t, c=0.1, k=3.0):
    w = math.sqrt(k - c * c / 4)
    y = torch.exp(-c * t / 2) * torch.sin(w * t) / w  # y(0) = 0, y'(0) = 1
    v = torch.exp(-c * t / 2) * (torch.cos(w * t) - c / (2 * w) * torch.sin(w * t))
    return torch.stack([y, v], dim=-1)


def _solve(model, z0, grid, guess=None, **options):
    """One sample of ``model`` (no unknown coefficients: the augmented state is the state)."""
    system = AugmentedSystem(model, [], DT, torch.device("cpu"))
    return solve_on_grid_batch(system, z0.unsqueeze(0), grid, guess=None if guess is None else guess.unsqueeze(0),
                               **options)


def test_grid_solve_matches_the_closed_form():
    grid = torch.linspace(0, 6.5, 651, dtype=DT)
    z0 = torch.tensor([0.0, 1.0], dtype=DT)
    rtol, atol = 1e-10, 1e-12
    solved = _solve(_Damped(), z0, grid, rtol=rtol, atol=atol)
    assert bool(solved.ok[0]) and not bool(solved.over_budget[0])
    # linear model: the first step lands within the integration error (Newton's matrices are
    # the coarse RK4 steps', not the extrapolated map's derivative); a second leaves a correction
    # at that error, and the third, a chord step, confirms it
    assert int(solved.newton_iterations[0]) == 3
    # each interval within rtol / sqrt(N); accumulated over the grid, within sqrt(N) rtol at worst
    X = solved.traj[0]
    err = (X - _damped_exact(grid)).abs().max().item()
    assert err < (650**0.5) * (atol + rtol)
    assert X[0].tolist() == z0.tolist()


def test_grid_solve_agrees_with_dopri5_on_a_nonlinear_model():
    grid = torch.linspace(0, 5, 501, dtype=DT)
    z0 = torch.tensor([0.5, 0.0], dtype=DT)
    model = _Duffing()
    truth = solve(model, z0, grid, solver="dopri8", rtol=1e-13, atol=1e-15)
    dopri5 = solve(model, z0, grid, solver="dopri5", rtol=1e-10, atol=1e-12)
    # a guess near the solution (as a linear prediction would be): quadratic convergence
    guess = truth + 1e-3 * torch.sin(3 * grid).unsqueeze(-1)
    solved = _solve(model, z0, grid, guess, rtol=1e-10, atol=1e-12)
    assert bool(solved.ok[0]) and int(solved.newton_iterations[0]) <= 4
    err, err5 = (solved.traj[0] - truth).abs().max().item(), (dopri5 - truth).abs().max().item()
    assert err < max(10 * err5, 1e-9), (err, err5)


def test_grid_solve_calls_a_batch_taking_model_once_and_vmaps_one_that_is_not():
    """A model written for a batch of states (``x.unbind(-1)``) is called once per RK4 stage on every
    interval; one written for a single state is vmapped, whether the batch makes it fail or only
    gives wrong values; each solves its problem to the values of its batch-taking twin."""
    grid = torch.linspace(0, 5, 101, dtype=DT)
    z0 = torch.tensor([0.5, 0.0], dtype=DT)
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
        X = _solve(batch_taking, z0, grid, rtol=1e-10, atol=1e-12).traj
        X_one = _solve(one_state, z0, grid, rtol=1e-10, atol=1e-12).traj
        assert bool(torch.isfinite(X).all())
        torch.testing.assert_close(X_one, X, rtol=1e-12, atol=1e-14)


def test_grid_solve_failures_are_the_samples_own():
    """A sample fails without an error: over the step budget (``over_budget``), or Newton out of
    iterations (not over the budget); a bad ``max_substeps`` is an error."""
    grid = torch.linspace(0, 5, 11, dtype=DT)
    z0 = torch.tensor([0.5, 0.0], dtype=DT)
    tight = _solve(_Duffing(), z0, grid, rtol=1e-12, atol=1e-14, max_substeps=4)
    assert not bool(tight.ok[0]) and bool(tight.over_budget[0]) and bool(torch.isnan(tight.traj).all())
    short = _solve(_Duffing(), z0, torch.linspace(0, 5, 101, dtype=DT), rtol=1e-10, atol=1e-12, max_newton=1)
    assert not bool(short.ok[0]) and not bool(short.over_budget[0]) and int(short.newton_iterations[0]) == 1
    with pytest.raises(ValueError, match="power of two"):
        _solve(_Duffing(), z0, grid, rtol=1e-10, atol=1e-12, max_substeps=3)


def test_a_sample_whose_newton_correction_grows_again_fails_alone():
    """Three Duffing samples, the middle one's Newton started from node values off by up to 1:
    its correction grows again at the third iteration, so it stops there (not ok, not over the
    budget) while the other two, from near their solutions, converge to what each gets alone."""
    grid = torch.linspace(0, 5, 51, dtype=DT)
    model = _Duffing()
    z0 = torch.tensor([[0.5, 0.0], [0.5, 0.0], [0.3, 0.1]], dtype=DT)
    truth = torch.stack([solve(model, z0[s], grid, solver="dopri8", rtol=1e-13, atol=1e-15) for s in (0, 2)])
    far = torch.sin(3 * grid).unsqueeze(-1).expand(-1, 2) + z0[1]  # off by up to 1 at every node
    guess = torch.stack([truth[0] + 1e-3 * torch.sin(3 * grid).unsqueeze(-1), far,
                         truth[1] - 1e-3 * torch.cos(2 * grid).unsqueeze(-1)])
    system = AugmentedSystem(model, [], DT, torch.device("cpu"))
    solved = solve_on_grid_batch(system, z0, grid, rtol=1e-10, atol=1e-12, guess=guess, max_newton=25)
    assert solved.ok.tolist() == [True, False, True] and not bool(solved.over_budget[1])
    assert int(solved.newton_iterations[1]) == 3  # stopped by the growth, not by max_newton
    for s in (0, 2):
        alone = solve_on_grid_batch(system, z0[s:s + 1], grid, rtol=1e-10, atol=1e-12, guess=guess[s:s + 1])
        torch.testing.assert_close(solved.traj[s], alone.traj[0], rtol=1e-13, atol=0)
        assert int(solved.newton_iterations[s]) == int(alone.newton_iterations[0])
