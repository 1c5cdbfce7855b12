"""The storage grid's interpolants against the model between their nodes (torchql.storage_check)."""

import math

import pytest
import torch

import torchql
from torchql.linearize import linearize, map_fields
from torchql.model import AugmentedSystem, ODEModel
from torchql.models import LinearOscillator, NonlinearOscillator
from torchql.storage_check import MISS_FACTOR, interpolation_misfit, storage_misses

DT = torch.float64


class _Friction(ODEModel):
    """``x' = v``, ``v' = -2 x - 0.1 v - 0.3 tanh(50 v)``: a friction that switches over ``|v| < 0.02``."""

    state_names = ("x", "v")

    def forward(self, t, x):
        p, v = x.unbind(-1)
        return torch.stack((v, -0.1 * v - 0.3 * torch.tanh(50.0 * v) - 2.0 * p), -1)


def _misfit(model, intervals: int, degree: int, span: float = 10.0) -> float:
    """The misfit of the storage of ``model``'s solution from ``(1, 0)`` on ``intervals`` uniform intervals."""
    system = AugmentedSystem(model, [], DT, torch.device("cpu"))
    t = torch.linspace(0.0, span, intervals + 1, dtype=DT)
    z = torchql.simulate(model, torch.tensor([1.0, 0.0], dtype=DT), t, rtol=1e-13, atol=1e-15)
    lin = linearize(system, t, z, second=degree == 5)
    lin = map_fields(lin, lambda v: v.unsqueeze(0))
    return float(interpolation_misfit(system.f, t, z.unsqueeze(0), lin, degree, system.n)[0])


@pytest.mark.parametrize("degree", [3, 5])
def test_on_a_smooth_solution_the_misfit_is_the_interpolation_error_of_its_order(degree):
    """Halving the intervals of a nonlinear oscillation's storage divides the misfit by 2^(degree + 2):
    the interpolants' error of order ``h^(degree + 1)`` in the slope, times the interval's length
    (measured 32.05 for the cubic and 125.6 for the quintic from 400 to 800 intervals); and 400
    intervals are far below the miss threshold."""
    model = NonlinearOscillator()
    coarse, fine = _misfit(model, 400, degree), _misfit(model, 800, degree)
    assert coarse / fine == pytest.approx(2.0 ** (degree + 2), rel=0.1)
    assert coarse < 0.02 * MISS_FACTOR * math.sqrt(1e-10)


def test_a_linear_model_is_stored_exactly_on_any_grid():
    """For a linear model ``f = A z`` the Hermite interpolant of ``f`` is ``A`` times that of ``z``:
    no misfit to rounding on 10 intervals, where the interpolants of the solution itself are far off."""
    assert _misfit(LinearOscillator(0.1, 3.0), 10, 3) < 1e-14


def test_a_switch_between_the_nodes_is_a_miss_on_either_storage():
    """``tanh(50 v)`` switches within a fraction of one of 200 intervals: the interpolants stray by
    2e-3 (cubic) and 3e-3 (quintic) of the states over an interval, 19 and 32 times the threshold
    at the default ``rtol``; a smooth oscillation on the same grid, by 3e-6 (0.03 of it)."""
    for degree in (3, 5):
        misfit = _misfit(_Friction(), 200, degree)
        assert misfit > 1e-3
        assert bool(storage_misses(torch.tensor([misfit], dtype=DT), 1e-10)[0])
    assert not bool(storage_misses(torch.tensor([_misfit(NonlinearOscillator(), 200, 3)], dtype=DT), 1e-10)[0])


class _Relaxation(ODEModel):
    """``x' = -k (x - cos t)``: affine in ``x``."""

    state_names = ("x",)

    def __init__(self, k: float = 30.0) -> None:
        super().__init__()
        self.register_buffer("k", torch.tensor(k, dtype=DT))

    def forward(self, t, x):
        return -self.k * (x - torch.cos(t))


def test_a_transient_between_two_nodes_is_a_miss_where_an_unknown_coefficient_reads_it():
    """From ``x(0) = 0`` the relaxation's transient, of width ``1 / k = 0.033``, passes between the
    first two of 20 nodes over 2: the interpolants of ``f`` and of ``z`` agree with each other (``f``
    is affine in ``x``), but not with the model (the slope of ``z``'s interpolant, 0.13 of the
    state over the interval), and ``k``'s column reads that trajectory: a miss. With ``x(0)`` the
    only unknown the Jacobian is constant and the trajectory's own error moves nothing: what is left
    is the interpolation of ``cos t`` in ``h f``, 8e-7 (0.008 of the threshold)."""
    t = torch.linspace(0.0, 2.0, 21, dtype=DT)
    misfits = []
    for params in (["k"], []):
        system = AugmentedSystem(_Relaxation(), params, DT, torch.device("cpu"))
        x = torchql.simulate(_Relaxation(), torch.zeros(1, dtype=DT), t, rtol=1e-13, atol=1e-15)
        z = torch.cat([x, torch.full_like(x, 30.0)], dim=1) if params else x
        lin = map_fields(linearize(system, t, z), lambda v: v.unsqueeze(0))
        misfits.append(float(interpolation_misfit(system.f, t, z.unsqueeze(0), lin, 3, system.n)[0]))
    assert misfits[0] > 0.1 and bool(storage_misses(torch.tensor(misfits[:1], dtype=DT), 1e-10)[0])
    assert misfits[1] < 0.01 * MISS_FACTOR * math.sqrt(1e-10)


def test_padded_intervals_of_per_sample_grids_count_nothing():
    """A grid padded at its end by repeating its last node (zero-length intervals) gets the misfit
    of its real intervals."""
    model = LinearOscillator(0.1, 3.0)
    system = AugmentedSystem(model, [], DT, torch.device("cpu"))
    t = torch.linspace(0.0, 5.0, 41, dtype=DT)
    padded = torch.cat([t, t[-1:].expand(5)])
    z = torchql.simulate(model, torch.tensor([1.0, 0.0], dtype=DT), t, rtol=1e-13, atol=1e-15)
    misfits = []
    for grid, values in ((t, z), (padded, torch.cat([z, z[-1:].expand(5, -1)]))):
        lin = map_fields(linearize(system, grid, values), lambda v: v.unsqueeze(0))
        misfits.append(interpolation_misfit(system.f, grid.unsqueeze(0), values.unsqueeze(0), lin, 3, system.n))
    assert torch.isfinite(misfits[1]).all()
    torch.testing.assert_close(misfits[1], misfits[0], rtol=1e-12, atol=0.0)


def test_a_floor_on_the_states_scale_measures_small_states_against_it():
    """The friction's switch on 200 intervals (a miss): a ``floor`` below the states' scales (of
    order 1) changes nothing; one of 1e3 (``atol / rtol`` for states that small against it) measures
    the same stray against 1e3, no miss."""
    model = _Friction()
    system = AugmentedSystem(model, [], DT, torch.device("cpu"))
    t = torch.linspace(0.0, 10.0, 201, dtype=DT)
    z = torchql.simulate(model, torch.tensor([1.0, 0.0], dtype=DT), t, rtol=1e-13, atol=1e-15)
    lin = map_fields(linearize(system, t, z), lambda v: v.unsqueeze(0))
    plain, low, high = (interpolation_misfit(system.f, t, z.unsqueeze(0), lin, 3, system.n, floor=floor)
                        for floor in (0.0, 1e-2, 1e3))
    torch.testing.assert_close(low, plain, rtol=1e-12, atol=0.0)
    largest = float(z.abs().amax())
    assert 0.0 < float(high) <= float(plain) * largest / 1e3 * (1 + 1e-12)
    assert bool(storage_misses(plain, 1e-10)[0]) and not bool(storage_misses(high, 1e-10)[0])


def test_the_same_fit_in_smaller_units_is_the_same_fit():
    """A damped oscillation (1 % noise) with its values, noise and initial guesses in units 1e5
    times smaller: the same estimates, to 1e-6 relative (the default ``atol = 1e-12`` is 1e-7 of
    states of 1e-5), the same status, and no note that the storage grid missed the model (the
    grid, sized with the absolute tolerance, is coarser there, as the tolerances allow)."""
    torch.manual_seed(0)
    t = torch.arange(14, dtype=DT) * 0.5
    y = torchql.simulate(LinearOscillator(0.1, 3.0), torch.tensor([0.0, 1.0], dtype=DT), t)[:, :1]
    y = y + 0.01 * torch.randn_like(y)
    results = [torchql.fit(LinearOscillator(0.5, 1.0), torchql.Observations(t, y * s, observe=["y"], sigma=0.01 * s),
                           x0=torch.tensor([0.5, 0.5], dtype=DT) * s) for s in (1.0, 1e-5)]
    for r in results:
        assert r.status is torchql.Status.CONVERGED and "storage grid" not in r.message
    for name in ("A", "B"):
        assert float(results[1].params[name]) == pytest.approx(float(results[0].params[name]), rel=1e-6)
