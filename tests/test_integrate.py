"""``torchql.simulate``: plain forward (and backward) integration of a model."""

import contextlib
import math
import signal

import pytest
import torch

import torchql
from torchql.models import HarmonicOscillator

K = 0.7
X0 = 2.0


class Decay(torchql.ODEModel):
    """``y' = -k y``."""

    state_names = ("y",)

    def __init__(self, k=K, dtype=torch.float64):
        super().__init__()
        self.register_buffer("k", torch.tensor(k, dtype=dtype))

    def forward(self, t, x):
        return -self.k * x


def exact(t, t0=0.0):
    return X0 * torch.exp(-K * (t - t0))


def test_matches_analytic_solution():
    t = torch.linspace(0.0, 3.0, 7, dtype=torch.float64)
    x = torchql.simulate(Decay(), torch.tensor([X0], dtype=torch.float64), t, rtol=1e-11, atol=1e-13)
    assert x.shape == (7, 1) and x.dtype == torch.float64
    assert x[0, 0].item() == X0
    torch.testing.assert_close(x[:, 0], exact(t), rtol=0, atol=1e-9)


def test_default_tolerances_are_tight_in_float64():
    t = torch.linspace(0.0, 3.0, 7, dtype=torch.float64)
    x = torchql.simulate(Decay(), [X0], t)
    torch.testing.assert_close(x[:, 0], exact(t), rtol=0, atol=1e-8)


def test_integrates_backwards_before_t0():
    t = torch.tensor([-1.0, -0.5, 0.0, 0.5, 1.0], dtype=torch.float64)
    x = torchql.simulate(Decay(), torch.tensor([X0], dtype=torch.float64), t, t0=0.0, rtol=1e-11, atol=1e-13)
    assert x.shape == (5, 1)
    assert x[2, 0].item() == X0
    torch.testing.assert_close(x[:, 0], exact(t), rtol=1e-9, atol=0)


def test_all_times_before_t0():
    t = torch.tensor([-2.0, -1.0], dtype=torch.float64)
    x = torchql.simulate(Decay(), torch.tensor([X0], dtype=torch.float64), t, t0=0.5, rtol=1e-11, atol=1e-13)
    torch.testing.assert_close(x[:, 0], exact(t, 0.5), rtol=1e-9, atol=0)


def test_t0_between_output_times():
    t = torch.tensor([0.0, 1.0, 2.0], dtype=torch.float64)
    x = torchql.simulate(Decay(), torch.tensor([X0], dtype=torch.float64), t, t0=0.4, rtol=1e-11, atol=1e-13)
    torch.testing.assert_close(x[:, 0], exact(t, 0.4), rtol=1e-9, atol=0)


def test_two_state_model_and_single_time():
    t = torch.linspace(0.0, 2.0, 5, dtype=torch.float64)
    x = torchql.simulate(HarmonicOscillator(4.0), torch.tensor([1.0, 0.0], dtype=torch.float64), t,
                         rtol=1e-11, atol=1e-13)
    torch.testing.assert_close(x, torch.stack([torch.cos(2 * t), -2 * torch.sin(2 * t)], dim=1), rtol=0, atol=1e-9)
    one = torchql.simulate(HarmonicOscillator(4.0), torch.tensor([1.0, 0.0], dtype=torch.float64), [0.0])
    assert torch.equal(one, torch.tensor([[1.0, 0.0]], dtype=torch.float64))


def test_float32_model_gives_float32():
    x = torchql.simulate(Decay(dtype=torch.float32), [X0], [0.0, 1.0])
    assert x.dtype == torch.float32
    assert x[1, 0].item() == pytest.approx(X0 * math.exp(-K), rel=1e-5)


def test_fixed_step_solver():
    t = torch.linspace(0.0, 1.0, 101, dtype=torch.float64)
    x = torchql.simulate(Decay(), [X0], t, solver="rk4")
    torch.testing.assert_close(x[:, 0], exact(t), rtol=1e-8, atol=0)


def test_model_and_inputs_not_modified():
    model = Decay()
    x0 = torch.tensor([X0], dtype=torch.float64)
    t = torch.tensor([0.0, 1.0], dtype=torch.float64)
    torchql.simulate(model, x0, t)
    assert model.k.item() == K and x0.item() == X0 and torch.equal(t, torch.tensor([0.0, 1.0], dtype=torch.float64))


@pytest.mark.parametrize("solver", ["rk45", "DOPRI5", "scipy_solver", ""])
def test_bad_solver_name_lists_valid_ones(solver):
    with pytest.raises(ValueError, match=r"`solver` must be one of \(.*'dopri5'.*\); received") as info:
        torchql.simulate(Decay(), [X0], [0.0, 1.0], solver=solver)
    for name in torchql.SOLVER_NAMES:
        assert repr(name) in str(info.value)


def test_the_default_solver_is_auto_explicit_where_the_model_is_not_stiff():
    """``"auto"``: DOP853 (the same solution as ``solver="dop853"``), and ``"auto"`` is a name it takes."""
    t = torch.linspace(0.0, 10.0, 21, dtype=torch.float64)
    x0 = torch.tensor([1.0, 0.0], dtype=torch.float64)
    x = torchql.simulate(HarmonicOscillator(4.0), x0, t)
    assert torch.equal(x, torchql.simulate(HarmonicOscillator(4.0), x0, t, solver="dop853"))
    assert torch.equal(x, torchql.simulate(HarmonicOscillator(4.0), x0, t, solver="auto"))
    torch.testing.assert_close(x, torch.stack([torch.cos(2 * t), -2 * torch.sin(2 * t)], dim=1), rtol=0, atol=1e-9)


def test_auto_takes_the_stiff_solver_for_a_model_stiff_at_its_initial_state():
    """``y' = -1e5 y`` over 1 time unit: the decay rate times the span, 1e5, is above the stiffness
    ratio (1e4) at ``x0``: Rodas5P's solution, exact to the tolerance."""
    t = torch.tensor([0.0, 1e-5, 3e-5, 1e-4, 0.5, 1.0], dtype=torch.float64)
    x = torchql.simulate(Decay(1e5), [X0], t)
    assert torch.equal(x, torchql.simulate(Decay(1e5), [X0], t, solver="rodas5p"))
    torch.testing.assert_close(x[:, 0], X0 * torch.exp(-1e5 * t), rtol=1e-8, atol=1e-12)


def test_auto_integrates_again_by_the_stiff_solver_where_the_explicit_one_finds_stiffness():
    """Robertson's kinetics are not stiff at ``(1, 0, 0)`` (decay rates 0.04 and 0) and become so
    within 1e-3 time units: DOP853 fails, saying so, and the result is Rodas5P's, where
    torchdiffeq's ``"dopri5"``, the former default, ran over 100 s. ``"auto"`` tests DOP853's steps
    from the start: it gives up after about 80 steps (about 1,000 evaluations), where at Hairer's
    first test, the 1,000th step, it had spent 14,500 (most of the time)."""
    from torchql.models.stiff import Robertson

    class Counted(Robertson):
        calls = 0

        def forward(self, t, x):
            Counted.calls += 1
            return super().forward(t, x)

    t = torch.logspace(-5, 3, 9, dtype=torch.float64)
    x0 = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    with pytest.raises(torchql.IntegrationError, match="stiff"):
        torchql.simulate(Robertson(), x0, t, solver="dop853")
    x = torchql.simulate(Counted(), x0, t)
    auto_calls, Counted.calls = Counted.calls, 0
    assert torch.equal(x, torchql.simulate(Counted(), x0, t, solver="rodas5p"))
    assert auto_calls - Counted.calls < 12 * 200  # DOP853's 12 evaluations a step, 200 steps
    torch.testing.assert_close(x.sum(dim=1), torch.ones(9, dtype=torch.float64), rtol=0, atol=1e-9)  # mass conserved


def test_auto_sees_a_model_stiff_backwards_as_stiff():
    """``y' = +1e5 y`` integrated from ``t0 = 0`` back to -1: its growth rate is the reversed field's
    decay rate, stiff; DOP853 took 6,800 steps there before its own test gave up (and said the time
    without its sign)."""
    t = torch.tensor([-1.0, -0.5, -1e-4, 0.0], dtype=torch.float64)
    x = torchql.simulate(Decay(-1e5), [X0], t, t0=0.0)
    assert torch.equal(x, torchql.simulate(Decay(-1e5), [X0], t, t0=0.0, solver="rodas5p"))
    torch.testing.assert_close(x[:, 0], X0 * torch.exp(1e5 * t), rtol=1e-8, atol=1e-12)
    with pytest.raises(torchql.IntegrationError, match=r"became stiff at t = -"):
        torchql.simulate(Decay(-1e5), [X0], t, t0=0.0, solver="dop853")


class _Item(torchql.ODEModel):
    """``y' = -k y`` computed in NumPy: a model torch.func cannot vmap or differentiate."""

    state_names = ("y",)

    def forward(self, t, x):
        return torch.as_tensor(-K * x.detach().numpy())


def test_auto_integrates_a_model_that_leaves_torch_as_the_former_default_did():
    """DOP853 and Rodas5P vmap and differentiate the model; one computed in NumPy is integrated
    by torchdiffeq's ``"dopri5"``, which calls it as it is (the former default's result)."""
    t = torch.linspace(0.0, 3.0, 7, dtype=torch.float64)
    x = torchql.simulate(_Item(), [X0], t)
    assert torch.equal(x, torchql.simulate(_Item(), [X0], t, solver="dopri5"))
    torch.testing.assert_close(x[:, 0], exact(t), rtol=0, atol=1e-8)


def test_solver_names():
    assert "dopri5" in torchql.SOLVER_NAMES and "rk4" in torchql.SOLVER_NAMES
    assert "scipy_solver" not in torchql.SOLVER_NAMES


@pytest.mark.parametrize("x0", [[1.0, 2.0], [[1.0]], 1.0, []])
def test_bad_x0_shape(x0):
    with pytest.raises(ValueError, match=r"`x0` must have shape \(n_states,\) = \(1,\)"):
        torchql.simulate(Decay(), x0, [0.0, 1.0])


@pytest.mark.parametrize("t", [[], [[0.0, 1.0]], 0.0])
def test_bad_t_shape(t):
    with pytest.raises(ValueError, match="`t` must be a non-empty one-dimensional tensor"):
        torchql.simulate(Decay(), [X0], t)


@pytest.mark.parametrize("t", [[0.0, 0.0], [1.0, 0.0]])
def test_t_not_increasing(t):
    with pytest.raises(ValueError, match="`t` must be strictly increasing"):
        torchql.simulate(Decay(), [X0], t)
    # (and where: the pair received)
    with pytest.raises(ValueError, match=r"received t\[2\] = 2 followed by t\[3\] = 1\.5$"):
        torchql.simulate(Decay(), [X0], [0.0, 1.0, 2.0, 1.5])


# ------------------------------------------------------------------ validation gaps (see reasons)
@contextlib.contextmanager
def time_limit(seconds):
    """Turn a hang into a TimeoutError (POSIX only)."""

    def handler(signum, frame):
        raise TimeoutError(f"did not return within {seconds} s")

    previous = signal.signal(signal.SIGALRM, handler)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


@pytest.mark.skipif(not hasattr(signal, "SIGALRM"), reason="needs SIGALRM")
def test_infinite_output_time_rejected():
    with time_limit(1.0):
        with pytest.raises(ValueError, match="`t` must be finite"):
            torchql.simulate(Decay(), [X0], [0.0, math.inf])


@pytest.mark.parametrize("t0", [math.nan, math.inf])
def test_non_finite_t0_rejected(t0):
    with pytest.raises(ValueError, match="`t0` must be"):
        torchql.simulate(Decay(), [X0], [0.0, 1.0], t0=t0)


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_non_finite_x0_rejected(bad):
    with pytest.raises(ValueError, match="`x0` must be finite"):
        torchql.simulate(Decay(), [bad], [0.0, 1.0])


@pytest.mark.parametrize("tolerances", [dict(rtol=-1.0), dict(rtol=0.0, atol=0.0), dict(atol=math.nan)])
def test_bad_tolerances_rejected(tolerances):
    with pytest.raises(ValueError, match="`(rtol|atol)` must be a positive finite number"):
        torchql.simulate(Decay(), [X0], [0.0, 1.0], **tolerances)


def test_model_not_an_odemodel():
    with pytest.raises(TypeError, match="`model` must be a torchql.ODEModel"):
        torchql.simulate(torch.nn.Linear(1, 1), [X0], [0.0, 1.0])


def test_a_step_size_underflow_in_float32_names_the_precision():
    """Van der Pol (mu = 1000) in float32 stops at its first jump near t = 807, where no step is
    shorter than 10 eps |t| = 1e-3; the message blamed singularities or tolerances only."""
    from torchql.models import VanDerPol

    t = torch.tensor([100.0, 900.0])
    with pytest.raises(torchql.IntegrationError, match=r"in float32 no step near t = 80\d\.\d+ is shorter than "
                                                        r"10 eps \|t\| = 0\.00096.*model\.double\(\)"):
        torchql.simulate(VanDerPol().float(), torch.tensor([2.0, 0.0]), t, t0=0.0, rtol=1e-3, atol=1e-5)


@pytest.mark.parametrize("solver", ["dop853", "rodas5p"])
def test_a_simulation_at_clock_times_equals_the_one_near_zero(solver):
    """An autonomous model integrated at t ~ 1e9 (clock times in seconds): each step advanced the
    state by h and the clock by fl(t + h), an ulp of t (1e-7) apart, and the solution drifted 5e-7
    from the one near zero (DOP853; Rodas5P 3e-7). The step taken is the one the clock takes."""
    from torchql.models import NonlinearOscillator

    t = torch.linspace(0.0, 20.0, 41, dtype=torch.float64)
    x0 = torch.tensor([1.0, 0.0], dtype=torch.float64)
    near = torchql.simulate(NonlinearOscillator(), x0, t, solver=solver, rtol=1e-10, atol=1e-12)
    for offset in (1e6, 1e9):
        far = torchql.simulate(NonlinearOscillator(), x0, t + offset, solver=solver, rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(far, near, rtol=0, atol=1e-11)


@pytest.mark.parametrize("solver", ["auto", "dop853", "dopri5", "rodas5p"])
def test_a_forward_not_finite_at_x0_is_named_so(solver):
    """A forward that is NaN at ``x0`` (``sqrt`` of a negative state): every solver's error names the
    forward and the derivative at ``x0``, where it read "underflow in dt 0.0" (dopri5) or "the step size
    underflowed" (DOP853)."""

    class Root(torchql.ODEModel):
        state_names = ("y",)

        def __init__(self):
            super().__init__()
            self.register_buffer("k", torch.tensor(1.0, dtype=torch.float64))

        def forward(self, t, x):
            return -self.k * torch.sqrt(x)

    t = torch.linspace(0.0, 1.0, 5, dtype=torch.float64)
    with pytest.raises(torchql.IntegrationError, match=r"`model` forward is not finite at `x0` = \[-1.0\]: "
                                                       r"dy/dt = nan at t0 = 0; the solution cannot start there"):
        torchql.simulate(Root(), torch.tensor([-1.0], dtype=torch.float64), t, solver=solver)
