"""The storage grid: ``grid="smooth"`` chooses as few intervals as the trajectories need."""

import math

import pytest
import torch

import torchql
from torchql.grid import DEFAULT_INTERVALS, MIN_INTERVALS, SMOOTH_SAFETY, make_grid, refine, smooth_intervals
from torchql.models import CoastingCar

DT = torch.float64
AREA, MASS = 17.3, 80.43
CAR_T = torch.arange(9, dtype=DT) * 5.0


@pytest.mark.parametrize("omega", [0.2, 0.5])
def test_smooth_intervals_follow_the_hermite_error_bound(omega):
    """``x = sin(omega t)``: ``max |x''''| = omega^4``, so ``h = (384 s rtol / omega^4)^(1/4)``
    (tolerance ``rtol max |x|``); the third differences of the slopes find it to a few percent,
    and the cubic Hermite interpolant on that grid stays within the allowed error."""
    t = torch.linspace(0.0, 10.0, 1001, dtype=DT)
    x, slopes = torch.sin(omega * t), omega * torch.cos(omega * t)
    rtol = 1e-10
    count = smooth_intervals(t, x.reshape(1, -1, 1), slopes.reshape(1, -1, 1), rtol, 0.0)
    expected = 10.0 / (384 * SMOOTH_SAFETY * rtol / omega**4) ** 0.25
    assert count == pytest.approx(expected, rel=0.03)
    nodes = torch.linspace(0.0, 10.0, count + 1, dtype=DT)
    h = nodes[1] - nodes[0]
    mid = nodes[:-1] + h / 2  # where the cubic Hermite error of a smooth function is largest
    y0, y1 = torch.sin(omega * nodes[:-1]), torch.sin(omega * nodes[1:])
    d0, d1 = omega * torch.cos(omega * nodes[:-1]), omega * torch.cos(omega * nodes[1:])
    hermite = (y0 + y1) / 2 + h * (d0 - d1) / 8
    assert float((hermite - torch.sin(omega * mid)).abs().max()) <= 1.1 * SMOOTH_SAFETY * rtol


def test_smooth_intervals_limits():
    t = torch.linspace(0.0, 1.0, 1001, dtype=DT)
    line = (2 * t).reshape(1, -1, 1)
    assert smooth_intervals(t, line, torch.full_like(line, 2.0), 1e-10, 1e-12) == MIN_INTERVALS
    fast = torch.sin(200 * t).reshape(1, -1, 1)
    assert smooth_intervals(t, fast, 200 * torch.cos(200 * t).reshape(1, -1, 1), 1e-10, 1e-12) == DEFAULT_INTERVALS
    broken = line.clone()
    broken[0, 5, 0] = float("nan")
    assert smooth_intervals(t, broken, broken, 1e-10, 1e-12) == DEFAULT_INTERVALS
    # per-sample times: the sample that needs most sets the count
    both = torch.stack([t, 4 * t])
    x = torch.stack([torch.sin(t), torch.sin(t)]).unsqueeze(-1)
    assert smooth_intervals(both, x, x, 1e-10, 0.0) > smooth_intervals(t, x[:1], x[:1], 1e-10, 0.0)


@pytest.fixture(scope="module")
def cars():
    g = torch.Generator().manual_seed(5)
    data = []
    for _ in range(3):
        C_D = 0.45 + 0.05 * torch.randn((), generator=g, dtype=DT)
        mu = 0.015 + 0.003 * torch.randn((), generator=g, dtype=DT)
        v = torchql.simulate(CoastingCar(AREA, MASS, float(C_D), float(mu)), torch.tensor([117.3], dtype=DT), CAR_T,
                             rtol=1e-12, atol=1e-12)
        data.append(torchql.Observations(CAR_T, v + 0.3 * torch.randn(9, 1, generator=g, dtype=DT), observe=["v"]))
    return data


def test_smooth_grid_fits_as_the_default_grid_on_fewer_nodes(cars):
    """A coasting car needs about 180 of the default 1000 intervals: the estimates agree to 1e-8
    (the step tolerance), the SSE to 1e-10; fit_many with the same grid equals fit."""
    x0 = torch.tensor([117.0], dtype=DT)
    default = torchql.fit(CoastingCar(AREA, MASS), cars[0], x0)
    smooth = torchql.fit(CoastingCar(AREA, MASS), cars[0], x0, grid="smooth")
    assert default.success and smooth.success
    assert torch.allclose(smooth.estimates, default.estimates, rtol=1e-8, atol=0)
    assert smooth.sse == pytest.approx(default.sse, rel=1e-10)
    nodes = smooth.history[-1].trajectory.shape[0]
    assert MIN_INTERVALS < nodes < len(make_grid(None, torch.tensor(0.0, dtype=DT), CAR_T)) // 3
    batch = torchql.fit_many(CoastingCar(AREA, MASS), [cars[0]] * 2, x0, grid="smooth")
    assert torch.allclose(batch.estimates, smooth.estimates.expand(2, -1), rtol=1e-12, atol=0)
    several = torchql.fit_many(CoastingCar(AREA, MASS), cars, x0, grid="smooth")
    assert bool(several.success.all())


def test_unknown_grid_names_are_errors(cars):
    match = r'`grid` must be a number of intervals, a tensor of times, "auto" or "smooth"; received \'fine\''
    with pytest.raises(ValueError, match=match):
        torchql.fit(CoastingCar(AREA, MASS), cars[0], torch.tensor([117.0], dtype=DT), grid="fine")
    with pytest.raises(ValueError, match=match):
        torchql.FitOptions(grid="fine")
    assert math.isclose(SMOOTH_SAFETY, 1 / 16)


def test_refine_with_second_derivatives_is_the_quintic_interpolant():
    """``refine(..., second=)``: the node values unchanged, and the sub-nodes' values of ``sin`` within
    ``h^6`` (halving ``h`` divides the error by about 64, the cubic's by about 16)."""
    errors = {}
    for G in (6, 11):
        grid = torch.linspace(0.0, 3.0, G, dtype=torch.float64)
        x = torch.sin(grid).reshape(1, -1, 1)
        slopes, second = torch.cos(grid).reshape(1, -1, 1), -torch.sin(grid).reshape(1, -1, 1)
        for degree, extra in ((3, None), (5, second)):
            fine, values = refine(grid, x, slopes, 4, extra)
            assert torch.equal(values[0, ::4, 0], x[0, :, 0])
            errors[degree, G] = float((values[0, :, 0] - torch.sin(fine)).abs().max())
    assert 12 < errors[3, 6] / errors[3, 11] < 22
    assert 45 < errors[5, 6] / errors[5, 11] < 85
    assert errors[5, 11] < errors[3, 11] / 100
