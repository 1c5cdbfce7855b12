"""``torchql.solvers``: Rodas5P, batched and single, on problems with known solutions.

Bounds: a tolerance-controlled integration's global error is a small multiple of the tolerance
(the local errors add up, each at most ``atol + rtol |y|``); errors are measured in that mixed
norm, ``|y - exact| / (atol + rtol |exact|)``, and asserted below a small constant.
"""

import math

import numpy as np
import pytest
import torch

import torchql
from testmodels import Decay
from torchql.integrate import IntegrationError, solve
from torchql.model import AugmentedSystem
from torchql.models import Robertson
from torchql.solvers import MAX_STEPS, NON_FINITE, STEP_UNDERFLOW, STOPPED, SUCCESS, rodas5p_batch, rodas5p_solve

DT = torch.float64
LAMBDA = -1e6


def prothero_robinson(t, y):
    """``y' = lambda (y - cos t) - sin t``: solution ``cos t + (y0 - 1) exp(lambda t)``, stiff for ``lambda = -1e6``."""
    return LAMBDA * (y - torch.cos(t)) - torch.sin(t)


def forced_oscillator(t, y):
    """``y'' + y = sin 2t``: from ``(1, 0)``, ``y = cos t + 2/3 sin t - 1/3 sin 2t`` (non-autonomous)."""
    return torch.stack((y[1], -y[0] + torch.sin(2 * t)))


def forced_exact(t):
    return torch.stack((torch.cos(t) + 2 / 3 * torch.sin(t) - torch.sin(2 * t) / 3,
                        -torch.sin(t) + 2 / 3 * torch.cos(t) - 2 / 3 * torch.cos(2 * t)), dim=-1)


def mixed(y, exact, rtol, atol):
    return ((y - exact).abs() / (atol + rtol * exact.abs())).max().item()


@pytest.mark.parametrize("y0", [1.0, 0.0])
@pytest.mark.parametrize("hit", [False, True])
def test_stiff_linear_problem_matches_its_analytic_solution(y0, hit):
    # y0 = 0 starts a transient of time scale 1e-6; the outputs in between are interpolated
    # (hit=False) or landed on (hit=True): both within the tolerance
    t = torch.linspace(0, 2, 21, dtype=DT)
    rtol, atol = 1e-8, 1e-10
    y, sol = rodas5p_solve(prothero_robinson, torch.tensor([y0], dtype=DT), t, rtol=rtol, atol=atol,
                           hit=t if hit else None)
    exact = torch.cos(t) + (y0 - 1) * torch.exp(LAMBDA * t)
    assert bool(sol.ok[0]) and sol.message() is None
    assert mixed(y[:, 0], exact, rtol, atol) < 3
    assert sol.n_accepted.item() < 120  # an explicit solver needs ~1e6 steps here


def test_order_five_on_a_fixed_grid():
    # a loose tolerance accepts every step, and landing on each node of a uniform grid fixes the
    # step size: the error at the end falls as h^5 (non-autonomous: checks the f_t terms too)
    errors = []
    for N in (8, 16, 32):
        t = torch.linspace(0, 4, N + 1, dtype=DT)
        y, sol = rodas5p_solve(forced_oscillator, torch.tensor([1.0, 0.0], dtype=DT), t, rtol=1e3, atol=1e3, hit=t)
        assert sol.n_accepted.item() == N and sol.n_rejected.item() == 0
        errors.append((y[-1] - forced_exact(t[-1])).abs().max().item())
    orders = [math.log2(errors[i] / errors[i + 1]) for i in range(2)]
    assert all(4.6 < p < 5.6 for p in orders), orders


@pytest.mark.parametrize("rtol", [1e-6, 1e-10])
def test_dense_output_error_is_of_the_tolerance(rtol):
    t = torch.linspace(0, 10, 401, dtype=DT)
    y, sol = rodas5p_solve(forced_oscillator, torch.tensor([1.0, 0.0], dtype=DT), t, rtol=rtol, atol=rtol)
    assert sol.n_accepted.item() < 320  # fewer steps than the 400 nodes: they are interpolated
    assert mixed(y, forced_exact(t), rtol, rtol) < 10


def _robertson_batch():
    system = AugmentedSystem(Robertson(), ["k1", "k2", "k3"], DT, torch.device("cpu"))
    z0 = torch.tensor([[1, 0, 0, 0.04, 3e7, 1e4], [1, 0, 0, 0.08, 3e7, 1e4], [1, 0, 0, 0.04, 1e7, 3e4]], dtype=DT)
    grid = torch.cat([torch.zeros(1, dtype=DT), torch.logspace(-4, 1, 12, dtype=DT)])
    return system, z0, grid


def test_batched_equals_per_sample_with_their_own_steps():
    system, z0, grid = _robertson_batch()
    land = torch.zeros(grid.shape[0], dtype=torch.bool)
    sol = rodas5p_batch(system.f, z0, grid, rtol=1e-7, atol=1e-14, error_components=3, land=land)
    assert sol.ok.all() and sol.y.shape == (3, 13, 6)
    for s in range(3):
        alone, single = rodas5p_solve(system.model_with(z0[s, 3:]), z0[s, :3], grid, rtol=1e-7, atol=1e-14)
        torch.testing.assert_close(sol.y[s, :, :3], alone, rtol=1e-12, atol=1e-18)
        assert sol.n_accepted[s] == single.n_accepted[0] and sol.n_rejected[s] == single.n_rejected[0]
    assert len(set(sol.n_accepted.tolist())) == 3  # each sample on its own step history
    # the coefficients ride along unchanged (to roundoff: the pivoted LU mixes their zero rows in)
    torch.testing.assert_close(sol.y[:, :, 3:], z0[:, None, 3:].expand(3, 13, 3), rtol=1e-14, atol=0)


def barrier(t, z):
    """``y' = p y`` below ``y = 2``, NaN above: from ``y = 1`` it fails at ``t = ln 2 / p``."""
    y, p = z.unbind(-1)
    return torch.stack((torch.where(y < 2, p * y, torch.nan), torch.zeros_like(p)))


def test_per_sample_grids_and_failures_do_not_touch_the_others():
    z0 = torch.tensor([[1.0, 0.25], [1.0, 2.0]], dtype=DT)
    grid = torch.tensor([[0.0, 1.0, 2.0], [0.0, 1.5, 1.5]], dtype=DT)
    sol = rodas5p_batch(barrier, z0, grid, rtol=1e-9, atol=1e-12, error_components=1)
    assert sol.status.tolist() == [SUCCESS, NON_FINITE]
    torch.testing.assert_close(sol.y[0, :, 0], torch.exp(0.25 * grid[0]), rtol=1e-8, atol=0)
    assert torch.isnan(sol.y[1]).all() and "non-finite" in sol.message(1)
    assert abs(sol.t[1].item() - math.log(2) / 2) < 1e-6 and sol.message(0) is None


def test_a_stop_test_ends_a_sample_at_a_landed_node_and_leaves_the_others():
    """``stop`` is asked after landings only (the last node's too, where its answer is moot), sees
    the values landed so far and NaN from the next node on, and ends the samples it names as
    ``STOPPED``; the other samples' steps and values are those of the run without it."""
    z0 = torch.tensor([[1.0, 0.5], [1.0, 1.0], [1.0, 0.25]], dtype=DT)
    grid = torch.linspace(0.0, 1.0, 11, dtype=DT)
    land = torch.zeros(11, dtype=torch.bool)
    land[[2, 5, 8]] = True  # the others (but the last) from the dense output
    asked = []

    def stop(rows, y, reached):
        asked.append((rows.clone(), reached.clone()))
        for k, r in enumerate(rows.tolist()):
            landed = [g for g in (0, 2, 5, 8) if g < reached[k]]
            torch.testing.assert_close(y[k, landed, 0], torch.exp(z0[r, 1] * grid[landed]), rtol=1e-7, atol=0)
            assert torch.isnan(y[k, int(reached[k]):]).all()
        # sample 1 once e^t > 1.5; "all" at the last node, which must not stop any
        return ((rows == 1) & (y[:, :, 0].nan_to_num(0).amax(dim=1) > 1.5)) | (reached == 11)

    sol = rodas5p_batch(barrier, z0, grid, rtol=1e-9, atol=1e-12, error_components=1, land=land, stop=stop)
    free = rodas5p_batch(barrier, z0, grid, rtol=1e-9, atol=1e-12, error_components=1, land=land)
    assert sol.status.tolist() == [SUCCESS, STOPPED, SUCCESS]
    assert sol.t[1].item() == pytest.approx(grid[5].item())  # e^0.4 < 1.5 < e^0.5: at the second landing
    assert torch.isnan(sol.y[1]).all() and "stopped at t = 0.5" in sol.message(1) and not sol.ok[1]
    for s in (0, 2):
        assert torch.equal(sol.y[s], free.y[s]) and sol.n_accepted[s] == free.n_accepted[s]
    reached = torch.cat([r for _, r in asked])
    assert set(reached.tolist()) == {3, 6, 9, 11} and torch.cat([rows for rows, _ in asked]).numel() == 4 + 2 + 4


def _solutions_equal(a, b) -> bool:
    same = (torch.equal(a.y.nan_to_num(7.0), b.y.nan_to_num(7.0)) and torch.equal(a.status, b.status)
            and torch.equal(a.t, b.t) and torch.equal(a.n_accepted, b.n_accepted)
            and torch.equal(a.n_rejected, b.n_rejected) and (a.n_f, a.n_jac) == (b.n_f, b.n_jac))
    if a.steps is not None:
        same = same and all(torch.equal(getattr(a.steps, k), getattr(b.steps, k)) for k in ("t", "h", "end", "y", "K"))
    return same


def test_one_sample_takes_the_batched_loops_steps_to_the_bit(monkeypatch):
    """One sample runs a loop whose step control is in Python numbers; every step, value, count
    and status equals the batched loop's (made to run it here), on every path: landing on every
    node, the dense output between landings (its error controlled too), a per-sample grid, the
    step budget, a blow-up, a non-finite start, repeated nodes, the stop test, the steps kept."""
    from torchql.solvers import rosenbrock

    def vdp(t, y):  # van der Pol, mu = 300: stiff drifts and fast jumps
        return torch.stack((y[1], 300.0 * (1 - y[0] ** 2) * y[1] - y[0]))

    grid = torch.cat([torch.zeros(1, dtype=DT), torch.linspace(17.5, 700.0, 40, dtype=DT)])
    every7 = torch.zeros(41, dtype=torch.bool)
    every7[::7] = True
    y0 = torch.tensor([[2.0, 0.0]], dtype=DT)
    rob, r0 = Robertson(), torch.tensor([[1.0, 0.0, 0.0]], dtype=DT)
    r_grid = torch.cat([torch.zeros(1, dtype=DT), torch.logspace(-4, 5, 28, dtype=DT)])
    cases = [
        (vdp, y0, grid, dict(rtol=1e-6, atol=1e-8)),
        (vdp, y0, grid, dict(rtol=1e-6, atol=1e-8, land=every7, keep_steps=True, vectorize=False)),
        (vdp, y0, grid.unsqueeze(0), dict(rtol=1e-6, atol=1e-8, land=every7.unsqueeze(0))),
        (vdp, y0, grid, dict(rtol=1e-6, atol=1e-8, max_steps=30)),
        (vdp, y0, grid, dict(rtol=1e-6, atol=1e-8, land=every7, stop=lambda rows, y, reached: reached >= 15)),
        (vdp, y0, torch.tensor([0.0, 0.0, 1.0, 1.0, 2.0], dtype=DT), dict(rtol=1e-6, atol=1e-8)),
        (rob.forward, r0, r_grid, dict(rtol=1e-8, atol=1e-14, land=torch.zeros(29, dtype=torch.bool), keep_steps=True)),
        (lambda t, y: y * y, torch.ones(1, 1, dtype=DT), torch.tensor([0.0, 0.5, 2.0], dtype=DT), dict(rtol=1e-8, atol=1e-10)),
        (lambda t, y: y, torch.full((1, 1), math.nan, dtype=DT), torch.tensor([0.0, 1.0], dtype=DT), dict(rtol=1e-8, atol=1e-10)),
    ]
    alone = [rodas5p_batch(f, y, g, **kw) for f, y, g, kw in cases]
    monkeypatch.setattr(rosenbrock, "_one_sample", rosenbrock._batched)
    batched = [rodas5p_batch(f, y, g, **kw) for f, y, g, kw in cases]
    assert [int(s.status[0]) for s in alone] == [SUCCESS] * 3 + [MAX_STEPS, STOPPED, SUCCESS, SUCCESS, STEP_UNDERFLOW,
                                                                  NON_FINITE]
    assert alone[1].steps.t.shape[0] > 100 and alone[4].t.item() == grid[14].item()  # the landing on node 14
    for a, b in zip(alone, batched):
        assert _solutions_equal(a, b)


def test_float32_on_the_models_dtype():
    t = torch.tensor([0.0, 1.0, 40.0])
    y32 = torchql.simulate(Robertson().float(), [1.0, 0.0, 0.0], t, solver="rodas5p", rtol=1e-5, atol=1e-9)
    y64 = torchql.simulate(Robertson(), [1.0, 0.0, 0.0], t.double(), solver="rodas5p", rtol=1e-8, atol=1e-14)
    assert y32.dtype == torch.float32
    assert mixed(y32.double(), y64, 1e-5, 1e-9) < 10


def test_backward_in_time_through_simulate():
    t = torch.tensor([-1.0, -0.5, 0.0, 0.5, 1.0], dtype=DT)
    y = torchql.simulate(Decay(0.7, dtype=DT), [2.0], t, t0=0.0, solver="rodas5p", rtol=1e-11, atol=1e-13)
    torch.testing.assert_close(y[:, 0], 2.0 * torch.exp(-0.7 * t), rtol=1e-9, atol=0)


def test_step_budget_and_blow_up_raise_integration_error():
    y0 = torch.tensor([1.0, 0.0], dtype=DT)
    t = torch.tensor([0.0, 100.0], dtype=DT)
    with pytest.raises(IntegrationError, match="step budget .max_steps=5."):
        solve(forced_oscillator, y0, t, solver="rodas5p", rtol=1e-8, atol=1e-8, max_steps=5)
    with pytest.raises(IntegrationError, match="non-finite .NaN or inf. at t = 0.34657"):
        solve(barrier, torch.tensor([1.0, 2.0], dtype=DT), torch.tensor([0.0, 2.0], dtype=DT),
              solver="rodas5p", rtol=1e-8, atol=1e-8)
    _, sol = rodas5p_solve(forced_oscillator, y0, t, rtol=1e-8, atol=1e-8, max_steps=5)
    assert sol.status.item() == MAX_STEPS and sol.status.item() != NON_FINITE


def test_a_model_jacrev_cannot_differentiate_is_reported():
    def numpy_field(t, y):
        return torch.as_tensor(-np.asarray(y))
    with pytest.raises(IntegrationError, match="jacrev"):
        solve(numpy_field, torch.tensor([1.0], dtype=DT), torch.tensor([0.0, 1.0], dtype=DT), solver="rodas5p",
              rtol=1e-6, atol=1e-6)


def test_the_solver_name_is_registered_and_a_wrong_one_lists_the_valid():
    assert "rodas5p" in torchql.SOLVER_NAMES and "dopri5" in torchql.SOLVER_NAMES
    with pytest.raises(ValueError, match="rodas5p"):
        torchql.simulate(Robertson(), [1.0, 0.0, 0.0], [0.0, 1.0], solver="rodas")


def test_bad_arguments_name_the_argument():
    f = forced_oscillator
    grid = torch.tensor([0.0, 1.0], dtype=DT)
    with pytest.raises(TypeError, match="`y0`"):
        rodas5p_batch(f, torch.tensor([1.0, 0.0], dtype=DT), grid, rtol=1e-6, atol=1e-6)
    with pytest.raises(ValueError, match="`grid`"):
        rodas5p_batch(f, torch.ones(1, 2, dtype=DT), grid.flip(0), rtol=1e-6, atol=1e-6)
    with pytest.raises(ValueError, match="`rtol`"):
        rodas5p_batch(f, torch.ones(1, 2, dtype=DT), grid, rtol=-1.0, atol=1e-6)
    with pytest.raises(ValueError, match="`land`"):
        rodas5p_batch(f, torch.ones(1, 2, dtype=DT), grid, rtol=1e-6, atol=1e-6, land=torch.ones(3, dtype=torch.bool))
    with pytest.raises(TypeError, match="`stop` must be a callable"):
        rodas5p_batch(f, torch.ones(1, 2, dtype=DT), grid, rtol=1e-6, atol=1e-6, stop=1.5)


def test_adjoint_fit_refuses_the_stiff_solver_by_name():
    t = torch.linspace(0, 1, 5, dtype=DT)
    data = torchql.Observations(t, torch.ones(5, 1, dtype=DT), observe=["y1"])
    with pytest.raises(ValueError, match="`solver` of adjoint_fit must be a torchdiffeq method"):
        torchql.baselines.adjoint_fit(Robertson(), data, x0=torch.tensor([1.0, 0.0, 0.0], dtype=DT),
                                      solver="rodas5p")


def test_nodes_passed_on_per_sample_padded_grids_equal_the_single_solves():
    """Nodes filled from the recorded steps' dense output on per-sample grids ``(S, G)`` (the
    shorter padded by its last node): each sample as its own solve on its own grid."""
    system, z0, _ = _robertson_batch()
    grid = torch.tensor([[0.0, 1e-3, 0.01, 0.1, 1.0, 10.0], [0.0, 0.02, 0.3, 2.0, 2.0, 2.0],
                         [0.0, 1e-4, 5e-4, 0.5, 0.7, 5.0]], dtype=DT)
    land = torch.zeros_like(grid, dtype=torch.bool)
    sol = rodas5p_batch(system.f, z0, grid, rtol=1e-7, atol=1e-14, error_components=3, land=land)
    assert sol.ok.all()
    for s in range(3):
        alone, _ = rodas5p_solve(system.model_with(z0[s, 3:]), z0[s, :3], grid[s], rtol=1e-7, atol=1e-14)
        torch.testing.assert_close(sol.y[s, :, :3], alone, rtol=1e-12, atol=1e-18)
    torch.testing.assert_close(sol.y[1, 3:], sol.y[1, 3:4].expand(3, -1), rtol=0, atol=0)


def test_a_budget_between_two_nodes_fails_only_where_an_interval_spends_it(monkeypatch):
    """``interval_steps`` (a fit's ``max_steps``, which torchdiffeq counts per output time) caps the
    trial steps between two nodes, not the whole run's: van der Pol (mu = 300) on 40 intervals
    takes 558 trial steps, at most 222 of them (measured) in one interval. So a budget of 222
    changes no step, 221 fails in that interval, and a whole-run budget of 300 fails as such; the
    one-sample loop and the batched loop agree to the bit."""
    from torchql.solvers import rosenbrock

    def vdp(t, y):
        return torch.stack((y[1], 300.0 * (1 - y[0] ** 2) * y[1] - y[0]))

    grid = torch.cat([torch.zeros(1, dtype=DT), torch.linspace(17.5, 700.0, 40, dtype=DT)])
    y0 = torch.tensor([[2.0, 0.0]], dtype=DT)

    def runs():
        free = rodas5p_batch(vdp, y0, grid, rtol=1e-6, atol=1e-8)
        roomy = rodas5p_batch(vdp, y0, grid, rtol=1e-6, atol=1e-8, interval_steps=222)
        short = rodas5p_batch(vdp, y0, grid, rtol=1e-6, atol=1e-8, interval_steps=221)
        whole = rodas5p_batch(vdp, y0, grid, rtol=1e-6, atol=1e-8, max_steps=300)
        return free, roomy, short, whole

    free, roomy, short, whole = alone = runs()
    assert int(free.n_accepted + free.n_rejected) == 558
    assert _solutions_equal(free, roomy)
    assert int(short.status) == MAX_STEPS and short.message(0).startswith("max_steps = 221 steps between two grid nodes")
    assert int(whole.status) == MAX_STEPS and "step budget (max_steps=300)" in whole.message(0)
    monkeypatch.setattr(rosenbrock, "_one_sample", rosenbrock._batched)
    assert all(_solutions_equal(a, b) for a, b in zip(alone, runs()))
    with pytest.raises(ValueError, match="`interval_steps` must be a positive integer or None; received 0"):
        rodas5p_batch(vdp, y0, grid, rtol=1e-6, atol=1e-8, interval_steps=0)
