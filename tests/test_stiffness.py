"""torchql.stiffness: the test that chooses the stiff solver, along the data or along a trajectory."""

import torch

from torchql.stiffness import STIFF_RATIO, stiff_along

DT = torch.float64


def jacobians(*matrices) -> torch.Tensor:
    """``(S, 1, 2, 2)``: one node per sample."""
    return torch.tensor(matrices, dtype=DT).unsqueeze(1)


def test_stiff_along_compares_the_fastest_decay_rate_times_the_span_with_the_ratio():
    span = torch.tensor([10.0, 2.0, 1.0, 1.0], dtype=DT)
    jac = jacobians([[0.0, 1.0], [-4.0, -0.1]],  # an oscillator: decay 0.05, not stiff
                    [[-1e4, 1e4], [0.0, -1.0]],  # a lag of 1e-4 over 2: 2e4
                    [[-5e3, 0.0], [0.0, 1.0]],  # 5e3: below the ratio
                    [[0.0, 1e5], [-1e5, 0.0]])  # a fast oscillation: no decay, its Gershgorin bound 1e5
    assert stiff_along(jac, 2, span).tolist() == [False, True, False, False]


def test_stiff_along_reads_the_states_block_and_any_node():
    """Columns beyond the states (the coefficients' null equations) do not count; one stiff node is enough;
    a node that is not finite is not."""
    jac = torch.zeros(2, 3, 3, 3, dtype=DT)
    jac[:, :, 0, 2] = 1e9  # d x' / d p: not a state's rate
    jac[0, 1, 0, 0] = -2 * STIFF_RATIO
    jac[1, 1, 0, 0] = float("nan")
    jac[1, 2, 1, 1] = -0.5
    assert stiff_along(jac, 2, torch.ones(2, dtype=DT)).tolist() == [True, False]
