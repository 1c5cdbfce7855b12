"""Integrators for a batch of samples on one grid: each sample on its own error control."""

import torch

from torchql.batch_integrate import dopri_batch, propagate_linear_batch
from torchql.linearize import linearize
from torchql.model import AugmentedSystem
from torchql.models import CoastingCar
from torchql.models.car import AIR_DENSITY, GRAVITY
from torchql.superposition import initial_columns, propagate_linear
from torchql.trajectory import LinearizedReference

DT = torch.float64
AREA, MASS = 17.3, 80.43


def _cars(S=5):
    system = AugmentedSystem(CoastingCar(AREA, MASS), ["C_D", "mu"], DT, torch.device("cpu"))
    z0 = torch.stack([torch.linspace(100, 120, S, dtype=DT), torch.linspace(0.3, 0.6, S, dtype=DT),
                      torch.linspace(0.01, 0.02, S, dtype=DT)], dim=1)
    return system, z0


def _exact_speed(t, z0):
    """``v' = -a v^2 - c`` in closed form, ``(S, G)``."""
    a = (0.5 * AIR_DENSITY * AREA * z0[:, 1] / MASS).unsqueeze(1)
    c = (z0[:, 2] * GRAVITY).unsqueeze(1)
    return torch.sqrt(c / a) * torch.tan(torch.atan(z0[:, :1] * torch.sqrt(a / c)) - torch.sqrt(a * c) * t)


def test_dopri_lands_on_every_node_within_tolerance():
    system, z0 = _cars()
    grid = torch.linspace(0, 40, 41, dtype=DT)
    traj, ok, evals = dopri_batch(system, z0, grid, rtol=1e-10, atol=1e-12)
    assert ok.all() and evals > 0
    exact = _exact_speed(grid, z0)
    # local errors within 1e-10 over some 40 steps: the global error stays below 1e-9 relative
    assert float(((traj[..., 0] - exact) / exact).abs().max()) < 1e-9
    assert torch.equal(traj[..., 1:], z0[:, 1:].unsqueeze(1).expand(-1, 41, -1))


def test_dense_output_between_landing_nodes():
    system, z0 = _cars()
    grid = torch.linspace(0, 40, 41, dtype=DT)
    land = torch.zeros(41, dtype=torch.bool)
    land[::10] = True
    exact = _exact_speed(grid, z0)
    for rtol in (1e-6, 1e-9):
        dense, ok, evals = dopri_batch(system, z0, grid, rtol=rtol, atol=rtol * 1e-2, land=land)
        _, _, evals_landing = dopri_batch(system, z0, grid, rtol=rtol, atol=rtol * 1e-2)
        assert ok.all() and evals < evals_landing / 2  # long steps, the nodes in between interpolated
        # the fourth-order interpolant is as accurate as the steps (a few times rtol)
        assert float(((dense[..., 0] - exact) / exact).abs().max()) < 10 * rtol
        # the landing nodes are the solver's own values
        assert float(((dense[:, ::10, 0] - exact[:, ::10]) / exact[:, ::10]).abs().max()) < 5 * rtol


def test_a_sample_that_blows_up_fails_alone():
    # v' = -a v^2 - c with a < 0 and a large speed: v -> inf in finite time
    system, z0 = _cars(3)
    z0[1, 1] = -50.0
    grid = torch.linspace(0, 40, 21, dtype=DT)
    traj, ok, _ = dopri_batch(system, z0, grid, rtol=1e-8, atol=1e-10, max_steps=2000)
    assert ok.tolist() == [True, False, True]
    assert torch.isnan(traj[1]).all() and torch.isfinite(traj[[0, 2]]).all()


def test_linear_propagation_equals_the_single_propagation_per_sample():
    system, z0 = _cars(4)
    grid = torch.linspace(0, 40, 25, dtype=DT)
    traj, ok, _ = dopri_batch(system, z0, grid, rtol=1e-10, atol=1e-12)
    S, G, M = traj.shape
    lin = linearize(system, grid.repeat(S), traj.reshape(-1, M))
    lin = type(lin)(*(v.reshape(S, G, *v.shape[1:]) for v in lin))
    unknown = torch.arange(M)
    w0 = torch.stack([initial_columns(z0[s] + 0.5, unknown) for s in range(S)])  # off the reference
    W, failed, evals = propagate_linear_batch(grid, traj, lin.f, lin, w0, rtol=1e-10, atol=1e-12)
    assert not failed.any() and evals > 0
    for s in range(S):
        ref = LinearizedReference(grid, traj[s], lin.f[s], type(lin)(*(v[s] for v in lin)))
        W_single, _ = propagate_linear(ref, w0[s], rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(W[s], W_single, rtol=1e-13, atol=1e-13)


def test_single_node_grid():
    system, z0 = _cars(2)
    grid = torch.zeros(1, dtype=DT)
    traj, ok, evals = dopri_batch(system, z0, grid, rtol=1e-8, atol=1e-10)
    assert ok.all() and evals == 0 and torch.equal(traj[:, 0], z0)
