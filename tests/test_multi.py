"""Several experiments sharing the coefficients, fitted as one stacked problem."""

import pytest
import torch

import torchql
from torchql.models import LinearOscillator

DT = torch.float64
X0_TRUE = torch.tensor([[0.0, 1.0], [1.0, -0.5]], dtype=DT)


def simulate(x0, t):
    return torchql.simulate(LinearOscillator(A=0.1, B=3.0), x0, t, rtol=1e-13, atol=1e-15)


@pytest.fixture(scope="module")
def experiments():
    t1 = torch.arange(14, dtype=DT) * 0.5
    t2 = torch.linspace(2.0, 5.0, 9, dtype=DT)  # later start, different span, both states observed
    d1 = torchql.Observations(t1, simulate(X0_TRUE[0], t1)[:, :1], observe=["y"])
    d2 = torchql.Observations(t2, simulate(X0_TRUE[1], t2), observe=["y", "v"])
    return d1, d2, t2


@pytest.fixture(scope="module")
def fitted(experiments):
    d1, d2, _ = experiments
    guess = torch.tensor([[0.5, 0.5], [0.8, 0.0]], dtype=DT)
    return torchql.fit(LinearOscillator(A=0.5, B=1.0), [d1, d2], x0=guess)


def test_shared_coefficients_and_each_initial_state_recovered(fitted):
    r = fitted
    assert r.success, r.message
    assert r.unknown_names == ["y[0](t0)", "v[0](t0)", "y[1](t0)", "v[1](t0)", "A", "B"]
    assert r.x0.shape == (2, 2) and torch.allclose(r.x0, X0_TRUE, atol=1e-9)
    assert abs(r.params["A"].item() - 0.1) < 1e-9 and abs(r.params["B"].item() - 3.0) < 1e-8
    assert set(r.params) == {"A", "B"} and r.experiment_t0 == [0.0, 2.0]
    assert set(r.stderr) == set(r.unknown_names)


def test_predict_per_experiment(fitted, experiments):
    _, _, t2 = experiments
    assert torch.allclose(fitted.predict(t2, experiment=1), simulate(X0_TRUE[1], t2), atol=1e-8)
    with pytest.raises(ValueError, match="experiment"):
        fitted.predict(t2)
    with pytest.raises(ValueError, match="experiment"):
        fitted.predict(t2, experiment=2)


def test_matches_the_single_experiment_fit_when_one_is_given(experiments):
    d1, _, _ = experiments
    x0 = torch.tensor([0.5, 0.5], dtype=DT)
    single = torchql.fit(LinearOscillator(A=0.5, B=1.0), d1, x0=x0)
    stacked = torchql.fit(LinearOscillator(A=0.5, B=1.0), [d1], x0=x0.unsqueeze(0))
    assert single.success and stacked.success
    assert torch.allclose(stacked.estimates, single.estimates, rtol=1e-9, atol=1e-11)
    assert stacked.sse == pytest.approx(single.sse, abs=1e-18)


def test_fixed_states_and_state_bounds_apply_to_every_experiment(experiments):
    d1, d2, _ = experiments
    r = torchql.fit(LinearOscillator(A=0.5, B=1.0), [d1, d2], x0=torch.tensor([[0.0, 0.5], [1.0, 0.0]], dtype=DT),
                    fixed_x0=["y"], bounds={"v": (-2.0, 2.0), "A": (0.0, None)})
    assert r.success, r.message
    assert r.unknown_names == ["v[0](t0)", "v[1](t0)", "A", "B"]
    assert torch.allclose(r.x0, X0_TRUE, atol=1e-9)


@pytest.mark.parametrize("kwargs, error, match", [
    (dict(x0=torch.zeros(2)), ValueError, r"`x0` must have shape \(E, n_states\) = \(2, 2\)"),
    (dict(x0=torch.zeros(2, 2), t0=[0.0]), ValueError, r"`t0` must be one time or one per experiment"),
    (dict(x0=torch.zeros(2, 2), t0=[0.0, 3.0]), ValueError, r"not be later than each experiment's first"),
    (dict(x0=torch.zeros(2, 2), grid=torch.linspace(0, 1, 5)), ValueError, r"`grid` must be a number"),
])
def test_bad_arguments_with_several_experiments(experiments, kwargs, error, match):
    d1, d2, _ = experiments
    with pytest.raises(error, match=match):
        torchql.fit(LinearOscillator(), [d1, d2], **kwargs)


def test_bad_data_lists(experiments):
    d1, _, _ = experiments
    with pytest.raises(ValueError, match="empty list"):
        torchql.fit(LinearOscillator(), [], x0=torch.zeros(0, 2))
    with pytest.raises(TypeError, match=r"`data\[1\]` must be a torchql.Observations"):
        torchql.fit(LinearOscillator(), [d1, "data"], x0=torch.zeros(2, 2))
