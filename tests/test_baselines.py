"""The gradient baseline `torchql.baselines.adjoint_fit`: recovery, gradients, status, validation.

Data: the linear oscillator (y0 = 0, v0 = 1, A = 0.1, B = 3), y at t = 0, 0.5, ..., 6.5 made at
rtol 1e-13. Guess about 20 % off the truth. Each loss evaluation is a full forward (and
adjoint) solve, so the runs are kept short: L-BFGS to convergence, Adam for a fixed budget.
"""

import copy

import pytest
import torch

import torchql
from torchql.baselines import OPTIMIZERS, _GradientRun, adjoint_fit
from torchql.fit import _Problem
from torchql.models import LinearOscillator

DT = torch.float64
TRUTH = torch.tensor([0.0, 1.0, 0.1, 3.0], dtype=DT)  # y(t0), v(t0), A, B
GUESS_X0 = torch.tensor([0.1, 1.2], dtype=DT)


def guess_model():
    return LinearOscillator(A=0.12, B=2.4)


def rel_error(estimates, truth):
    """Relative error, absolute where the truth is zero."""
    scale = torch.where(truth == 0, torch.ones_like(truth), truth.abs())
    return ((estimates - truth).abs() / scale).max().item()


@pytest.fixture(scope="module")
def data():
    t = torch.arange(14, dtype=DT) * 0.5
    x = torchql.simulate(LinearOscillator(), torch.tensor([0.0, 1.0], dtype=DT), t, rtol=1e-13, atol=1e-15)
    return torchql.Observations(t, x[:, :1], observe=["y"])


@pytest.fixture(scope="module")
def lbfgs_run(data):
    model = guess_model()
    before = {k: v.clone() for k, v in model.named_buffers()}
    steps = []
    result = adjoint_fit(model, data, x0=GUESS_X0, optimizer="lbfgs",
                         callback=lambda step, sse, est: steps.append((step, sse, est)))
    return result, model, before, steps


def test_lbfgs_adjoint_recovers_linear_oscillator(lbfgs_run):
    result, _, _, _ = lbfgs_run
    assert isinstance(result, torchql.FitResult)
    assert result.success and result.status is torchql.Status.CONVERGED, result.message
    assert result.method == "lbfgs"
    assert result.unknown_names == ["y(t0)", "v(t0)", "A", "B"]
    assert rel_error(result.estimates, TRUTH) < 1e-3
    assert result.sse < 1e-8
    # the uncertainty machinery is filled at the estimates
    assert result.jacobian.shape == (14, 4) and torch.isfinite(result.jacobian).all()
    assert torch.isfinite(result.covariance).all()


@pytest.mark.parametrize("kind", ["h(x, p)", "lognormal"])
def test_observations_that_fit_takes_are_fitted_alike(data, kind):
    """An output ``s y + o`` with its scale and offset estimated (``observe=h(x, p)``), and values with
    log-normal noise (residuals of logarithms): ``adjoint_fit`` minimizes the objective ``fit``
    does (it called ``h(x)`` without the coefficients, and took no logarithms)."""
    if kind == "lognormal":
        noise = torch.randn(data.y.shape, generator=torch.Generator().manual_seed(2), dtype=DT)
        y = (3.0 + data.y) * torch.exp(0.05 * noise)  # positive: the oscillation about 3
        observations = torchql.Observations(data.t, y, observe=lambda x: x[..., :1] + 3.0, noise="lognormal")
        model = guess_model()
    else:
        observations = torchql.Observations(data.t, 2.0 * data.y + 0.1,
                                            observe=lambda x, p: p["s"] * x[..., :1] + p["o"])
        model = _Scaled()
    # (a scale of the output and the initial state are not separable: the latter is held, at the truth)
    held = dict(x0=TRUTH[:2], fixed_x0=["y", "v"]) if kind == "h(x, p)" else dict(x0=GUESS_X0)
    reference = torchql.fit(copy.deepcopy(model), observations, **held)
    result = adjoint_fit(model, observations, optimizer="lbfgs", **held)
    assert reference.success and result.success, result.message
    assert rel_error(result.estimates, reference.estimates) < 1e-3
    assert result.sse == pytest.approx(reference.sse, rel=1e-4, abs=1e-12)


class _Scaled(LinearOscillator):
    """The linear oscillator with an output scale ``s`` and offset ``o`` among its coefficients."""

    def __init__(self) -> None:
        super().__init__(A=0.12, B=2.4)
        self.register_buffer("s", torch.tensor(1.5, dtype=DT))
        self.register_buffer("o", torch.tensor(0.0, dtype=DT))


def test_history_callback_and_counts(lbfgs_run):
    result, _, _, steps = lbfgs_run
    assert len(result.history) == result.iterations + 1
    assert [rec.iteration for rec in result.history] == list(range(result.iterations + 1))
    assert result.history[0].params["A"].item() == pytest.approx(0.12)
    assert torch.equal(result.history[0].x0, GUESS_X0)
    assert result.history[-1].sse < 1e-3 * result.history[0].sse
    assert [s[0] for s in steps] == list(range(result.iterations + 1))
    assert torch.allclose(steps[-1][2], result.estimates)
    assert result.nfev > 0 and result.fit_kwargs["gradient_run"]["optimizer"] == "lbfgs"
    result.report()  # the report works on a baseline result


def test_user_model_unchanged(lbfgs_run):
    _, model, before, _ = lbfgs_run
    after = dict(model.named_buffers())
    assert after.keys() == before.keys()
    for k in before:
        assert torch.equal(after[k], before[k]) and not after[k].requires_grad
    assert list(model.parameters()) == []


def _gradient(data, adjoint, x0=GUESS_X0):
    problem = _Problem(guess_model(), data, x0, None, None, None, "kantorovich", None, 0, "dopri5", 1e-10, 1e-12,
                       None, None, None, None, "integrate", None)
    run = _GradientRun(problem, "adam", 1e-2, 0, 1e-6, 1e-6, 1, adjoint, None, False)
    sse, grad = run.evaluate()
    return sse, grad / run.scale  # d SSE / d unknowns


def test_adjoint_and_backprop_gradients_agree(data):
    sse_a, g_a = _gradient(data, adjoint=True)
    sse_b, g_b = _gradient(data, adjoint=False)
    assert sse_a == pytest.approx(sse_b, rel=1e-8)
    assert torch.allclose(g_a, g_b, rtol=1e-6, atol=1e-8 * g_a.abs().max().item())
    # and both agree with torchql's own sensitivities: d SSE / du = -2 J^T r
    at_guess = torchql.fit(guess_model(), data, x0=GUESS_X0, max_iter=0)
    g_ref = -2.0 * at_guess.jacobian.T @ at_guess.residuals
    assert torch.allclose(g_a, g_ref, rtol=1e-6, atol=1e-8 * g_ref.abs().max().item())


def test_adam_decreases_loss_and_reports_budget(data):
    result = adjoint_fit(guess_model(), data, x0=GUESS_X0, optimizer="adam", adjoint=False, max_steps=120,
                         rtol=1e-6, atol=1e-8)
    sse = [rec.sse for rec in result.history]
    assert result.method == "adam" and result.iterations == 120 and len(sse) == 121
    assert sse[-1] < 0.05 * sse[0]
    # monotone-ish: every block of 20 steps ends lower than it started
    assert all(sse[k + 20] < sse[k] for k in range(0, 100, 20)), sse[::20]
    assert rel_error(result.estimates, TRUTH) < rel_error(torch.tensor([0.1, 1.2, 0.12, 2.4], dtype=DT), TRUTH)
    assert not result.success and result.status is torchql.Status.MAX_ITER
    assert "`max_steps` = 120" in result.message


@pytest.mark.parametrize("optimizer", OPTIMIZERS)
def test_tiny_budget_says_so(data, optimizer):
    result = adjoint_fit(guess_model(), data, x0=GUESS_X0, optimizer=optimizer, max_steps=1, adjoint=False)
    assert result.status is torchql.Status.MAX_ITER and not result.success
    assert "max_steps" in result.message and result.iterations == 1 and len(result.history) == 2


def test_zero_steps_evaluates_the_guess(data):
    result = adjoint_fit(guess_model(), data, x0=GUESS_X0, max_steps=0)
    assert result.iterations == 0 and torch.allclose(result.estimates, torch.tensor([0.1, 1.2, 0.12, 2.4], dtype=DT))
    assert result.status is torchql.Status.MAX_ITER


def test_max_time_budget(data):
    result = adjoint_fit(guess_model(), data, x0=GUESS_X0, max_steps=10_000, max_time=1e-9, adjoint=False)
    assert result.status is torchql.Status.MAX_ITER and "`max_time`" in result.message
    assert result.iterations == 0


@pytest.mark.parametrize("adjoint", [False, True])
def test_max_time_is_checked_inside_a_step(data, adjoint):
    """The budget is checked at every evaluation of the model, inside a solve and its adjoint: a
    first step of an oscillator guessed at ``B = 3e4`` took 25 s of a 2 s budget (the whole call
    121 s). Spent at once, the run stops at the first evaluation, at the guesses."""
    result = adjoint_fit(guess_model(), data, x0=GUESS_X0, max_time=1e-9, adjoint=adjoint)
    assert result.status is torchql.Status.MAX_ITER and "used up after 0 adam steps" in result.message
    assert result.nfev == 0 and result.iterations == 0
    assert torch.equal(result.estimates, torch.tensor([0.1, 1.2, 0.12, 2.4], dtype=DT))


def test_fixed_x0_and_params_subset(data):
    result = adjoint_fit(LinearOscillator(A=0.1, B=2.5), data, x0=torch.tensor([0.0, 1.0], dtype=DT),
                         params=["B"], fixed_x0=["y", "v"], optimizer="lbfgs", adjoint=False)
    assert result.unknown_names == ["B"] and result.success, result.message
    assert result.params["B"].item() == pytest.approx(3.0, rel=1e-4)
    assert result.x0.tolist() == [0.0, 1.0] and result.params["A"].item() == 0.1


def test_bad_optimizer_lists_valid_ones(data):
    with pytest.raises(ValueError, match=r"`optimizer` must be one of \('adam', 'lbfgs'\); received 'sgd'"):
        adjoint_fit(guess_model(), data, x0=GUESS_X0, optimizer="sgd")


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        (dict(lr=0.0), ValueError, "`lr` must be a positive"),
        (dict(max_steps=-1), ValueError, "`max_steps` must be a non-negative integer"),
        (dict(tol=float("nan")), ValueError, "`tol`"),
        (dict(adjoint="yes"), TypeError, "`adjoint`"),
        (dict(callback=3), TypeError, "`callback` must be callable"),
        (dict(solver="euler2"), ValueError, "`solver` must be one of"),
        (dict(params=["C"]), ValueError, "`params` names unknown buffer 'C'"),
        (dict(x0=torch.zeros(3, dtype=DT)), ValueError, "`x0` must have shape"),
    ],
)
def test_invalid_arguments(data, kwargs, error, match):
    kwargs = {"x0": GUESS_X0, **kwargs}
    with pytest.raises(error, match=match):
        adjoint_fit(guess_model(), data, **kwargs)


@pytest.mark.parametrize("solver", ["dop853", "rodas5p"])
def test_torchqls_own_solvers_are_refused_by_name(data, solver):
    """torchql's DOP853 and implicit solvers are not differentiated through torchdiffeq: a clear error
    listing the methods that are (``"dop853"`` failed inside torchdiffeq, on the first loss)."""
    with pytest.raises(ValueError, match=r"`solver` of adjoint_fit must be a torchdiffeq method.*'dopri5'.*"
                                         rf"received '{solver}'"):
        adjoint_fit(guess_model(), data, x0=GUESS_X0, solver=solver)
    with pytest.raises(ValueError, match="must be a torchdiffeq method"):
        adjoint_fit(guess_model(), data, x0=GUESS_X0, options=torchql.FitOptions(solver=solver))


def test_auto_solver_is_dopri5(data):
    """``"auto"``, FitOptions' default, is this function's own default (it named "dop853" inside torchdiffeq)."""
    auto = adjoint_fit(guess_model(), data, x0=GUESS_X0, optimizer="lbfgs", adjoint=False, max_steps=3,
                       solver="auto")
    own = adjoint_fit(guess_model(), data, x0=GUESS_X0, optimizer="lbfgs", adjoint=False, max_steps=3)
    assert torch.equal(auto.estimates, own.estimates) and auto.sse == own.sse


def test_exact_values_rejected(data):
    exact = torchql.Observations(data.t, data.y, observe=["y"], exact=torch.arange(14) == 0)
    with pytest.raises(ValueError, match="`exact`"):
        adjoint_fit(guess_model(), exact, x0=GUESS_X0)


def test_not_a_model(data):
    with pytest.raises(TypeError, match="`model` must be a torchql.ODEModel"):
        adjoint_fit(copy.deepcopy, data, x0=GUESS_X0)
