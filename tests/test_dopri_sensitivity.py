"""The explicit pair's steps differentiated: a non-stiff model's solution with its sensitivities."""

import pytest
import torch

import torchql
from testmodels import Relaxation, relaxation_solution
from torchql.dopri_sensitivity import explicit_sensitivities
from torchql.model import AugmentedSystem
from torchql.models import LinearOscillator
from torchql.solvers import sensitivity

DT = torch.float64
RTOL, ATOL = 1e-10, 1e-12


def _relaxation(grid, x0=2.0, k=2.0):
    """``x(t)`` and its derivatives in ``x0`` and ``k``, scaled as the engine scales its columns."""
    x0_, k_ = torch.tensor(x0, dtype=DT, requires_grad=True), torch.tensor(k, dtype=DT, requires_grad=True)
    exact = relaxation_solution(grid, x0_, k_)
    d_x0 = torch.stack([torch.autograd.grad(e, x0_, retain_graph=True)[0] for e in exact])
    d_k = torch.stack([torch.autograd.grad(e, k_, retain_graph=True)[0] for e in exact])
    return exact.detach(), (x0 * d_x0, k * d_k)


@pytest.mark.parametrize("method", ["dop853", "dopri5"])
def test_columns_are_the_closed_form_derivatives(method):
    """``x' = -k (x - cos t)`` with ``k = 2`` (not stiff) over ``[0, 6]``: the solution and both
    columns within a few tolerances of the closed form, at every node (each one landed on)."""
    system = AugmentedSystem(Relaxation(2.0), ["k"], DT, torch.device("cpu"))
    grid = torch.linspace(0, 6, 61, dtype=DT)
    z0 = torch.tensor([[2.0, 2.0]], dtype=DT)
    columns = torch.tensor([[[2.0, 0.0], [0.0, 2.0]]], dtype=DT)
    z, V, errors, evals = explicit_sensitivities(system, z0, columns, grid, rtol=RTOL, atol=ATOL, method=method)
    assert errors == [None] and evals > 0
    x, scaled = _relaxation(grid)
    assert ((z[0, :, 0] - x).abs() / (ATOL + RTOL * x.abs())).max() < 20
    for column in (0, 1):
        error = (V[0, :, 0, column] - scaled[column]).abs() / (ATOL + RTOL * (scaled[column].abs() + x.abs()))
        assert error.max() < 20, (column, error.max())
    assert torch.equal(V[0, :, 1], columns[0, 1].expand(61, 2))  # the coefficient's row stays constant


def test_an_oscillation_of_many_periods_agrees_with_rodas5p_and_with_finite_differences():
    """A lightly damped oscillator over 16 periods: the columns agree with Rodas5P's differentiated
    steps and with central differences of tightly integrated solutions, to 1e-8 of their scale."""
    system = AugmentedSystem(LinearOscillator(A=0.1, B=400.0), ["A", "B"], DT, torch.device("cpu"))
    grid = torch.linspace(0, 5, 51, dtype=DT)
    z0 = torch.tensor([[1.0, 0.5, 0.1, 400.0]], dtype=DT)
    columns = torch.diag_embed(z0.abs())
    z, V, errors, _ = explicit_sensitivities(system, z0, columns, grid, rtol=RTOL, atol=ATOL)
    _, z_r, V_r = sensitivity.rodas5p_sensitivities(system, z0, columns, grid, rtol=RTOL, atol=ATOL)
    scale = V.abs().max()
    assert errors == [None] and float((V - V_r).abs().max()) < 1e-8 * scale
    for column in range(4):
        step = 1e-6 * z0[:, column].abs()
        ends = []
        for sign in (1, -1):
            shifted = z0.clone()
            shifted[:, column] += sign * step
            ends.append(torchql.dopri.dopri_batch(system, shifted, grid, rtol=1e-13, atol=1e-15, method="dop853")[0])
        difference = (ends[0] - ends[1]) / (2e-6)
        assert float((difference[..., :2] - V[..., :2, column]).abs().max()) < 1e-8 * scale, column


def test_each_sample_on_its_own_padded_grid_equals_its_single_solve_and_a_failed_one_says_why():
    """Per-sample grids ``(S, G)``, the shorter padded by its last node: each sample's solution
    and columns are those of its own solve; a sample whose start is not finite fails alone."""
    system = AugmentedSystem(Relaxation(2.0), ["k"], DT, torch.device("cpu"))
    grid = torch.tensor([[0.0, 0.5, 1.0, 2.5, 4.0], [0.0, 0.3, 2.0, 2.0, 2.0], [0.0, 1.0, 2.0, 3.0, 4.0]], dtype=DT)
    z0 = torch.tensor([[2.0, 2.0], [1.0, 3.0], [float("nan"), 2.0]], dtype=DT)
    columns = torch.diag_embed(torch.tensor([[2.0, 2.0], [1.0, 3.0], [1.0, 2.0]], dtype=DT))
    z, V, errors, _ = explicit_sensitivities(system, z0, columns, grid, rtol=RTOL, atol=ATOL)
    assert errors[:2] == [None, None] and "not finite" in errors[2]
    for s in range(2):
        z1, V1, _, _ = explicit_sensitivities(system, z0[s:s + 1], columns[s:s + 1], grid[s], rtol=RTOL, atol=ATOL)
        torch.testing.assert_close(z1[0], z[s], rtol=1e-12, atol=1e-15)
        torch.testing.assert_close(V1[0], V[s], rtol=1e-10, atol=1e-14)
    assert torch.equal(V[1, 2:], V[1, 2:3].expand(3, -1, -1))


def test_the_final_pass_of_a_non_stiff_model_differentiates_the_explicit_steps(monkeypatch):
    """Where the storage grid misses a fast change of a model that is not stiff (friction with
    ``tanh(50 v)``), the final pass's sensitivities integrated with the solution come from the
    explicit pair's own steps, not from Rodas5P's (an implicit solver's short steps on a non-stiff
    model: on an oscillation over 318 periods the whole fit took 77.5 s against 22.3 s,
    ``benchmarks/final_sensitivities.py --fit``)."""
    from test_engine_final import _Friction

    def refuse(*args, **kwargs):
        raise AssertionError("Rodas5P's sensitivities for a model that is not stiff")
    monkeypatch.setattr("torchql.engine_evaluate.rodas5p_sensitivities", refuse)
    t = torch.linspace(0, 10, 41, dtype=DT)
    x = torchql.simulate(_Friction(), torch.tensor([1.0, 0.0], dtype=DT), t)
    noise = 0.01 * torch.randn(41, 1, generator=torch.Generator().manual_seed(5), dtype=DT)
    data = torchql.Observations(t, x[:, :1] + noise, observe=["x"])
    x0 = torch.tensor([1.0, 0.0], dtype=DT)
    result = torchql.fit(_Friction(0.2, 0.2), data, x0)
    optimum = torchql.fit(_Friction(0.2, 0.2), data, x0, method="shooting")
    assert result.status is torchql.Status.CONVERGED, result.message
    assert "storage" in result.message and abs(result.sse - optimum.sse) <= 1e-9 * optimum.sse
