"""``torchql.solvers.sensitivity``: a solution and its sensitivities, Rodas5P's steps differentiated.

The reference is a stiff, non-autonomous linear model with a closed-form solution, whose exact
sensitivities to the initial state and to the rate come from differentiating that closed form
(``torch.autograd``), independently of the variational system. Errors are measured in the mixed
norm of the solver's error control, ``|error| / (atol + rtol |exact|)`` per component, and a
tolerance-controlled integration's global error is a small multiple of one.
"""

import pytest
import torch

from testmodels import Relaxation, relaxation_solution
from torchql.model import AugmentedSystem
from torchql.models import Robertson
from torchql.solvers import rodas5p_batch
from torchql.solvers.sensitivity import rodas5p_sensitivities

DT = torch.float64
RTOL, ATOL = 1e-8, 1e-12


def solve(system, z0, columns, grid, vectorize):
    """``(z, V)``; ``vectorize``: the batched path (each sample ``vmap``-ed over the augmented
    state), taken here on the samples and a copy of them; else one sample at a time (its model bound)."""
    if vectorize and z0.shape[0] == 1:
        z, V = solve(system, z0.expand(2, -1), columns.expand(2, -1, -1), grid, vectorize)
        return z[:1], V[:1]
    if not vectorize and z0.shape[0] > 1:
        parts = [solve(system, z0[s:s + 1], columns[s:s + 1], grid, vectorize) for s in range(z0.shape[0])]
        return torch.cat([z for z, _ in parts]), torch.cat([V for _, V in parts])
    sol, z, V = rodas5p_sensitivities(system, z0, columns, grid, rtol=RTOL, atol=ATOL)
    assert sol.ok.all()
    return z, V


@pytest.mark.parametrize("vectorize", [False, True])
def test_sensitivities_match_the_closed_form_derivatives(vectorize):
    system = AugmentedSystem(Relaxation(), ["k"], DT, torch.device("cpu"))
    grid = torch.tensor([0.0, 1e-4, 1e-3, 0.01, 0.1, 1.0, 3.0], dtype=DT)
    x0, k = torch.tensor(2.0, dtype=DT, requires_grad=True), torch.tensor(1e3, dtype=DT, requires_grad=True)
    exact = relaxation_solution(grid, x0, k)
    d_x0 = torch.stack([torch.autograd.grad(e, x0, retain_graph=True)[0] for e in exact])
    d_k = torch.stack([torch.autograd.grad(e, k, retain_graph=True)[0] for e in exact])
    # columns scaled as the engine scales them: d/dx0 by |x0|, d/dk by |k|
    z0 = torch.tensor([[2.0, 1e3]], dtype=DT)
    columns = torch.tensor([[[2.0, 0.0], [0.0, 1e3]]], dtype=DT)
    z, V = solve(system, z0, columns, grid, vectorize)
    x = exact.detach()
    assert ((z[0, :, 0] - x).abs() / (ATOL + RTOL * x.abs())).max() < 20
    for column, derivative, scale in ((0, d_x0, 2.0), (1, d_k, 1e3)):
        scaled = scale * derivative
        # the column's accuracy is relative to the unknown's effect on x, as its error control holds it
        error = (V[0, :, 0, column] - scaled).abs() / (ATOL + RTOL * (scaled.abs() + x.abs()))
        assert error.max() < 20, (column, error)
    assert torch.equal(z[0, :, 1], torch.full_like(grid, 1e3)) and torch.equal(V[0, :, 1], columns[0, 1].expand(7, 2))


def test_batched_and_single_sensitivities_agree_on_a_nonlinear_stiff_model():
    """Robertson kinetics over ``[0, 4]``: each sample of a batch (``torch.vmap`` of
    ``torch.func`` derivatives) equals its single-sample solve (``torch.autograd``) to rounding
    of the step sequence (the same steps, derivatives equal to round-off)."""
    system = AugmentedSystem(Robertson(), ["k1", "k2", "k3"], DT, torch.device("cpu"))
    grid = torch.tensor([0.0, 0.04, 0.4, 4.0], dtype=DT)
    rates = torch.tensor([[0.04, 3e7, 1e4], [0.05, 2e7, 2e4]], dtype=DT)
    z0 = torch.cat([torch.tensor([[1.0, 0.0, 0.0]], dtype=DT).expand(2, 3), rates], dim=1)
    columns = torch.zeros(2, 6, 3, dtype=DT)
    columns[:, 3:] = torch.diag_embed(rates)
    z, V = solve(system, z0, columns, grid, vectorize=True)
    for s in range(2):
        z1, V1 = solve(system, z0[s:s + 1], columns[s:s + 1], grid, vectorize=False)
        assert torch.allclose(z1[0], z[s], rtol=1e-10, atol=1e-16)
        assert torch.allclose(V1[0], V[s], rtol=1e-8, atol=1e-14)
    # against central differences of plain solves at a tight tolerance (step 1e-5 relative)
    eps = 1e-5
    for j in range(3):
        up, down = rates[:1].clone(), rates[:1].clone()
        up[0, j] *= 1 + eps
        down[0, j] *= 1 - eps
        ends = [rodas5p_batch(system.model_with(r[0]), z0[:1, :3], grid, rtol=1e-11, atol=1e-16, vectorize=False).y[0]
                for r in (up, down)]
        fd = (ends[0] - ends[1]) / (2 * eps)  # d x / d log k_j, the scaled column
        assert torch.allclose(V[0, :, :3, j], fd, rtol=1e-5, atol=1e-10), j


def _relaxation_derivatives(grid, x0=2.0, k=1e3):
    """The closed form on ``grid`` and its derivatives in ``x0`` and ``k`` scaled by them."""
    x0, k = torch.tensor(x0, dtype=DT, requires_grad=True), torch.tensor(k, dtype=DT, requires_grad=True)
    exact = relaxation_solution(grid, x0, k)
    scaled = [torch.stack([torch.autograd.grad(e, v, retain_graph=True)[0] for e in exact]) * v.detach()
              for v in (x0, k)]
    return exact.detach(), scaled


@pytest.mark.parametrize("vectorize", [False, True])
def test_columns_between_the_landed_nodes_come_from_the_dense_output(vectorize):
    """Nodes the steps pass without landing (all but the last here) take the columns from the
    step's dense output, within the tolerance as the landed ones."""
    system = AugmentedSystem(Relaxation(), ["k"], DT, torch.device("cpu"))
    grid = torch.cat([torch.zeros(1, dtype=DT), torch.logspace(-5, -2, 20, dtype=DT),
                      torch.linspace(0.05, 3, 400, dtype=DT)])
    land = torch.zeros(grid.shape[0], dtype=torch.bool)
    z0 = torch.tensor([[2.0, 1e3]], dtype=DT).expand(2 if vectorize else 1, -1)
    columns = torch.tensor([[[2.0, 0.0], [0.0, 1e3]]], dtype=DT).expand(z0.shape[0], -1, -1)
    sol, z, V = rodas5p_sensitivities(system, z0, columns, grid, rtol=RTOL, atol=ATOL, land=land)
    assert sol.ok.all() and int(sol.n_accepted[0]) < grid.shape[0] // 2  # most nodes lie inside steps
    x, scaled = _relaxation_derivatives(grid)
    assert ((z[0, :, 0] - x).abs() / (ATOL + RTOL * x.abs())).max() < 20
    for column in (0, 1):
        error = (V[0, :, 0, column] - scaled[column]).abs() / (ATOL + RTOL * (scaled[column].abs() + x.abs()))
        assert error.max() < 20, (column, error)


def test_each_sample_on_its_own_padded_grid_equals_its_single_solve():
    """Per-sample grids ``(S, G)``, the shorter padded by its last node, some nodes passed
    without landing: each sample's solution and columns are those of its own solve."""
    system = AugmentedSystem(Robertson(), ["k1", "k2", "k3"], DT, torch.device("cpu"))
    grid = torch.tensor([[0.0, 0.01, 0.1, 0.5, 1.0, 4.0], [0.0, 0.02, 0.3, 2.0, 2.0, 2.0]], dtype=DT)
    land = torch.tensor([[False, False, True, False, False, True], [False, True, False, True, True, True]])
    rates = torch.tensor([[0.04, 3e7, 1e4], [0.05, 2e7, 2e4]], dtype=DT)
    z0 = torch.cat([torch.tensor([[1.0, 0.0, 0.0]], dtype=DT).expand(2, 3), rates], dim=1)
    columns = torch.zeros(2, 6, 3, dtype=DT)
    columns[:, 3:] = torch.diag_embed(rates)
    sol, z, V = rodas5p_sensitivities(system, z0, columns, grid, rtol=RTOL, atol=ATOL, land=land)
    assert sol.ok.all()
    for s in range(2):
        one, z1, V1 = rodas5p_sensitivities(system, z0[s:s + 1], columns[s:s + 1], grid[s], rtol=RTOL, atol=ATOL,
                                            land=land[s])
        assert torch.allclose(z1[0], z[s], rtol=1e-10, atol=1e-16)
        assert torch.allclose(V1[0], V[s], rtol=1e-8, atol=1e-14)
    assert torch.equal(z[1, 3:], z[1, 3:4].expand(3, -1)) and torch.equal(V[1, 3:], V[1, 3:4].expand(3, -1, -1))


@pytest.mark.parametrize("samples", [1, 2])
def test_samples_that_all_fail_at_once_get_their_first_columns_not_an_index_error(samples):
    """A start where the model is not finite (a polishing step's far point): no sample takes a step.
    The solution says each failed, and the columns are the first ones throughout (finite stand-ins,
    as for one failed sample among others), where indexing the steps' maps raised ``IndexError``."""
    system = AugmentedSystem(Relaxation(), ["k"], DT, torch.device("cpu"))
    grid = torch.tensor([0.0, 0.5, 1.0], dtype=DT)
    z0 = torch.tensor([[float("nan"), 1.0]], dtype=DT).expand(samples, -1)
    columns = torch.tensor([[[1.0, 0.0], [0.0, 1.0]]], dtype=DT).expand(samples, -1, -1)
    sol, z, V = rodas5p_sensitivities(system, z0, columns, grid, rtol=RTOL, atol=ATOL)
    assert not sol.ok.any()
    assert V.shape == (samples, 3, 2, 2) and torch.equal(V, columns.unsqueeze(1).expand(-1, 3, -1, -1))
