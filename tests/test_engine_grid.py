"""The automatic storage grid (``grid="auto"``, the default; torchql/engine_grid.py).

Each dataset's intervals come from the size of the fourth derivative of the model's solutions
along its first reference (from the model's slopes and their rates of change there): the count follows the closed-form bound for an oscillator, a coasting car gets
the fewest, the fit on the chosen grid equals the fit on the fine fixed grid, and a batch whose
samples choose different grids is fitted group by group, each sample as its own ``fit``.
"""

from __future__ import annotations

import math
from unittest import mock

import pytest
import torch

import torchql
import torchql.engine_grid as engine_grid
from torchql.engine_grid import derivative_scale, fourth_derivative_scale
from torchql.grid import AUTO_COUNTS, AUTO_SAFETY, auto_counts, needed_intervals
from torchql.models import CoastingCar, LinearOscillator
from testmodels import Relaxation

DT = torch.float64


def _grid_of(result) -> torch.Tensor:
    return result.history[-1].trajectory_t


def test_fourth_derivative_scale_of_an_oscillation_is_omega_to_the_fourth_times_its_amplitude():
    omega = 2.0
    t = torch.linspace(0, 2 * math.pi / omega, 101, dtype=DT)  # one period
    slopes = torch.stack([-omega * torch.sin(omega * t), -omega**2 * torch.cos(omega * t)], dim=-1)  # (y', v')
    rates = torch.stack([-omega**2 * torch.cos(omega * t), omega**3 * torch.sin(omega * t)], dim=-1)  # (y'', v'')
    scale = fourth_derivative_scale(slopes.unsqueeze(0), rates.unsqueeze(0))
    # y = cos: y = omega^4; v = -omega sin: v = omega^5
    torch.testing.assert_close(scale[0, 0], torch.tensor([omega**4, omega**5], dtype=DT), rtol=1e-12, atol=0)


def test_fourth_derivative_scale_of_a_logistic_curve_is_within_its_stated_bound():
    r, K, x0, h = 1.3, 10.0, 0.5, 0.01
    t = torch.arange(0, 8, h, dtype=DT, requires_grad=True)
    x = K / (1 + (K / x0 - 1) * torch.exp(-r * t))
    derivatives = [x]
    for _ in range(4):  # the closed form's derivatives, by autograd
        derivatives.append(torch.autograd.grad(derivatives[-1].sum(), t, create_graph=True)[0])
    true = float(derivatives[4].detach().abs().max())
    scale = float(fourth_derivative_scale(derivatives[1].detach().reshape(1, -1, 1),
                                          derivatives[2].detach().reshape(1, -1, 1)))
    assert true / 12 < scale < true / 6  # "a ninth": 1.7 times too few intervals at the fourth root


def test_fourth_derivative_scale_along_a_data_reference_is_the_models():
    # exact data of an oscillator, few points a period: the reference's derived velocity is a
    # smoothing spline's slope, whose differences would overstate y's fourth derivative
    omega, t = 3.0**0.5, torch.linspace(0, 6.5, 14, dtype=DT)
    seen = []
    real = fourth_derivative_scale

    def spy(slopes, rates):
        out = real(slopes, rates)
        seen.append(out / torch.tensor([1 / omega, 1.0], dtype=DT))  # per amplitude (y = sin(wt)/w, v = cos(wt))
        return out

    x = torchql.simulate(LinearOscillator(0.0, omega**2), torch.tensor([0.0, 1.0], dtype=DT), t, rtol=1e-12,
                         atol=1e-14)
    with mock.patch.object(engine_grid, "fourth_derivative_scale", spy):
        result = torchql.fit(LinearOscillator(0.05, 2.5), torchql.Observations(t, x[:, :1], observe=["y"]),
                             torch.tensor([0.0, 0.9], dtype=DT))
    assert result.success
    # omega^4 = 9 per unit amplitude (differences of the reference's slopes gave 32 for y): y's
    # within 5%; v's within 25%, the derived velocity (the spline's slope) being 6% high at its
    # peak, which the estimate's cube and square raise to 20%
    y_scale, v_scale = seen[0][0, 0].tolist()
    assert y_scale == pytest.approx(omega**4, rel=0.05)
    assert v_scale == pytest.approx(omega**4, rel=0.25)


def test_auto_counts_take_the_fewest_listed_count_that_suffices():
    needed = torch.tensor([0.5, 20.0, 20.5, 99.0, 201.0, 5000.0, math.inf], dtype=DT)
    assert auto_counts(needed).tolist() == [20, 20, 25, 100, 250, 1000, 1000]
    assert list(AUTO_COUNTS) == sorted(AUTO_COUNTS)


def test_oscillator_gets_the_count_of_the_hermite_bound_and_a_car_the_fewest():
    # exact data: the first reference is the data's interpolant, the model's solution to a few 1e-5
    omega = 2.0
    t = torch.linspace(0, 6, 25, dtype=DT)
    x = torchql.simulate(LinearOscillator(0.0, omega**2), torch.tensor([1.0, 0.0], dtype=DT), t, rtol=1e-12,
                         atol=1e-14)
    result = torchql.fit(LinearOscillator(0.05, 3.8), torchql.Observations(t, x, observe=["y", "v"]),
                         torch.tensor([1.0, 0.0], dtype=DT))
    assert result.success
    # h^4 omega^4 / 384 = sqrt(rtol) / 16 gives 96.4 intervals over [0, 6]: the listed count 100
    rtol = AUTO_SAFETY * math.sqrt(1e-10)
    assert math.isclose(6 / ((384 * rtol) ** 0.25 / omega), 96.4, rel_tol=1e-3)
    widths = _grid_of(result).diff()
    assert float(widths.max()) <= 6 / 100 * (1 + 1e-9)
    assert float(widths.max()) > 6 / 200
    car_t = torch.linspace(0, 40, 9, dtype=DT)
    v = torchql.simulate(CoastingCar(frontal_area=17.3, mass=80.43, C_D=0.5, mu=0.02),
                         torch.tensor([117.0], dtype=DT), car_t, rtol=1e-12, atol=1e-12)
    car = torchql.fit(CoastingCar(frontal_area=17.3, mass=80.43, C_D=0.4, mu=0.03),
                      torchql.Observations(car_t, v, observe=["v"]), torch.tensor([116.0], dtype=DT),
                      params=["C_D", "mu"])
    assert car.success
    assert float(_grid_of(car).diff().max()) == pytest.approx(40 / 20, rel=1e-9)  # the fewest listed, 20


@pytest.mark.parametrize("noise", [0.0, 1e-3])
def test_the_fit_on_the_chosen_grid_equals_the_fit_on_the_fine_grid(noise):
    t = torch.linspace(0, 6, 25, dtype=DT)
    x = torchql.simulate(LinearOscillator(0.3, 4.0), torch.tensor([1.0, 0.0], dtype=DT), t, rtol=1e-12, atol=1e-14)
    g = torch.Generator().manual_seed(3)
    y = x[:, :1] + noise * torch.randn(25, 1, generator=g, dtype=DT)
    data = torchql.Observations(t, y, observe=["y"])
    auto = torchql.fit(LinearOscillator(0.4, 3.5), data, torch.tensor([0.9, 0.1], dtype=DT))
    fine = torchql.fit(LinearOscillator(0.4, 3.5), data, torch.tensor([0.9, 0.1], dtype=DT), grid=1000)
    assert auto.status == fine.status and auto.success
    assert len(_grid_of(auto)) < len(_grid_of(fine)) // 4
    if noise == 0.0:  # both at the truth, to the integration's accuracy
        truth = torch.tensor([1.0, 0.0, 0.3, 4.0], dtype=DT)
        assert float((auto.estimates - truth).abs().max()) < 1e-8
    stderr = fine.covariance.diagonal().sqrt() if noise else torch.ones(4, dtype=DT)
    # noisy: the grid's Jacobian error moves the optimum by a fraction of a standard error
    assert float(((auto.estimates - fine.estimates) / stderr).abs().max()) < (1e-4 if noise else 1e-8)
    assert auto.sse == pytest.approx(fine.sse, rel=1e-7, abs=1e-18)


def test_samples_that_choose_different_grids_are_each_fitted_as_alone():
    data, x0, guesses = _four_oscillators()
    t, rows, guesses = data.t, [data.y[k] for k in range(4)], guesses["B"].tolist()
    batch = torchql.fit_many(LinearOscillator(0.25, 1.0), data, x0, guesses={"B": torch.tensor(guesses, dtype=DT)})
    widths = []
    for k in range(4):
        alone = torchql.fit(LinearOscillator(0.25, guesses[k]), torchql.Observations(t, rows[k], observe=["y"]),
                            x0[k])
        assert batch[k].status == alone.status and alone.success
        assert batch[k].iterations == alone.iterations
        torch.testing.assert_close(batch[k].estimates, alone.estimates, rtol=1e-10, atol=1e-12)
        assert batch[k].sse == pytest.approx(alone.sse, rel=1e-10)
        widths.append(float(_grid_of(alone).diff().max()))
    assert min(widths[0], widths[2]) > 1.5 * max(widths[1], widths[3])  # two groups of grids


def _four_oscillators():
    """Two slow and two fast oscillators (interleaved): two groups of grids."""
    t = torch.linspace(0, 6, 31, dtype=DT)
    rows, guesses = [], []
    for k, B in enumerate([1.0, 16.0, 1.2, 14.0]):
        x = torchql.simulate(LinearOscillator(0.2, B), torch.tensor([1.0, 0.0], dtype=DT), t, rtol=1e-12, atol=1e-14)
        g = torch.Generator().manual_seed(k)
        rows.append(x[:, :1] + 1e-3 * torch.randn(31, 1, generator=g, dtype=DT))
        guesses.append(B * 1.1)
    data = torchql.Observations(t, torch.stack(rows), observe=["y"])
    return data, torch.tensor([1.0, 0.0], dtype=DT).expand(4, 2), {"B": torch.tensor(guesses, dtype=DT)}


def test_groups_of_grids_share_one_final_dormand_prince_pass_with_the_same_results():
    """Where each group's final pass would call the batched Dormand–Prince (here: no sample-interval
    budget for the grid solver), the groups' final solutions come from one call, each sample on
    its own padded grid, and every result is the one the groups' own calls give."""
    import torchql.engine_evaluate as engine_evaluate
    import torchql.engine_final as engine_final

    data, x0, guesses = _four_oscillators()
    calls = []
    real = engine_evaluate.dopri_batch

    def spy(system, z0, grid, **kwargs):
        calls.append((z0.shape[0], grid.shape, kwargs["rtol"]))
        return real(system, z0, grid, **kwargs)

    def fit():
        calls.clear()
        with mock.patch.object(engine_evaluate, "_SHOOTING_POINTS", 0), \
                mock.patch.object(engine_evaluate, "dopri_batch", spy), mock.patch.object(engine_final, "dopri_batch", spy):
            result = torchql.fit_many(LinearOscillator(0.25, 1.0), data, x0, guesses=guesses)
        rtol = result.solver_options["rtol"]
        return result, [c for c in calls if c[2] == rtol]

    shared, shared_calls = fit()
    with mock.patch.object(engine_final.FinalPass, "_share_final_solutions", lambda self, parts: None):
        apart, apart_calls = fit()
    assert len(apart_calls) == 2 and sorted(c[0] for c in apart_calls) == [2, 2]  # one per group
    assert len(shared_calls) == 1 and shared_calls[0][0] == 4 and len(shared_calls[0][1]) == 2  # padded (4, G)
    assert [s for s in shared.status] == [s for s in apart.status] and all(shared.success)
    assert torch.equal(shared.iterations, apart.iterations)
    torch.testing.assert_close(shared.estimates, apart.estimates, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(shared.sse, apart.sse, rtol=1e-12, atol=1e-18)
    torch.testing.assert_close(shared.covariance, apart.covariance, rtol=1e-10, atol=1e-18)


def test_difference_slopes_are_exact_for_quadratics_on_uneven_and_padded_grids():
    grid = torch.tensor([[0.0, 0.1, 0.4, 0.5, 1.3, 2.0], [0.0, 0.3, 0.35, 1.0, 1.0, 1.0]], dtype=DT)
    x = torch.stack([3 * grid**2 - grid + 2, -grid**2 + 5 * grid], dim=-1)  # (S, G, 2)
    slopes = engine_grid.difference_slopes(grid, x)
    exact = torch.stack([6 * grid - 1, -2 * grid + 5], dim=-1)
    # second order everywhere, one-sided at the ends and at the padded grid's last node (its padding is not read)
    real = torch.tensor([[True] * 6, [True] * 4 + [False] * 2])
    torch.testing.assert_close(slopes[real], exact[real], rtol=1e-12, atol=1e-12)
    assert torch.isfinite(slopes).all()
    two = torch.tensor([[0.0, 0.5]], dtype=DT)  # one interval: its mean slope at both ends
    torch.testing.assert_close(engine_grid.difference_slopes(two, (two**2).unsqueeze(-1)),
                               torch.full((1, 2, 1), 0.5, dtype=DT), rtol=1e-12, atol=0)


def _stiff_relaxation():
    """Exact values of the stiff relaxation (k = 1e3, x(0) = 2) at 30 log-spaced times over
    [1e-4, 10^0.5], and the options of a fit of k by Rodas5P at rtol 1e-8."""
    t = torch.logspace(-4, 0.5, 30, dtype=DT)
    x = torchql.simulate(Relaxation(k=1e3), torch.tensor([2.0], dtype=DT), torch.cat([torch.zeros(1, dtype=DT), t]),
                         solver="rodas5p", rtol=1e-12, atol=1e-14)[1:]
    data = torchql.Observations(t, x, observe=["x"])
    return data, dict(t0=0.0, params=["k"], fixed_x0=["x"], solver="rodas5p", rtol=1e-8, atol=1e-12)


def test_a_stiff_models_grid_keeps_its_geometric_nodes_and_chooses_its_uniform_intervals():
    """``grid="auto"`` on the stiff path: the geometric early nodes stay, the uniform intervals
    besides are the fewest that interpolate the first reference (here far fewer than the fixed
    1,000), and the fit equals the one on the fixed grid within its tolerance."""
    data, options = _stiff_relaxation()
    auto = torchql.fit(Relaxation(k=700.0), data, torch.tensor([2.0], dtype=DT), **options)
    fixed = torchql.fit(Relaxation(k=700.0), data, torch.tensor([2.0], dtype=DT), grid=1000, **options)
    assert auto.success and fixed.success, (auto.message, fixed.message)
    nodes, fine = _grid_of(auto), _grid_of(fixed)
    assert len(nodes) < len(fine) // 4
    assert float(nodes[1]) < 1e-11  # the earliest geometric node, 3e-13 after t0
    early = nodes[(nodes > 0) & (nodes < 1e-4)]
    assert float((early[1:] / early[:-1]).max()) < 1.3  # ten per decade, none dropped
    torch.testing.assert_close(auto.estimates, fixed.estimates, rtol=1e-7, atol=1e-10)


def test_a_stiff_fits_early_transfers_are_loose_and_its_converged_iterate_tight():
    """Inexact transfers on the stiff path (engine_evaluate.INEXACT_FACTOR): the first iterate's
    and the long steps' trials are propagated at the loose tolerance, the iterate that converges at
    ``rtol``; the estimates equal those of a fit with every transfer at ``rtol``."""
    import torchql.batch_integrate as batch_integrate
    import torchql.engine_evaluate as engine_evaluate

    data, options = _stiff_relaxation()
    tolerances = []
    propagate = batch_integrate.propagate_linear_batch

    def recorded(*args, rtol, **kwargs):
        tolerances.append(rtol)
        return propagate(*args, rtol=rtol, **kwargs)

    with mock.patch.object(engine_evaluate, "propagate_linear_batch", recorded):
        inexact = torchql.fit(Relaxation(k=300.0), data, torch.tensor([2.0], dtype=DT), **options)
    with mock.patch("torchql.engine.INEXACT_FACTOR", 0.0), mock.patch("torchql.engine._LOOSE_RTOL", 0.0):
        exact = torchql.fit(Relaxation(k=300.0), data, torch.tensor([2.0], dtype=DT), **options)
    assert inexact.success and exact.success, (inexact.message, exact.message)
    assert tolerances[0] == 1e-6 and tolerances[1] == 1e-6 and tolerances[-1] == 1e-8, tolerances
    assert inexact.params["k"].item() == pytest.approx(1e3, rel=1e-7)
    torch.testing.assert_close(inexact.estimates, exact.estimates, rtol=1e-8, atol=0)


def test_a_stiff_fits_first_iterate_is_integrated_once_from_the_guesses():
    """The first reference of a stiff Kantorovich fit is the model's solution from the guesses on
    the fit's grid, at the fit's tolerance (a loose one's error, times the stiffness, would enter
    its storage's slopes): the second opinion on the first iterate (and its re-anchoring) reuse it
    instead of integrating the same solution again; the fit still converges to the truth."""
    import torchql.engine_evaluate as engine_evaluate

    data, options = _stiff_relaxation()
    starts = []
    model = engine_evaluate.rodas5p_model

    def recorded(system, z0, grid, **kwargs):
        starts.append((z0[0, -1].item(), kwargs["rtol"]))
        return model(system, z0, grid, **kwargs)

    with mock.patch.object(engine_evaluate, "rodas5p_model", recorded):
        result = torchql.fit(Relaxation(k=100.0), data, torch.tensor([2.0], dtype=DT), **options)
    assert result.success, result.message
    assert result.params["k"].item() == pytest.approx(1e3, rel=1e-7)
    assert starts.count((100.0, options["rtol"])) == 1, starts
    assert (100.0, 1e-6) not in starts, starts
    assert len(starts) >= 2  # the later iterates did get their second opinions
    assert math.isfinite(result.history[0].model_merit)  # the first iterate's model SSE, known from the start


def test_sixth_derivative_scale_of_an_oscillation_is_omega_to_the_sixth_times_its_amplitude():
    omega = 2.0
    t = torch.linspace(0, 2 * math.pi / omega, 101, dtype=DT)
    slopes = torch.stack([-omega * torch.sin(omega * t), -omega**2 * torch.cos(omega * t)], dim=-1)
    rates = torch.stack([-omega**2 * torch.cos(omega * t), omega**3 * torch.sin(omega * t)], dim=-1)
    scale = derivative_scale(slopes.unsqueeze(0), rates.unsqueeze(0), 6)
    torch.testing.assert_close(scale[0, 0], torch.tensor([omega**6, omega**7], dtype=DT), rtol=1e-12, atol=0)
    torch.testing.assert_close(derivative_scale(slopes.unsqueeze(0), rates.unsqueeze(0), 4),
                               fourth_derivative_scale(slopes.unsqueeze(0), rates.unsqueeze(0)), rtol=0, atol=0)


def test_needed_intervals_follow_the_hermite_error_bound_of_each_degree():
    """Width ``(384 tol / x'''')^(1/4)`` for cubic interpolation, ``(46080 tol / x^(6))^(1/6)`` for quintic."""
    x = torch.ones(1, 5, 1, dtype=DT)
    span = torch.tensor([10.0], dtype=DT)
    derivative = torch.full((1, 3, 1), 2.0, dtype=DT)
    cubic = needed_intervals(derivative, x, 1e-6, 0.0, span)
    quintic = needed_intervals(derivative, x, 1e-6, 0.0, span, degree=5)
    assert float(cubic) == pytest.approx(10.0 / (384 * 1e-6 / 2.0) ** 0.25, rel=1e-12)
    assert float(quintic) == pytest.approx(10.0 / (46080 * 1e-6 / 2.0) ** (1 / 6), rel=1e-12)


def test_quintic_storage_takes_fewer_intervals_at_the_same_accuracy():
    """``linear_solver="taylor_quintic"`` stores ``z``, ``h f`` and ``h A`` as quintic interpolants, and
    the automatic grid counts its intervals by the quintic's error: on a noisy oscillator over two
    periods a quarter of the cubic storage's uniform intervals, with the estimates and standard
    errors of a 1,000-interval grid within 1e-7 and 1e-5 (measured: 25 against 100 uniform intervals,
    37 against 112 with the observation times; 1.6e-10 and 7.8e-8; the cubic storage's ``h A`` on 25
    intervals misses the standard errors by about 1e-4)."""
    t = torch.arange(14, dtype=DT) * 0.5
    x = torchql.simulate(LinearOscillator(0.1, 3.0), torch.tensor([0.0, 1.0], dtype=DT), t, rtol=1e-12, atol=1e-14)
    noise = 0.01 * torch.randn(t.shape[0], 1, generator=torch.Generator().manual_seed(3), dtype=DT)
    data = torchql.Observations(t, x[:, :1] + noise, observe=["y"])

    def fit(**options):
        return torchql.fit(LinearOscillator(0.5, 1.0), data, torch.tensor([0.5, 0.5], dtype=DT), **options)

    reference, cubic, quintic = fit(grid=1000), fit(), fit(linear_solver="taylor_quintic")
    assert reference.success and cubic.success and quintic.success
    intervals = {name: _grid_of(r).shape[-1] - 1 for name, r in (("cubic", cubic), ("quintic", quintic))}
    assert intervals["quintic"] * 2.5 <= intervals["cubic"], intervals
    assert float(((quintic.estimates - reference.estimates).abs() / reference.estimates.abs().clamp(min=0.1)).max()) < 1e-7
    errors = {name: torch.tensor(list(r.stderr.values()), dtype=DT) for name, r in (("ref", reference), ("q", quintic))}
    assert float(((errors["q"] - errors["ref"]).abs() / errors["ref"]).max()) < 1e-5
