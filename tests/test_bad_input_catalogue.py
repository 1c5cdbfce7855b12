"""Every bad input and every failure a user can provoke, in one catalogue.

Each case either raises at the public entry point (TypeError/ValueError naming the argument,
what was expected and what was received) or returns an unsuccessful FitResult whose status and
message say what happened and what to do. Nothing crashes with anything else.
"""

import math

import pytest
import torch

import torchql
from testmodels import Decay
from torchql.baselines import adjoint_fit

DT = torch.float64
T = torch.linspace(0, 2, 11, dtype=DT)
Y = (1.5 * torch.exp(-0.7 * T)).unsqueeze(-1)


def data(**kwargs):
    return torchql.Observations(T, Y, observe=["y"], **kwargs)


class NaNAfterOne(torchql.ODEModel):
    """``y' = -k y`` that returns NaN for t > 1 (a model failing mid-integration)."""

    state_names = ("y",)

    def __init__(self, k=0.5):
        super().__init__()
        self.register_buffer("k", torch.tensor(k, dtype=DT))

    def forward(self, t, x):
        return torch.where(t > 1.0, torch.full_like(x, math.nan), -self.k * x)


X0 = torch.tensor([1.0], dtype=DT)
RAISES = [
    ("NaN time", lambda: torchql.Observations(T.clone().index_fill_(0, torch.tensor([3]), math.nan), Y, observe=["y"]),
     ValueError, r"`t`"),
    ("inf value", lambda: torchql.Observations(T, Y.clone().index_fill_(0, torch.tensor([3]), math.inf), observe=["y"]),
     ValueError, r"`y`"),
    ("unsorted times", lambda: torchql.Observations(T.flip(0), Y, observe=["y"]), ValueError, r"`t`"),
    ("sigma zero", lambda: data(sigma=0.0), ValueError, r"`sigma`"),
    ("sigma negative", lambda: data(sigma=-1.0), ValueError, r"`sigma`"),
    ("NaN in x0", lambda: torchql.fit(Decay(0.3), data(), torch.tensor([math.nan], dtype=DT)), ValueError, r"`x0`"),
    ("inf in x0", lambda: torchql.fit(Decay(0.3), data(), torch.tensor([math.inf], dtype=DT)), ValueError, r"`x0`"),
    ("NaN guess of a coefficient", lambda: torchql.fit(Decay(math.nan), data(), X0), ValueError, r"guesses of \['k'\]"),
    ("x0 of the wrong shape", lambda: torchql.fit(Decay(0.3), data(), torch.zeros(2, dtype=DT)), ValueError, r"`x0`"),
    ("data not Observations", lambda: torchql.fit(Decay(0.3), (T, Y), X0), TypeError, r"`data"),
    ("bounds lower >= upper", lambda: torchql.fit(Decay(0.3), data(), X0, bounds={"k": (1.0, 0.1)}), ValueError,
     r"`bounds\['k'\]` needs lower < upper"),
    ("bounds lower == upper", lambda: torchql.fit(Decay(0.3), data(), X0, bounds={"k": (0.5, 0.5)}), ValueError,
     r"`bounds\['k'\]` needs lower < upper; received \(0.5, 0.5\), a fixed value: fix it instead .*`params=`"),
    ("NaN bound", lambda: torchql.fit(Decay(0.3), data(), X0, bounds={"k": (math.nan, None)}), ValueError,
     r"`bounds\['k'\]` lower bound is NaN"),
    ("bound on an unknown name", lambda: torchql.fit(Decay(0.3), data(), X0, bounds={"q": (0, 1)}), ValueError,
     r"`bounds` names unknown 'q'"),
    ("more exact values than unknowns",
     lambda: torchql.fit(Decay(0.3), data(exact=torch.ones(11, dtype=torch.bool)), X0), ValueError, r"`exact`"),
    ("fewer observations than unknowns",
     lambda: torchql.fit(Decay(0.3), torchql.Observations(T[:1], Y[:1], observe=["y"]), X0), ValueError,
     r"fewer usable observations"),
    ("negative rtol", lambda: torchql.fit(Decay(0.3), data(), X0, rtol=-1e-8), ValueError, r"`rtol`"),
    ("unknown method", lambda: torchql.fit(Decay(0.3), data(), X0, method="newton"), ValueError, r"`method`"),
    ("unknown solver", lambda: torchql.fit(Decay(0.3), data(), X0, solver="rk45"), ValueError, r"`solver`"),
    ("unknown linear solver", lambda: torchql.fit(Decay(0.3), data(), X0, linear_solver="magic"), ValueError,
     r"`linear_solver`"),
    ("unknown damping", lambda: torchql.fit(Decay(0.3), data(), X0, damping="trust"), ValueError, r"`damping`"),
    ("empty list of experiments", lambda: torchql.fit(Decay(0.3), [], X0), ValueError, r"`data`"),
    ("a batch of datasets given to fit",
     lambda: torchql.fit(Decay(0.3), torchql.Observations(T, Y.expand(3, -1, -1), observe=["y"]), X0), ValueError,
     r"`data` holds a batch of 3 .*torchql.fit_many"),
    ("a batch among experiments",
     lambda: torchql.fit(Decay(0.3), [data(), torchql.Observations(T, Y.expand(2, -1, -1), observe=["y"])], X0),
     ValueError, r"`data\[1\]` holds a batch"),
    ("a batch of datasets given to adjoint_fit",
     lambda: adjoint_fit(Decay(0.3), torchql.Observations(T, Y.expand(3, -1, -1), observe=["y"]), x0=X0), ValueError,
     r"`data` holds a batch.*torchql.fit_many"),
]


@pytest.mark.parametrize("case, call, error, match", RAISES, ids=[c[0] for c in RAISES])
def test_bad_input_raises_naming_the_argument(case, call, error, match):
    with pytest.raises(error, match=match):
        call()


def _contradictory_exact():
    """The same state measured twice at t0, both values exact and different: no iterate meets both."""
    y = torch.stack([Y[:, 0], Y[:, 0]], dim=1)
    y[0, 1] += 0.1
    exact = torch.zeros(11, 2, dtype=torch.bool)
    exact[0] = True
    return torchql.fit(Decay(0.3), torchql.Observations(T, y, observe=["y", "y"], exact=exact), X0)


FAILS = [
    ("exact values that contradict each other", _contradictory_exact, torchql.Status.EXACT_INFEASIBLE, r"exact"),
    ("model returns NaN mid-integration", lambda: torchql.fit(NaNAfterOne(), data(), X0),
     torchql.Status.INTEGRATION_FAILED, r"ODE solver failed"),
    ("integrator exceeds its step budget", lambda: torchql.fit(Decay(0.3), data(), X0, max_steps=1, grid=1),
     torchql.Status.INTEGRATION_FAILED, r"max_num_steps|step"),
    ("iteration budget exhausted", lambda: torchql.fit(Decay(0.3), data(), X0, max_iter=1),
     torchql.Status.MAX_ITER, r"Increase `max_iter`"),
]


@pytest.mark.parametrize("case, call, status, match", FAILS, ids=[c[0] for c in FAILS])
def test_failure_is_a_status_with_an_actionable_message(case, call, status, match):
    result = call()
    assert not result.success
    assert result.status is status, result.message
    assert __import__("re").search(match, result.message), result.message
    with pytest.raises(torchql.FitError):
        raise torchql.FitError(result)
