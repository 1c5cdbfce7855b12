"""Values marked ``exact`` in mid-series: the iteration's merit and its constrained steps agree.

Every step meets the exact rows as equality constraints (:func:`torchql.lstsq.solve_update`).
The merit that accepts the steps was once the sum of squares plus ``1e6`` times the exact rows'
*squared* misfit: its minimum lies off the exact values by the constraint's multiplier over
``2e6`` (about ``1e-8`` on the oscillator below), where the point scores below the constrained
optimum, so that no step toward the exact values could be accepted and the default fit STALLED
at the truth (``damping=None`` converged). Damping did not shorten the step toward the exact
values either, so a shooting fit from far guesses stalled with an exact value missed by 0.48.

The merit is now Han's exact penalty, the misfit's magnitude weighted above the multipliers
(:meth:`torchql.engine.Engine._weigh_exact`), whose minimum is the constrained optimum, and a
damping ``lambda`` meets the fraction ``1 / (1 + lambda)`` of the exact rows' misfit.

Bounds: a converged fit meets its linearized exact rows to rounding (about 1e-15); the reported
misfit is the model's own solution's at the estimates, integrated at ``rtol = 1e-10`` relative to
values of magnitude at most 1, so it is at most about ``1e-10`` (observed 5e-14 to 2e-13).
"""

from __future__ import annotations

import pytest
import torch

import torchql
from torchql.lstsq import solve_update
from torchql.models import LinearOscillator

DT = torch.float64
TIMES = torch.arange(14, dtype=DT) * 0.5
MET = 1e-10  # rtol times the largest |y| (see the module's notes)


def _data() -> torch.Tensor:
    """The linear oscillator (A, B) = (0.1, 3) from (0, 1), y observed with noise 1e-2: ``(14, 1)``."""
    y = torchql.simulate(LinearOscillator(0.1, 3.0), torch.tensor([0.0, 1.0], dtype=DT), TIMES)[:, :1]
    return y + 1e-2 * torch.randn(y.shape, generator=torch.Generator().manual_seed(0), dtype=DT)


def _marked(*rows: int) -> torch.Tensor:
    exact = torch.zeros(14, 1, dtype=torch.bool)
    exact[list(rows)] = True
    return exact


@pytest.fixture(scope="module")
def noisy() -> torch.Tensor:
    return _data()


@pytest.mark.parametrize("row", [5, 3, 9])
def test_fit_from_the_truth_converges_with_the_exact_value_met(noisy, row):
    """From the true coefficients, one exact value at y(2.5) STALLED (exact misfit 2e-8) and at
    y(1.5) stopped CONVERGED_SSE; each now CONVERGES as the undamped iteration does, at its
    optimum (the same SSE and estimates to 1e-9), the exact value met to ``MET``."""
    data = torchql.Observations(TIMES, noisy, observe=["y"], exact=_marked(row))
    x0 = torch.tensor([0.0, 1.0], dtype=DT)
    result = torchql.fit(LinearOscillator(0.1, 3.0), data, x0)
    undamped = torchql.fit(LinearOscillator(0.1, 3.0), data, x0, damping=None)
    assert result.status is torchql.Status.CONVERGED, result.message
    assert result.exact_residual < MET
    assert result.sse == pytest.approx(undamped.sse, rel=1e-9)
    torch.testing.assert_close(result.estimates, undamped.estimates, rtol=1e-9, atol=1e-11)


def test_fit_many_meets_each_samples_exact_value_as_fit_does(noisy):
    """A batch of the three datasets (one exact value each, at different times): every sample
    CONVERGED, its exact value met to ``MET``, with its single fit's status and iterations."""
    exact = torch.stack([_marked(5), _marked(3), _marked(9)])
    y = noisy.expand(3, -1, -1)
    x0 = torch.tensor([0.0, 1.0], dtype=DT)
    batch = torchql.fit_many(LinearOscillator(0.1, 3.0), torchql.Observations(TIMES, y, observe=["y"], exact=exact), x0)
    for b in range(3):
        single = torchql.fit(LinearOscillator(0.1, 3.0),
                             torchql.Observations(TIMES, noisy, observe=["y"], exact=exact[b]), x0)
        assert batch.status[b] is torchql.Status.CONVERGED, batch.message[b]
        assert batch.status[b] is single.status and int(batch.iterations[b]) == single.iterations
        assert float(batch.exact_residual[b]) < MET


def test_shooting_from_far_guesses_reaches_the_optimum(noisy):
    """Shooting from (A, B) = (0.5, 1), y(0) and y(2.5) exact: it stalled at A = 2.52, B = 7.36
    (SSE 1.14, y(2.5) missed by 0.48), the damping unable to shorten the step toward the exact
    values. It now reaches Kantorovich's optimum (SSE 0.00262, to 1e-9) with both values met."""
    data = torchql.Observations(TIMES, noisy, observe=["y"], exact=_marked(0, 5))
    shooting = torchql.fit(LinearOscillator(0.5, 1.0), data, torch.tensor([0.2, 0.8], dtype=DT), method="shooting")
    reference = torchql.fit(LinearOscillator(0.1, 3.0), data, torch.tensor([0.0, 1.0], dtype=DT), damping=None)
    assert reference.success and reference.sse == pytest.approx(0.0026213, rel=1e-4)
    assert shooting.status is torchql.Status.CONVERGED, shooting.message
    assert shooting.sse == pytest.approx(reference.sse, rel=1e-9)
    assert shooting.exact_residual < MET


def test_a_fit_stopped_with_an_exact_value_unmet_says_so(noisy):
    """One iteration from far guesses leaves the nonlinear misfit of the exact value (its
    linearization met): the unconverged result's message names it."""
    data = torchql.Observations(TIMES, noisy, observe=["y"], exact=_marked(0, 5))
    result = torchql.fit(LinearOscillator(0.5, 1.0), data, torch.tensor([0.2, 0.8], dtype=DT), max_iter=1)
    assert not result.success and result.exact_residual > 1e-6
    assert "The values marked `exact` are not met: the largest misfit is" in result.message


class _Logistic(torchql.ODEModel):
    state_names = ("N",)

    def __init__(self, r: float, K: float) -> None:
        super().__init__()
        self.register_buffer("r", torch.tensor(r, dtype=DT))
        self.register_buffer("K", torch.tensor(K, dtype=DT))

    def forward(self, t, x):
        return self.r * x * (1 - x / self.K)


@pytest.mark.parametrize("K", [11.466734, 12.0])
def test_a_fit_stopped_by_the_sum_of_squares_test_meets_its_exact_value(K):
    """Logistic growth, K held, r and N(0) fitted to 12 noisy values with the sixth marked exact.
    The SSE test (``ftol``, the step below ``sqrt(xtol)``) stopped these fits with the exact value
    missed by 5e-6 and 4e-6 (1e-6 relative), reported as success with an SSE below the constrained
    optimum: the final pass now takes Gauss–Newton steps on the model until it is met. Reference:
    the closed form, N(0) solved from the exact value for each r, and r by a bounded 1-D search."""
    import numpy as np
    from scipy.optimize import minimize_scalar

    t = np.linspace(0.0, 8.0, 12)

    def closed_form(r, N0):
        e = np.exp(r * t)
        return K * N0 * e / (K + N0 * (e - 1.0))

    e = np.exp(0.8 * t)  # the data: r = 0.8, K = 10, N0 = 0.5, noise 0.3
    y = 10.0 * 0.5 * e / (10.0 + 0.5 * (e - 1.0)) + 0.3 * np.random.default_rng(3).standard_normal(12)

    def start_meeting_the_exact_value(r):
        e5 = np.exp(r * t[5])
        return y[5] * K / (K * e5 - y[5] * (e5 - 1.0))

    def sse(r):
        return float(np.sum(np.delete(closed_form(r, start_meeting_the_exact_value(r)) - y, 5) ** 2))

    best = minimize_scalar(sse, bounds=(0.3, 1.2), method="bounded", options={"xatol": 1e-12})
    exact = torch.zeros(12, 1, dtype=torch.bool)
    exact[5] = True
    data = torchql.Observations(torch.tensor(t), torch.tensor(y).unsqueeze(-1), observe=["N"], exact=exact)
    result = torchql.fit(_Logistic(0.79, K), data, torch.tensor([0.49], dtype=DT), params=["r"])
    assert result.success, result.message
    assert result.exact_residual <= MET * abs(y[5])
    assert result.params["r"].item() == pytest.approx(best.x, rel=1e-7)
    assert result.x0.item() == pytest.approx(start_meeting_the_exact_value(best.x), rel=1e-6)
    assert result.sse == pytest.approx(best.fun, rel=1e-9)


def _problem():
    g = torch.Generator().manual_seed(11)
    C = torch.randn(12, 4, generator=g, dtype=DT) * torch.tensor([1.0, 10.0, 0.1, 5.0], dtype=DT)
    d = torch.randn(12, generator=g, dtype=DT)
    w = torch.rand(12, generator=g, dtype=DT) + 0.5
    exact = torch.zeros(12, dtype=torch.bool)
    exact[[2, 7]] = True
    return C, d, w, exact


def test_multipliers_are_those_of_the_kkt_system():
    """``solve_update``'s multipliers solve the KKT system of min ||W (C a - d)||^2 subject to
    ``W_e C_e a = W_e d_e`` (per unit of the exact rows' weighted values), to rounding."""
    C, d, w, exact = _problem()
    sol = solve_update(C, d, w, exact, rcond=1e-12)
    A, b = C[~exact] * w[~exact, None], d[~exact] * w[~exact]
    E, e = C[exact] * w[exact, None], d[exact] * w[exact]
    kkt = torch.zeros(6, 6, dtype=DT)
    kkt[:4, :4], kkt[:4, 4:], kkt[4:, :4] = 2 * A.T @ A, E.T, E
    expected = torch.linalg.solve(kkt, torch.cat([2 * A.T @ b, e]))
    torch.testing.assert_close(sol.alpha, expected[:4], rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(sol.multipliers, expected[4:], rtol=1e-10, atol=1e-12)
    assert solve_update(C, d, w, torch.zeros_like(exact), rcond=1e-12).multipliers.numel() == 0


@pytest.mark.parametrize("damping", [0.0, 1e-3, 1.0, 1e6])
def test_a_damped_step_meets_its_fraction_of_the_exact_misfit(damping):
    """Damping ``lambda`` meets ``1 / (1 + lambda)`` of the exact rows' misfit (all at 0), so a
    large damping shortens the whole step: at 1e6 its length is of order a millionth of the undamped
    one's (both its parts scale as ``1 / lambda``; 2.4e-6 here, below 1e-5)."""
    C, d, w, exact = _problem()
    step = solve_update(C, d, w, exact, rcond=1e-12, damping=damping).alpha
    torch.testing.assert_close(C[exact] @ step, d[exact] / (1 + damping), rtol=1e-10, atol=1e-13)
    if damping == 1e6:
        full = solve_update(C, d, w, exact, rcond=1e-12).alpha
        assert torch.linalg.vector_norm(step) < 1e-5 * torch.linalg.vector_norm(full)


class _Pendulum(torchql.ODEModel):
    """``theta'' = -c theta' - g sin theta``."""

    state_names = ("theta", "omega")

    def __init__(self, g=9.81, c=0.3):
        super().__init__()
        self.register_buffer("g", torch.tensor(g, dtype=DT))
        self.register_buffer("c", torch.tensor(c, dtype=DT))

    def forward(self, t, x):
        theta, omega = x.unbind(-1)
        return torch.stack((omega, -self.c * omega - self.g * torch.sin(theta)), dim=-1)


def test_exact_values_that_a_later_iterate_cannot_meet_are_no_contradiction_of_the_data():
    """A pendulum's angle, exact data, three values marked exact (t = 0, 1.75, 5) and four unknowns:
    the truth meets them, and Kantorovich from guesses three times off converges meeting them.
    Shooting from those guesses wanders to g = 47, c = 8, where the pendulum has come to rest
    before t = 1.75: there no step can meet the marked values. That fit stalled; it said
    EXACT_INFEASIBLE, "they are linearly dependent or contradictory. Mark fewer values exact"."""
    t = torch.linspace(0, 10, 41, dtype=DT)
    x0 = torch.tensor([1.0, 0.0], dtype=DT)
    exact = torch.zeros(41, 1, dtype=torch.bool)
    exact[[0, 7, 20], 0] = True
    data = torchql.Observations(t, torchql.simulate(_Pendulum(), x0, t)[:, :1], observe=["theta"], exact=exact)
    kantorovich = torchql.fit(_Pendulum(g=29.43, c=0.9), data, x0=x0)
    assert kantorovich.success and kantorovich.exact_residual < 1e-10, kantorovich.message
    shooting = torchql.fit(_Pendulum(g=29.43, c=0.9), data, x0=x0, method="shooting")
    assert shooting.status is torchql.Status.STALLED, shooting.message
    assert "the data need not contradict them" in shooting.message


def test_an_exact_value_on_an_initial_state_held_fixed_at_it_is_no_contradiction():
    """``y(0) = 1`` measured exactly and given as known (``fixed_x0=["y"]``): the exact row has no
    unknown to move and is met, and the fit is the one with ``y(t0)`` free (which the exact value
    pins at 1). It ended EXACT_INFEASIBLE at the guesses; ``profile`` of the free fit's ``y(t0)``
    raised, where its interval is the estimate itself."""
    t = torch.linspace(0, 10, 41, dtype=DT)
    y = torchql.simulate(LinearOscillator(0.3, 2.0), torch.tensor([1.0, 0.0], dtype=DT), t)[:, :1]
    y = y + 0.05 * torch.randn(y.shape, generator=torch.Generator().manual_seed(0), dtype=DT)
    y[0, 0] = 1.0
    exact = torch.zeros(41, 1, dtype=torch.bool)
    exact[0] = True
    data = torchql.Observations(t, y, observe=["y"], exact=exact)
    known = torchql.fit(LinearOscillator(0.5, 1.5), data, x0=torch.tensor([1.0, 0.1], dtype=DT), fixed_x0=["y"])
    free = torchql.fit(LinearOscillator(0.5, 1.5), data, x0=torch.tensor([0.8, 0.1], dtype=DT))
    assert known.status is free.status is torchql.Status.CONVERGED, known.message
    assert float(free.x0[0]) == 1.0
    torch.testing.assert_close(known.estimates, free.estimates[1:], rtol=1e-8, atol=1e-10)
    assert known.sse == pytest.approx(free.sse, rel=1e-10)
    pinned = torchql.profile(free, "y(t0)")
    assert pinned.interval == (1.0, 1.0) and pinned.closed == (True, True)
