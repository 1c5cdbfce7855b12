"""The exponential propagator: exact for constant coefficients, order 5 otherwise, stable for stiff A."""

import math

import pytest
import torch

import torchql
from torchql.integrate import IntegrationError
from torchql.linearize import Linearization
from torchql.models import LinearOscillator
from torchql.propagators import ExponentialRadau, linear_propagator
from torchql.propagators.exponential import exponential_series
from torchql.trajectory import IntervalSystem, LinearizedReference
from torchql.transfer import Transfers, _Coefficients, compose_transfers

DT = torch.float64
EPS = torch.finfo(DT).eps


def _linear(t, A, A_dot, b, b_dot):
    """``w' = A(t) w + b(t)`` as a reference about ``z = 0`` (so ``B = b``), all given as functions of ``t``."""
    G = t.shape[0]
    M = b(t).shape[-1]
    lin = Linearization(f=b(t), jac=A(t), f_dot=b_dot(t), jac_dot=A_dot(t))
    return LinearizedReference(t, torch.zeros(G, M, dtype=DT), torch.zeros(G, M, dtype=DT), lin)


def _constant(t, A, b):
    G = t.shape[0]
    return _linear(t, lambda t: A.expand(G, *A.shape), lambda t: torch.zeros(G, *A.shape, dtype=DT),
                   lambda t: b.expand(G, *b.shape), lambda t: torch.zeros(G, *b.shape, dtype=DT))


def _transfers(ref, rtol=1e-10, atol=1e-12, name="exponential"):
    return linear_propagator(name).transfers(IntervalSystem(ref), rtol=rtol, atol=atol, solver="dopri5",
                                             max_steps=None)


@pytest.mark.parametrize("A, b", [
    ([[-0.3, 2.0], [-2.0, -0.1]], [1.0, -0.5]),      # a damped rotation, forced
    ([[-1.0, 0.5], [0.0, -1e6]], [1.0, 2e6]),        # stiff: eigenvalues -1 and -1e6 over unit intervals
    ([[-1.0, 0.0], [3e5, -1e6]], [0.0, 0.0]),        # stiff and unforced, the slow mode feeding the fast
])
def test_constant_coefficients_give_the_matrix_exponential(A, b):
    A, b = torch.tensor(A, dtype=DT), torch.tensor(b, dtype=DT)
    t = torch.arange(6, dtype=DT)  # intervals of length 1
    transfers, n_evals = _transfers(_constant(t, A, b))
    X = torch.zeros(3, 3, dtype=DT)
    X[:2, :2], X[:2, 2] = A, b
    exact = torch.linalg.matrix_exp(X).expand(5, 3, 3)
    # the correction vanishes: the transfer is exp(h X) up to the exponential's rounding, eps ||h A||
    # relative (its normwise backward error); both sides carry it, hence twice
    bound = 2 * 8 * EPS * float(A.abs().sum(dim=1).max()) * max(1.0, float(exact.abs().max()))
    assert (transfers.full() - exact).abs().max() <= bound
    assert n_evals == 12  # one pass, no refinement


def test_constant_coefficients_match_the_closed_form_of_the_stiff_system():
    # w2' = -1e6 w2 + 2e6 jumps to 2; w1' = -w1 + w2 / 2 + 1: closed form over one unit interval
    A, b = torch.tensor([[-1.0, 0.5], [0.0, -1e6]], dtype=DT), torch.tensor([1.0, 2e6], dtype=DT)
    T = _transfers(_constant(torch.arange(2, dtype=DT), A, b))[0].full()[0]
    lam = 1e6
    phi_12 = 0.5 * (math.exp(-1) - math.exp(-lam)) / (lam - 1)
    # c_1 = int_0^1 e^{-(1-s)} (1 + w2(s) / 2) ds with w2 = 2 (1 - e^{-lam s})
    c_1 = 2 * (1 - math.exp(-1)) - (math.exp(-1) - math.exp(-lam)) / (lam - 1)
    expected = torch.tensor([[math.exp(-1), phi_12, c_1], [0.0, 0.0, 2.0], [0, 0, 1]], dtype=DT)
    assert torch.allclose(T, expected, rtol=0, atol=16 * EPS * lam)


def _polynomial(grid, k=1.5):
    """``w' = a(t) w + b(t)`` with ``a = -k (1 + t - t^2 / 4)`` and ``b = 1 - a (1 + t)``: the solution
    from ``w(0) = 1`` is ``1 + t``; ``a`` quadratic and ``b`` cubic, so their Hermite interpolants are exact."""
    a = lambda t: (-k * (1 + t - t**2 / 4)).reshape(-1, 1, 1)
    a_dot = lambda t: (-k * (1 - t / 2)).reshape(-1, 1, 1)
    b = lambda t: (1 - a(t)[:, 0, 0] * (1 + t)).unsqueeze(-1)
    b_dot = lambda t: (-a_dot(t)[:, 0, 0] * (1 + t) - a(t)[:, 0, 0]).unsqueeze(-1)
    return _linear(grid, a, a_dot, b, b_dot)


def _end_error(G, rtol):
    grid = torch.linspace(0, 2, G + 1, dtype=DT)
    out = exponential_series(_Coefficients(IntervalSystem(_polynomial(grid))), rtol=rtol, atol=rtol)
    w = compose_transfers(torchql.transfer.Transfers(out.Y, torch.arange(2)), torch.ones(1, 1, dtype=DT))
    return float((w[:, 0, 0] - (1 + grid)).abs().max()), out


def test_time_varying_coefficients_converge_at_order_five_and_meet_the_tolerance():
    # a loose tolerance leaves every interval at its first pass (two steps): the grid decides
    errors = [_end_error(G, rtol=1.0)[0] for G in (4, 8, 16)]
    assert all(out_steps == 2 for out_steps in _end_error(8, rtol=1.0)[1].substeps.tolist())
    rates = [math.log2(errors[i] / errors[i + 1]) for i in range(2)]
    assert min(rates) > 4.5, (errors, rates)  # Radau IIA's order 5 (a rate of 4 would be Magnus')
    # with error control: the whole solution within the per-interval tolerance times the intervals
    error, out = _end_error(8, rtol=1e-11)
    assert error <= 8 * 1e-11 * 3 and int(out.substeps.max()) > 2


def _stiff(grid, L):
    """``w' = a(t) (w - g(t)) + g'(t)`` with ``a = -L (1 + t / 2)`` and ``g = 1 + t / 2 - t^2 / 10``:
    solution ``g(t) + (w(0) - g(0)) exp(int a)``, and ``b = g' - a g`` cubic."""
    a = lambda t: (-L * (1 + t / 2)).reshape(-1, 1, 1)
    a_dot = lambda t: torch.full((t.shape[0], 1, 1), -L / 2, dtype=DT)
    g = lambda t: 1 + t / 2 - t**2 / 10
    g_dot = lambda t: 0.5 - t / 5
    b = lambda t: (g_dot(t) - a(t)[:, 0, 0] * g(t)).unsqueeze(-1)
    b_dot = lambda t: (-0.2 - a_dot(t)[:, 0, 0] * g(t) - a(t)[:, 0, 0] * g_dot(t)).unsqueeze(-1)
    return _linear(grid, a, a_dot, b, b_dot), g


@pytest.mark.parametrize("L", [1e6, 1e8])
def test_a_stiff_time_varying_problem_stays_accurate_where_the_others_give_up(L):
    grid = torch.linspace(0, 2, 101, dtype=DT)  # h |lambda| from 0.02 L to 0.04 L
    ref, g = _stiff(grid, L)
    for name in ("taylor", "rk4_doubling"):
        with pytest.raises(IntegrationError):  # both hit their cap of 1024 substeps per interval
            _transfers(ref, name=name)
    transfers, n_evals = _transfers(ref)
    assert n_evals == 12  # the first pass (two steps per interval) met the tolerance everywhere
    T = transfers.full()
    assert T[:, 0, 0].abs().max() < 1e-300  # exp(int a) underflows
    # from any start the solution is on g(t) one node later
    assert (T[:, 0, 1] - g(grid[1:])).abs().max() < 1e-9
    w = compose_transfers(transfers, torch.tensor([[0.0]], dtype=DT))
    assert (w[1:, 0, 0] - g(grid[1:])).abs().max() < 1e-9


@pytest.mark.parametrize("L", [1e3, 1e4])
def test_intermediate_stiffness_is_refined_by_at_most_eightfold_steps_per_pass(L):
    """``h |lambda|`` of 20 to 400 per interval (``L = 1e4``; van der Pol's drift at ``mu`` in the
    hundreds is in this range): the first difference (one step against two) is far from its
    asymptotic order, and the steps predicted from it were 512 to 1,024 per interval where 16 meet
    the tolerance (measured). Refined at most eightfold per pass, every interval stops at 16 steps,
    and the composed solution is the closed form's to 1e-10 (``rtol``)."""
    grid = torch.linspace(0, 2, 101, dtype=DT)
    ref, g = _stiff(grid, L)
    coefficients = _Coefficients(IntervalSystem(ref))
    out = exponential_series(coefficients, rtol=1e-10, atol=1e-12, freeze=False)
    assert not bool(out.failed.any()) and int(out.substeps.max()) <= 16
    w = compose_transfers(Transfers(out.Y, coefficients.order), torch.tensor([[0.0]], dtype=DT))
    t = grid[1:]
    exact = g(t) - g(torch.zeros(1, dtype=DT)) * torch.exp(-L * (t + t**2 / 4))  # w(0) = 0
    assert (w[1:, 0, 0] - exact).abs().max() < 1e-10


def test_it_is_registered_and_not_a_grid_solver():
    propagator = linear_propagator("exponential")
    assert isinstance(propagator, ExponentialRadau) and propagator == "exponential"
    assert "exponential" in torchql.LINEAR_SOLVERS and not propagator.grid_solver


def test_fit_with_it_reaches_the_default_fit():
    t = torch.arange(14, dtype=DT) * 0.5
    x0 = torch.tensor([0.0, 1.0], dtype=DT)
    data = torchql.Observations(t, torchql.simulate(LinearOscillator(0.1, 3.0), x0, t)[:, :1], observe=["y"])
    default = torchql.fit(LinearOscillator(0.5, 1.0), data, x0=x0)
    mine = torchql.fit(LinearOscillator(0.5, 1.0), data, x0=x0, linear_solver="exponential")
    assert mine.success and default.success
    assert torch.allclose(mine.estimates, default.estimates, rtol=1e-8, atol=1e-10)


def test_a_huge_error_ratio_refines_to_the_cap_instead_of_overflowing():
    """An interval whose first error ratio is astronomically large (1e300: the predicted number of
    steps, 2**333, overflows int64 to 0) is refined to ``max_substeps`` and failed, not divided by zero."""
    from torchql.propagators import exponential

    ref = _constant(torch.linspace(0.0, 1.0, 3, dtype=DT), torch.tensor([[-1.0]], dtype=DT),
                    torch.tensor([1.0], dtype=DT))
    coefficients = _Coefficients(IntervalSystem(ref))
    original = exponential._pair

    def huge_first_ratio(coefficients, index, n, rtol, atol, freeze=True):
        Y, ratio, evals = original(coefficients, index, n, rtol, atol, freeze)
        return Y, torch.full_like(ratio, 1e300 if n == 1 else 10.0), evals

    exponential._pair = huge_first_ratio
    try:
        out = exponential.exponential_series(coefficients, rtol=1e-8, atol=1e-10, max_substeps=8)
    finally:
        exponential._pair = original
    assert bool(out.failed.all()) and int(out.substeps.max()) == 8


def test_a_singular_stage_system_is_a_nan_step_not_an_exception():
    """Where ``h A`` makes Radau IIA's stage system singular (here ``h a = 1 / R_00`` at the first node,
    zero elsewhere: a zero pivot), the step is NaN, which the step doubling refines or marks failed,
    instead of torch's LinAlgError escaping the fit (van der Pol, mu = 100, data across its jumps)."""
    from torchql.propagators.exponential import _RADAU, _step

    R = torch.tensor(_RADAU, dtype=torch.float64).reshape(3, 3)
    Xc = torch.zeros(3, 2, 1, 2, dtype=torch.float64)  # two intervals, one active component, its forcing column
    Xc[0, 0, 0, 0] = 1.0 / R[0, 0]
    Xc[:, 1, 0, 0] = -0.5  # the second, an ordinary decay
    out = _step(torch.zeros(2, 1, 2, dtype=torch.float64), Xc, freeze=False)
    assert torch.isnan(out[0]).all()
    assert torch.isfinite(out[1]).all() and 0.5 < float(out[1, 0, 0]) < 0.7  # exp(-0.5) to the method's order
