"""The embedded Runge–Kutta pairs of the batched explicit integrator: orders, dense output, error
control, and each sample's solution independent of the batch around it."""

import math

import pytest
import torch

from torchql.dopri import dopri_batch
from torchql.integrate import IntegrationError, solve
from torchql.model import AugmentedSystem
from torchql.models import CoastingCar, LinearOscillator
from torchql.rk_pairs import PAIRS

DT = torch.float64


def _oscillators(S=3):
    """Damped oscillators ``y'' + A y' + B y = 0`` from ``(0, 1)``, ``(S, 4)`` start states."""
    system = AugmentedSystem(LinearOscillator(0.1, 3.0), ["A", "B"], DT, torch.device("cpu"))
    A = torch.linspace(0.05, 0.2, S, dtype=DT)
    B = torch.linspace(2.5, 3.5, S, dtype=DT)
    return system, torch.stack([torch.zeros(S, dtype=DT), torch.ones(S, dtype=DT), A, B], dim=1)


def _exact_position(t, z0):
    """``y(t)`` of :func:`_oscillators`' samples in closed form, ``(S, G)``."""
    a, B = (z0[:, 2] / 2).unsqueeze(1), z0[:, 3].unsqueeze(1)
    w = torch.sqrt(B - a * a)
    return torch.exp(-a * t) * (z0[:, :1] * torch.cos(w * t) + (z0[:, 1:2] + a * z0[:, :1]) / w * torch.sin(w * t))


@pytest.mark.parametrize("method, order", [("dopri5", 5), ("dop853", 8)])
def test_each_pair_has_its_order(method, order):
    # tolerances so loose that every step is the interval to the next node: fixed steps, whose
    # global error falls as h^order
    system, z0 = _oscillators()
    errors = []
    for nodes in (9, 17):
        grid = torch.linspace(0, 4, nodes, dtype=DT)
        traj, ok, _ = dopri_batch(system, z0, grid, rtol=1.0, atol=1.0, method=method, first_step=4 / (nodes - 1))
        assert ok.all()
        errors.append(float((traj[:, -1, 0] - _exact_position(grid, z0)[:, -1]).abs().max()))
    assert 2 ** (order - 0.5) < errors[0] / errors[1] < 2 ** (order + 0.7), errors


def test_dop853s_dense_output_is_of_seventh_order():
    # one step of 4 h (so loose a tolerance that it is accepted), three nodes inside it from the
    # dense output: their error falls as h^8
    system, z0 = _oscillators()
    errors = []
    for h in (0.125, 0.0625):
        grid = torch.linspace(0, 4 * h, 5, dtype=DT)
        land = torch.tensor([True, False, False, False, True])
        traj, ok, evals = dopri_batch(system, z0, grid, rtol=1.0, atol=1.0, land=land, method="dop853",
                                      first_step=4 * h)
        assert ok.all() and evals == 3 * (1 + 12 + 3)  # one step, its dense output, for each sample
        errors.append(float((traj[:, 1:4, 0] - _exact_position(grid, z0)[:, 1:4]).abs().max()))
    assert 2 ** 7.5 < errors[0] / errors[1] < 2 ** 9, errors


@pytest.mark.parametrize("rtol", [1e-6, 1e-8, 1e-10, 1e-12])
def test_dop853_meets_its_tolerance_in_far_fewer_evaluations(rtol):
    system, z0 = _oscillators(5)
    grid = torch.linspace(0, 6.5, 115, dtype=DT)
    land = torch.zeros(115, dtype=torch.bool)
    land[::8] = True
    exact = _exact_position(grid, z0)
    out = {}
    for method in PAIRS:
        traj, ok, evals = dopri_batch(system, z0, grid, rtol=rtol, atol=rtol * 1e-2, land=land, method=method)
        assert ok.all()
        out[method] = float((traj[..., 0] - exact).abs().max()), evals
    # the global error of a few dozen steps within a few tolerances (amplitude about 0.6)
    assert out["dop853"][0] < 5 * rtol
    # fewer evaluations at every tolerance here, far fewer at the tight ones
    assert out["dop853"][1] < (0.35 if rtol <= 1e-10 else 0.65) * out["dopri5"][1], out


def test_a_sample_in_a_batch_is_integrated_as_alone_to_the_bit():
    system = AugmentedSystem(CoastingCar(2.0, 1500.0), ["C_D", "mu"], DT, torch.device("cpu"))
    g = torch.Generator().manual_seed(0)
    S = 7
    z0 = torch.stack([30 + torch.randn(S, generator=g, dtype=DT), 0.35 + 0.05 * torch.randn(S, generator=g, dtype=DT),
                      0.015 + 0.002 * torch.randn(S, generator=g, dtype=DT)], dim=1)
    grid = torch.linspace(0, 60, 41, dtype=DT)
    land = torch.zeros(41, dtype=torch.bool)
    land[::4] = True
    together, ok, _ = dopri_batch(system, z0, grid, rtol=1e-10, atol=1e-12, land=land, method="dop853")
    assert ok.all()
    for s in range(S):
        alone, _, _ = dopri_batch(system, z0[s:s + 1], grid, rtol=1e-10, atol=1e-12, land=land, method="dop853")
        assert torch.equal(together[s:s + 1], alone)


def test_solve_by_dop853_forward_backward_and_through_hit_and_jump_times():
    model = LinearOscillator(0.1, 3.0).to(DT)
    y0 = torch.tensor([0.0, 1.0], dtype=DT)
    t = torch.linspace(0.4, 6.5, 15, dtype=DT)
    for times in (t, t.flip(0)):
        reference = solve(model, y0, times, solver="dopri5", rtol=1e-13, atol=1e-15)
        plain = solve(model, y0, times, solver="dop853", rtol=1e-10, atol=1e-12)
        assert float((plain - reference).abs().max()) < 5e-10
    reference = solve(model, y0, t, solver="dopri5", rtol=1e-13, atol=1e-15)
    landed = solve(model, y0, t, solver="dop853", rtol=1e-10, atol=1e-12, hit=torch.tensor([0.3, 1.7, 2.0], dtype=DT),
                   jumps=torch.tensor([1.0], dtype=DT), norm=lambda x: x.abs().max(), first_step=0.5)
    assert landed.shape == (15, 2) and float((landed - reference).abs().max()) < 5e-10
    with pytest.raises(IntegrationError, match="max_steps = 1 steps"):
        solve(model, y0, t, solver="dop853", rtol=1e-10, atol=1e-12, max_steps=1)


def test_dop853s_error_is_hairers_damped_fifth_order_estimate():
    # Hairer's err = |h| e5^2 / sqrt(e5^2 + 0.01 e3^2) in the RMS norm: at most |h| e5, and the
    # RMS of the fifth-order estimate where the third-order one vanishes
    pair = PAIRS["dop853"](DT, torch.device("cpu"))
    K = torch.randn(13, 2, 3, dtype=DT, generator=torch.Generator().manual_seed(1))
    hc = torch.tensor([[0.5], [2.0]], dtype=DT)
    sc = torch.full((2, 3), 1e-3, dtype=DT)
    rms = lambda x: x.square().mean(dim=1).sqrt()  # noqa: E731
    ratio = pair.error_ratio(K, hc, sc, rms)
    e5 = rms((pair.row_e5 @ K[:12].reshape(12, -1)).reshape(2, 3) / sc)
    e3 = rms((pair.row_e3 @ K[:12].reshape(12, -1)).reshape(2, 3) / sc)
    torch.testing.assert_close(ratio, hc.squeeze(1) * e5 ** 2 / torch.sqrt(e5 ** 2 + 0.01 * e3 ** 2), rtol=1e-14, atol=0)
    assert bool((ratio <= hc.squeeze(1) * e5).all())
    assert math.isclose(float(pair.error_ratio(torch.zeros_like(K), hc, sc, rms)[0]), 0.0)


@pytest.mark.parametrize("method", ["dopri5", "dop853"])
def test_a_stiff_sample_is_found_stiff_long_before_the_step_budget_and_the_others_go_on_as_alone(method):
    """Robertson's kinetics at its standard rates (eigenvalues to -1e4) beside the same reactions
    a million times slower in ``k2``, ``k3`` (not stiff): Hairer's test ends the stiff sample after
    about a thousand steps (each pair's own ``h lambda`` bound), with words that say so, where the
    explicit pair crawled until its 100,000-step budget ran out; the other is integrated as alone,
    to the bit."""
    from torchql.models import Robertson
    system = AugmentedSystem(Robertson(), ["k1", "k2", "k3"], DT, torch.device("cpu"))
    z0 = torch.tensor([[1.0, 0.0, 0.0, 0.04, 3e7, 1e4], [1.0, 0.0, 0.0, 0.04, 30.0, 0.01]], dtype=DT)
    grid = torch.tensor([0.0, 1.0, 40.0], dtype=DT)
    messages: list = []
    out, ok, evals = dopri_batch(system, z0, grid, rtol=1e-10, atol=1e-12, method=method, messages=messages)
    assert not ok[0] and "became stiff" in messages[0] and "rodas5p" in messages[0]
    assert evals < 3000 * PAIRS[method].evals
    assert ok[1] and messages[1] is None
    alone, _, _ = dopri_batch(system, z0[1:], grid, rtol=1e-10, atol=1e-12, method=method)
    assert torch.equal(out[1:], alone)


@pytest.mark.parametrize("method, span", [("dopri5", 15.0), ("dop853", 60.0)])
def test_an_oscillation_of_many_periods_is_not_found_stiff(method, span):
    """A lightly damped oscillation over 48 or 190 periods at ``rtol=1e-10`` takes over a thousand steps,
    so the test runs, but accuracy holds the steps (``h lambda`` well inside the stability bound):
    it integrates to the end, as a stiff-looking count of steps alone would not tell."""
    system = AugmentedSystem(LinearOscillator(A=0.01, B=400.0), [], DT, torch.device("cpu"))
    grid = torch.linspace(0, span, 11, dtype=DT)
    out, ok, evals = dopri_batch(system, torch.tensor([[1.0, 0.0]], dtype=DT), grid, rtol=1e-10, atol=1e-12,
                                 method=method)
    assert ok.all() and evals > 1000 * PAIRS[method].evals
    t = grid[-1]
    omega = math.sqrt(400.0 - 0.01**2 / 4)
    exact = math.exp(-0.005 * t) * (math.cos(omega * t) + 0.005 / omega * math.sin(omega * t))
    assert abs(float(out[0, -1, 0]) - exact) < 1e-6
