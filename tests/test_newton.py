"""``torchql.newton_raphson``: algebraic Newton-Raphson."""

import math

import pytest
import torch

import torchql

ROOT = torch.tensor([math.sqrt(2.0), 3.0 / math.sqrt(2.0)], dtype=torch.float64)


def residual(x):
    """``x0^2 - 2 = 0``, ``x0 x1 - 3 = 0``: root ``(sqrt 2, 3 / sqrt 2)``."""
    return torch.stack([x[0] ** 2 - 2.0, x[0] * x[1] - 3.0])


def jacobian(x):
    return torch.stack([torch.stack([2.0 * x[0], torch.zeros_like(x[0])]), torch.stack([x[1], x[0]])])


@pytest.mark.parametrize("jac", [None, jacobian])
def test_converges_quadratically(jac):
    x0 = torch.tensor([2.0, 1.0], dtype=torch.float64)
    x0_before = x0.clone()
    sol = torchql.newton_raphson(residual, x0, jacobian=jac)
    assert isinstance(sol, torchql.NewtonResult)
    assert sol.success and sol.message == "Converged."
    torch.testing.assert_close(sol.x, ROOT, rtol=0, atol=1e-14)
    assert torch.equal(x0, x0_before)
    assert torch.equal(sol.history[0], x0)
    assert len(sol.history) == len(sol.residual_norms) == sol.iterations + 1
    assert sol.residual_norms[-1] < 1e-13
    errors = [float((x - ROOT).abs().max()) for x in sol.history]
    ratios = [e1 / e0**2 for e0, e1 in zip(errors, errors[1:]) if 1e-7 < e0]
    assert len(ratios) >= 3
    assert max(ratios) < 2.0
    assert errors[-1] < 1e-14


def test_analytic_and_autodiff_jacobians_give_the_same_iterates():
    x0 = torch.tensor([2.0, 1.0], dtype=torch.float64)
    a = torchql.newton_raphson(residual, x0)
    b = torchql.newton_raphson(residual, x0, jacobian=jacobian)
    assert a.iterations == b.iterations
    for xa, xb in zip(a.history, b.history):
        torch.testing.assert_close(xa, xb, rtol=1e-15, atol=1e-15)


def test_scalar_equation_and_list_input():
    sol = torchql.newton_raphson(lambda x: x**3 - 8.0, [3])  # integer list -> float64
    assert sol.x.dtype == torch.float64
    assert sol.success
    assert sol.x.item() == pytest.approx(2.0, abs=1e-14)


def test_overdetermined_system_is_gauss_newton():
    # consistent overdetermined system: x0 = 1, x1 = 2, x0 + x1 = 3 (with a nonlinear twist)
    def r(x):
        return torch.stack([x[0] ** 2 - 1.0, x[1] - 2.0, x[0] + x[1] - 3.0])

    sol = torchql.newton_raphson(r, torch.tensor([2.0, 0.0], dtype=torch.float64))
    assert sol.success
    torch.testing.assert_close(sol.x, torch.tensor([1.0, 2.0], dtype=torch.float64), rtol=0, atol=1e-12)


@pytest.mark.parametrize("x0", [torch.ones(2, 1), torch.tensor(1.0), torch.ones(1, 2, 1)])
def test_bad_x0_shape(x0):
    with pytest.raises(ValueError, match=r"`x0` must be one-dimensional, shape \(m,\)"):
        torchql.newton_raphson(residual, x0)


def test_non_finite_x0():
    with pytest.raises(ValueError, match="`x0` must be finite"):
        torchql.newton_raphson(residual, torch.tensor([math.nan, 1.0]))


@pytest.mark.parametrize("shape", [(2,), (2, 3), (3, 2), (1, 2)])
def test_jacobian_wrong_shape(shape):
    with pytest.raises(ValueError, match=rf"`jacobian` must return shape \(2, 2\); received {re_shape(shape)}"):
        torchql.newton_raphson(residual, torch.tensor([2.0, 1.0], dtype=torch.float64),
                               jacobian=lambda x: torch.ones(shape, dtype=x.dtype))


def re_shape(shape):
    return r"\(" + r",\s*".join(str(s) for s in shape) + (r",\)" if len(shape) == 1 else r"\)")


def test_residual_must_return_a_vector():
    with pytest.raises(ValueError, match="`residual` must return a one-dimensional tensor"):
        torchql.newton_raphson(lambda x: (x**2).sum(), torch.tensor([2.0, 1.0], dtype=torch.float64))


@pytest.mark.parametrize("name, value", [("xtol", -1.0), ("xtol", float("nan")), ("ftol", float("nan")),
                                         ("ftol", -1e-3), ("xtol", "1e-8")])
def test_tolerances_must_be_non_negative_numbers(name, value):
    """A negative or NaN ``xtol`` stopped nothing: a root found to 9e-16 was reported as "maximum
    number of iterations"."""
    with pytest.raises(ValueError, match=f"`{name}` must be a non-negative finite number"):
        torchql.newton_raphson(residual, torch.tensor([2.0, 1.0], dtype=torch.float64), **{name: value})


@pytest.mark.parametrize("wrong, received", [(lambda J: J.numpy(), "ndarray"), (lambda J: J.float(), "torch.float32"),
                                             (lambda J: J.tolist(), "list")])
def test_a_jacobian_of_another_type_or_dtype_is_named(wrong, received):
    with pytest.raises(TypeError, match=f"`jacobian` must return a tensor of x's dtype torch.float64; "
                                        f"received .*{received}"):
        torchql.newton_raphson(residual, torch.tensor([2.0, 1.0], dtype=torch.float64),
                               jacobian=lambda x: wrong(jacobian(x)))
    with pytest.raises(TypeError, match="`jacobian` must be callable"):
        torchql.newton_raphson(residual, torch.tensor([2.0, 1.0], dtype=torch.float64), jacobian=jacobian(ROOT))
    with pytest.raises(TypeError, match="`residual` must return a tensor of x0's dtype torch.float64; "
                                        "received torch.float32"):
        torchql.newton_raphson(lambda x: residual(x).float(), torch.tensor([2.0, 1.0], dtype=torch.float64))
    with pytest.raises(TypeError, match="`residual` must be callable as R\\(x\\) -> Tensor; received Tensor"):
        torchql.newton_raphson(ROOT, torch.tensor([2.0, 1.0], dtype=torch.float64))


@pytest.mark.parametrize("max_iter", [-1, True, 1.5])
def test_max_iter_invalid(max_iter):
    with pytest.raises(ValueError, match="`max_iter` must be a non-negative integer"):
        torchql.newton_raphson(residual, torch.tensor([2.0, 1.0], dtype=torch.float64), max_iter=max_iter)


def test_max_iter_zero_returns_the_guess_unconverged():
    x0 = torch.tensor([2.0, 1.0], dtype=torch.float64)
    calls = []
    sol = torchql.newton_raphson(residual, x0, max_iter=0, jacobian=lambda x: calls.append(x) or jacobian(x))
    assert not sol.success
    assert sol.iterations == 0
    assert torch.equal(sol.x, x0)
    assert sol.x is not x0
    assert len(sol.history) == 1 and torch.equal(sol.history[0], x0)
    assert sol.residual_norms == [pytest.approx(2.0)]
    assert "max_iter" in sol.message
    assert calls == []


def test_max_iter_reached_reports_failure():
    sol = torchql.newton_raphson(residual, torch.tensor([2.0, 1.0], dtype=torch.float64), max_iter=2)
    assert not sol.success and sol.iterations == 2 and len(sol.history) == 3
    assert "Increase `max_iter`" in sol.message


def test_ftol_stops_early():
    loose = torchql.newton_raphson(residual, torch.tensor([2.0, 1.0], dtype=torch.float64), ftol=1e-3, xtol=0.0)
    tight = torchql.newton_raphson(residual, torch.tensor([2.0, 1.0], dtype=torch.float64))
    assert loose.success and loose.residual_norms[-1] <= 1e-3
    assert loose.iterations < tight.iterations


def test_divergence_is_reported():
    # a residual that becomes infinite at the first iterate (x = 2)
    def r(x):
        return torch.where(x > 1.5, torch.full_like(x, math.inf), x - 2.0)

    sol = torchql.newton_raphson(r, torch.tensor([0.0], dtype=torch.float64), jacobian=lambda x: torch.ones(1, 1, dtype=x.dtype))
    assert not sol.success
    assert "diverged" in sol.message


def test_singular_jacobian_is_an_unsuccessful_result():
    # R(x) = (x0 + x1 - 1, 2 x0 + 2 x1 - 2): the Jacobian is singular everywhere
    residual = lambda x: torch.stack([x[0] + x[1] - 1.0, 2 * x[0] + 2 * x[1] - 2.5])
    result = torchql.newton_raphson(residual, torch.tensor([0.0, 0.0], dtype=torch.float64))
    assert not result.success and "singular" in result.message
    assert torch.isfinite(result.x).all()


def test_guess_meeting_ftol_takes_no_step():
    residual = lambda x: x**2 - 4.0
    result = torchql.newton_raphson(residual, torch.tensor([2.0], dtype=torch.float64), ftol=1e-12)
    assert result.success and result.iterations == 0 and len(result.history) == 1


def test_a_float32_guess_converges_at_its_own_precision():
    """In float32 the default step test is 100 of its roundoffs (a step of 1e-12 is below them):
    the root of the float64 solve, to float32's precision, reported converged."""
    def circle_and_hyperbola(x):
        return torch.stack((x[0] ** 2 + x[1] ** 2 - 4.0, x[0] * x[1] - 1.0))

    single = torchql.newton_raphson(circle_and_hyperbola, torch.tensor([2.0, 0.3]))
    double = torchql.newton_raphson(circle_and_hyperbola, torch.tensor([2.0, 0.3], dtype=torch.float64))
    assert single.success and double.success, single.message
    assert single.x.dtype == torch.float32 and single.iterations <= double.iterations
    torch.testing.assert_close(single.x.double(), double.x, rtol=1e-6, atol=0)


def test_a_step_below_xtol_far_from_any_root_is_not_success():
    """``sin(x)`` from ``pi / 2``, where its derivative is 6e-17: the first step throws the iterate to
    ``-1.6e16``, where every later step is below ``xtol`` beside ``|x|``; it was reported converged
    with ``|sin(x)| = 0.66``. The residual did not fall: no root, said so."""
    sol = torchql.newton_raphson(torch.sin, torch.tensor([math.pi / 2], dtype=torch.float64))
    assert not sol.success
    assert sol.residual_norms[-1] > 0.1
    assert "no root was found" in sol.message and "ftol" in sol.message
    near = torchql.newton_raphson(torch.sin, torch.tensor([3.0], dtype=torch.float64))
    assert near.success and abs(float(near.x[0]) - math.pi) < 1e-15


@pytest.mark.parametrize("start", [math.sqrt(2.0), 1.4142135623731, 1.414213562373])
def test_a_guess_at_the_root_converges(start):
    """From the root itself (or within rounding of it) the residual cannot fall a thousandfold: it
    is at its rounding from the start (4e-16), and that is convergence."""
    sol = torchql.newton_raphson(lambda x: x**2 - 2.0, torch.tensor([start], dtype=torch.float64))
    assert sol.success, sol.message
    assert abs(float(sol.x[0]) - math.sqrt(2.0)) < 1e-15


def test_a_scaled_residual_at_its_rounding_converges():
    """``1e8 (e^x - 3)`` near ``ln 3``: the residual's rounding is about 1e-7; from 2.9e-6 it falls to
    4.4e-8, 65 times, and that is the root to rounding."""
    sol = torchql.newton_raphson(lambda x: 1e8 * (torch.exp(x) - 3.0), torch.tensor([1.0986122886681],
                                                                                    dtype=torch.float64))
    assert sol.success, sol.message
    assert abs(float(sol.x[0]) - math.log(3.0)) < 1e-15
