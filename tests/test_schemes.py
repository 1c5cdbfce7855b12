"""Iteration schemes as objects: the registered names, a scheme passed as an object, a new scheme."""

import pytest
import torch

import torchql
import torchql.schemes as schemes_module
from torchql.models import LinearOscillator
from torchql.schemes import METHODS, Kantorovich, Scheme, Shooting, register_scheme, scheme_strategy

DT = torch.float64
X0_GUESS = torch.tensor([0.5, 0.5], dtype=DT)


@pytest.fixture(scope="module")
def oscillator_data():
    """The thesis' linear oscillator (A = 0.1, B = 3, y(0) = 0, y'(0) = 1), 14 exact positions."""
    t = torch.arange(14, dtype=DT) * 0.5
    x = torchql.simulate(LinearOscillator(A=0.1, B=3.0), torch.tensor([0.0, 1.0], dtype=DT), t, rtol=1e-13,
                         atol=1e-15)
    return torchql.Observations(t, x[:, :1], observe=["y"])


def test_registered_names_and_errors():
    assert METHODS == ("kantorovich", "shooting") == torchql.METHODS
    assert isinstance(scheme_strategy("kantorovich"), Kantorovich)
    assert scheme_strategy("shooting").integrates_model and not scheme_strategy("kantorovich").integrates_model
    with pytest.raises(ValueError, match=r"`method` must be one of \('kantorovich', 'shooting'\); received 'newton'"):
        scheme_strategy("newton")
    with pytest.raises(TypeError, match="`method` must be a string, one of .* or a torchql.schemes.Scheme; received int"):
        scheme_strategy(1)
    with pytest.raises(TypeError, match="must be a torchql.schemes.Scheme; received str"):
        register_scheme("kantorovich")


@pytest.mark.parametrize("name, scheme", [("kantorovich", Kantorovich()), ("shooting", Shooting())])
def test_a_scheme_object_is_its_name(oscillator_data, name, scheme):
    by_name = torchql.fit(LinearOscillator(A=0.5, B=1.0), oscillator_data, X0_GUESS, method=name)
    by_object = torchql.fit(LinearOscillator(A=0.5, B=1.0), oscillator_data, X0_GUESS, method=scheme)
    assert by_name.success and by_object.method == name
    assert torch.equal(by_name.estimates, by_object.estimates) and by_name.iterations == by_object.iterations
    truth = torch.tensor([0.0, 1.0, 0.1, 3.0], dtype=DT)
    assert torch.allclose(by_object.estimates, truth, rtol=0, atol=1e-8)


def test_a_new_scheme_drives_fit_and_fit_many(oscillator_data, monkeypatch):
    """A subclass (Kantorovich that counts its trials) registered by name: fit and fit_many use its
    trials; a scheme whose iterates solve the model takes the data-built start as shooting does."""
    monkeypatch.setattr(schemes_module._REGISTRY, "entries", dict(schemes_module._REGISTRY.entries))  # leave the registry as found

    class Counting(Kantorovich):
        name = "counting"

        def __init__(self):
            self.trials = 0

        def trial(self, engine, act, cur, z0_new, z_new):
            self.trials += act.numel()
            return super().trial(engine, act, cur, z0_new, z_new)

    counting = register_scheme(Counting())
    single = torchql.fit(LinearOscillator(A=0.5, B=1.0), oscillator_data, X0_GUESS, method="counting")
    plain = torchql.fit(LinearOscillator(A=0.5, B=1.0), oscillator_data, X0_GUESS)
    # every iteration but the converged last (whose step is taken without a trial) is a trial of the scheme
    assert single.method == "counting" and counting.trials >= single.iterations - 1 >= 1
    assert torch.equal(single.estimates, plain.estimates)
    counting.trials = 0
    batch = torchql.fit_many(LinearOscillator(A=0.5, B=1.0), [oscillator_data] * 3, X0_GUESS, method=counting)
    assert counting.trials >= int(batch.iterations.sum()) - 3 >= 3
    assert batch[0].method == "counting"  # the name, as fit reports it
    assert torch.allclose(batch.estimates, single.estimates.expand(3, -1), rtol=1e-10, atol=1e-14)

    class Integrating(Shooting):
        name = "integrating"

    # a scheme whose iterates solve the model starts from the model integrated from the data's start
    own = torchql.fit(LinearOscillator(A=0.5, B=1.0), oscillator_data, X0_GUESS, method=Integrating(),
                      initial_trajectory="data")
    shooting = torchql.fit(LinearOscillator(A=0.5, B=1.0), oscillator_data, X0_GUESS, method="shooting",
                           initial_trajectory="data")
    assert own.success and torch.equal(own.estimates, shooting.estimates) and own.iterations == shooting.iterations
    assert isinstance(scheme_strategy(Integrating()), Scheme)


def test_a_shooting_trial_stops_integrating_once_it_cannot_be_accepted(monkeypatch):
    """The thesis' nonlinear oscillator (66 exact positions) by shooting from poor guesses: a
    damped trial whose grid solve fails goes to Dormand–Prince, which stops it once its sum of
    squares over the data passed exceeds the current iterate's (1,078 steps integrated whole, 259
    stopped). The fit is the one that integrates every trial whole, to the bit, with fewer
    evaluations; and each fit_many sample is its fit."""
    from torchql import engine_evaluate
    from torchql.models import NonlinearOscillator
    t = torch.arange(66, dtype=DT) * 0.1
    x = torchql.simulate(NonlinearOscillator(), torch.tensor([0.0, 1.0], dtype=DT), t, rtol=1e-13, atol=1e-15)
    data = torchql.Observations(t, x[:, :1], observe=["y"])

    solver = engine_evaluate.dopri_batch

    def fit():  # and the Dormand–Prince evaluations it took
        counted = []

        def counting(*args, **kwargs):
            out = solver(*args, **kwargs)
            counted.append(out[2])
            return out
        monkeypatch.setattr(engine_evaluate, "dopri_batch", counting)
        return torchql.fit(NonlinearOscillator(0.5, 2.0, 0.5, 2.0), data, X0_GUESS, method="shooting"), sum(counted)
    stopping, stopping_evals = fit()
    monkeypatch.setattr(engine_evaluate, "STOP_EARLY", False)
    whole, whole_evals = fit()
    assert stopping.success and stopping.status == whole.status and stopping.iterations == whole.iterations
    assert torch.equal(stopping.estimates, whole.estimates) and stopping.sse == whole.sse
    assert stopping_evals < 0.6 * whole_evals, (stopping_evals, whole_evals)
    truth = torch.tensor([0.0, 1.0, 0.1, 3.0, 0.2, 4.0], dtype=DT)
    assert float((stopping.estimates - truth).abs().max()) < 1e-8
    monkeypatch.setattr(engine_evaluate, "STOP_EARLY", True)
    batch = torchql.fit_many(NonlinearOscillator(0.5, 2.0, 0.5, 2.0), [data, data], X0_GUESS.expand(2, 2),
                             method="shooting")
    for k in range(2):
        assert batch[k].iterations == stopping.iterations and batch[k].status == stopping.status
        assert torch.allclose(batch[k].estimates, stopping.estimates, rtol=0, atol=1e-10)


def test_a_kantorovich_second_opinion_stops_integrating_once_the_trial_cannot_be_accepted(monkeypatch):
    """The thesis' nonlinear oscillator (31 exact positions) by Kantorovich from far guesses and
    its integrated start: a trial iterate that the particular solutions cannot decide gets the
    model's own sum of squares as a second opinion, by Dormand–Prince (a non-stiff model), which
    stops it once its sum over the data passed exceeds the current iterate's. The fit is the one
    that integrates every second opinion whole, to the bit, with fewer evaluations."""
    from torchql import engine_evaluate
    from torchql.models import NonlinearOscillator
    t = torch.linspace(0.0, 6.0, 31, dtype=DT)
    x0 = torch.tensor([0.0, 1.0], dtype=DT)
    x = torchql.simulate(NonlinearOscillator(0.1, 3.0, 0.2, 4.0), x0, t, rtol=1e-13, atol=1e-15)
    data = torchql.Observations(t, x[:, :1], observe=["y"])
    solver = engine_evaluate.dopri_batch

    def fit():  # and the Dormand–Prince evaluations it took, and how many samples a stop test ended
        evaluations, stopped = [], []

        def counting(*args, **kwargs):
            out = solver(*args, **kwargs)
            evaluations.append(out[2])
            if kwargs.get("stop") is not None:
                stopped.append(int((~out[1]).sum()))
            return out
        monkeypatch.setattr(engine_evaluate, "dopri_batch", counting)
        result = torchql.fit(NonlinearOscillator(1.0, 1.0, 1.0, 1.0), data, x0, method="kantorovich",
                             initial_trajectory="integrate")
        return result, sum(evaluations), sum(stopped)
    stopping, stopping_evals, ended = fit()
    monkeypatch.setattr(engine_evaluate, "STOP_EARLY", False)
    whole, whole_evals, _ = fit()
    assert ended >= 1  # a second opinion was cut short
    assert stopping.success and stopping.status == whole.status and stopping.iterations == whole.iterations
    assert torch.equal(stopping.estimates, whole.estimates) and stopping.sse == whole.sse
    assert stopping_evals < 0.7 * whole_evals, (stopping_evals, whole_evals)
    truth = torch.tensor([0.0, 1.0, 0.1, 3.0, 0.2, 4.0], dtype=DT)
    assert float((stopping.estimates - truth).abs().max()) < 1e-8
