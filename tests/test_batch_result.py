"""``fit_many(...)[i]`` is sample ``i``'s :class:`torchql.FitResult`: the one ``torchql.fit`` gives."""

import math
import re

import pytest
import torch

import torchql
from torchql.models import CoastingCar

DT = torch.float64
AREA, MASS = 17.3, 80.43
CAR_T = torch.arange(9, dtype=DT) * 5.0


def cars(B: int, seed: int = 11) -> tuple[torchql.Observations, torch.Tensor]:
    """A batch of ``B`` noisy coast-down logs (values ``(B, 9, 1)``) and each one's first speed ``(B, 1)``."""
    g = torch.Generator().manual_seed(seed)
    ys = []
    for _ in range(B):
        C_D = 0.45 + 0.05 * torch.randn((), generator=g, dtype=DT)
        mu = 0.015 + 0.003 * torch.randn((), generator=g, dtype=DT)
        v = torchql.simulate(CoastingCar(AREA, MASS, float(C_D), float(mu)), torch.tensor([117.3], dtype=DT), CAR_T,
                             rtol=1e-12, atol=1e-12)
        ys.append(v + 0.3 * torch.randn(9, 1, generator=g, dtype=DT))
    y = torch.stack(ys)
    return torchql.Observations(CAR_T, y, observe=["v"]), y[:, 0]


@pytest.fixture(scope="module")
def fleet():
    data, x0 = cars(3)
    batch = torchql.fit_many(CoastingCar(AREA, MASS), data, x0, grid=20)
    singles = [torchql.fit(CoastingCar(AREA, MASS), data[b], x0[b], grid=20) for b in range(3)]
    return data, batch, singles


def test_a_sample_is_the_fit_result_of_fit(fleet):
    """Everything a single fit reports, from the batch: the final evaluations agree to the
    integration tolerance's effect on them (the batch integrates on its own batched path: 1e-8
    relative leaves a wide margin over the 1e-10 rtol)."""
    _, batch, singles = fleet
    for b, single in enumerate(singles):
        sample = batch[b]
        assert isinstance(sample, torchql.FitResult) and sample.index == b and single.index is None
        assert sample.status is single.status and sample.message == single.message
        assert sample.unknown_names == single.unknown_names
        assert torch.allclose(sample.estimates, single.estimates, rtol=1e-8, atol=0)
        assert sample.residuals.shape == single.residuals.shape == (9,)
        assert torch.allclose(sample.residuals, single.residuals, rtol=1e-6, atol=1e-8)
        assert torch.allclose(sample.jacobian, single.jacobian, rtol=1e-6, atol=1e-10)
        assert torch.allclose(sample.singular_values, single.singular_values, rtol=1e-6, atol=0)
        assert sample.condition_number == pytest.approx(single.condition_number, rel=1e-6)
        assert sample.dof == single.dof and sample.n_observations == single.n_observations
        for name, (lo, hi) in single.confidence_intervals().items():
            lo_b, hi_b = sample.confidence_intervals()[name]
            assert lo_b == pytest.approx(lo, rel=1e-6) and hi_b == pytest.approx(hi, rel=1e-6)
        assert not sample.exact_mask.any() and sample.exact_residual == 0.0
        # the guesses and the estimates: the first and last records of the single fit's history
        assert [r.iteration for r in sample.history] == [0, single.iterations]
        assert sample.history[0].sse == pytest.approx(single.history[0].sse, rel=1e-4)
        assert float(sample.history[0].params["C_D"]) == float(single.history[0].params["C_D"])
        assert sample.history[-1].sse == pytest.approx(single.sse, rel=1e-8)


def test_a_sample_reports_predicts_and_profiles_like_a_fit(fleet):
    data, batch, singles = fleet
    sample, single = batch[1], singles[1]
    text = sample.report()
    assert "C_D" in text and "mu" in text and "Converged" in text
    t = torch.linspace(0.0, 40.0, 5, dtype=DT)
    assert torch.allclose(sample.predict(t), single.predict(t), rtol=1e-8, atol=0)
    assert torch.equal(sample.data.y, data[1].y)
    # a profile re-fits that sample alone, with the batch's settings (grid=20)
    prof = torchql.profile(sample, "C_D", max_points=4)
    ref = torchql.profile(single, "C_D", max_points=4)
    assert prof.interval == pytest.approx(ref.interval, rel=1e-5)
    assert prof.sse_min == pytest.approx(ref.sse_min, rel=1e-8)


def test_a_failed_sample_has_no_evaluation_and_no_intervals():
    """A sample whose model cannot be integrated (a negative drag coefficient: the speed blows
    up): NaN SSE, residuals and Jacobian, no singular values, NaN intervals, and its history
    ends at the estimates returned."""
    data, x0 = cars(2, seed=4)
    batch = torchql.fit_many(CoastingCar(AREA, MASS), data, x0, guesses={"C_D": torch.tensor([0.4, -40.0], dtype=DT)},
                             grid=20, initial_trajectory="integrate")  # from the data, both converge
    good, bad = batch[0], batch[1]
    assert good.success and bad.status is torchql.Status.INTEGRATION_FAILED, batch.summary()
    assert math.isnan(bad.sse) and torch.isnan(bad.residuals).all() and torch.isnan(bad.jacobian).all()
    assert bad.singular_values.numel() == 0 and math.isnan(bad.condition_number)
    assert all(math.isnan(lo) and math.isnan(hi) for lo, hi in bad.confidence_intervals().values())
    assert bad.history[-1].iteration == bad.iterations == 0
    assert float(bad.history[0].params["C_D"]) == -40.0


def test_callback_receives_each_samples_records_as_fit_hands_them():
    """``fit_many(callback=...)`` gets ``(sample, record)`` for every completed iterate of every
    sample: per sample, the iterations and SSEs ``fit``'s callback sees for that dataset alone."""
    data, x0 = cars(3, seed=4)
    seen: dict[int, list] = {0: [], 1: [], 2: []}
    torchql.fit_many(CoastingCar(AREA, MASS), data, x0, grid=20,
                     callback=lambda b, record: seen[b].append((record.iteration, record.sse)))
    for b in range(3):
        alone = []
        torchql.fit(CoastingCar(AREA, MASS), data[b], x0[b], grid=20,
                    callback=lambda record: alone.append((record.iteration, record.sse)))
        assert [i for i, _ in seen[b]] == [i for i, _ in alone], b
        assert all(abs(s - t) <= 1e-8 * t for (_, s), (_, t) in zip(seen[b], alone)), b
    with pytest.raises(TypeError, match="`callback` must be callable"):
        torchql.fit_many(CoastingCar(AREA, MASS), data, x0, callback=3)


def test_a_batch_joined_from_parts_keeps_every_record_and_the_likelihoods_last_one():
    """A batch whose samples carry their own inputs is fitted part by part and joined: with a
    ``callback`` each sample keeps every record, as with shared inputs. With estimated sigmas the
    last record holds the objective ``sse + 2 sum log sigma`` as the first does and as ``fit``'s."""
    t = torch.linspace(0, 10, 21, dtype=DT)
    times = torch.linspace(0, 10, 11, dtype=DT)
    g = torch.Generator().manual_seed(0)
    data = []
    for _ in range(2):
        force = torchql.Inputs(times, torch.rand(11, 1, generator=g, dtype=DT) * 2 - 1, names="force")
        y = torchql.simulate(_Driven(0.3, 4.0), torch.tensor([0.1, 0.0], dtype=DT), t, inputs=force)[:, :1]
        noisy = y + 0.01 * torch.randn(y.shape, generator=g, dtype=DT)
        data.append(torchql.Observations(t, noisy, observe=["y"], inputs=force, sigma="estimate"))
    seen: dict[int, int] = {0: 0, 1: 0}
    batch = torchql.fit_many(_Driven(), data, torch.zeros(2, dtype=DT),
                             callback=lambda b, record: seen.__setitem__(b, seen[b] + 1))
    plain = torchql.fit_many(_Driven(), data, torch.zeros(2, dtype=DT))  # the guesses and the estimates only
    for b in range(2):
        alone = torchql.fit(_Driven(), data[b], torch.zeros(2, dtype=DT))
        assert len(batch[b].history) == seen[b] == len(alone.history), b
        assert alone.likelihood and alone.history[-1].sse < 0  # the objective, not the sum of squares
        for kept in (batch[b].history, plain[b].history):  # (the first iterate re-anchored: the model's)
            assert kept[0].sse == pytest.approx(alone.history[0].sse, rel=1e-8)
            assert kept[-1].sse == pytest.approx(alone.history[-1].sse, rel=1e-8)


class _Driven(torchql.ODEModel):
    """A damped spring driven by a measured force: ``y'' = force - c y' - k y``."""

    state_names, input_names = ("y", "v"), ("force",)

    def __init__(self, c: float = 0.5, k: float = 2.0) -> None:
        super().__init__()
        self.register_buffer("c", torch.tensor(c, dtype=DT))
        self.register_buffer("k", torch.tensor(k, dtype=DT))

    def forward(self, t, x, u):
        y, v = x.unbind(-1)
        return torch.stack((v, u[..., 0] - self.c * v - self.k * y), dim=-1)


def test_a_sample_is_indexed_by_any_integer_and_nothing_else(fleet):
    """``result[i]`` takes a NumPy integer or a one-element integer tensor (as ``(~result.success).nonzero()``
    gives) like an int; a float, a bool or a tensor of several indices is an error that says what it received."""
    import numpy as np

    result = fleet[1]
    for index in (np.int64(1), torch.tensor(1), torch.tensor([1]), -len(result) + 1):
        assert torch.equal(result[index].estimates, result[1].estimates)
    for index, received in ((1.0, "float"), (True, "bool"), (torch.tensor([0, 1]), "shape (2,)"),
                            (torch.tensor(1.0), "dtype torch.float32")):
        with pytest.raises(TypeError, match=f"a sample index must be an integer; received .*{re.escape(received)}"):
            result[index]
    with pytest.raises(IndexError, match="out of range for a batch of"):
        result[np.int64(len(result))]
