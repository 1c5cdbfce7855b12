"""``torchql.fit_many_ray``: batches fitted by Ray tasks on a local instance, gathered in input order."""

import pytest
import torch

import torchql
from torchql.models import CoastingCar

ray = pytest.importorskip("ray", reason="the Ray backend is optional: pip install 'torchql[ray]'")

DT = torch.float64
T = torch.arange(9, dtype=DT) * 5.0


def fleet(B: int):
    g = torch.Generator().manual_seed(11)
    data = []
    for _ in range(B):
        C_D = 0.45 + 0.05 * torch.randn((), generator=g, dtype=DT)
        v = torchql.simulate(CoastingCar(17.3, 80.43, float(C_D), 0.015), torch.tensor([117.3], dtype=DT), T,
                             rtol=1e-12, atol=1e-12)
        data.append(torchql.Observations(T, v + 0.3 * torch.randn(9, 1, generator=g, dtype=DT), observe=["v"]))
    return data, torch.stack([d.y[0] for d in data])


@pytest.mark.slow
def test_local_ray_run_equals_fit_many_in_input_order():
    data, x0 = fleet(5)
    # sample 2 blows up, integrated from its guess: a failure per sample (from the data it converges)
    C_D = torch.tensor([0.4, 0.4, -40.0, 0.4, 0.35], dtype=DT)
    times = torch.stack([T + 0.5 * b for b in range(5)])  # the same logs recorded at other clock times
    model = CoastingCar(17.3, 80.43)
    seen = []
    try:
        ray.init(num_cpus=1, include_dashboard=False, log_to_driver=False)
    except Exception as exc:  # noqa: BLE001 - an environment that cannot start Ray skips, saying why
        pytest.skip(f"a local Ray instance cannot start here: {exc}")
    try:
        remote = torchql.fit_many_ray(model, data, x0, guesses={"C_D": C_D}, batch_size=2, grid=20, initial_trajectory="integrate",
                                      progress=lambda done, total: seen.append((done, total)))
        batch = torchql.Observations(T, torch.stack([d.y for d in data]), observe=["v"])  # sliced into tasks
        remote_batch = torchql.fit_many_ray(model, batch, x0, guesses={"C_D": C_D}, batch_size=2, grid=20, initial_trajectory="integrate")
        own = torchql.Observations(times, batch.y, observe=["v"])  # per-sample times: each task gets its samples'
        remote_own = torchql.fit_many_ray(model, own, x0, guesses={"C_D": C_D}, batch_size=2, grid=20, initial_trajectory="integrate")
        # samples of two experiments each (two logs of one car), their initial speeds per sample (B, E, n)
        pairs = [[data[0], data[1]], [data[2], data[3]], [data[4], data[0]]]
        starts = torch.stack([x0[[0, 1]], x0[[2, 3]], x0[[4, 0]]])
        remote_pairs = torchql.fit_many_ray(model, pairs, starts, batch_size=2, grid=20)
        # options= (its max_iter was given twice by the check that runs before the tasks)
        by_options = torchql.fit_many_ray(model, data, x0, guesses={"C_D": C_D}, batch_size=2,
                                          options=torchql.FitOptions(grid=20, initial_trajectory="integrate",
                                                                     max_iter=30))
        with pytest.raises(torchql.BatchFitError) as thrown:  # raised once, for the whole batch
            torchql.fit_many_ray(model, data, x0, guesses={"C_D": C_D}, batch_size=2, grid=20,
                                 initial_trajectory="integrate", throw=True)
    finally:
        ray.shutdown()
    local = torchql.fit_many(model, data, x0, guesses={"C_D": C_D}, grid=20, initial_trajectory="integrate")
    assert len(remote) == 5 and seen[-1] == (5, 5)
    assert [s.name for s in remote.status] == [s.name for s in local.status]
    assert remote.status[2].name == "INTEGRATION_FAILED" and remote.success.sum() == 4
    assert torch.allclose(remote.estimates, local.estimates, rtol=1e-12, atol=0)
    assert torch.equal(remote.iterations, local.iterations)
    assert torch.allclose(remote.params["C_D"][[0, 1, 3, 4]], local.params["C_D"][[0, 1, 3, 4]], rtol=1e-12)
    assert [s.name for s in remote_batch.status] == [s.name for s in local.status]
    assert torch.allclose(remote_batch.estimates, local.estimates, rtol=1e-12, atol=0)
    local_own = torchql.fit_many(model, own, x0, guesses={"C_D": C_D}, grid=20, initial_trajectory="integrate")
    assert [s.name for s in remote_own.status] == [s.name for s in local_own.status]
    assert torch.allclose(remote_own.estimates, local_own.estimates, rtol=1e-12, atol=0)
    assert torch.equal(remote_own.t0, times[:, 0]) and torch.equal(local_own.t0, times[:, 0])
    assert torch.equal(by_options.estimates, remote.estimates)
    local_pairs = torchql.fit_many(model, pairs, starts, grid=20)
    assert [s.name for s in remote_pairs.status] == [s.name for s in local_pairs.status]
    assert torch.allclose(remote_pairs.estimates, local_pairs.estimates, rtol=1e-12, atol=0)
    assert remote_pairs.x0.shape == (3, 2, 1) and remote_pairs.experiment_t0 == local_pairs.experiment_t0
    assert thrown.value.failed == [2] and len(thrown.value.result) == 5
    assert torch.allclose(thrown.value.result.estimates, local.estimates, rtol=1e-12, atol=0)


def test_parts_with_their_own_t0_concatenate_to_per_sample_t0():
    """A batch split into parts whose samples share t0 within a part but not across parts."""
    from torchql.ray_backend import concatenate

    data, x0 = fleet(3)
    model = CoastingCar(17.3, 80.43)
    early = torchql.fit_many(model, data[:2], x0[:2], grid=10, max_iter=0)
    late = torchql.fit_many(model, [torchql.Observations(T + 2.0, data[2].y, ["v"])], x0[2:], grid=10, max_iter=0)
    assert early.t0 == 0.0 and late.t0 == 2.0
    whole = concatenate([early, late])
    assert torch.equal(whole.t0, torch.tensor([0.0, 0.0, 2.0], dtype=DT)) and whole[2].t0 == 2.0
    assert concatenate([early, early]).t0 == 0.0


def test_bad_arguments_fail_before_ray_is_used():
    data, x0 = fleet(2)
    with pytest.raises(ValueError, match="`batch_size`"):
        torchql.fit_many_ray(CoastingCar(17.3, 80.43), data, x0, batch_size=0)
    with pytest.raises(TypeError, match="`throw` must be True or False"):
        torchql.fit_many_ray(CoastingCar(17.3, 80.43), data, x0, throw="yes")
    with pytest.raises(ValueError, match=r"`x0` must have shape"):
        torchql.fit_many_ray(CoastingCar(17.3, 80.43), data, torch.zeros(2, 3))
    with pytest.raises(ValueError, match="empty list"):
        torchql.fit_many_ray(CoastingCar(17.3, 80.43), [], x0)
    with pytest.raises(TypeError, match="a single dataset: use torchql.fit"):
        torchql.fit_many_ray(CoastingCar(17.3, 80.43), data[0], x0[0])
    with pytest.raises(ValueError, match=r"`data\[1\]` has T = 8 observation times but `data\[0\]` has 9"):
        torchql.fit_many_ray(CoastingCar(17.3, 80.43), [data[0], torchql.Observations(T[:8], data[1].y[:8], ["v"])],
                             x0)
    assert not ray.is_initialized()
