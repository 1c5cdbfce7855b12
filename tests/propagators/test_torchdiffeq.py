"""``linear_solver="torchdiffeq"``: every interval's transfer in one torchdiffeq call."""

import pytest
import torch

import torchql
from torchql.models import Robertson

DT = torch.float64


def test_a_stiff_model_whose_transfers_outgrow_the_implicit_solver_says_what_to_change():
    """Robertson (``solver="auto"``: Rodas5P) on its automatic grid: the stacked transfers are
    10,332 components, beyond what the implicit solver factorises densely (4,096). The error names
    ``linear_solver`` and the way out (it spoke of a ``y0`` the user never passed)."""
    t = torch.logspace(-4, 5, 28, dtype=DT)
    x0 = torch.tensor([1.0, 0.0, 0.0], dtype=DT)
    x = torchql.simulate(Robertson(), x0, torch.cat([torch.zeros(1, dtype=DT), t]), solver="rodas5p", rtol=1e-11,
                         atol=1e-16)[1:]
    data = torchql.Observations(t, x, observe=["y1", "y2", "y3"], sigma=(0.01 * x).clamp(min=1e-30))
    with pytest.raises(ValueError, match=r"`linear_solver='torchdiffeq'` integrates the \d+ grid intervals' "
                                         r"transfers as one system of \d+ components.*default `linear_solver`"):
        torchql.fit(Robertson(0.05, 2e7, 1.2e4), data, x0, linear_solver="torchdiffeq", params=["k1", "k2", "k3"],
                    fixed_x0=["y1", "y2", "y3"], t0=0.0, rtol=1e-8, atol=1e-14)
