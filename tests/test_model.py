"""``torchql.model``: coefficient discovery and the augmented system ``z = (x, p)``."""

import copy

import pytest
import torch
from torch import nn

import torchql
from testmodels import Decay
from torchql.linearize import linearize
from torchql.model import AugmentedSystem, coefficient_names
from torchql.models import NonlinearOscillator

F64 = torch.float64
CPU = torch.device("cpu")


class Sub(nn.Module):
    def __init__(self):
        super().__init__()
        self.register_buffer("c", torch.tensor(0.5, dtype=F64))


class Mixed(torchql.ODEModel):
    """Two states; a scalar, an int, a vector ``W (2,)`` and a matrix ``K (2, 3)`` buffer, one nested."""

    state_names = ("a", "b")

    def __init__(self):
        super().__init__()
        self.register_buffer("s", torch.tensor(2.0, dtype=F64))
        self.register_buffer("count", torch.tensor(3))  # int: never a coefficient
        self.register_buffer("W", torch.tensor([1.0, -2.0], dtype=F64))
        self.register_buffer("K", torch.arange(6, dtype=F64).reshape(2, 3) / 10)
        self.register_buffer("flag", torch.tensor([True, False]))
        self.sub = Sub()

    def forward(self, t, x):
        u = torch.stack([x[..., 0], x[..., 1], t * torch.ones_like(x[..., 0])], dim=-1)
        return -self.s * x + self.W * torch.sin(x) + (self.K @ u.unsqueeze(-1)).squeeze(-1) - self.sub.c * x**2


def test_coefficient_names_lists_float_buffers_only():
    assert coefficient_names(Mixed()) == ["s", "W", "K", "sub.c"]


def test_model_basics():
    model = Mixed()
    assert model.n_states == 2
    assert torchql.ODEModel.constants == ()
    with pytest.raises(NotImplementedError, match="must implement forward"):
        torchql.ODEModel()(torch.tensor(0.0), torch.zeros(1))


def test_element_names_and_sizes():
    system = AugmentedSystem(Mixed(), ["W", "K", "s", "sub.c"], F64, CPU)
    assert system.n == 2
    assert system.P == 2 + 6 + 1 + 1
    assert system.M == system.n + system.P
    assert system.element_names == ["W[0]", "W[1]", "K[0,0]", "K[0,1]", "K[0,2]", "K[1,0]", "K[1,1]", "K[1,2]",
                                    "s", "sub.c"]
    assert system.component_names == ["a", "b"] + system.element_names


def test_pack_unpack_round_trip():
    model = Mixed()
    system = AugmentedSystem(model, ["W", "K", "sub.c"], F64, CPU)
    p = system.pack_params()
    expected = torch.cat([model.W, model.K.reshape(-1), model.sub.c.reshape(1)])
    assert torch.equal(p, expected)
    # K is packed row-major: "K[0,1]" is K[0, 1]
    assert p[system.element_names.index("K[0,1]")] == model.K[0, 1]
    assert p[system.element_names.index("K[1,0]")] == model.K[1, 0]
    parts = system.unpack_params(p)
    assert list(parts) == ["W", "K", "sub.c"]
    assert torch.equal(parts["W"], model.W)
    assert torch.equal(parts["K"], model.K)
    assert parts["sub.c"].shape == () and torch.equal(parts["sub.c"], model.sub.c)
    q = torch.randn(system.P, dtype=F64, generator=torch.Generator().manual_seed(0))
    assert torch.equal(torch.cat([v.reshape(-1) for v in system.unpack_params(q).values()]), q)


def test_unpack_splits_a_batch_of_vectors_into_a_batch_of_each_shape():
    for names in (["s", "sub.c"], ["W", "K", "s"]):  # scalars only (one view each), and mixed shapes
        system = AugmentedSystem(Mixed(), names, F64, CPU)
        q = torch.randn(3, 5, system.P, dtype=F64, generator=torch.Generator().manual_seed(1))
        parts = system.unpack_params(q)
        assert list(parts) == names
        start = 0
        for name, shape, size in zip(names, system.param_shapes, system.param_sizes):
            assert parts[name].shape == (3, 5, *shape)
            assert torch.equal(parts[name].reshape(3, 5, size), q[..., start:start + size])
            start += size


def test_no_params():
    system = AugmentedSystem(Mixed(), [], F64, CPU)
    assert system.P == 0 and system.M == 2
    assert system.pack_params().shape == (0,)


def test_augmented_rhs_zero_parameter_rows_and_state_rows_use_z():
    model = Mixed()
    system = AugmentedSystem(model, ["W", "K"], F64, CPU)
    gen = torch.Generator().manual_seed(1)
    z = torch.randn(system.M, dtype=F64, generator=gen)
    t = torch.tensor(0.3, dtype=F64)
    out = system.f(t, z)
    assert out.shape == (system.M,)
    assert torch.equal(out[system.n:], torch.zeros(system.P, dtype=F64))
    # the state rows are the model evaluated with the buffers taken from z
    reference = copy.deepcopy(model)
    reference.W = z[2:4].clone()
    reference.K = z[4:10].reshape(2, 3).clone()
    torch.testing.assert_close(out[: system.n], reference(t, z[: system.n]), rtol=1e-15, atol=1e-15)


def test_augmented_system_casts_dtype_without_touching_the_user_model():
    model = Mixed()
    system = AugmentedSystem(model, ["W"], torch.float32, CPU)
    assert system.model is not model
    assert system.model.W.dtype == torch.float32 and system.model.sub.c.dtype == torch.float32
    assert system.model.count.dtype == torch.int64
    assert model.W.dtype == F64 and model.sub.c.dtype == F64
    assert system.pack_params().dtype == torch.float32


def _central_differences(fun, t, z, h=1e-5):
    cols = []
    for j in range(z.shape[0]):
        e = torch.zeros_like(z)
        e[j] = h
        cols.append((fun(t, z + e) - fun(t, z - e)) / (2 * h))
    return torch.stack(cols, dim=-1)


def test_jacobian_matches_central_differences_nonlinear_oscillator():
    system = AugmentedSystem(NonlinearOscillator(), ["A", "B", "C", "D"], F64, CPU)
    gen = torch.Generator().manual_seed(1234)
    z = torch.randn(3, system.M, dtype=F64, generator=gen)
    t = torch.rand(3, dtype=F64, generator=gen)
    lin = linearize(system, t, z)
    assert lin.f.shape == (3, system.M) and lin.jac.shape == (3, system.M, system.M)
    for j in range(3):
        fd = _central_differences(system.f, t[j], z[j])
        torch.testing.assert_close(lin.jac[j], fd, rtol=0, atol=1e-7)
        torch.testing.assert_close(lin.f[j], system.f(t[j], z[j]), rtol=1e-15, atol=1e-15)
    # the parameter rows (null equations p' = 0) are identically zero
    assert torch.equal(lin.jac[:, system.n:, :], torch.zeros(3, system.P, system.M, dtype=F64))
    # the analytic Jacobian of the state rows, at the first point
    y, v, A, B, C, D = z[0].tolist()
    expected = torch.tensor([[0.0, 1.0, 0, 0, 0, 0],
                             [-B - 3 * D * y**2, -A - 3 * C * v**2, -v, -y, -v**3, -y**3]], dtype=F64)
    torch.testing.assert_close(lin.jac[0, :2], expected, rtol=1e-14, atol=1e-14)


def test_jacobian_matches_central_differences_vector_and_matrix_buffers():
    system = AugmentedSystem(Mixed(), ["s", "W", "K", "sub.c"], F64, CPU)  # non-autonomous: K[:, 2] multiplies t
    gen = torch.Generator().manual_seed(2)
    z = torch.randn(2, system.M, dtype=F64, generator=gen)
    t = torch.tensor([0.7, -1.3], dtype=F64)
    lin = linearize(system, t, z)
    for j in range(2):
        torch.testing.assert_close(lin.jac[j], _central_differences(system.f, t[j], z[j]), rtol=0, atol=1e-7)
        torch.testing.assert_close(lin.f[j], system.f(t[j], z[j]), rtol=1e-15, atol=1e-15)


def test_model_with_does_not_modify_the_original():
    model = NonlinearOscillator()
    before = {k: v.clone() for k, v in model.named_buffers()}
    system = AugmentedSystem(model, ["A", "D"], F64, CPU)
    system_before = {k: v.clone() for k, v in system.model.named_buffers()}
    p = torch.tensor([0.7, 9.0], dtype=F64)
    fitted = system.model_with(p)
    assert isinstance(fitted, NonlinearOscillator)
    assert fitted is not model and fitted is not system.model
    assert fitted.A.item() == 0.7 and fitted.D.item() == 9.0
    assert fitted.B.item() == 3.0 and fitted.C.item() == 0.2
    for name, value in model.named_buffers():
        assert torch.equal(value, before[name])
    for name, value in system.model.named_buffers():
        assert torch.equal(value, system_before[name])
    # the fitted buffers do not alias p
    p.add_(1.0)
    assert fitted.A.item() == 0.7 and fitted.D.item() == 9.0


def test_model_with_vector_and_matrix_buffers():
    model = Mixed()
    system = AugmentedSystem(model, ["W", "K"], F64, CPU)
    p = torch.arange(8, dtype=F64)
    fitted = system.model_with(p)
    assert torch.equal(fitted.W, p[:2]) and torch.equal(fitted.K, p[2:].reshape(2, 3))
    assert torch.equal(model.W, torch.tensor([1.0, -2.0], dtype=F64))


@pytest.mark.parametrize("model, params, direct", [
    (NonlinearOscillator(), ["A", "B", "C", "D"], True),  # unbind(-1): takes a batch with its coefficients
    (Decay(0.7), ["k"], False),  # -k * x, (S,) * (S, 1): the wrong shape
    (Mixed(), ["W", "K", "s", "sub.c"], False),  # matrix and vector coefficients: wrong values or shapes
], ids=["oscillator", "decay", "mixed"])
def test_the_batched_augmented_field_is_used_only_where_it_gives_the_vmapped_values(model, params, direct):
    """``AugmentedSystem.f`` of a batch (one model call, each sample's coefficients as buffers ``(S, ...)``)
    is taken by :class:`torchql.model.BatchedCall` where it equals ``vmap(f)``; the values are vmap's
    either way, and the model's own buffers are left as they were."""
    from torchql.model import BatchedCall

    system = AugmentedSystem(model, params, F64, CPU)
    before = {k: v.clone() for k, v in system.model.named_buffers()}
    g = torch.Generator().manual_seed(1)
    z = torch.randn(5, system.M, generator=g, dtype=F64)
    t = torch.linspace(0.0, 1.0, 5, dtype=F64)
    expected = torch.vmap(system.f)(t, z)
    call = BatchedCall(system.f)
    torch.testing.assert_close(call(t, z), expected, rtol=0, atol=0)
    assert call.direct is direct
    torch.testing.assert_close(call(t, z), expected, rtol=1e-13, atol=1e-15)
    if direct:
        torch.testing.assert_close(system.f(t, z), expected, rtol=1e-13, atol=1e-15)
    torch.testing.assert_close(call(t[3:4], z[3:4]), expected[3:4], rtol=1e-13, atol=1e-15)  # one row, either way
    assert all(torch.equal(v, before[k]) for k, v in system.model.named_buffers())


def test_the_batched_call_is_checked_on_a_few_rows_whatever_the_batch():
    """The check of :class:`torchql.model.BatchedCall` calls the batched function on
    ``PROBE_ROWS`` rows only: a model broadcasting coefficients ``(I,)`` against states ``(I, 1)``
    would otherwise build an ``(I, I)`` array on a large batch (1,000 cars: 0.9 s per fit_many)."""
    from torchql.model import PROBE_ROWS, BatchedCall

    system = AugmentedSystem(Decay(0.7), ["k"], F64, CPU)
    seen = []

    def one(t, z):  # under vmap a single state (M,); called on a batch, (I, M)
        if z.dim() == 2:
            seen.append(z.shape[0])
        return system.f(t, z)

    z = torch.rand(1000, system.M, dtype=F64)
    t = torch.zeros(1000, dtype=F64)
    call = BatchedCall(one)
    torch.testing.assert_close(call(t, z), torch.vmap(system.f)(t, z), rtol=0, atol=0)
    assert call.direct is False and seen and max(seen) == PROBE_ROWS
    seen.clear()
    call(t, z)
    assert not seen  # vmapped from then on


def test_a_coefficient_tied_between_submodules():
    """One tensor held by two submodules (PyTorch's weight tying): the fit substituted it under the first
    name while the forward read the second, and ended NOT_IDENTIFIABLE at the guess; a fit now refuses
    the model, naming both. One submodule registered under two names holds one coefficient: its
    nn.Parameter raised a bare KeyError, and is now fitted (through either name)."""
    from torch import nn

    t = torch.linspace(0, 5, 21, dtype=torch.float64)
    data = torchql.Observations(t, torch.exp(-t).unsqueeze(-1), observe=["y"])
    x0 = torch.tensor([1.0], dtype=torch.float64)

    class Tied(torchql.ODEModel):
        state_names = ("y",)

        def __init__(self, shared_module: bool):
            super().__init__()
            k = nn.Parameter(torch.tensor(0.5, dtype=torch.float64))
            if shared_module:
                self.a = self.b = nn.Module()
                self.a.k = k
            else:
                self.a, self.b = nn.Module(), nn.Module()
                self.a.k = self.b.k = k

        def forward(self, t, x):
            return -self.b.k * x

    with pytest.raises(ValueError, match="one coefficient under two names, 'a.k' and 'b.k'"):
        torchql.fit(Tied(shared_module=False), data, x0=x0)
    fit = torchql.fit(Tied(shared_module=True), data, x0=x0, fixed_x0=["y"])
    assert fit.status is torchql.Status.CONVERGED and fit.params["a.k"].item() == pytest.approx(1.0, rel=1e-9)
    assert isinstance(fit.model.b.k, nn.Parameter) and fit.model.b.k.item() == pytest.approx(1.0, rel=1e-9)
