"""Several experiments sharing the coefficients, fitted as one stacked problem."""

import pytest
import torch

import torchql
from torchql import Parameter
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


class _Chain(torchql.ODEModel):
    """a -> b -> (out), the first rate scaled by a per-experiment multiplier."""

    state_names = ("a", "b")
    constants = ("mult",)

    def __init__(self, k1=1.0, k2=0.5, mult=1.0, s=1.0):
        super().__init__()
        for name, value in dict(k1=k1, k2=k2, mult=mult, s=s).items():
            self.register_buffer(name, torch.tensor(value, dtype=torch.float64))

    def forward(self, t, x):
        a, b = x.unbind(-1)
        r = self.k1 * self.mult * a
        return torch.stack((-r, r - self.k2 * b), dim=-1)


def _chain_experiments():
    t = torch.linspace(0, 8, 17, dtype=torch.float64)
    cases = [(1.0, [2.0, 0.1]), (2.5, [1.0, 0.6]), (0.0, [0.0, 1.1])]  # multiplier 1, s = 2.5, switched off
    datasets, x0 = [], []
    for mult, start in cases:
        state = torch.tensor(start, dtype=torch.float64)
        x = torchql.simulate(_Chain(0.7, 0.3, mult=mult), state, t, rtol=1e-12, atol=1e-14)
        datasets.append(torchql.Observations(t, x, observe=["a", "b"]))
        x0.append(state)
    return datasets, torch.stack(x0)


def test_conditions_set_constants_and_local_parameters_per_experiment():
    datasets, x0 = _chain_experiments()
    conditions = [{"mult": 1.0}, {"mult": "s"}, {"mult": 0.0}]
    guess = torch.ones(3, 2, dtype=torch.float64)
    guess[2, 0] = 0.0  # known: nothing of 'a' in the third experiment
    result = torchql.fit(_Chain(), datasets, x0=guess, conditions=conditions, fixed_x0=[[], [], ["a"]])
    assert result.success, result.message
    assert "a[2](t0)" not in result.unknown_names and "s" in result.unknown_names
    for name, value in {"k1": 0.7, "k2": 0.3, "s": 2.5}.items():
        assert float(result.params[name]) == pytest.approx(value, rel=1e-8)
    torch.testing.assert_close(result.x0, x0, rtol=0, atol=1e-8)
    t = torch.linspace(0, 3, 4, dtype=torch.float64)
    expected = torchql.simulate(_Chain(0.7, 0.3, mult=2.5), x0[1], t, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(result.predict(t, experiment=1), expected, rtol=0, atol=1e-7)
    assert float(result.experiment_model(2).mult) == 0.0 and float(result.experiment_model(1).mult) == pytest.approx(2.5)


def test_conditions_recover_the_truth_with_known_initial_states():
    datasets, x0 = _chain_experiments()
    conditions = [{"mult": 1.0}, {"mult": "s"}, {"mult": 0.0}]
    result = torchql.fit(_Chain(), datasets, x0=x0, conditions=conditions, fixed_x0=["a"])
    assert result.success, result.message
    for name, value in {"k1": 0.7, "k2": 0.3, "s": 2.5}.items():
        assert float(result.params[name]) == pytest.approx(value, rel=1e-8)
    assert "mult" not in result.unknown_names  # set in every experiment: not an unknown


@pytest.mark.parametrize("conditions, error, match", [
    ([{"mult": 1.0}], ValueError, "one dict per experiment \\(3\\); received 1 entries"),
    ([{"rate": 1.0}, {}, {}], ValueError, "`conditions\\[0\\]` names unknown coefficient 'rate'"),
    ([{}, {"mult": "q"}, {}], ValueError, "`conditions\\[1\\]\\['mult'\\]` = 'q' must name another coefficient"),
    ([{}, {}, {"mult": float("nan")}], ValueError, "must be finite"),
    ([{}, {}, {"mult": object()}], TypeError, "must be a number, a tensor of shape"),
    ([{}, 3, {}], TypeError, "`conditions\\[1\\]` must be a dict"),
])
def test_bad_conditions_are_named(conditions, error, match):
    datasets, x0 = _chain_experiments()
    with pytest.raises(error, match=match):
        torchql.fit(_Chain(), datasets, x0=x0, conditions=conditions)


def test_conditions_need_several_experiments_and_fixed_x0_lists_are_checked():
    datasets, x0 = _chain_experiments()
    with pytest.raises(ValueError, match="`conditions` applies to several experiments"):
        torchql.fit(_Chain(), datasets[0], x0=x0[0], conditions=[{}])
    with pytest.raises(ValueError, match="`fixed_x0\\[2\\]` names unknown state 'c'"):
        torchql.fit(_Chain(), datasets, x0=x0, fixed_x0=[[], [], ["c"]])


def _noisy(datasets, seed):
    g = torch.Generator().manual_seed(seed)
    return [torchql.Observations(d.t, d.y + 1e-3 * torch.randn(d.y.shape, generator=g, dtype=DT), observe=d.observe)
            for d in datasets]


def test_fit_many_fits_several_experiments_per_sample_as_fit_does():
    """Three samples of the three chain experiments (one exact, two noisy), the conditions shared, each
    sample's own guesses: every sample's result equals ``fit`` on its experiments alone."""
    datasets, x0 = _chain_experiments()
    samples = [datasets, _noisy(datasets, 1), _noisy(datasets, 2)]
    conditions = [{"mult": 1.0}, {"mult": "s"}, {"mult": 0.0}]
    guesses = torch.stack([x0, 1.1 * x0, 0.9 * x0])
    batch = torchql.fit_many(_Chain(), samples, x0=guesses, conditions=conditions, fixed_x0=["a"])
    assert batch.x0.shape == (3, 3, 2) and batch.experiment_t0 == [0.0, 0.0, 0.0]
    for b, sample in enumerate(samples):
        one = torchql.fit(_Chain(), sample, x0=guesses[b], conditions=conditions, fixed_x0=["a"])
        assert batch.status[b] is one.status and int(batch.iterations[b]) == one.iterations
        torch.testing.assert_close(batch.estimates[b], one.estimates, rtol=1e-9, atol=1e-12)
        assert float(batch.sse[b]) == pytest.approx(one.sse, rel=1e-8, abs=1e-20)
        torch.testing.assert_close(batch[b].covariance, one.covariance, rtol=1e-6, atol=1e-20)
    assert float(batch.params["s"][0]) == pytest.approx(2.5, rel=1e-8)
    t = torch.linspace(0, 3, 4, dtype=DT)
    torch.testing.assert_close(batch[0].predict(t, experiment=1),
                               torchql.simulate(_Chain(0.7, 0.3, mult=2.5), x0[1], t, rtol=1e-12, atol=1e-14),
                               rtol=0, atol=1e-7)


def test_fit_many_with_several_experiments_names_bad_samples():
    datasets, x0 = _chain_experiments()
    conditions = [{"mult": 1.0}, {"mult": "s"}, {"mult": 0.0}]
    with pytest.raises(ValueError, match="`data\\[1\\]` holds 2 experiments but `data\\[0\\]` holds 3"):
        torchql.fit_many(_Chain(), [datasets, datasets[:2]], x0=x0, conditions=conditions)
    later = [datasets[0], torchql.Observations(datasets[1].t + 0.1, datasets[1].y, observe=["a", "b"]), datasets[2]]
    with pytest.raises(ValueError, match="`data\\[1\\]\\[1\\]` has other times than `data\\[0\\]\\[1\\]`"):
        torchql.fit_many(_Chain(), [datasets, later], x0=x0, conditions=conditions)
    # each experiment observes the same states, with the same noise model, in every sample
    d1 = datasets[1]
    for other, match in ((torchql.Observations(d1.t, d1.y.flip(-1), observe=["b", "a"]), "observes something else"),
                         (torchql.Observations(d1.t, d1.y, observe=["a", "b"], sigma=0.1), "gives `sigma` but"),
                         (torchql.Observations(d1.t, d1.y, observe=["a", "b"], noise="lognormal"),
                          "has another noise model")):
        with pytest.raises(ValueError, match=f"`data\\[1\\]\\[1\\]` {match}.*`data\\[0\\]\\[1\\]`"):
            torchql.fit_many(_Chain(), [datasets, [datasets[0], other, datasets[2]]], x0=x0, conditions=conditions)
    with pytest.raises(ValueError, match="`conditions` apply to several experiments per sample"):
        torchql.fit_many(_Chain(), datasets, x0=x0, conditions=conditions)
    with pytest.raises(ValueError, match="\\(B, E, n_states\\) with B = 2"):
        torchql.fit_many(_Chain(), [datasets, datasets], x0=torch.stack([x0] * 3), conditions=conditions)


def test_parameters_keep_a_coefficient_replaced_in_every_experiment_out_of_the_unknowns():
    """``parameters=`` gives the fit its keywords stand for: ``mult``, replaced in every experiment,
    stays out of the unknowns as with the keywords (it was made an unknown that nothing reads, and
    the fit, otherwise the same, said NOT_IDENTIFIABLE), in ``fit`` and in ``fit_many``."""
    class Chain(_Chain):
        constants = ()  # mult is held by the conditions alone

    datasets, x0 = _chain_experiments()
    conditions = [{"mult": 1.0}, {"mult": "s"}, {"mult": 0.0}]
    keywords = torchql.fit(Chain(k2=0.3), datasets, x0=x0, conditions=conditions, fixed_x0=["a"], params=["k1", "s"])
    given = torchql.fit(Chain(), datasets, x0=x0, conditions=conditions, fixed_x0=["a"],
                        parameters={"k2": Parameter(0.3, vary=False)})
    assert given.status is keywords.status is torchql.Status.CONVERGED, given.message
    assert given.unknown_names == keywords.unknown_names and "mult" not in given.unknown_names
    torch.testing.assert_close(given.estimates, keywords.estimates, rtol=1e-12, atol=0)
    batch = torchql.fit_many(Chain(), [datasets, datasets], x0=x0, conditions=conditions, fixed_x0=["a"],
                             parameters={"k2": Parameter(0.3, vary=False)})
    assert all(batch[i].status is torchql.Status.CONVERGED and batch[i].unknown_names == keywords.unknown_names
               for i in range(2))


def test_a_one_output_observe_function_may_return_a_scalar_in_every_experiment():
    """``observe`` of one output may return a scalar (as for one dataset); stacked, each experiment's is
    made shape (1,) before they are joined (a zero-dimensional output crashed the concatenation)."""
    t = torch.arange(14, dtype=DT) * 0.5
    data = [torchql.Observations(t, simulate(x0, t)[:, :1], observe=lambda x: x[0]) for x0 in X0_TRUE]
    by_name = [torchql.Observations(d.t, d.y, observe=["y"]) for d in data]
    guess = torch.tensor([[0.1, 0.8], [0.8, -0.2]], dtype=DT)
    r = torchql.fit(LinearOscillator(A=0.3, B=2.0), data, x0=guess)
    named = torchql.fit(LinearOscillator(A=0.3, B=2.0), by_name, x0=guess)
    assert r.success, r.message
    assert torch.allclose(r.x0, X0_TRUE, atol=1e-8) and abs(r.params["B"].item() - 3.0) < 1e-8
    assert torch.allclose(r.estimates, named.estimates, rtol=1e-9, atol=1e-12)


def test_a_failing_observe_function_is_named_with_its_experiment_and_state_shape():
    t = torch.arange(14, dtype=DT) * 0.5
    y = simulate(X0_TRUE[0], t)[:, :1]
    data = [torchql.Observations(t, y, observe=["y"]), torchql.Observations(t, y, observe=lambda x: x[5])]
    with pytest.raises(ValueError, match=r"`observe` callable of experiment 1 failed on a state of shape \(2,\): "
                                         r"IndexError"):
        torchql.fit(LinearOscillator(A=0.3, B=2.0), data, x0=X0_TRUE.clone())
