"""``fit_many(..., initial_trajectory="data")``: each sample starts from its own data, as ``fit`` does."""

import pytest
import torch

import torchql
from test_batch import AREA, MASS, OSC_T, assert_same_as_single, car_data
from torchql.models import CoastingCar, LinearOscillator

DT = torch.float64


def test_cars_from_their_data_equal_single_fits():
    """Statuses, messages, iterations, estimates, SSE and covariance as ``fit`` from the data
    (to 1e-8): the same data-built start (smoothed speeds, slopes matched) for each car."""
    data, x0 = car_data(4, seed=3)
    batch = torchql.fit_many(CoastingCar(AREA, MASS), data, x0, grid=50, initial_trajectory="data")
    singles = [torchql.fit(CoastingCar(AREA, MASS), data[b], x0[b], grid=50, initial_trajectory="data")
               for b in range(4)]
    assert batch.success.all(), batch.summary()
    assert_same_as_single(batch, singles)
    # the history's first record: the first iterate (the coefficients fitted to the data's slopes)
    # and its sum of squares, as the single fit records them
    for b in range(4):
        first, own = batch[b].history[0], singles[b].history[0]
        assert first.iteration == own.iteration == 0 and first.sse == pytest.approx(own.sse, rel=1e-10)
        assert all(float(first.params[k]) == pytest.approx(float(own.params[k]), rel=1e-12) for k in own.params)
        assert float(own.params["C_D"]) != 0.4  # not the guess


def test_oscillators_on_their_own_clocks_with_a_hidden_state():
    """Only y observed (v derived from the smoothed y by the model), 1 % noise, each sample on
    its own times (shifted clocks: per-sample grids, padded): each equals its single fit."""
    g = torch.Generator().manual_seed(2)
    times, values = [], []
    for k, (A, B) in enumerate(((0.1, 3.0), (0.3, 1.5), (0.05, 4.0))):
        t = OSC_T + 0.3 * k
        y = torchql.simulate(LinearOscillator(A, B), torch.tensor([0.2, 1.0], dtype=DT), t, t0=float(t[0]))[:, :1]
        times.append(t)
        values.append(y + 0.01 * torch.randn(y.shape, generator=g, dtype=DT))
    data = torchql.Observations(torch.stack(times), torch.stack(values), observe=["y"])
    x0 = torch.tensor([0.5, 0.5], dtype=DT)
    batch = torchql.fit_many(LinearOscillator(0.5, 1.0), data, x0, grid=100, initial_trajectory="data")
    singles = [torchql.fit(LinearOscillator(0.5, 1.0), data[b], x0, grid=100, initial_trajectory="data")
               for b in range(3)]
    assert batch.success.all(), batch.summary()
    assert_same_as_single(batch, singles)


def test_the_data_start_serves_shooting_as_fit_does():
    """Shooting from the data: each car's fit equals its single fit (the same matched start)."""
    data, x0 = car_data(3, seed=3)
    batch = torchql.fit_many(CoastingCar(AREA, MASS), data, x0, method="shooting", initial_trajectory="data")
    singles = [torchql.fit(CoastingCar(AREA, MASS), data[b], x0[b], method="shooting", initial_trajectory="data")
               for b in range(3)]
    assert batch.success.all(), batch.summary()
    assert_same_as_single(batch, singles)
    assert all(float(single.history[0].params["C_D"]) != 0.4 for single in singles)  # matched, not the guess
    with pytest.raises(ValueError, match="`initial_trajectory` must be one of"):
        torchql.fit_many(CoastingCar(AREA, MASS), data, x0, initial_trajectory="spline")
