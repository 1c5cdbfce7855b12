"""``torchql.solvers.sensitivity``: a solution and its sensitivities together by Rodas5P.

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
from torchql.solvers.sensitivity import SensitivityField, joint_state, split_joint

DT = torch.float64
RTOL, ATOL = 1e-8, 1e-12


def solve(system, z0, columns, grid, vectorize):
    m = columns.shape[-1]
    field = SensitivityField(system, m, vectorize=vectorize)
    sol = rodas5p_batch(field, joint_state(z0, columns, system.n), grid, rtol=RTOL, atol=ATOL,
                        error_components=system.n + system.n * m, vectorize=vectorize)
    assert sol.ok.all()
    return split_joint(sol.y, system.n, system.M, m)


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
