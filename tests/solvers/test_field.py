"""The implicit solver's view of a right-hand side (torchql/solvers/field.py): values and exact
Jacobians of S samples at once, each sample's in its own memory."""

from __future__ import annotations

import pytest
import torch

from torchql.linearize import AUTOGRAD_STATES
from torchql.solvers.field import BatchedField

DT = torch.float64


@pytest.mark.parametrize("M", [3, AUTOGRAD_STATES + 2])  # one backward pass through copies; jacrev
def test_linearize_gives_each_samples_jacobian_in_its_own_memory(M):
    """Against the Jacobian of each sample alone (autonomous: ``df/dt = 0``); writing one sample's
    rows leaves the others' (jacrev under vmap hands back shared, expanded zeros for ``df/dt``)."""
    W = torch.linspace(-1.0, 1.0, M * M, dtype=DT).reshape(M, M)

    def f(t, y):
        return torch.tanh(W @ y) - y ** 3

    S = 4
    y = torch.linspace(0.1, 0.9, S * M, dtype=DT).reshape(S, M)
    t = torch.zeros(S, dtype=DT)
    value, J, ft = BatchedField(f).linearize(t, y)
    for s in range(S):
        torch.testing.assert_close(value[s], f(t[s], y[s]), rtol=0, atol=1e-15)
        torch.testing.assert_close(J[s], torch.autograd.functional.jacobian(lambda x: f(t[s], x), y[s]),
                                   rtol=1e-14, atol=1e-15)
    assert torch.equal(ft, torch.zeros(S, M, dtype=DT))
    for tensor in (value, J, ft):
        tensor[0] = 7.0
        assert not bool((tensor[1:] == 7.0).all())
