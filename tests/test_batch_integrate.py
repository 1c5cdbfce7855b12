"""Integrators for a batch of samples on one grid: each sample on its own error control."""

import pytest
import torch

from torchql.batch_integrate import dopri_batch, integrate_each, propagate_linear_batch
from torchql.grid_solve import solve_on_grid_batch
from torchql.linearize import linearize
from torchql.model import AugmentedSystem
from torchql.models import CoastingCar, LinearOscillator
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


def test_each_failed_sample_is_said_in_words():
    """``messages`` says why each sample failed, where: a blow-up (``v' = 0.0128 v^2 - c`` from
    ``v = 110`` ends near ``t = 1 / (0.0128 * 110) = 0.71``), a non-finite initial state, a step
    budget; None for the samples that did not fail."""
    system, z0 = _cars(3)
    z0[1, 1] = -50.0
    z0[2, 0] = float("nan")
    grid = torch.linspace(0, 40, 21, dtype=DT)
    messages = []
    _, ok, _ = dopri_batch(system, z0, grid, rtol=1e-8, atol=1e-10, messages=messages)
    assert ok.tolist() == [True, False, False] and messages[0] is None
    assert messages[1].startswith("the step size underflowed")
    assert 0.70 < float(messages[1].split("t = ")[1]) < 0.72, messages[1]
    assert messages[2] == "the initial state is not finite"
    _, ok, _ = dopri_batch(system, z0[:1], grid, rtol=1e-8, atol=1e-10, max_steps=3, messages=messages)
    assert not bool(ok[0]) and messages[0].startswith("the budget of 3 steps ran out at t = "), messages


def test_a_step_budget_per_grid_interval_fails_only_the_sample_that_needs_more():
    """``interval_steps`` (the user's ``max_steps``, which torchdiffeq counts per output time)
    caps the trial steps between two grid nodes: on a grid of 4 intervals, the fast oscillator
    (``y'' = -400 y``, about 265 steps an interval at ``rtol = 1e-8``) runs out of 50, the slow one
    (``y'' = -y``, about 14) does not. A budget that binds no sample leaves every step as it was."""
    system = AugmentedSystem(LinearOscillator(0.0, 1.0), ["B"], DT, torch.device("cpu"))
    z0 = torch.tensor([[1.0, 0.0, 1.0], [1.0, 0.0, 400.0]], dtype=DT)
    grid = torch.linspace(0, 4, 5, dtype=DT)
    free, ok, evals = dopri_batch(system, z0, grid, rtol=1e-8, atol=1e-10)
    assert ok.all()
    messages = []
    capped, ok, _ = dopri_batch(system, z0, grid, rtol=1e-8, atol=1e-10, interval_steps=50, messages=messages)
    assert ok.tolist() == [True, False] and messages[0] is None
    assert messages[1].startswith("max_steps = 50 steps between two grid nodes ran out at t = "), messages
    assert float(messages[1].split("t = ")[1].split(" ")[0]) < 1.0  # in the first interval
    assert torch.equal(capped[0], free[0]) and torch.isnan(capped[1]).all()
    roomy, ok, roomy_evals = dopri_batch(system, z0, grid, rtol=1e-8, atol=1e-10, interval_steps=1000)
    assert ok.all() and torch.equal(roomy, free) and roomy_evals == evals


def test_a_stop_test_ends_only_the_samples_it_answers_true_at_a_node():
    """``stop`` is asked for the samples that landed on a node before their last (with the next
    node to reach, the values before it filled): the one it ends fails there, in words, with the
    values it had; the others' steps and values are those of a run without the test."""
    system, z0 = _cars(3)
    grid = torch.linspace(0, 40, 21, dtype=DT)
    free, ok, evals = dopri_batch(system, z0, grid, rtol=1e-10, atol=1e-12)
    assert ok.all()
    asked = []

    def stop(rows, out, reached):
        asked.append((rows.clone(), reached.clone()))
        assert bool((reached < 21).all()) and bool(torch.isfinite(out[0, :int(reached[0])]).all())
        return (rows == 1) & (reached == 8)  # sample 1, once it has landed on node 7

    messages = []
    stopped, ok, stopped_evals = dopri_batch(system, z0, grid, rtol=1e-10, atol=1e-12, messages=messages, stop=stop)
    assert ok.tolist() == [True, False, True] and messages[0] is None and messages[2] is None
    assert messages[1] == f"stopped at t = {float(grid[7]):.6g} by the caller's test on the values so far"
    assert torch.equal(stopped[[0, 2]], free[[0, 2]]) and stopped_evals < evals
    assert torch.isnan(stopped[1]).all()  # a failed sample's values are NaN, as any failure's
    assert max(int(r.max()) for _, r in asked) <= 20 and all(set(rows.tolist()) <= {0, 1, 2} for rows, _ in asked)


def test_a_blow_up_ends_in_a_step_size_underflow_not_the_step_budget():
    """Past an overflow every trial step is non-finite (NaN error estimates, from inf - inf): each
    one shrinks the step (by the controller's smallest factor, 0.2), so the sample fails after a
    few dozen rejections instead of retrying one step size until ``max_steps`` (5,000 steps,
    30,000 evaluations here). ``y'' = 300 y' - 2.5 y`` grows like ``exp(300 t)`` and overflows at
    ``t ~ 2.4``; reaching it takes about 990 steps at ``rtol = 1e-4`` (measured: 5,941 evaluations)."""
    system = AugmentedSystem(LinearOscillator(-300.0, 2.5), [], DT, torch.device("cpu"))
    z0 = torch.tensor([[0.0, 1.0]], dtype=DT)
    _, ok, evals = dopri_batch(system, z0, torch.linspace(0, 6.5, 51, dtype=DT), rtol=1e-4, atol=1e-6,
                               max_steps=5000)
    assert not bool(ok[0])
    assert evals < 8_000, evals


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


# ------------------------------------------------------------------ per-sample grids (S, G)
def _own_grids(S):
    """Each sample's grid of its own span and length, padded at the end by repeating its last node:
    ``(S, G)`` and the number of real nodes of each."""
    lengths = [41 - 6 * s for s in range(S)]
    G = max(lengths)
    rows = []
    for s, count in enumerate(lengths):
        own = torch.linspace(0.5 * s, 40 - 3 * s, count, dtype=DT)
        rows.append(torch.cat([own, own[-1:].expand(G - count)]))
    return torch.stack(rows), lengths


def test_dopri_on_per_sample_grids_with_padding():
    """Every sample on its own grid (its own start, end and length): within tolerance of the closed form
    at its nodes, its padding (zero-length intervals) repeating its last value, and the same values as
    the sample integrated alone on its unpadded grid."""
    system, z0 = _cars(4)
    grid, lengths = _own_grids(4)
    traj, ok, evals = dopri_batch(system, z0, grid, rtol=1e-10, atol=1e-12)
    assert ok.all() and evals > 0
    for s, count in enumerate(lengths):
        own = grid[s, :count]
        exact = _exact_speed(own - own[0], z0[s:s + 1])[0]
        assert float(((traj[s, :count, 0] - exact) / exact).abs().max()) < 1e-9
        assert torch.equal(traj[s, count:], traj[s, count - 1].expand(grid.shape[1] - count, -1))
        alone, _, _ = dopri_batch(system, z0[s:s + 1], own, rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(traj[s, :count], alone[0], rtol=1e-14, atol=0)
    # landing on a few nodes per sample, the others from the dense output
    land = torch.zeros_like(grid, dtype=torch.bool)
    land[:, ::8] = True
    dense, ok, _ = dopri_batch(system, z0, grid, rtol=1e-9, atol=1e-11, land=land)
    assert ok.all()
    for s, count in enumerate(lengths):
        own = grid[s, :count]
        exact = _exact_speed(own - own[0], z0[s:s + 1])[0]
        assert float(((dense[s, :count, 0] - exact) / exact).abs().max()) < 1e-8
        assert torch.equal(dense[s, count:, 0], dense[s, count - 1, 0].expand(grid.shape[1] - count))


def test_dopri_zero_length_interval_inside_a_grid():
    """A repeated node inside a grid is a step of length zero: the same value at both nodes."""
    system, z0 = _cars(2)
    grid = torch.tensor([[0.0, 5.0, 5.0, 10.0, 20.0], [0.0, 2.0, 4.0, 8.0, 8.0]], dtype=DT)
    traj, ok, _ = dopri_batch(system, z0, grid, rtol=1e-10, atol=1e-12)
    assert ok.all()
    assert torch.equal(traj[0, 1], traj[0, 2]) and torch.equal(traj[1, 3], traj[1, 4])
    for s in range(2):
        exact = _exact_speed(grid[s], z0[s:s + 1])[0]
        assert float(((traj[s, :, 0] - exact) / exact).abs().max()) < 1e-9


def test_one_node_sample_among_longer_ones():
    system, z0 = _cars(2)
    grid = torch.tensor([[3.0, 3.0, 3.0], [0.0, 1.0, 2.0]], dtype=DT)
    traj, ok, _ = dopri_batch(system, z0, grid, rtol=1e-10, atol=1e-12)
    assert ok.all() and torch.equal(traj[0], z0[0].expand(3, -1))
    exact = _exact_speed(grid[1], z0[1:])[0]
    assert float(((traj[1, :, 0] - exact) / exact).abs().max()) < 1e-9


def test_linear_propagation_and_shooting_on_per_sample_grids_equal_each_grid_alone():
    """Per-sample grids of different lengths: the Taylor propagation and the multiple shooting give each
    sample what its own grid alone gives (its tolerance spread over its own intervals, the padding
    transferring by the identity)."""
    system, z0 = _cars(3)
    grid, lengths = _own_grids(3)
    traj, ok, _ = dopri_batch(system, z0, grid, rtol=1e-10, atol=1e-12)
    S, G, M = traj.shape
    lin = linearize(system, grid.reshape(-1), traj.reshape(-1, M))
    lin = type(lin)(*(v.reshape(S, G, *v.shape[1:]) for v in lin))
    w0 = torch.stack([initial_columns(z0[s] + 0.5, torch.arange(M)) for s in range(S)])
    W, failed, _ = propagate_linear_batch(grid, traj, lin.f, lin, w0, rtol=1e-8, atol=1e-10)
    shot, good, *_ = solve_on_grid_batch(system, z0, grid, rtol=1e-8, atol=1e-10, guess=traj * 1.001)
    assert not failed.any() and good.all()
    for s, count in enumerate(lengths):
        sub = type(lin)(*(v[s:s + 1, :count] for v in lin))
        W_alone, _, _ = propagate_linear_batch(grid[s, :count], traj[s:s + 1, :count], sub.f, sub, w0[s:s + 1],
                                               rtol=1e-8, atol=1e-10)
        torch.testing.assert_close(W[s, :count], W_alone[0], rtol=1e-13, atol=1e-13)
        # the identity transfers of the padding (composed by the scan: equal up to rounding)
        torch.testing.assert_close(W[s, count:], W[s, count - 1].expand(G - count, -1, -1), rtol=1e-13, atol=1e-13)
        alone, *_ = solve_on_grid_batch(system, z0[s:s + 1], grid[s, :count], rtol=1e-8, atol=1e-10,
                                          guess=traj[s:s + 1, :count] * 1.001)
        torch.testing.assert_close(shot[s, :count], alone[0], rtol=1e-13, atol=0)
        torch.testing.assert_close(shot[s, count:], shot[s, count - 1].expand(G - count, -1), rtol=1e-13, atol=0)


def test_integrate_each_on_per_sample_grids_hits_each_samples_times():
    system, z0 = _cars(3)
    grid, lengths = _own_grids(3)
    hit = grid[:, :25:6].contiguous()  # nodes of each sample (before its padding)
    traj, errors, evals = integrate_each(system, z0, grid, solver="dopri5", rtol=1e-10, atol=1e-12, hit=hit)
    assert errors == [None] * 3 and evals > 0
    for s, count in enumerate(lengths):
        own = grid[s, :count]
        exact = _exact_speed(own - own[0], z0[s:s + 1])[0]
        assert float(((traj[s, :count, 0] - exact) / exact).abs().max()) < 1e-8
        assert torch.equal(traj[s, count:], traj[s, count - 1].expand(grid.shape[1] - count, -1))


def test_thin_landings_keeps_every_kth_observation_and_the_last_per_sample():
    """At most about ``most`` landings a sample, every ``k``-th and its last; a sample with no more is
    unchanged, and nodes that are not landings stay off."""
    from torchql.dopri import thin_landings

    land = torch.zeros(2, 12, dtype=torch.bool)
    land[0, 1:11] = True  # ten observations: every third, and the last
    land[1, [0, 5]] = True  # two: unchanged
    thinned = thin_landings(land, most=4)
    assert thinned[0].nonzero().flatten().tolist() == [3, 6, 9, 10]
    assert torch.equal(thinned[1], land[1])
    assert torch.equal(thin_landings(land[0], most=10), land[0])


def test_dense_observations_are_read_from_the_dense_output_within_tolerance():
    """21,000 observation times of an oscillation: the fit's explicit pair lands on about
    ``LANDED_OBSERVATIONS`` of them and reads the rest from its dense output (each landing ends a step:
    landing on all took 21,000 steps a solve where the accuracy asks about 300, 25 s a fit against 0.23 s
    at 19,000 times on the grid solver). The fit reaches scipy's optimum, as at 19,000 times."""
    import torchql
    from torchql.dopri import LANDED_OBSERVATIONS

    assert LANDED_OBSERVATIONS <= 1000
    t = torch.linspace(0, 14, 21_000, dtype=torch.float64)
    clean = torchql.simulate(LinearOscillator(0.1, 3.0), torch.tensor([0.0, 1.0], dtype=torch.float64), t)[:, :1]
    y = clean + 0.01 * torch.randn(clean.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    data = torchql.Observations(t, y, observe=["y"])
    result = torchql.fit(LinearOscillator(0.11, 2.9), data, x0=torch.tensor([0.0, 1.0], dtype=torch.float64),
                         initial_trajectory="integrate", max_time=60)
    assert result.success, result.message
    # scipy's least_squares over solve_ivp (DOP853, rtol 1e-10) on the same data: A = 0.100064, B = 2.999967
    assert float(result.params["A"]) == pytest.approx(0.100064, abs=2e-6)
    assert float(result.params["B"]) == pytest.approx(2.999967, abs=2e-6)
