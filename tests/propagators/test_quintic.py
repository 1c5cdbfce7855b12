"""``linear_solver="taylor_quintic"``: the reference, ``h f`` and ``h A`` as quintic Hermite interpolants."""

import pytest
import torch
from torch.func import jacrev

import torchql
import torchql.engine_final as engine_final
from torchql.batch_integrate import interval_coefficients, propagate_linear_batch
from torchql.linearize import linearize
from torchql.model import AugmentedSystem, ODEModel
from torchql.models import NonlinearOscillator
from torchql.propagators import TaylorQuintic, linear_propagator
from torchql.superposition import initial_columns
from torchql.trajectory import IntervalSystem, LinearizedReference
from torchql.transfer import hermite_to_power, raise_to_quintic

DT = torch.float64


class Logistic(ODEModel):
    """``x' = r x (1 - x / K)``: its solution has a closed form."""

    state_names = ("x",)

    def __init__(self, r: float = 1.5, K: float = 10.0) -> None:
        super().__init__()
        self.register_buffer("r", torch.tensor(r, dtype=DT))
        self.register_buffer("K", torch.tensor(K, dtype=DT))

    def forward(self, t, x):
        return self.r * x * (1 - x / self.K)


def _logistic(t, r=1.5, K=10.0, x0=0.5):
    return K / (1 + (K / x0 - 1) * torch.exp(-r * t))


def test_the_quintic_matches_values_slopes_and_second_derivatives_at_both_ends():
    g = torch.Generator().manual_seed(0)
    v0, d0, s0, v1, d1, s1 = torch.randn(6, 5, generator=g, dtype=DT)
    c = torch.zeros(6, 5, dtype=DT)
    c[:4] = hermite_to_power(torch.stack([v0, d0, v1, d1]))
    c = raise_to_quintic(c, s0, s1)
    k = torch.arange(6, dtype=DT).unsqueeze(1)
    assert torch.allclose(c[0], v0) and torch.allclose(c[1], d0) and torch.allclose(2 * c[2], s0)
    assert torch.allclose(c.sum(dim=0), v1, atol=1e-14)
    assert torch.allclose((k * c).sum(dim=0), d1, atol=1e-14)
    assert torch.allclose((k * (k - 1) * c).sum(dim=0), s1, atol=1e-13)


def _propagate(t, degree):
    """The particular solution along the exact logistic solution, with cubic or quintic storage."""
    system = AugmentedSystem(Logistic(), ["r", "K"], DT, torch.device("cpu"))
    z = torch.stack([_logistic(t), torch.full_like(t, 1.5), torch.full_like(t, 10.0)], dim=-1)
    lin = linearize(system, t, z)
    batch = type(lin)(*(v.unsqueeze(0) for v in lin))
    propagator = linear_propagator("taylor_quintic" if degree == 5 else "taylor")
    w0 = initial_columns(z[0], torch.tensor([0, 1, 2])).unsqueeze(0)
    W, failed, _ = propagate_linear_batch(t, z.unsqueeze(0), lin.f.unsqueeze(0), batch, w0, rtol=1e-14, atol=1e-16,
                                          propagator=propagator)
    assert not bool(failed.any())
    return W[0, :, 0, 0], z[:, 0]


def test_along_a_solution_the_quintic_storage_is_two_orders_more_accurate():
    """Along the model's own solution the particular solution is that solution; what separates the
    two is the interpolation of the reference between nodes: ``h^4`` against ``h^6``."""
    errors = {}
    for N in (10, 20):
        t = torch.linspace(0.0, 6.0, N + 1, dtype=DT)
        for degree in (3, 5):
            w, exact = _propagate(t, degree)
            errors[degree, N] = float((w - exact).abs().max() / exact.abs().max())
    assert errors[5, 10] < errors[3, 10] / 30
    assert errors[5, 20] < errors[3, 20] / 100
    # the orders: halving h divides the cubic error by about 16, the quintic's by about 64
    assert 10 < errors[3, 10] / errors[3, 20] < 24
    assert 40 < errors[5, 10] / errors[5, 20] < 90


def _sensitivity_error(t, second: bool) -> float:
    """Largest relative error of the homogeneous solutions (``dx/dx0``, ``dx/dr``, ``dx/dK``) along the
    exact logistic solution, by ``taylor_quintic`` from a linearization with (``second``) or without
    the second time derivative of ``A``, against their closed form."""
    system = AugmentedSystem(Logistic(), ["r", "K"], DT, torch.device("cpu"))
    z = torch.stack([_logistic(t), torch.full_like(t, 1.5), torch.full_like(t, 10.0)], dim=-1)
    lin = linearize(system, t, z, second=second)
    batch = type(lin)(*(v.unsqueeze(0) for v in lin))
    w0 = initial_columns(z[0], torch.tensor([0, 1, 2])).unsqueeze(0)
    W, failed, _ = propagate_linear_batch(t, z.unsqueeze(0), lin.f.unsqueeze(0), batch, w0, rtol=1e-14, atol=1e-16,
                                          propagator=TaylorQuintic())
    assert not bool(failed.any())
    unknowns = (torch.tensor(0.5, dtype=DT), torch.tensor(1.5, dtype=DT), torch.tensor(10.0, dtype=DT))
    exact = torch.stack(jacrev(lambda x0, r, K: _logistic(t, r, K, x0), argnums=(0, 1, 2))(*unknowns), dim=-1)
    return float(((W[0, :, 0, 1:] - exact).abs().amax(dim=0) / exact.abs().amax(dim=0)).max())


def test_with_the_second_derivative_of_a_the_sensitivities_are_of_sixth_order():
    """The homogeneous solutions read ``h A``: cubic, their error is of order ``h^4`` (halving ``h``
    divides it by about 16) whatever the storage of ``z``; quintic (the engine's linearization for
    this propagator), of order ``h^6`` and 100 times smaller on 10 intervals already (measured: 2.9e-4
    against 2.7e-6 on 10 intervals, 1.8e-5 against 4.9e-8 on 20)."""
    errors = {}
    for N in (10, 20):
        t = torch.linspace(0.0, 6.0, N + 1, dtype=DT)
        for second in (False, True):
            errors[second, N] = _sensitivity_error(t, second)
    assert 10 < errors[False, 10] / errors[False, 20] < 24
    assert 40 < errors[True, 10] / errors[True, 20] < 90
    assert errors[True, 10] < errors[False, 10] / 50 and errors[True, 20] < errors[False, 20] / 200


class Forced(ODEModel):
    """``x' = -k x + sin(t)``: explicit time dependence."""

    state_names = ("x",)

    def __init__(self, k: float = 0.7) -> None:
        super().__init__()
        self.register_buffer("k", torch.tensor(k, dtype=DT))

    def forward(self, t, x):
        return -self.k * x + torch.sin(t)


def _forcing_row_degrees(model, names, z_states):
    """The largest |coefficient| of degrees 4 and 5 in the ``h f`` row and in the ``z`` row of state 0."""
    t = torch.linspace(0.0, 4.0, 9, dtype=DT)
    system = AugmentedSystem(model, names, DT, torch.device("cpu"))
    z = torch.cat([z_states(t), torch.stack([getattr(model, n).expand(t.shape) for n in names], -1)], dim=-1)
    lin = linearize(system, t, z)
    batch = type(lin)(*(v.unsqueeze(0) for v in lin))
    coefficients = interval_coefficients(t, z.unsqueeze(0), lin.f.unsqueeze(0), batch, degree=5)
    M = coefficients.M
    return float(coefficients.data[4:, M].abs().max()), float(coefficients.data[4:, 0].abs().max())


def test_a_component_with_explicit_time_keeps_its_cubic_forcing_row():
    """Its ``f''`` would need ``f_tt``, which the linearization does not give: that row stays cubic
    (degrees 4 and 5 zero); the reference's own row is quintic all the same."""
    f_high, z_high = _forcing_row_degrees(Forced(), ["k"], lambda t: torch.cos(t).unsqueeze(-1))
    assert f_high == 0.0 and z_high > 0.0
    f_high, z_high = _forcing_row_degrees(Logistic(), ["r", "K"], lambda t: _logistic(t).unsqueeze(-1))
    assert f_high > 0.0 and z_high > 0.0


def test_a_model_with_explicit_time_reaches_the_same_optimum():
    t = torch.linspace(0.0, 6.0, 25, dtype=DT)
    x = torchql.simulate(Forced(0.7), torch.tensor([1.0], dtype=DT), t, rtol=1e-12, atol=1e-14)
    g = torch.Generator().manual_seed(5)
    data = torchql.Observations(t, x + 1e-3 * torch.randn(x.shape, generator=g, dtype=DT), observe=["x"])
    cubic = torchql.fit(Forced(0.3), data, torch.tensor([0.8], dtype=DT))
    quintic = torchql.fit(Forced(0.3), data, torch.tensor([0.8], dtype=DT), linear_solver="taylor_quintic")
    assert cubic.success and quintic.success
    assert torch.allclose(quintic.estimates, cubic.estimates, rtol=1e-7)


def _noisy_oscillator(seed: int, B: int = 1):
    t = torch.arange(41, dtype=DT) * 0.25
    truth = NonlinearOscillator(0.1, 3.0, 0.2, 4.0)
    x = torchql.simulate(truth, torch.tensor([0.3, 0.0], dtype=DT), t, rtol=1e-12, atol=1e-14)[:, :1]
    g = torch.Generator().manual_seed(seed)
    return [torchql.Observations(t, x + 1e-3 * torch.randn(x.shape, generator=g, dtype=DT), observe=["y"])
            for _ in range(B)]


def test_the_fixed_point_on_a_coarse_grid_is_far_closer_to_the_optimum(monkeypatch):
    """The final pass's Gauss-Newton steps off: the estimates are the Kantorovich fixed point of
    the grid. Against a 2,000-interval grid's, cubic storage on 160 intervals leaves a relative
    offset of 1.7e-5, quintic storage of ``z``, ``h f`` and ``h A`` 1.3e-8 (1,300 times less; 75
    times on 40 intervals, 2,800 times on 320: the orders ``h^4`` and ``h^6``)."""
    monkeypatch.setattr(engine_final, "POLISH_STEPS", 0)
    data = _noisy_oscillator(1)[0]
    x0 = torch.tensor([0.3, 0.0], dtype=DT)

    def fit(**options):
        return torchql.fit(NonlinearOscillator(0.2, 2.5, 0.3, 3.0), data, x0, **options)

    reference = fit(grid=2000)
    offsets = {}
    for solver in ("taylor", "taylor_quintic"):
        result = fit(grid=160, linear_solver=solver)
        assert result.success
        offsets[solver] = float(((result.estimates - reference.estimates).abs()
                                 / reference.estimates.abs()).max())
    assert offsets["taylor_quintic"] < offsets["taylor"] / 10
    assert offsets["taylor_quintic"] < 2e-6


def test_fit_many_with_quintic_storage_gives_each_sample_its_own_fit():
    data = _noisy_oscillator(2, B=1) + _noisy_oscillator(3, B=1) + _noisy_oscillator(4, B=1)
    x0 = torch.tensor([0.3, 0.0], dtype=DT)
    model = NonlinearOscillator(0.2, 2.5, 0.3, 3.0)
    batch = torchql.fit_many(model, data, x0, linear_solver="taylor_quintic")
    for i, d in enumerate(data):
        single = torchql.fit(model, d, x0, linear_solver="taylor_quintic")
        assert batch[i].status == single.status and batch[i].iterations == single.iterations
        assert torch.allclose(batch[i].estimates, single.estimates, rtol=1e-8, atol=1e-12)
        assert batch[i].sse == pytest.approx(single.sse, rel=1e-8)


def test_the_single_path_gives_the_batched_transfers():
    t = torch.linspace(0.0, 6.0, 13, dtype=DT)
    system = AugmentedSystem(Logistic(), ["r", "K"], DT, torch.device("cpu"))
    z = torch.stack([_logistic(t), torch.full_like(t, 1.5), torch.full_like(t, 10.0)], dim=-1)
    z = z + 1e-3 * torch.sin(3 * t).unsqueeze(-1) * torch.tensor([1.0, 0.0, 0.0], dtype=DT)
    lin = linearize(system, t, z)
    reference = LinearizedReference(t, z, lin.f, lin)
    transfers, _ = TaylorQuintic().transfers(IntervalSystem(reference), rtol=1e-12, atol=1e-14, solver="dopri5",
                                             max_steps=None)
    batch = type(lin)(*(v.unsqueeze(0) for v in lin))
    coefficients = interval_coefficients(t, z.unsqueeze(0), lin.f.unsqueeze(0), batch, degree=5)
    Y, failed, _ = TaylorQuintic().series(coefficients, rtol=1e-12, atol=1e-14, max_substeps=1024)
    assert not bool(failed.any()) and torch.equal(transfers.Y, Y)
