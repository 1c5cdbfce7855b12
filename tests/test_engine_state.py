"""The engine's per-sample state: copying iterates between samples (:func:`torchql.engine_state.put_samples`)."""

import torch

import torchql
from torchql.engine_state import put_samples
from torchql.linearize import Linearization

DT = torch.float64


def _iterate(S: int, value: float, shared: bool = False) -> dict:
    rz = torch.full((S, 3, 2), value, dtype=DT)
    lin = Linearization(*(torch.full((S, 3, 2), value, dtype=DT) for _ in range(4)))
    return dict(z0=torch.full((S, 2), value, dtype=DT), rz=rz, nl_traj=rz if shared else rz.clone(), lin=lin)


def test_taking_every_sample_gives_each_array_storage_of_its_own():
    """A re-anchored iterate's reference is its model solution, one tensor under two keys. Taken
    whole, then partly overwritten by a trial whose model solution is not known (NaN), the
    reference must keep its values."""
    cur = _iterate(2, 0.0)
    put_samples(cur, torch.arange(2), _iterate(2, 1.0, shared=True), torch.arange(2))
    assert cur["rz"].untyped_storage().data_ptr() != cur["nl_traj"].untyped_storage().data_ptr()
    trial = _iterate(1, 2.0)
    trial["nl_traj"] = torch.full_like(trial["nl_traj"], float("nan"))
    put_samples(cur, torch.tensor([0]), trial, torch.tensor([0]))
    assert torch.equal(cur["rz"][0], torch.full((3, 2), 2.0, dtype=DT))
    assert torch.equal(cur["rz"][1], torch.full((3, 2), 1.0, dtype=DT))
    assert torch.isnan(cur["nl_traj"][0]).all() and torch.equal(cur["nl_traj"][1], torch.full((3, 2), 1.0, dtype=DT))


class _Damped(torchql.ODEModel):
    """``y'' = -A y' - B y`` with the noise level ``sig`` a coefficient (``sigma=lambda p: p["sig"]``)."""

    state_names = ("y", "v")

    def __init__(self, A=0.5, B=1.0, sig=0.05):
        super().__init__()
        for name, value in dict(A=A, B=B, sig=sig).items():
            self.register_buffer(name, torch.tensor(value, dtype=DT))

    def forward(self, t, x):
        y, v = x.unbind(-1)
        return torch.stack((v, -self.A * v - self.B * y), -1)


def test_fit_many_with_re_anchored_samples_equals_fit_per_sample():
    """Two oscillators whose noise level is estimated: their iterates are re-anchored in the same
    round and later copied one at a time. When the re-anchored reference shared its model
    solution's storage, the batch's undamped trials failed on NaN references from then on, and
    the second sample ended CONVERGED_SSE after 9 iterations where its own fit takes 10."""
    from torchql.models import LinearOscillator

    g = torch.Generator().manual_seed(0)
    t = torch.arange(14, dtype=DT) * 0.5
    ys = []
    for b in range(2):
        y = torchql.simulate(LinearOscillator(0.1 + 0.02 * b, 3.0 - 0.1 * b), torch.tensor([0.0, 1.0], dtype=DT), t)
        ys.append(y[:, :1] + 1e-2 * torch.randn((14, 1), generator=g, dtype=DT))
    Y, x0 = torch.stack(ys), torch.tensor([0.2, 0.8], dtype=DT)

    def sigma(p):
        return p["sig"].reshape(1)
    batch = torchql.fit_many(_Damped(), torchql.Observations(t, Y, observe=["y"], sigma=sigma), x0)
    for b in range(2):
        single = torchql.fit(_Damped(), torchql.Observations(t, Y[b], observe=["y"], sigma=sigma), x0)
        assert single.status == batch[b].status and single.iterations == batch[b].iterations
        torch.testing.assert_close(batch[b].estimates, single.estimates, rtol=1e-10, atol=1e-12)
