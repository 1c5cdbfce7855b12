"""Interval transfers from their Taylor series: exactness, the truncation bound, substeps, failures."""

import math

import pytest
import torch

from torchql.integrate import IntegrationError
from torchql.linearize import Linearization
from torchql.superposition import initial_columns, propagate_linear
from torchql.taylor import _substep_matrices, series_transfers, taylor_transfers
from torchql.trajectory import IntervalSystem, LinearizedReference
from torchql.transfer import Transfers, _Coefficients, interval_transfers

DT = torch.float64


def _random_reference(G=9, M=4, moving=3, scale=0.3, seed=0, span=2.0):
    """A reference with arbitrary node values and slopes: the interval systems are generic
    polynomial-coefficient linear systems (components past ``moving`` are constant)."""
    g = torch.Generator().manual_seed(seed)
    t = torch.linspace(0, span, G, dtype=DT)
    z = torch.randn(G, M, generator=g, dtype=DT)
    z_dot = torch.randn(G, M, generator=g, dtype=DT)
    f = torch.randn(G, M, generator=g, dtype=DT)
    jac = scale * torch.randn(G, M, M, generator=g, dtype=DT)
    f_dot = torch.randn(G, M, generator=g, dtype=DT)
    jac_dot = scale * torch.randn(G, M, M, generator=g, dtype=DT)
    for v in (f, jac, f_dot, jac_dot, z_dot):
        v[:, moving:] = 0.0
    return LinearizedReference(t, z, z_dot, Linearization(f=f, jac=jac, f_dot=f_dot, jac_dot=jac_dot))


def _reference_transfers(system: IntervalSystem, rtol: float) -> torch.Tensor:
    """``[Phi | c]`` of every interval by the other method, RK4 with step doubling, at ``rtol / 100``."""
    return interval_transfers(system, rtol=rtol / 100, atol=rtol / 1e4, max_substeps=4096)[0].full()[:, :-1]


def _within(T: torch.Tensor, exact: torch.Tensor, rtol: float, atol: float) -> float:
    """Largest ratio of ``|T - exact|`` to ``atol + rtol * max(|I|, |exact|)``, entry by entry."""
    M = exact.shape[1]
    eye = torch.eye(M, M + 1, dtype=DT)
    return float(((T[:, :M] - exact).abs() / (atol + rtol * torch.maximum(eye, exact.abs()))).max())


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("rtol", [1e-6, 1e-10])
def test_every_transfer_is_within_its_tolerance(seed, rtol):
    ref = _random_reference(seed=seed)
    atol = rtol * 1e-2
    system = IntervalSystem(ref)
    transfers, passes = taylor_transfers(system, rtol=rtol, atol=atol)
    # the truncation bound holds (rounding is ~1e-15); the reference is within 1% of the tolerance
    assert _within(transfers.full(), _reference_transfers(system, rtol), rtol, atol) <= 1.01
    assert transfers.active == 3 and passes >= 8


def test_a_tighter_tolerance_sums_more_terms():
    system = IntervalSystem(_random_reference(seed=3))
    order = _Coefficients(system).order
    loose = series_transfers(_Coefficients(system), rtol=1e-5, atol=1e-7)
    tight = series_transfers(_Coefficients(system), rtol=1e-13, atol=1e-15)
    assert tight.passes > loose.passes
    assert _within(Transfers(loose.Y, order).full(), Transfers(tight.Y, order).full()[:, :-1], 1e-5, 1e-7) <= 1.0


def test_long_intervals_are_split_into_substeps():
    # ||h A|| of several units on every interval: substeps of rho <= RHO_MAX, still within tolerance
    ref = _random_reference(G=5, scale=3.0, seed=4)
    system = IntervalSystem(ref)
    out = series_transfers(_Coefficients(system), rtol=1e-8, atol=1e-10)
    assert (out.substeps >= 4).all() and not out.failed.any()
    order = _Coefficients(system).order
    assert _within(Transfers(out.Y, order).full(), _reference_transfers(system, 1e-8), 1e-8, 1e-10) <= 1.01


def test_substep_matrices_shift_a_cubic_exactly():
    n = 4
    W = _substep_matrices(n, DT, torch.device("cpu"))
    c = torch.tensor([0.3, -1.2, 2.5, 0.7], dtype=DT)  # sum_k c_k s^k
    sigma = torch.linspace(0, 1, 7, dtype=DT)
    powers = torch.stack([sigma**k for k in range(4)])  # (4, 7)
    for m in range(n):
        s = (m + sigma) / n
        torch.testing.assert_close((c @ W[m]) @ powers, c @ torch.stack([s**k for k in range(4)]), rtol=0, atol=1e-15)


def test_substep_matrices_are_built_once_per_count_and_degree():
    """The table for 1,024 substeps is a loop of 37,000 Python steps; an SIR fit whose rejected
    trials needed that many spent a third of its time building it again for each."""
    from torchql.taylor import _shift_table

    _shift_table.cache_clear()
    first = _substep_matrices(1024, DT, torch.device("cpu"), 5)
    first.zero_()  # a caller's copy: the cached table is not touched
    again = _substep_matrices(1024, DT, torch.device("cpu"), 5)
    assert _shift_table.cache_info().hits == 1 and _shift_table.cache_info().misses == 1
    assert again[0, 0, 0] == 1.0 and again[1, 1, 0] == 1 / 1024


def test_result_does_not_depend_on_which_intervals_are_summed_together():
    # the number of terms is decided per interval, so a batch of two references gives each the
    # same transfers, bit for bit, as alone
    a_ref, b_ref = _random_reference(seed=5), _random_reference(seed=6, scale=1.0)
    ca, cb = _Coefficients(IntervalSystem(a_ref)), _Coefficients(IntervalSystem(b_ref))
    assert torch.equal(ca.order, cb.order)
    both = _Coefficients.of(torch.cat([ca.data, cb.data], dim=-1), ca.order, ca.a, ca.M)
    together = series_transfers(both, rtol=1e-10, atol=1e-12)
    alone = [series_transfers(c, rtol=1e-10, atol=1e-12) for c in (ca, cb)]
    assert torch.equal(together.Y, torch.cat([alone[0].Y, alone[1].Y], dim=-1))


def test_a_sample_with_an_interval_beyond_the_substeps_is_not_summed_further():
    """Two samples' intervals in one call: the first has intervals that would need more substeps
    than allowed, so it fails as a whole, and its other intervals that need substeps are left
    unsummed (the work of a trial that is rejected anyway); the second's transfers are those it
    gets alone, bit for bit."""
    doomed, fine = _random_reference(G=5, scale=3.0, seed=4), _random_reference(G=5, scale=3.0, seed=10)
    doomed.jac = doomed.jac.clone()
    doomed.jac[2] *= 1e4  # the intervals on both sides of node 2
    ca, cb = _Coefficients(IntervalSystem(doomed)), _Coefficients(IntervalSystem(fine))
    data = torch.cat([ca.data, cb.data], dim=-1)
    together = series_transfers(_Coefficients.of(data, ca.order, ca.a, ca.M, samples=2), rtol=1e-8, atol=1e-10,
                                max_substeps=64)
    alone = series_transfers(cb, rtol=1e-8, atol=1e-10, max_substeps=64)
    assert together.failed.tolist() == [False, True, True, False] + [False] * 4
    assert torch.equal(together.Y[..., 4:], alone.Y)
    assert (together.substeps[[0, 3]] >= 4).all() and bool((together.Y[..., [0, 3]] == 0).all())
    assert together.points == alone.points  # all the work is the second sample's
    # the blocks are the samples: as one sample, the failure leaves every interval with substeps unsummed
    as_one = series_transfers(_Coefficients.of(data, ca.order, ca.a, ca.M), rtol=1e-8, atol=1e-10, max_substeps=64)
    assert as_one.failed.tolist() == together.failed.tolist() and as_one.points == 0


def test_agrees_with_rk4_doubling():
    ref = _random_reference(G=41, seed=7, span=4.0)
    system = IntervalSystem(ref)
    rtol, atol = 1e-10, 1e-12
    T_taylor = taylor_transfers(system, rtol=rtol, atol=atol)[0].full()
    T_rk4 = interval_transfers(system, rtol=rtol, atol=atol)[0].full()
    assert _within(T_taylor, T_rk4[:, :-1], 2 * rtol, 2 * atol) <= 1.0


def test_propagation_matches_the_closed_form():
    # w' = a(t) w with a quadratic in t: the Hermite interpolant of the Jacobian is exact
    c0, c1, c2 = -0.5, 0.3, -0.2
    t = torch.linspace(0, 4, 41, dtype=DT)
    a = c0 + c1 * t + c2 * t**2
    integral = c0 * t + c1 * t**2 / 2 + c2 * t**3 / 3
    z = torch.exp(integral).unsqueeze(-1)
    f = (a * z[:, 0]).unsqueeze(-1)
    lin = Linearization(f=f, jac=a.reshape(-1, 1, 1), f_dot=(((c1 + 2 * c2 * t) + a**2) * z[:, 0]).unsqueeze(-1),
                        jac_dot=(c1 + 2 * c2 * t).reshape(-1, 1, 1))
    ref = LinearizedReference(t, z, f, lin)
    W, _ = propagate_linear(ref, initial_columns(z[0], torch.tensor([0])), rtol=1e-12, atol=1e-14,
                            linear_solver="taylor")
    torch.testing.assert_close(W[:, 0, 1], torch.exp(integral), rtol=1e-11, atol=0)


def test_no_moving_component_gives_identities():
    ref = _random_reference(moving=0)
    out = series_transfers(_Coefficients(IntervalSystem(ref)), rtol=1e-10, atol=1e-12)
    assert out.Y.shape[0] == 0 and not out.failed.any() and out.passes == 0


def test_failures_are_marked_per_interval_and_raised_by_taylor_transfers():
    ref = _random_reference(seed=8)
    ref.jac = ref.jac.clone()
    ref.jac[3, 0, 1] = float("nan")  # the intervals on both sides of node 3
    system = IntervalSystem(ref)
    out = series_transfers(_Coefficients(system), rtol=1e-10, atol=1e-12)
    assert out.failed.tolist() == [False, False, True, True, False, False, False, False]
    with pytest.raises(IntegrationError, match=r"2 grid interval\(s\) is not finite.*t = 0\.5\b"):
        taylor_transfers(system, rtol=1e-10, atol=1e-12)


def test_too_many_substeps_fail():
    ref = _random_reference(G=3, scale=40.0, seed=9)  # ||h A|| in the hundreds
    system = IntervalSystem(ref)
    assert series_transfers(_Coefficients(system), rtol=1e-10, atol=1e-12, max_substeps=4).failed.all()
    with pytest.raises(IntegrationError, match="needs more than 4 substeps"):
        taylor_transfers(system, rtol=1e-10, atol=1e-12, max_substeps=4)
    with pytest.raises(ValueError, match="`max_substeps` must be a power of two"):
        series_transfers(_Coefficients(system), rtol=1e-10, atol=1e-12, max_substeps=6)


def test_float32():
    ref = _random_reference(seed=10)
    ref32 = LinearizedReference(ref.t.float(), ref.z.float(), ref.z_dot.float(),
                                Linearization(*(v.float() for v in (ref.f, ref.jac, ref.f_dot, ref.jac_dot))))
    T32 = taylor_transfers(IntervalSystem(ref32), rtol=1e-5, atol=1e-7)[0].full()
    assert T32.dtype == torch.float32
    assert _within(T32.double(), _reference_transfers(IntervalSystem(ref), 1e-5), 1e-5, 1e-7) <= 1.01



def test_a_spent_time_budget_stops_the_series_sum():
    """The first pass over the intervals sums every series term by term: a fit's spent budget stops it there
    (a Bruno fit from a far start once summed one iteration's series for minutes past its `max_time`)."""
    import time

    from torchql.budget import TimeBudgetExceeded, time_budget

    coefficients = _Coefficients(IntervalSystem(_random_reference(seed=5, scale=0.1)))  # no substeps: one pass
    series_transfers(coefficients, rtol=1e-10, atol=1e-12)  # no budget: runs through
    with time_budget(0.0):
        time.sleep(0.001)
        with pytest.raises(TimeBudgetExceeded):
            series_transfers(coefficients, rtol=1e-10, atol=1e-12)


def test_a_badly_scaled_state_is_summed_in_the_balanced_norm():
    """An oscillation in microseconds, ``y'' = -w^2 y`` with ``w = 1e4``: over an interval turning
    half a radian, ``h A = [[0, h], [-h w^2, 0]]`` has the infinity norm ``h w^2 = 5,000``, which
    asked 8,192 substeps (more than allowed: every fit of such data failed), where the norm in
    states scaled to balance it (:func:`torchql.taylor._balance`) is ``h w = 0.5``: no substeps.
    The transfers are the exact rotations, entry by entry within the tolerance."""
    w, rtol, atol = 1e4, 1e-10, 1e-12
    t = torch.linspace(0, 10 / w, 21, dtype=DT)
    A = torch.tensor([[0.0, 1.0], [-w * w, 0.0]], dtype=DT)
    z = torch.stack([torch.cos(w * t), -w * torch.sin(w * t)], dim=-1)
    f = z @ A.T
    lin = Linearization(f=f, jac=A.expand(21, 2, 2).clone(), f_dot=f @ A.T, jac_dot=torch.zeros(21, 2, 2, dtype=DT))
    coefficients = _Coefficients(IntervalSystem(LinearizedReference(t, z, f, lin)))
    out = series_transfers(coefficients, rtol=rtol, atol=atol, max_substeps=16)
    assert not out.failed.any() and (out.substeps == 1).all()
    T = Transfers(out.Y, coefficients.order).full()
    c, s = math.cos(0.5), math.sin(0.5)
    rotation = torch.tensor([[c, s / w], [-w * s, c]], dtype=DT)
    # the rotation within the tolerance; the particular column (exactly 0: the forcing h f - h A z
    # cancels) within the rounding of its terms, a few eps times |h f| = h w^2 = 5,000
    scale = atol + rtol * torch.maximum(torch.eye(2, dtype=DT), rotation.abs())
    assert float(((T[:, :2, :2] - rotation).abs() / scale).max()) <= 1.0
    assert float(T[:, :2, 2].abs().max()) <= 8 * torch.finfo(DT).eps * 5e3
