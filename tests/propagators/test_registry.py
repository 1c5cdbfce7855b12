"""Linear propagators as objects behind a registry: names, objects, errors, and a user's own."""

import pytest
import torch

import torchql
from torchql.models import LinearOscillator
from torchql.propagators import (PROPAGATORS, LinearPropagator, RK4Doubling, TaylorSeries, Torchdiffeq,
                                 linear_propagator, register_propagator)
from torchql.taylor import taylor_transfers

DT = torch.float64
T = torch.arange(14, dtype=DT) * 0.5
X0 = torch.tensor([0.0, 1.0], dtype=DT)


def data():
    y = torchql.simulate(LinearOscillator(0.1, 3.0), X0, T)[:, :1]
    return torchql.Observations(T, y, observe=["y"])


def test_the_built_in_names_are_registered_and_resolve_to_their_objects():
    assert tuple(PROPAGATORS)[:7] == torchql.LINEAR_SOLVERS == ("taylor", "rk4_doubling", "torchdiffeq", "exponential",
                                                               "radau", "rodas5p", "taylor_quintic")
    assert isinstance(linear_propagator("taylor"), TaylorSeries)
    assert isinstance(linear_propagator("rk4_doubling"), RK4Doubling)
    assert isinstance(linear_propagator("torchdiffeq"), Torchdiffeq)
    own = TaylorSeries()
    assert linear_propagator(own) is own
    assert own == "taylor" and "taylor" == own and own == TaylorSeries() and own != RK4Doubling()
    assert not Torchdiffeq().grid_solver and TaylorSeries().grid_solver


def test_an_unknown_name_lists_the_valid_ones_and_a_wrong_type_says_what_is_accepted():
    with pytest.raises(ValueError, match=r"`linear_solver` must be one of \('taylor', 'rk4_doubling', 'torchdiffeq'"):
        linear_propagator("magic")
    with pytest.raises(TypeError, match=r"`linear_solver` must be a string.*LinearPropagator; received int"):
        linear_propagator(3)
    with pytest.raises(ValueError, match=r"`linear_solver` must be one of"):
        torchql.fit(LinearOscillator(0.5, 1.0), data(), x0=X0, linear_solver="magic")
    with pytest.raises(TypeError, match="`propagator` must be"):
        register_propagator("taylor")


@pytest.mark.parametrize("name", ["taylor", "rk4_doubling", "torchdiffeq"])
def test_a_name_and_its_object_give_the_same_fit(name):
    by_name = torchql.fit(LinearOscillator(0.5, 1.0), data(), x0=X0, linear_solver=name)
    by_object = torchql.fit(LinearOscillator(0.5, 1.0), data(), x0=X0, linear_solver=type(linear_propagator(name))())
    assert by_name.success and torch.equal(by_name.estimates, by_object.estimates)
    assert by_name.iterations == by_object.iterations
    # exact data, rtol 1e-10 over a well-conditioned problem: the truth to 1e-8
    assert torch.allclose(by_name.estimates, torch.tensor([0.0, 1.0, 0.1, 3.0], dtype=DT), atol=1e-8, rtol=0)


class CountingTaylor(LinearPropagator):
    """A user's propagator: the Taylor series, counting its calls (one new class, registered by name)."""

    name = "counting_taylor"

    def __init__(self):
        self.calls = 0

    def transfers(self, system, *, rtol, atol, solver, max_steps):
        self.calls += 1
        return taylor_transfers(system, rtol=rtol, atol=atol)


def test_a_users_propagator_is_used_by_fit_and_can_be_registered_by_name():
    mine = CountingTaylor()
    result = torchql.fit(LinearOscillator(0.5, 1.0), data(), x0=X0, linear_solver=mine)
    reference = torchql.fit(LinearOscillator(0.5, 1.0), data(), x0=X0)
    assert mine.calls >= result.iterations + 1  # every propagation went through it
    # the same series, per sample (a user's propagator) and batched (the built-in one): equal to rounding
    assert torch.allclose(result.estimates, reference.estimates, rtol=1e-12, atol=1e-15)
    register_propagator(mine)
    try:
        again = torchql.fit(LinearOscillator(0.5, 1.0), data(), x0=X0, linear_solver="counting_taylor")
        assert torch.equal(again.estimates, result.estimates)  # by name as by object
    finally:
        del PROPAGATORS["counting_taylor"]
