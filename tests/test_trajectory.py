"""Storage of the iterate on a grid and propagation of the quasilinear system over it."""

import math

import pytest
import torch

from torchql.linearize import Linearization
from torchql.superposition import LINEAR_SOLVERS, initial_columns, propagate_linear
from torchql.trajectory import LinearizedReference, hermite_basis

DT = torch.float64


def test_hermite_basis_reproduces_cubics():
    # p(s) = 1 + 2s - 3s^2 + 4s^3 on [0, 1] from values and slopes at the ends
    p = lambda s: 1 + 2 * s - 3 * s**2 + 4 * s**3
    dp = lambda s: 2 - 6 * s + 12 * s**2
    s = torch.linspace(0, 1, 11, dtype=DT)
    b00, b10, b01, b11 = hermite_basis(s)
    interp = b00 * p(0.0) + b10 * dp(0.0) + b01 * p(1.0) + b11 * dp(1.0)
    torch.testing.assert_close(interp, p(s), rtol=0, atol=1e-14)


def _reference_for(a, grid):
    """Reference for w' = a(t) w (M = 1), linearized about the exact solution w = exp(int a)."""
    t = grid
    A = a(t)
    # exact solution of w' = a w with w(0) = 1, for a(t) = cos(t): w = exp(sin t)
    z = torch.exp(torch.sin(t)).unsqueeze(-1)
    f = (A * z[:, 0]).unsqueeze(-1)
    jac = A.reshape(-1, 1, 1)
    a_dot = -torch.sin(t)
    # along the solution: d/dt f = a' z + a z' = (a' + a^2) z ; d/dt A = a'
    f_dot = ((a_dot + A**2) * z[:, 0]).unsqueeze(-1)
    lin = Linearization(f=f, jac=jac, f_dot=f_dot, jac_dot=a_dot.reshape(-1, 1, 1))
    return LinearizedReference(t, z, f, lin), z


@pytest.mark.parametrize("linear_solver", LINEAR_SOLVERS)
def test_grid_propagation_matches_the_analytic_solution(linear_solver):
    grid = torch.linspace(0, 3, 301, dtype=DT)
    ref, z = _reference_for(torch.cos, grid)
    w0 = initial_columns(torch.tensor([1.0], dtype=DT), torch.tensor([0]))
    W, n_evals = propagate_linear(ref, w0, solver="dopri5", rtol=1e-12, atol=1e-14, linear_solver=linear_solver)
    assert W.shape == (301, 1, 2)
    # the particular solution reproduces the reference; the homogeneous one is exp(sin t) too
    torch.testing.assert_close(W[:, 0, 0], z[:, 0], rtol=1e-9, atol=0)
    torch.testing.assert_close(W[:, 0, 1], torch.exp(torch.sin(grid)), rtol=1e-9, atol=0)
    assert n_evals > 0


@pytest.mark.parametrize("linear_solver", LINEAR_SOLVERS)
def test_constant_coefficients_match_the_matrix_exponential(linear_solver):
    # z' = K z with K a rotation-plus-decay: propagate the homogeneous solutions and compare with expm
    K = torch.tensor([[-0.1, 2.0], [-2.0, -0.1]], dtype=DT)
    grid = torch.linspace(0, 2, 101, dtype=DT)
    z = torch.stack([torch.linalg.matrix_exp(K * ti) @ torch.tensor([1.0, 0.0], dtype=DT) for ti in grid])
    f = z @ K.T
    jac = K.expand(101, 2, 2)
    lin = Linearization(f=f, jac=jac, f_dot=f @ K.T, jac_dot=torch.zeros_like(jac))
    ref = LinearizedReference(grid, z, f, lin)
    w0 = initial_columns(z[0], torch.tensor([0, 1]))
    W, _ = propagate_linear(ref, w0, solver="dopri5", rtol=1e-12, atol=1e-14, linear_solver=linear_solver)
    expected = torch.linalg.matrix_exp(K * 2.0)
    torch.testing.assert_close(W[-1, :, 1:], expected, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(W[-1, :, 0], z[-1], rtol=1e-10, atol=1e-12)


def test_interpolation_error_is_fourth_order():
    # Forcing interpolated between nodes: halving the grid spacing cuts the error ~16x.
    errors = []
    for nodes in (21, 41):
        grid = torch.linspace(0, 3, nodes, dtype=DT)
        # reference deliberately off the solution: the particular solution then depends on the
        # interpolated forcing between nodes
        t = grid
        z = (1 + 0.5 * torch.sin(3 * t)).unsqueeze(-1)
        z_dot = (1.5 * torch.cos(3 * t)).unsqueeze(-1)
        a = -1.0
        f = (a * z[:, 0] + torch.cos(2 * t)).unsqueeze(-1)  # f(t, z) = a z + cos 2t
        jac = torch.full((nodes, 1, 1), a, dtype=DT)
        f_dot = (a * z_dot[:, 0] - 2 * torch.sin(2 * t)).unsqueeze(-1)
        lin = Linearization(f=f, jac=jac, f_dot=f_dot, jac_dot=torch.zeros_like(jac))
        ref = LinearizedReference(grid, z, z_dot, lin)
        W, _ = propagate_linear(ref, initial_columns(torch.tensor([0.0], dtype=DT), torch.tensor([0])),
                                solver="dopri5", rtol=1e-13, atol=1e-15)
        # exact solution of w' = -w + cos 2t, w(0) = 0
        T = 3.0
        exact = (math.cos(2 * T) + 2 * math.sin(2 * T) - math.exp(-T)) / 5
        errors.append(abs(W[-1, 0, 0].item() - exact))
    assert errors[1] < errors[0] / 10, errors


def test_model_defect_is_zero_on_a_solution_and_relative_to_the_slopes():
    from torchql.trajectory import model_defect

    t = torch.linspace(0, 1, 11, dtype=torch.float64)
    z = torch.stack([torch.exp(-2 * t), 3 * torch.ones_like(t)], dim=-1)  # y = e^{-2t}, a parameter column
    f = torch.stack([-2 * z[:, 0], torch.zeros_like(t)], dim=-1)
    z_dot = f.clone()
    assert float(model_defect(f, z_dot, 1)) == 0.0
    z_dot[4, 0] += 0.5  # one node off by 0.5 against slopes of size at most 2
    assert abs(float(model_defect(f, z_dot, 1)) - 0.25) < 1e-15
    batch = model_defect(torch.stack([f, f]), torch.stack([f, z_dot]), 1)  # (S, G, M) -> (S,)
    assert batch.shape == (2,) and float(batch[0]) == 0.0 and abs(float(batch[1]) - 0.25) < 1e-15
