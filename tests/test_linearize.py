"""The linearization along a trajectory: both orders of differentiation, the choice between them,
and reverse mode standing in where a model does not take nested forward mode."""

from unittest import mock

import pytest
import torch

from torchql import linearize as lin_module
from torchql.linearize import REVERSE_WORK_LIMIT, linearize
from torchql.model import AugmentedSystem
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


@pytest.mark.parametrize("order", ["reverse", "forward"])
def test_each_order_gives_the_jacobian_and_its_time_derivative(order):
    system = _system()
    t, z, z_dot = _nodes(7)
    lin = linearize(system, t, z, z_dot, order=order)
    A, A_dot = _by_hand(z, z_dot)
    torch.testing.assert_close(lin.f, torch.vmap(system.f)(t, z), rtol=0, atol=1e-14)
    torch.testing.assert_close(lin.jac, A, rtol=0, atol=1e-14)
    torch.testing.assert_close(lin.f_dot, (A @ z_dot.unsqueeze(-1)).squeeze(-1), rtol=0, atol=1e-14)
    torch.testing.assert_close(lin.jac_dot, A_dot, rtol=0, atol=1e-14)


def test_small_grids_take_reverse_mode_and_large_grids_forward_mode():
    system = _system()
    taken = []
    real = lin_module._linearize

    def spy(order, *args):
        taken.append(order)
        return real(order, *args)

    largest_reverse = REVERSE_WORK_LIMIT // system.M**2
    with mock.patch.object(lin_module, "_linearize", spy):
        linearize(system, *_nodes(largest_reverse))
        linearize(system, *_nodes(largest_reverse + 1))
    assert taken == ["reverse", "forward"]


def test_reverse_mode_stands_in_where_forward_mode_fails_and_forward_mode_is_not_tried_again():
    system = _system()
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
