"""Measured inputs: the three interpolations, their derivatives under torch.func, and bad input."""

import numpy as np
import pytest
import torch
from scipy.interpolate import CubicSpline
from torch.func import jacfwd, jvp, vmap

import torchql
from torchql.inputs import Inputs

DT = torch.float64


def _signal(kind, N=11, m=2, seed=0):
    g = torch.Generator().manual_seed(seed)
    t = torch.cumsum(0.5 + torch.rand(N, generator=g, dtype=DT), 0)
    u = torch.randn(N, m, generator=g, dtype=DT)
    return Inputs(t, u, names=[f"u{j}" for j in range(m)], kind=kind), t, u


def test_linear_is_numpy_interp_and_holds_the_ends():
    inputs, t, u = _signal("linear")
    tq = torch.linspace(float(t[0]) - 1, float(t[-1]) + 1, 301, dtype=DT)
    out = inputs(tq)
    assert out.shape == (301, 2)
    for j in range(2):
        np.testing.assert_allclose(out[:, j].numpy(), np.interp(tq.numpy(), t.numpy(), u[:, j].numpy()), atol=1e-14)


def test_cubic_is_the_not_a_knot_spline():
    inputs, t, u = _signal("cubic")
    tq = torch.linspace(float(t[0]), float(t[-1]), 257, dtype=DT)
    reference = CubicSpline(t.numpy(), u.numpy(), bc_type="not-a-knot")(tq.numpy())
    np.testing.assert_allclose(inputs(tq).numpy(), reference, atol=1e-12)


def test_zero_order_hold_holds_and_keeps_the_integral():
    inputs, t, u = _signal("zoh")
    half = inputs.ramp / 2
    assert 0 < inputs.ramp < 1e-6 * float(t[-1] - t[0])
    # held values between the steps, the mean at a sample, the end values outside
    mid = (t[:-1] + t[1:]) / 2
    torch.testing.assert_close(inputs(mid), u[:-1], rtol=0, atol=0)
    torch.testing.assert_close(inputs(t[1:] - half), u[:-1], rtol=0, atol=1e-12)
    torch.testing.assert_close(inputs(t[1:] + half), u[1:], rtol=0, atol=1e-12)
    torch.testing.assert_close(inputs(t[1:]), (u[:-1] + u[1:]) / 2, rtol=0, atol=1e-12)
    torch.testing.assert_close(inputs(t[-1:] + 5.0), u[-1:], rtol=0, atol=0)
    # the smoothed step has the held signal's integral: u(t_k - x) + u(t_k + x) = u_{k-1} + u_k
    x = torch.linspace(0, half, 7, dtype=DT)
    for k in (1, 4, 9):
        torch.testing.assert_close(inputs(t[k] - x) + inputs(t[k] + x), (u[k - 1] + u[k]).expand(7, 2),
                                   rtol=0, atol=1e-6 * float((u[k] - u[k - 1]).abs().max()))


@pytest.mark.parametrize("kind", ["zoh", "linear", "cubic"])
def test_derivatives_under_vmap_match_finite_differences(kind):
    inputs, t, _ = _signal(kind)
    tq = torch.linspace(float(t[0]) + 0.01, float(t[-1]) - 0.01, 37, dtype=DT)
    tq = tq[(tq.unsqueeze(-1) - t).abs().min(-1).values > 1e-3]  # away from the kinks
    one = torch.ones((), dtype=DT)
    values = vmap(inputs)(tq)
    slopes = vmap(lambda s: jvp(inputs, (s,), (one,))[1])(tq)
    torch.testing.assert_close(values, inputs(tq), rtol=0, atol=0)
    torch.testing.assert_close(vmap(jacfwd(inputs))(tq), slopes, rtol=1e-12, atol=1e-12)
    h = 1e-6
    torch.testing.assert_close(slopes, (inputs(tq + h) - inputs(tq - h)) / (2 * h), rtol=1e-6, atol=1e-8)


def test_a_hold_converted_to_a_coarser_dtype_keeps_its_steps_smooth_there():
    """Float64 samples of a zero-order hold converted to a float32 model's dtype: the step width is
    the one samples given in float32 have (1e5 of its roundoffs, at most a hundredth of an interval) (the float64 width,
    1e-8 here, is below float32's roundoff: true jumps, where the fit's solver failed)."""
    t = torch.linspace(0.0, 10.0, 26, dtype=torch.float64)
    u = torch.sin(t).unsqueeze(-1)
    fine = Inputs(t, u, names="u", kind="zoh")
    assert fine.ramp == pytest.approx(1e-8)
    coarse = fine.to(torch.float32)
    assert coarse.ramp == Inputs(t.float(), u.float(), names="u", kind="zoh").ramp
    # 1e5 float32 roundoffs of t = 10, capped at a hundredth of the shortest interval 0.4
    assert coarse.ramp == pytest.approx(min(1e5 * torch.finfo(torch.float32).eps * 10.0, 4e-3))
    assert coarse.to(torch.float64).ramp == coarse.ramp  # back in float64: as wide as in float32
    assert Inputs(t, u, names="u", kind="linear").to(torch.float32).ramp == 0.0


def test_linear_slope_at_the_first_sample_is_the_first_segment():
    inputs, t, u = _signal("linear")
    slope = jvp(inputs, (t[0],), (torch.ones((), dtype=DT),))[1]
    torch.testing.assert_close(slope, (u[1] - u[0]) / (t[1] - t[0]), rtol=1e-13, atol=0)


def test_nodes_and_jumps():
    zoh, t, _ = _signal("zoh")
    linear = Inputs(t, torch.zeros_like(t), "u", kind="linear")
    cubic = Inputs(t, torch.zeros_like(t), "u", kind="cubic")
    assert zoh.nodes.numel() == 2 * (t.numel() - 1) and zoh.jumps is not None
    assert linear.nodes.numel() == 2 * t.numel() - 1 and torch.equal(linear.jumps, t)
    assert torch.equal(cubic.nodes, t) and cubic.jumps is None


def test_select_orders_by_name():
    inputs, t, u = _signal("linear")
    swapped = inputs.select(["u1", "u0"])
    assert swapped.names == ("u1", "u0")
    torch.testing.assert_close(swapped(t), u.flip(-1), rtol=0, atol=0)
    with pytest.raises(ValueError, match="unknown input 'u1'; the model's inputs are \\('u0',\\)"):
        inputs.select(["u0"])
    with pytest.raises(ValueError, match="lacks the model's input 'w'"):
        inputs.select(["u0", "u1", "w"])


@pytest.mark.parametrize("args, kwargs, error, match", [
    (([0.0, 1.0], [1.0, 2.0]), {"names": "u", "kind": "spline"}, ValueError, "`kind` must be one of"),
    (([0.0, 1.0], [1.0, 2.0]), {"names": 3}, TypeError, "`names` must be a string"),
    (([0.0, 1.0], [1.0, 2.0]), {"names": ["u", "u"]}, ValueError, "distinct"),
    (([0.0, 1.0], [[1.0, 2.0]]), {"names": "u"}, ValueError, "`u` must have shape \\(N, m\\) = \\(2, 1\\)"),
    (([0.0, 1.0], [[1.0], [2.0]]), {"names": ["a", "b"]}, ValueError, "1 columns but 2 names"),
    (([1.0, 0.0], [1.0, 2.0]), {"names": "u"}, ValueError, "strictly increasing; received t\\[0\\] = 1"),
    (([0.0, 1.0], [1.0, float("nan")]), {"names": "u"}, ValueError, "must be finite"),
    (([0.0], [1.0]), {"names": "u", "kind": "linear"}, ValueError, "at least 2 sample times"),
    (("abc", [1.0]), {"names": "u"}, TypeError, "`inputs t` must be a tensor or array"),
])
def test_bad_inputs_are_named(args, kwargs, error, match):
    with pytest.raises(error, match=match):
        Inputs(*args, **kwargs)


def test_one_sample_zero_order_hold_is_a_constant():
    inputs = Inputs([2.0], [[3.0, 4.0]], names=["a", "b"], kind="zoh")
    torch.testing.assert_close(inputs(torch.tensor([0.0, 2.0, 9.0], dtype=DT)),
                               torch.tensor([[3.0, 4.0]] * 3, dtype=DT), rtol=0, atol=0)


def test_observations_carry_inputs_per_sample():
    t = torch.linspace(0, 1, 5, dtype=DT)
    a = Inputs(t, t, "u")
    b = Inputs(t, 2 * t, "u")
    y = torch.zeros(3, 5, 1, dtype=DT)
    shared = torchql.Observations(t, y, observe=["y"], inputs=a)
    assert shared[1].inputs is a and shared.inputs_of(2) is a
    own = torchql.Observations(t, y, observe=["y"], inputs=[a, b, a])
    assert own[1].inputs is b and own[1:].inputs == (b, a)
    same = torchql.Observations(t, y, observe=["y"], inputs=[a, Inputs(t, t.clone(), "u"), a])
    assert same.inputs is a  # equal signals are one shared signal
    assert "inputs=['u']" in repr(own)
    with pytest.raises(ValueError, match="one per sample \\(3\\); received 2"):
        torchql.Observations(t, y, observe=["y"], inputs=[a, b])
    with pytest.raises(TypeError, match="`inputs\\[1\\]` must be a torchql.Inputs"):
        torchql.Observations(t, y, observe=["y"], inputs=[a, "b", a])
    with pytest.raises(TypeError, match="`inputs` must be a torchql.Inputs; received list"):
        torchql.Observations(t, y[0], observe=["y"], inputs=[a])
