"""compare: a fitted model on validation data, its fit percentage (NRMSE) and plot."""

import matplotlib

matplotlib.use("Agg")

import pytest  # noqa: E402
import torch  # noqa: E402

import torchql  # noqa: E402
from torchql.compare import fit_percent  # noqa: E402
from torchql.models import DrivenOscillator  # noqa: E402

from test_fit_inputs import GUESS_X0, force, measured  # noqa: E402

DT = torch.float64


def test_fit_percent_is_the_nrmse_fit():
    y = torch.tensor([[1.0, 2.0], [2.0, float("nan")], [4.0, 6.0]], dtype=DT)
    predicted = torch.tensor([[1.5, 2.0], [2.0, 0.0], [3.5, 5.0]], dtype=DT)
    mean0 = 7.0 / 3
    expected0 = 100 * (1 - (0.25 + 0.25) ** 0.5 / ((1 - mean0) ** 2 + (2 - mean0) ** 2 + (4 - mean0) ** 2) ** 0.5)
    expected1 = 100 * (1 - 1.0 / (2.0**2 + 2.0**2) ** 0.5)  # the NaN skipped
    torch.testing.assert_close(fit_percent(y, predicted), torch.tensor([expected0, expected1], dtype=DT))
    assert fit_percent(y, y)[0] == 100.0
    assert torch.isnan(fit_percent(torch.ones(3, 1, dtype=DT), torch.zeros(3, 1, dtype=DT)))[0]


def test_compare_on_a_second_input_signal():
    result = torchql.fit(DrivenOscillator(), measured(force(1), noise=0.02, seed=3), x0=GUESS_X0)
    validation = measured(force(4), noise=0.02, seed=9)
    comparison = torchql.compare(result, validation)
    # the model is right and its coefficients are within their errors: the fit percentage is limited by
    # the noise alone, 100 (1 - 0.02 / rms spread of the positions)
    spread = (validation.y - validation.y.mean()).norm() / validation.y.numel() ** 0.5
    ceiling = 100 * (1 - 0.02 / float(spread))
    assert ceiling - 3 < float(comparison.fit_percent[0]) <= 100
    assert comparison.output_names == ["y"] and comparison.predicted.shape == (41, 1)
    # the same model with the wrong stiffness does much worse
    wrong = torchql.fit(DrivenOscillator(), measured(force(1), noise=0.02, seed=3), x0=GUESS_X0, params=["c"])
    assert float(torchql.compare(wrong, validation).fit_percent[0]) < float(comparison.fit_percent[0]) - 20
    fig, axes = comparison.plot()
    assert len(axes) == 1 and "fit" in axes[0].get_legend().get_texts()[1].get_text()
    assert "y: " in repr(comparison)


def test_compare_from_a_given_initial_state():
    result = torchql.fit(DrivenOscillator(), measured(force(1)), x0=GUESS_X0)
    x0 = torch.tensor([-0.3, 0.2], dtype=DT)
    times = torch.linspace(2, 10, 25, dtype=DT)
    validation = measured(force(4), x0=x0, times=times)
    assert float(torchql.compare(result, validation, x0=x0).fit_percent[0]) > 99.999
    assert float(torchql.compare(result, validation).fit_percent[0]) < 99  # the fit's own x0 at t0 = 0
    import pickle  # a comparison pickles, its curve with it (a closure did not)

    comparison = torchql.compare(result, validation, x0=x0)
    again = pickle.loads(pickle.dumps(comparison))
    torch.testing.assert_close(again.curve(times), comparison.predicted, rtol=0, atol=0)
    assert repr(again) == repr(comparison)


def test_compare_refuses_what_it_cannot_compare():
    first, second = measured(force(1)), measured(force(4))
    result = torchql.fit(DrivenOscillator(), [first, second], x0=torch.zeros(2, 2, dtype=DT))
    with pytest.raises(ValueError, match="`experiment` must be an index 0..1"):
        torchql.compare(result, second)
    assert float(torchql.compare(result, second, experiment=1).fit_percent[0]) > 99.999
    batch = torchql.Observations(first.t, torch.stack([first.y, second.y]), observe=["y"])
    with pytest.raises(TypeError, match="one torchql.Observations \\(a validation experiment\\); received a batch"):
        torchql.compare(result, batch)
    one = torchql.fit(DrivenOscillator(), first, x0=torch.zeros(2, dtype=DT))
    with pytest.raises(ValueError, match="`experiment` applies only to fits of several experiments; received 7"):
        torchql.compare(one, second, experiment=7)  # as predict says; it was ignored
    with pytest.raises(TypeError, match="`result` must be a torchql.FitResult; received str"):
        torchql.compare("not a result", second)


def test_validation_data_without_their_inputs_are_refused():
    """The fitted model still holds the training signal; validation data that carry no inputs of their
    own would be simulated with it, silently. An error as ``fit`` gives, naming the inputs."""
    result = torchql.fit(DrivenOscillator(), measured(force(1)), x0=GUESS_X0)
    bare = torchql.Observations(measured(force(4)).t, measured(force(4)).y, observe=["y"])
    with pytest.raises(ValueError, match=r"`model` takes inputs \('u',\) .* but `data` carries none"):
        torchql.compare(result, bare)


class _Decay(torchql.ODEModel):
    """``y' = -k y``, with two more coefficients ``k_a``, ``k_b`` for experiments' ``conditions``."""

    state_names = ("y",)

    def __init__(self, k: float = 1.0) -> None:
        super().__init__()
        for name in ("k", "k_a", "k_b"):
            self.register_buffer(name, torch.tensor(k, dtype=DT))

    def forward(self, t, x):
        return -self.k * x


def test_with_an_initial_state_a_fit_whose_experiments_have_their_own_coefficients_needs_experiment():
    """Two decays fitted with ``conditions`` (``k`` is ``k_a`` in one, ``k_b`` in the other): given an
    ``x0``, comparing without ``experiment`` is an error (it simulated the model's ``k``, the guess,
    never fitted: 42 %); with it, each experiment's own rate fits its data exactly. Without
    conditions the experiments share one model and need no index."""
    t = torch.linspace(0, 3, 16, dtype=DT)
    one = torch.ones(1, dtype=DT)
    data = [torchql.Observations(t, torchql.simulate(_Decay(k), one, t), observe=["y"]) for k in (0.5, 2.0)]
    result = torchql.fit(_Decay(1.0), data, x0=torch.ones(2, 1, dtype=DT), params=["k_a", "k_b"],
                         conditions=[{"k": "k_a"}, {"k": "k_b"}])
    assert result.success
    with pytest.raises(ValueError, match="`experiment` must be an index 0..1 .* when its `conditions` give"):
        torchql.compare(result, data[1], x0=one)
    for e in (0, 1):
        assert float(torchql.compare(result, data[e], x0=one, experiment=e).fit_percent[0]) > 99.9999
    shared = torchql.fit(_Decay(1.0), data[:1] * 2, x0=torch.ones(2, 1, dtype=DT), params=["k"])
    assert float(torchql.compare(shared, data[0], x0=one).fit_percent[0]) > 99.9999
