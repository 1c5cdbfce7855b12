"""The linearization along a trajectory: the three ways of differentiating, the choice between them,
the others standing in where a model does not take one, and the per-node Jacobians."""

from unittest import mock

import pytest
import torch

import torchql
from torchql import linearize as lin_module
from torchql.linearize import AUTOGRAD_STATES, REVERSE_WORK_LIMIT, linearize, node_jacobian
from torchql.model import AugmentedSystem, ODEModel
from torchql.models import FitzHughNagumo


def _system() -> AugmentedSystem:
    return AugmentedSystem(FitzHughNagumo(), ["a", "b", "c"], torch.float64, torch.device("cpu"))


def _nodes(G: int, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    t = torch.linspace(0.0, 2.0, G, dtype=torch.float64)
    z = torch.rand(G, 5, generator=gen, dtype=torch.float64) + torch.tensor([-1.0, 0.0, 0.0, 0.0, 2.0])
    z_dot = torch.randn(G, 5, generator=gen, dtype=torch.float64)
    z_dot[:, 2:] = 0.0  # the coefficients are constant along a trajectory
    return t, z, z_dot


def _by_hand(z: torch.Tensor, z_dot: torch.Tensor):
    """FitzHugh–Nagumo's ``A = df/dz`` and ``d/dt A`` along ``z'``, written out."""
    V, R, a, b, c = z.unbind(-1)
    Vd, Rd = z_dot[:, 0], z_dot[:, 1]
    G = z.shape[0]
    A = torch.zeros(G, 5, 5, dtype=z.dtype)
    A[:, 0, 0], A[:, 0, 1], A[:, 0, 4] = c * (1 - V**2), c, V - V**3 / 3 + R
    A[:, 1, 0], A[:, 1, 1] = -1 / c, -b / c
    A[:, 1, 2], A[:, 1, 3], A[:, 1, 4] = 1 / c, -R / c, (V - a + b * R) / c**2
    A_dot = torch.zeros_like(A)
    A_dot[:, 0, 0], A_dot[:, 0, 4] = -2 * c * V * Vd, (1 - V**2) * Vd + Rd
    A_dot[:, 1, 3], A_dot[:, 1, 4] = -Rd / c, (Vd + b * Rd) / c**2
    return A, A_dot


@pytest.mark.parametrize("order", ["autograd", "reverse", "forward"])
def test_each_order_gives_the_jacobian_and_its_time_derivative(order):
    system = _system()
    t, z, z_dot = _nodes(7)
    lin = linearize(system, t, z, z_dot, order=order)
    A, A_dot = _by_hand(z, z_dot)
    torch.testing.assert_close(lin.f, torch.vmap(system.f)(t, z), rtol=0, atol=1e-14)
    torch.testing.assert_close(lin.jac, A, rtol=0, atol=1e-14)
    torch.testing.assert_close(lin.f_dot, (A @ z_dot.unsqueeze(-1)).squeeze(-1), rtol=0, atol=1e-14)
    torch.testing.assert_close(lin.jac_dot, A_dot, rtol=0, atol=1e-14)


def _spy(taken: list):
    real = lin_module._linearize

    def spy(order, *args):
        taken.append(order)
        return real(order, *args)

    return spy


def test_models_of_few_states_take_autograd_on_any_grid():
    system = _system()
    assert system.n <= AUTOGRAD_STATES
    taken = []
    with mock.patch.object(lin_module, "_linearize", _spy(taken)):
        linearize(system, *_nodes(5))
        linearize(system, *_nodes(REVERSE_WORK_LIMIT // system.M**2 + 1))
    assert taken == ["autograd", "autograd"]


def test_more_states_take_reverse_mode_on_small_grids_and_forward_mode_on_large_ones():
    system = _system()
    taken = []
    largest_reverse = REVERSE_WORK_LIMIT // system.M**2
    with mock.patch.object(lin_module, "AUTOGRAD_STATES", system.n - 1), \
            mock.patch.object(lin_module, "_linearize", _spy(taken)):
        linearize(system, *_nodes(largest_reverse))
        linearize(system, *_nodes(largest_reverse + 1))
    assert taken == ["reverse", "forward"]


def test_reverse_mode_stands_in_where_autograd_fails_and_autograd_is_not_tried_again():
    system = _system()
    t, z, z_dot = _nodes(7)
    expected = linearize(system, t, z, z_dot, order="reverse")
    calls = []

    def no_double_backward(f, t, z, z_dot, n):
        calls.append(1)
        raise RuntimeError("trying to differentiate twice a function that was marked with @once_differentiable")

    with mock.patch.object(lin_module, "_by_autograd", no_double_backward):
        first = linearize(system, t, z, z_dot)
        second = linearize(system, t, z, z_dot)
    assert "autograd" not in system.linearization_orders
    assert len(calls) == 1
    for got in (first, second):
        torch.testing.assert_close(got.jac_dot, expected.jac_dot, rtol=0, atol=0)


def test_reverse_mode_stands_in_where_forward_mode_fails_and_forward_mode_is_not_tried_again():
    system = _system()
    system.linearization_orders = ("reverse", "forward")
    t, z, z_dot = _nodes(REVERSE_WORK_LIMIT // system.M**2 + 1)
    expected = linearize(system, t, z, z_dot, order="reverse")
    calls = []

    def no_nested_forward(f):
        def node(*args):
            calls.append(1)
            raise RuntimeError("this operation has no forward-mode derivative")
        return node

    with mock.patch.object(lin_module, "_forward_over_forward", no_nested_forward):
        first = linearize(system, t, z, z_dot)
        second = linearize(system, t, z, z_dot)
    assert system.linearization_orders == ("reverse",)
    assert len(calls) == 1
    for got in (first, second):
        torch.testing.assert_close(got.jac_dot, expected.jac_dot, rtol=0, atol=0)


@pytest.mark.parametrize("replicate", [False, True])
@pytest.mark.parametrize("rows", [2, AUTOGRAD_STATES, AUTOGRAD_STATES + 1])
def test_node_jacobian_by_either_path_matches_the_jacobian_node_by_node(rows, replicate):
    """Up to AUTOGRAD_STATES rows by autograd (one backward pass per row, or one through copies of
    the nodes), more by jacrev: each node's own Jacobian."""
    gen = torch.Generator().manual_seed(3)
    K = AUTOGRAD_STATES + 2
    W = torch.randn(K, 3, dtype=torch.float64, generator=gen)

    def f(p, t, x):  # K outputs, nonlinear in p and x, with t
        return torch.sin(W @ x) * p[0] + p[1] * torch.exp(t) * (W @ x) ** 2

    N = 9
    p = torch.rand(N, 2, dtype=torch.float64, generator=gen)
    t = torch.linspace(0.0, 1.0, N, dtype=torch.float64)
    x = torch.randn(N, 3, dtype=torch.float64, generator=gen)
    value, (J_p, J_x) = node_jacobian(f, (p, t, x), (0, 2), rows, replicate=replicate)
    assert value.shape == (N, K)
    assert J_p.shape == (N, rows, 2) and J_x.shape == (N, rows, 3)
    for j in range(N):
        torch.testing.assert_close(value[j], f(p[j], t[j], x[j]), rtol=0, atol=1e-14)
        Jp, Jx = torch.autograd.functional.jacobian(lambda a, b: f(a, t[j], b), (p[j], x[j]))
        torch.testing.assert_close(J_p[j], Jp[:rows], rtol=1e-14, atol=1e-14)
        torch.testing.assert_close(J_x[j], Jx[:rows], rtol=1e-14, atol=1e-14)


@pytest.mark.parametrize("replicate", [False, True])
def test_node_jacobian_of_arguments_an_output_ignores_is_zero(replicate):
    """An argument that no output uses (an autonomous model's time) and outputs free of every
    argument get zero Jacobians, not an error."""
    t = torch.linspace(0.0, 1.0, 4, dtype=torch.float64)
    x = torch.rand(4, 2, dtype=torch.float64)
    value, (J_t, J_x) = node_jacobian(lambda t, x: torch.stack([x[0] * x[1], x[1]]), (t, x), (0, 1), 2,
                                      replicate=replicate)
    assert torch.equal(J_t, torch.zeros(4, 2, dtype=torch.float64))
    torch.testing.assert_close(J_x[:, 0], torch.stack([x[:, 1], x[:, 0]], 1), rtol=0, atol=0)
    value, (J_x,) = node_jacobian(lambda x: torch.ones(2, dtype=x.dtype), (x,), (0,), 2, replicate=replicate)
    assert torch.equal(value, torch.ones(4, 2, dtype=torch.float64))
    assert torch.equal(J_x, torch.zeros(4, 2, 2, dtype=torch.float64))


def test_node_jacobian_falls_back_to_jacrev_where_autograd_fails():
    x = torch.linspace(0.5, 2.0, 6, dtype=torch.float64).reshape(3, 2)

    def f(x):
        return torch.stack([x[0] * x[1], x[0] ** 2])

    with mock.patch.object(lin_module, "_node_jacobian_by_autograd", side_effect=RuntimeError("no autograd")):
        value, (J,) = node_jacobian(f, (x,), (0,), 2)
    expected = torch.stack([torch.stack([x[:, 1], x[:, 0]], 1), torch.stack([2 * x[:, 0], 0 * x[:, 0]], 1)], 1)
    torch.testing.assert_close(J, expected, rtol=0, atol=1e-15)


def _second_by_hand(z: torch.Tensor, z_dot: torch.Tensor, z_ddot: torch.Tensor) -> torch.Tensor:
    """FitzHugh–Nagumo's ``d^2/dt^2 A`` along ``z'`` and ``z''``, written out (``a``, ``b``, ``c`` constant)."""
    V, R, a, b, c = z.unbind(-1)
    Vd, Rd, Vdd, Rdd = z_dot[:, 0], z_dot[:, 1], z_ddot[:, 0], z_ddot[:, 1]
    A_ddot = torch.zeros(z.shape[0], 5, 5, dtype=z.dtype)
    A_ddot[:, 0, 0] = -2 * c * (Vd**2 + V * Vdd)
    A_ddot[:, 0, 4] = -2 * V * Vd**2 + (1 - V**2) * Vdd + Rdd
    A_ddot[:, 1, 3], A_ddot[:, 1, 4] = -Rdd / c, (Vdd + b * Rdd) / c**2
    return A_ddot


@pytest.mark.parametrize("order", ["autograd", "reverse", "forward", None])
def test_each_order_gives_the_second_time_derivative_of_the_jacobian(order):
    """``second=True``: ``d^2/dt^2 A`` along the slopes given and ``z'' = f'``, the same by every way of
    differentiating; without it the plain linearization, unchanged."""
    system = _system()
    t, z, z_dot = _nodes(9)
    lin = linearize(system, t, z, z_dot, order=order, second=True)
    plain = linearize(system, t, z, z_dot, order=order)
    assert type(plain).__name__ == "Linearization" and type(lin).__name__ == "SecondLinearization"
    for a, b in zip(lin, plain):  # the first four fields are the plain linearization's
        torch.testing.assert_close(a, b, rtol=0, atol=1e-14)
    torch.testing.assert_close(lin.jac_ddot, _second_by_hand(z, z_dot, lin.f_dot), rtol=1e-12, atol=1e-12)


class Driven(ODEModel):
    """``x' = -k x^2 + sin(w t) x``, ``v' = x - v``: explicit time dependence, nonlinear in ``x``."""

    state_names = ("x", "v")

    def __init__(self, k: float = 0.4, w: float = 1.3) -> None:
        super().__init__()
        self.register_buffer("k", torch.tensor(k, dtype=torch.float64))
        self.register_buffer("w", torch.tensor(w, dtype=torch.float64))

    def forward(self, t, x):
        return torch.stack([-self.k * x[0] ** 2 + torch.sin(self.w * t) * x[0], x[0] - x[1]])


def test_the_second_derivative_has_the_explicit_time_terms_along_a_solution():
    """Along the model's own solution ``d^2/dt^2 A`` is the second derivative in time of the Jacobian
    there: against central differences (step 1e-3: their error is about 1e-7 of ``A''``), by
    autograd and by forward mode alike."""
    model = Driven()
    system = AugmentedSystem(model, ["k", "w"], torch.float64, torch.device("cpu"))
    delta = 1e-3
    centres = torch.tensor([0.5, 1.7, 3.1], dtype=torch.float64)
    times = torch.stack([centres - delta, centres, centres + delta], dim=1).reshape(-1)
    start = torch.zeros(1, dtype=torch.float64)
    x = torchql.simulate(model, torch.tensor([0.8, 0.1], dtype=torch.float64), torch.cat([start, times]),
                         rtol=1e-13, atol=1e-15)[1:]
    z = torch.cat([x, torch.tensor([0.4, 1.3], dtype=torch.float64).expand(x.shape[0], 2)], dim=1)
    lin = linearize(system, times, z, second=True)
    A = lin.jac.reshape(3, 3, 4, 4)
    differences = (A[:, 2] - 2 * A[:, 1] + A[:, 0]) / delta**2
    middle = lin.jac_ddot.reshape(3, 3, 4, 4)[:, 1]
    scale = float(middle.abs().amax())
    assert float((middle - differences).abs().amax()) < 1e-6 * scale
    jets = linearize(system, times, z, order="forward", second=True)
    torch.testing.assert_close(jets.jac_ddot, lin.jac_ddot, rtol=1e-12, atol=1e-12 * scale)


_UNDER_W_ERROR = '''
import torch, torchql

class Chain5(torchql.ODEModel):
    state_names = ("a", "b", "c", "d", "e")

    def __init__(self, k=1.0):
        super().__init__()
        self.register_buffer("k", torch.tensor(k, dtype=torch.float64))

    def forward(self, t, x):
        return torch.cat([-self.k * x[..., :1], self.k * (x[..., :-1] - x[..., 1:])], dim=-1)

t = torch.linspace(0, 4, 9, dtype=torch.float64)
x0 = torch.tensor([1.0, 0, 0, 0, 0], dtype=torch.float64)
y = torchql.simulate(Chain5(0.8), x0, t)
r = torchql.fit(Chain5(), torchql.Observations(t, y, observe=list(Chain5.state_names)), x0=x0,
                fixed_x0=list(Chain5.state_names))
print(r.status.name, float(r.params["k"]))
'''


def test_a_fit_under_warnings_as_errors_is_not_blamed_on_the_model():
    """A five-state model is linearized in forward mode; torch's first ``jvp`` loads decompositions
    it scripts with the deprecated ``torch.jit.script``. Under ``-W error`` that warning failed the
    fit as "`model` forward could not be differentiated". A fresh process: torch loads them once."""
    import subprocess
    import sys

    run = subprocess.run([sys.executable, "-W", "error", "-c", _UNDER_W_ERROR], capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    status, k = run.stdout.split()
    assert status == "CONVERGED"
    assert abs(float(k) - 0.8) < 1e-8
