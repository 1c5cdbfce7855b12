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
    C_D = torch.tensor([0.4, 0.4, -40.0, 0.4, 0.35], dtype=DT)  # sample 2 blows up: a failure per sample
    model = CoastingCar(17.3, 80.43)
    seen = []
    try:
        ray.init(num_cpus=1, include_dashboard=False, log_to_driver=False)
    except Exception as exc:  # noqa: BLE001 - an environment that cannot start Ray skips, saying why
        pytest.skip(f"a local Ray instance cannot start here: {exc}")
    try:
        remote = torchql.fit_many_ray(model, data, x0, guesses={"C_D": C_D}, batch_size=2, grid=20,
                                      progress=lambda done, total: seen.append((done, total)))
        batch = torchql.Observations(T, torch.stack([d.y for d in data]), observe=["v"])  # sliced into tasks
        remote_batch = torchql.fit_many_ray(model, batch, x0, guesses={"C_D": C_D}, batch_size=2, grid=20)
    finally:
        ray.shutdown()
    local = torchql.fit_many(model, data, x0, guesses={"C_D": C_D}, grid=20)
    assert len(remote) == 5 and seen[-1] == (5, 5)
    assert [s.name for s in remote.status] == [s.name for s in local.status]
    assert remote.status[2].name == "INTEGRATION_FAILED" and remote.success.sum() == 4
    assert torch.allclose(remote.estimates, local.estimates, rtol=1e-12, atol=0)
    assert torch.equal(remote.iterations, local.iterations)
    assert torch.allclose(remote.params["C_D"][[0, 1, 3, 4]], local.params["C_D"][[0, 1, 3, 4]], rtol=1e-12)
    assert [s.name for s in remote_batch.status] == [s.name for s in local.status]
    assert torch.allclose(remote_batch.estimates, local.estimates, rtol=1e-12, atol=0)


def test_bad_arguments_fail_before_ray_is_used():
    data, x0 = fleet(2)
    with pytest.raises(ValueError, match="`batch_size`"):
        torchql.fit_many_ray(CoastingCar(17.3, 80.43), data, x0, batch_size=0)
    with pytest.raises(ValueError, match=r"`x0` must have shape"):
        torchql.fit_many_ray(CoastingCar(17.3, 80.43), data, torch.zeros(2, 3))
    with pytest.raises(ValueError, match="empty list"):
        torchql.fit_many_ray(CoastingCar(17.3, 80.43), [], x0)
    with pytest.raises(TypeError, match="a single dataset: use torchql.fit"):
        torchql.fit_many_ray(CoastingCar(17.3, 80.43), data[0], x0[0])
    with pytest.raises(ValueError, match=r"`data\[1\]` has observation times different"):
        torchql.fit_many_ray(CoastingCar(17.3, 80.43), [data[0], torchql.Observations(T + 1, data[1].y, ["v"])], x0)
    assert not ray.is_initialized()
