"""Interval transfers by RK4 with step doubling, and their composition by a prefix scan."""

import math

import pytest
import torch

from torchql.integrate import IntegrationError
from torchql.linearize import Linearization
from torchql.superposition import DEFAULT_LINEAR_SOLVER, LINEAR_SOLVERS, initial_columns, propagate_linear
from torchql.trajectory import IntervalSystem, LinearizedReference
from torchql.transfer import Transfers, compose_transfers, interval_transfers, prefix_products

DT = torch.float64


def _polynomial_decay(grid, c0=-0.5, c1=0.3, c2=-0.2):
    """``w' = a(t) w`` with ``a = c0 + c1 t + c2 t^2`` linearized about its exact solution.

    The Jacobian is quadratic in t, so its cubic Hermite interpolant is exact, and the transfer
    of ``[t_j, t_{j+1}]`` is ``exp(int a)`` in closed form. Returns the reference and that
    integral as a function.
    """
    a = lambda t: c0 + c1 * t + c2 * t**2
    a_dot = lambda t: c1 + 2 * c2 * t
    integral = lambda t: c0 * t + c1 * t**2 / 2 + c2 * t**3 / 3
    t = grid
    z = torch.exp(integral(t)).unsqueeze(-1)
    f = (a(t) * z[:, 0]).unsqueeze(-1)
    lin = Linearization(f=f, jac=a(t).reshape(-1, 1, 1), f_dot=((a_dot(t) + a(t) ** 2) * z[:, 0]).unsqueeze(-1),
                        jac_dot=a_dot(t).reshape(-1, 1, 1))
    return LinearizedReference(t, z, f, lin), integral


def _rotation(grid, omega=3.0, with_parameter=True):
    """``x' = omega(t) J x`` with ``omega(t) = omega (1 + t / 2)``: a rotation by ``int omega``.

    With ``with_parameter`` a third, constant component (a null equation, as a coefficient
    has) rides along, so that the active-row storage is exercised.
    """
    M = 3 if with_parameter else 2
    t = grid
    G = t.shape[0]
    om = omega * (1 + t / 2)
    om_dot = torch.full_like(t, omega / 2)
    theta = omega * (t + t**2 / 4)
    z = torch.zeros(G, M, dtype=DT)
    z[:, 0], z[:, 1] = torch.cos(theta), torch.sin(theta)
    if with_parameter:
        z[:, 2] = 0.7
    J = torch.zeros(G, M, M, dtype=DT)
    J[:, 0, 1], J[:, 1, 0] = -om, om
    J_dot = torch.zeros_like(J)
    J_dot[:, 0, 1], J_dot[:, 1, 0] = -om_dot, om_dot
    f = torch.einsum("gij,gj->gi", J, z)
    f_dot = torch.einsum("gij,gj->gi", J_dot, z) + torch.einsum("gij,gj->gi", J, f)
    lin = Linearization(f=f, jac=J, f_dot=f_dot, jac_dot=J_dot)
    return LinearizedReference(t, z, f, lin), theta


def test_the_choices_are_exported():
    assert DEFAULT_LINEAR_SOLVER in LINEAR_SOLVERS
    assert "torchdiffeq" in LINEAR_SOLVERS


def test_transfers_match_the_closed_form():
    grid = torch.linspace(0, 4, 81, dtype=DT)
    ref, integral = _polynomial_decay(grid)
    rtol, atol = 1e-10, 1e-12
    transfers, n_evals = interval_transfers(IntervalSystem(ref), rtol=rtol, atol=atol)
    T = transfers.full()
    exact = torch.exp(integral(grid[1:]) - integral(grid[:-1]))
    # every interval's propagator is within its tolerance (the estimate is of the unextrapolated
    # solution, so the bound holds with room)
    assert (T[:, 0, 0] - exact).abs().max() <= atol + rtol * exact.abs().max()
    # the forced response is that of the Hermite-interpolated reference's defect, O(h^4) per interval
    assert T[:, 0, 1].abs().max() < 1e-8
    assert n_evals >= 5


@pytest.mark.parametrize("with_parameter", [False, True])
def test_rotation_over_the_grid_matches_the_closed_form(with_parameter):
    grid = torch.linspace(0, 2, 201, dtype=DT)
    ref, theta = _rotation(grid, with_parameter=with_parameter)
    M = ref.z.shape[1]
    w0 = initial_columns(ref.z[0], torch.arange(M))
    W, _ = propagate_linear(ref, w0, rtol=1e-10, atol=1e-12)
    c, s = torch.cos(theta), torch.sin(theta)
    # the Jacobian is linear in t, so its interpolant is exact: the homogeneous solutions meet the
    # tolerance (accumulated over the grid)
    torch.testing.assert_close(W[:, 0, 1], c, rtol=0, atol=1e-9)  # from e_0
    torch.testing.assert_close(W[:, 1, 1], s, rtol=0, atol=1e-9)
    torch.testing.assert_close(W[:, 0, 2], -s, rtol=0, atol=1e-9)  # from e_1
    # the particular one is the reference, up to its cubic Hermite interpolation (O(h^4) ~ 1e-8)
    torch.testing.assert_close(W[:, :, 0], ref.z, rtol=0, atol=5e-8)
    if with_parameter:
        assert (W[:, 2, 1:3] == 0).all() and (W[:, 2, 3] == 1).all()


@pytest.mark.parametrize("make", [_polynomial_decay, _rotation])
def test_agrees_with_the_torchdiffeq_path(make):
    grid = torch.linspace(0, 3, 151, dtype=DT)
    ref = make(grid)[0]
    M = ref.z.shape[1]
    # start off the reference, so that the particular solution carries a forced response
    w0 = initial_columns(ref.z[0] + 0.1, torch.arange(M))
    rtol, atol = 1e-9, 1e-11
    W_new, evals_new = propagate_linear(ref, w0, rtol=rtol, atol=atol)
    W_old, evals_old = propagate_linear(ref, w0, solver="dopri5", rtol=rtol, atol=atol, linear_solver="torchdiffeq")
    # both meet rtol/atol over the whole grid, so they agree to twice that, relative to the size
    scale = W_old.abs().max()
    assert (W_new - W_old).abs().max() <= 2 * (atol + rtol * scale)
    assert evals_new > 0 and evals_old > 0


def test_error_is_fifth_order_in_the_interval():
    # fixed single-pass transfers (tolerance loose enough that no refinement happens)
    errors = []
    for nodes in (11, 21):
        grid = torch.linspace(0, 2, nodes, dtype=DT)
        ref, theta = _rotation(grid, with_parameter=False)
        T = interval_transfers(IntervalSystem(ref), rtol=1.0, atol=1.0)[0].full()
        d = theta[1:] - theta[:-1]
        errors.append(max((T[:, 0, 0] - torch.cos(d)).abs().max().item(), (T[:, 1, 0] - torch.sin(d)).abs().max().item()))
    # halving h: local error of the extrapolated transfer falls ~2^5 or faster
    assert errors[1] < errors[0] / 20, errors


def _sequential(T, w0):
    """The reference composition: ``w_{j+1} = Phi_j w_j + c_j e_0^T`` node by node."""
    M = w0.shape[0]
    out = [w0]
    w = w0
    for j in range(T.shape[0]):
        w = T[j, :M, :M] @ w
        w[:, 0] += T[j, :M, M]
        out.append(w)
    return torch.stack(out)


@pytest.mark.parametrize("N", [1, 2, 7, 64, 100])
def test_scan_equals_the_sequential_composition(N):
    g = torch.Generator().manual_seed(N)
    M = 4
    T = torch.eye(M + 1, dtype=DT).repeat(N, 1, 1)
    T[:, :M] += 0.1 * torch.randn(N, M, M + 1, generator=g, dtype=DT)
    w0 = torch.randn(M, 3, generator=g, dtype=DT)
    expected = _sequential(T, w0)
    W = compose_transfers(Transfers.from_full(T), w0)
    torch.testing.assert_close(W, expected, rtol=1e-13, atol=1e-13)
    # the running products themselves
    P = prefix_products(Transfers.from_full(T).Y)
    running = torch.eye(M + 1, dtype=DT)
    for j in range(N):
        running = T[j] @ running
    torch.testing.assert_close(P[..., -1], running[:M], rtol=1e-13, atol=1e-13)


def test_scan_with_constant_components_equals_the_sequential_composition():
    grid = torch.linspace(0, 1, 41, dtype=DT)
    ref = _rotation(grid)[0]
    transfers, _ = interval_transfers(IntervalSystem(ref), rtol=1e-10, atol=1e-12)
    assert transfers.active == 2  # the constant third component is not integrated
    w0 = initial_columns(ref.z[0], torch.tensor([0, 2]))
    torch.testing.assert_close(compose_transfers(transfers, w0), _sequential(transfers.full(), w0),
                               rtol=1e-13, atol=1e-13)


def _fast_interval(omega_fast):
    """A rotation that is slow everywhere but on one short stretch of the grid."""
    grid = torch.linspace(0, 1, 21, dtype=DT)
    G = grid.shape[0]
    om = torch.full((G,), 1.0, dtype=DT)
    om[10] = omega_fast  # a spike at one node: the two intervals beside it are fast
    J = torch.zeros(G, 2, 2, dtype=DT)
    J[:, 0, 1], J[:, 1, 0] = -om, om
    z = torch.zeros(G, 2, dtype=DT)
    z[:, 0] = 1.0
    f = torch.einsum("gij,gj->gi", J, z)
    lin = Linearization(f=f, jac=J, f_dot=torch.zeros_like(f), jac_dot=torch.zeros_like(J))
    return LinearizedReference(grid, z, torch.zeros_like(z), lin)


def test_refinement_only_where_needed():
    ref = _fast_interval(40.0)
    rtol, atol = 1e-10, 1e-12
    transfers, n_evals = interval_transfers(IntervalSystem(ref), rtol=rtol, atol=atol)
    assert n_evals > 5  # refined
    # against a reference integration of the same interval system
    w0 = initial_columns(torch.tensor([1.0, 0.0], dtype=DT), torch.tensor([0, 1]))
    W_new, _ = propagate_linear(ref, w0, rtol=rtol, atol=atol)
    W_ref, _ = propagate_linear(ref, w0, solver="dopri8", rtol=1e-13, atol=1e-15, linear_solver="torchdiffeq")
    assert (W_new - W_ref).abs().max() < 10 * (atol + rtol * W_ref.abs().max())


def test_refinement_cap_raises():
    ref = _fast_interval(5000.0)
    with pytest.raises(IntegrationError, match=r"did not meet the tolerance.*4 RK4 steps each.*t = 0\.(45|5)\b"):
        interval_transfers(IntervalSystem(ref), rtol=1e-12, atol=1e-14, max_substeps=4)


def test_non_finite_coefficients_raise():
    ref = _fast_interval(1.0)
    ref.jac = ref.jac.clone()
    ref.jac[3, 0, 1] = float("nan")
    with pytest.raises(IntegrationError, match="non-finite"):
        interval_transfers(IntervalSystem(ref), rtol=1e-8, atol=1e-10, max_substeps=8)


def test_invalid_choices():
    ref = _fast_interval(1.0)
    with pytest.raises(ValueError, match="`max_substeps` must be a power of two"):
        interval_transfers(IntervalSystem(ref), rtol=1e-8, atol=1e-10, max_substeps=6)
    w0 = initial_columns(torch.tensor([1.0, 0.0], dtype=DT), torch.tensor([0]))
    with pytest.raises(ValueError, match="`linear_solver` must be one of"):
        propagate_linear(ref, w0, rtol=1e-8, atol=1e-10, linear_solver="euler")


def test_float32():
    grid = torch.linspace(0, 2, 101, dtype=torch.float32)
    ref, theta = _rotation(grid.double())
    ref32 = LinearizedReference(grid, ref.z.float(), ref.z_dot.float(),
                                Linearization(ref.f.float(), ref.jac.float(), ref.f_dot.float(), ref.jac_dot.float()))
    w0 = initial_columns(ref32.z[0], torch.tensor([0, 1]))
    W, _ = propagate_linear(ref32, w0, rtol=1e-6, atol=1e-8)
    assert W.dtype == torch.float32
    torch.testing.assert_close(W[:, 0, 1], torch.cos(theta).float(), rtol=0, atol=1e-5)
    torch.testing.assert_close(W[:, 1, 1], torch.sin(theta).float(), rtol=0, atol=1e-5)


def test_single_node_grid():
    grid = torch.zeros(1, dtype=DT)
    ref = _polynomial_decay(grid)[0]
    w0 = initial_columns(ref.z[0], torch.tensor([0]))
    W, n_evals = propagate_linear(ref, w0, rtol=1e-10, atol=1e-12)
    assert W.shape == (1, 1, 2) and n_evals == 0
    assert math.isclose(W[0, 0, 0].item(), 1.0)


def test_rk4_series_of_several_samples_side_by_side_is_each_alone():
    """``linear_solver="rk4_doubling"`` in ``fit_many``: the intervals of three references (one
    with a fast interval that needs refining, one whose interval cannot meet the tolerance within
    the cap) integrated side by side; each interval's transfer and failure are those of its own
    reference alone (an interval's refinement never depends on the others integrated with it)."""
    from torchql.transfer import _Coefficients, rk4_series

    parts = [_Coefficients(IntervalSystem(_fast_interval(rate))) for rate in (1.0, 40.0, 5000.0)]
    joined = _Coefficients.of(torch.cat([c.data for c in parts], dim=-1), parts[0].order, parts[0].a, parts[0].M)
    together = rk4_series(joined, rtol=1e-10, atol=1e-12, max_substeps=512)
    N = parts[0].intervals
    for k, coefficients in enumerate(parts):
        alone = rk4_series(coefficients, rtol=1e-10, atol=1e-12, max_substeps=512)
        columns = slice(k * N, (k + 1) * N)
        assert torch.equal(together.failed[columns], alone.failed)
        assert torch.equal(together.substeps[columns], alone.substeps)
        passed = ~alone.failed
        torch.testing.assert_close(together.Y[..., columns][..., passed], alone.Y[..., passed], rtol=1e-14, atol=1e-15)
    failed = together.failed.reshape(3, N).any(dim=1)
    assert failed.tolist() == [False, False, True]  # only the 5000 rate's fast interval fails
    assert int(together.substeps[N:2 * N].max()) > 2  # the 40 rate's fast interval was refined
