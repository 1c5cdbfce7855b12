"""The alpha update: weighted least squares, exact rows, rank decisions."""

import math

import pytest
import torch

from torchql.lstsq import ExactRowsError, relative_spectrum, solve_update, solve_update_batch

torch.manual_seed(0)
DT = torch.float64


def _problem(L=20, m=4, seed=0):
    g = torch.Generator().manual_seed(seed)
    C = torch.randn(L, m, generator=g, dtype=DT)
    d = torch.randn(L, generator=g, dtype=DT)
    w = torch.rand(L, generator=g, dtype=DT) + 0.5
    return C, d, w


def test_matches_weighted_least_squares_solution():
    C, d, w = _problem()
    sol = solve_update(C, d, w, torch.zeros(20, dtype=torch.bool), rcond=1e-12)
    expected = torch.linalg.lstsq(C * w[:, None], d * w).solution
    torch.testing.assert_close(sol.alpha, expected, rtol=1e-12, atol=1e-12)
    assert not sol.rank_deficient


def test_badly_scaled_columns_are_solved_accurately():
    # unknowns differing by 1e8 in scale: column scaling keeps the solve exact
    C, _, w = _problem()
    C = C * torch.tensor([1e-4, 1.0, 1e4, 1.0], dtype=DT)
    alpha_true = torch.tensor([3e3, -2.0, 5e-5, 0.7], dtype=DT)
    d = C @ alpha_true
    sol = solve_update(C, d, w, torch.zeros(20, dtype=torch.bool), rcond=1e-12)
    torch.testing.assert_close(sol.alpha, alpha_true, rtol=1e-10, atol=0)


def test_exact_rows_are_met_and_the_rest_is_the_constrained_optimum():
    C, d, w = _problem()
    exact = torch.zeros(20, dtype=torch.bool)
    exact[[0, 7]] = True
    sol = solve_update(C, d, w, exact, rcond=1e-12)
    torch.testing.assert_close(C[exact] @ sol.alpha, d[exact], rtol=0, atol=1e-12)
    # KKT system of  min ||W(C a - d)||^2  s.t.  C_e a = d_e
    A, b = C[~exact] * w[~exact, None], d[~exact] * w[~exact]
    E = C[exact]
    kkt = torch.zeros(6, 6, dtype=DT)
    kkt[:4, :4] = 2 * A.T @ A
    kkt[:4, 4:] = E.T
    kkt[4:, :4] = E
    rhs = torch.cat([2 * A.T @ b, d[exact]])
    expected = torch.linalg.solve(kkt, rhs)[:4]
    torch.testing.assert_close(sol.alpha, expected, rtol=1e-9, atol=1e-11)


def test_dependent_exact_rows_raise():
    C, d, w = _problem()
    C[1] = 2 * C[0]
    exact = torch.zeros(20, dtype=torch.bool)
    exact[[0, 1]] = True
    with pytest.raises(ExactRowsError, match="exact"):
        solve_update(C, d, w, exact, rcond=1e-10)


def test_dependent_exact_rows_that_agree_are_met_as_one():
    """A value marked twice (a row and twice that row, their values alike), or an exact value no
    unknown moves and that is met already (a zero row: an initial state held fixed at its measured
    value), constrain nothing more: the step is the one with that row left out; they were called
    contradictory, the fit EXACT_INFEASIBLE."""
    C, d, w = _problem()
    C[1], d[1] = 2 * C[0], 2 * d[0]
    C[3], d[3] = 0.0, 0.0
    exact = torch.zeros(20, dtype=torch.bool)
    exact[[0, 1, 3]] = True
    sol = solve_update(C, d, w, exact, rcond=1e-10)
    kept = torch.ones(20, dtype=torch.bool)
    kept[[1, 3]] = False
    alone = solve_update(C[kept], d[kept], w[kept], exact[kept], rcond=1e-10)
    torch.testing.assert_close(sol.alpha, alone.alpha, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(C[exact] @ sol.alpha, d[exact], rtol=0, atol=1e-12)
    assert sol.multipliers.shape == (3,) and bool(torch.isfinite(sol.multipliers).all())
    zero = solve_update(C, d, w, torch.arange(20) == 3, rcond=1e-10)  # the zero row alone: no constraint
    torch.testing.assert_close(zero.alpha, solve_update(C, d, w, torch.zeros(20, dtype=torch.bool), 1e-10).alpha)
    assert zero.multipliers.shape == (1,) and float(zero.multipliers[0]) == 0.0
    d[3] = 1e-3  # a zero row whose value is not met: no step meets it
    with pytest.raises(ExactRowsError, match="exact"):
        solve_update(C, d, w, exact, rcond=1e-10)


def test_rank_deficiency_is_detected_with_its_null_direction():
    C, d, w = _problem()
    C[:, 3] = C[:, 1] * 2.0  # unknowns 1 and 3 only appear as u1 + 2 u3
    sol = solve_update(C, d, w, torch.zeros(20, dtype=torch.bool), rcond=1e-10)
    assert sol.rank_deficient
    assert sol.null_vectors.shape == (4, 1)
    v = sol.null_vectors[:, 0]
    torch.testing.assert_close(C @ v, torch.zeros(20, dtype=DT), rtol=0, atol=1e-12)
    assert v[0].abs() < 1e-12 and v[2].abs() < 1e-12
    assert torch.isfinite(sol.alpha).all()


def test_damping_equals_the_augmented_least_squares_problem():
    """``damping = lam`` solves min ||A b - r||^2 + lam S0^2 ||b||^2 in the column-scaled unknowns."""
    g = torch.Generator().manual_seed(3)
    C = torch.randn(12, 4, generator=g, dtype=torch.float64) * torch.tensor([1.0, 10.0, 0.1, 5.0], dtype=torch.float64)
    d = torch.randn(12, generator=g, dtype=torch.float64)
    w = torch.ones(12, dtype=torch.float64)
    none = torch.zeros(12, dtype=torch.bool)
    lam = 0.3
    scale = torch.linalg.vector_norm(C, dim=0)
    Cs = C / scale
    s0 = torch.linalg.svdvals(Cs)[0]
    augmented = torch.cat([Cs, (lam ** 0.5) * s0 * torch.eye(4, dtype=torch.float64)])
    rhs = torch.cat([d, torch.zeros(4, dtype=torch.float64)])
    expected = torch.linalg.lstsq(augmented, rhs.unsqueeze(-1)).solution.squeeze(-1) / scale
    got = solve_update(C, d, w, none, 1e-12, damping=lam).alpha
    assert torch.allclose(got, expected, rtol=1e-12, atol=1e-14)
    # zero damping is the plain solution; growing damping shortens the step
    plain = solve_update(C, d, w, none, 1e-12).alpha
    assert torch.equal(solve_update(C, d, w, none, 1e-12, damping=0.0).alpha, plain)
    norms = [torch.linalg.vector_norm(solve_update(C, d, w, none, 1e-12, damping=x).alpha * scale).item()
             for x in (0.0, 0.01, 1.0, 100.0)]
    assert norms == sorted(norms, reverse=True)


def test_relative_spectrum_is_that_of_the_damped_problem():
    """The squared singular values relative to the largest of the weighted matrix with unit
    columns (the units of the unknowns and a common weight do not change them); directions
    below ``rcond`` are NaN; they are the ones ``solve_update_batch`` filters."""
    theta = 0.3  # two unit columns at angle theta: singular values^2 = 1 +- cos(theta)
    C = torch.tensor([[1.0, math.cos(theta)], [0.0, math.sin(theta)], [0.0, 0.0]], dtype=torch.float64)
    C = (C * torch.tensor([5.0, 1e-4], dtype=torch.float64)).unsqueeze(0)  # other units
    w = torch.full((1, 3), 7.0, dtype=torch.float64)
    r = relative_spectrum(C, w, rcond=1e-12)
    expected = (1 - math.cos(theta)) / (1 + math.cos(theta))
    assert r[0, 0].item() == 1.0 and r[0, 1].item() == pytest.approx(expected, rel=1e-12)
    assert torch.equal(torch.isnan(relative_spectrum(C, w, rcond=0.5)), torch.tensor([[False, True]]))
    _, _, Sv = solve_update_batch(C, torch.ones(1, 3, dtype=torch.float64), w, 1e-12, None)
    torch.testing.assert_close(r, (Sv / Sv[:, :1]) ** 2, rtol=1e-12, atol=0)
