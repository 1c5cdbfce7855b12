"""``fit_many(..., method="shooting")``: each sample is the shooting ``torchql.fit`` of it alone."""

import pytest
import torch

import torchql
from test_batch import AREA, MASS, assert_same_as_single, car_data, exact_oscillators
from torchql.models import CoastingCar, LinearOscillator

DT = torch.float64


def test_cars_by_shooting_equal_single_shooting_fits():
    """Four noisy coast-down logs: statuses, messages, iterations, estimates, SSE and covariance
    as ``torchql.fit(..., method="shooting")`` gives each one (to 1e-8, the batch integrating on
    its own batched path at rtol 1e-10)."""
    data, x0 = car_data(4, seed=3)
    batch = torchql.fit_many(CoastingCar(AREA, MASS), data, x0, grid=50, method="shooting")
    singles = [torchql.fit(CoastingCar(AREA, MASS), data[b], x0[b], grid=50, method="shooting") for b in range(4)]
    assert batch.success.all(), batch.summary()
    assert_same_as_single(batch, singles)
    assert all(batch[b].method == "shooting" for b in range(4))


def test_oscillators_by_shooting_reach_the_truth():
    """Exact data: every sample's estimates are the truth to 1e-10 (integration error of the
    data, 1e-13, and the fit's rtol 1e-10), in the iterations the single fits take."""
    truths, data, guesses, x0 = exact_oscillators()
    batch = torchql.fit_many(LinearOscillator(), data, x0, guesses=guesses, grid=100, method="shooting")
    assert batch.success.all(), batch.summary()
    assert ((batch.estimates - truths).abs() / truths.abs().clamp(min=1.0)).max() <= 1e-10
    single = torchql.fit(LinearOscillator(float(guesses["A"][1]), float(guesses["B"][1])), data[1], x0[1], grid=100,
                         method="shooting")
    assert int(batch.iterations[1]) == single.iterations


def test_an_unknown_method_is_named():
    data, x0 = car_data(1)
    with pytest.raises(ValueError, match=r"`method` must be one of \('kantorovich', 'shooting'\); received 'newton'"):
        torchql.fit_many(CoastingCar(AREA, MASS), data, x0, method="newton")
