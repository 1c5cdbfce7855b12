"""``fit_many(..., bounds=...)``: each sample is the bounded ``torchql.fit`` of that dataset alone."""

import pytest
import torch

import torchql
from testmodels import SIR
from torchql.models import BranchedReactions, LinearOscillator

DT = torch.float64
RATES = {"k1": 0.9, "k2": 0.4, "k3": 0.25}
POSITIVE_RATES = {"k1": (0.0, None), "k2": (0.0, None), "k3": (0.0, None)}
K_X0 = torch.tensor([1.0, 0.0, 0.0], dtype=DT)


def assert_sample_is_the_fit(sample, single, rel=1e-8, same_path=True):
    """Statuses, messages and iteration counts identical; estimates and SSE to ``rel``: both run
    the same iteration, the batch with batched integrators (1e-10 rtol), so 1e-8 leaves margin."""
    assert sample.status is single.status, (sample.message, single.message)
    if same_path:
        assert sample.message == single.message
        assert sample.iterations == single.iterations
    assert sample.moved_guesses == single.moved_guesses
    assert torch.equal(sample.lower, single.lower) and torch.equal(sample.upper, single.upper)
    assert torch.allclose(sample.estimates, single.estimates, rtol=rel, atol=1e-14)
    assert sample.sse == pytest.approx(single.sse, rel=1e-6, abs=1e-20)


def test_rates_on_and_inside_their_bound_as_single_fits():
    """Three-rate kinetics, every rate bounded below by 0: one sample guessed on the bound (moved
    to 1e-3, as ``fit`` moves it), one inside; exact data, so both end at the truth (1e-8)."""
    t = torch.arange(21, dtype=DT) * 0.5
    x = torchql.simulate(BranchedReactions(**RATES), K_X0, t, rtol=1e-13, atol=1e-15)
    data = torchql.Observations(t, x, observe=["A", "B", "C"])
    guesses = {k: torch.tensor([0.0, 0.5], dtype=DT) for k in RATES}
    batch = torchql.fit_many(BranchedReactions(), [data, data], K_X0, guesses=guesses, bounds=POSITIVE_RATES)
    singles = [torchql.fit(BranchedReactions(g, g, g), data, K_X0, bounds=POSITIVE_RATES) for g in (0.0, 0.5)]
    for b in range(2):
        assert_sample_is_the_fit(batch[b], singles[b])
        assert max(abs(batch[b].params[k].item() - v) / v for k, v in RATES.items()) < 1e-8
    assert batch.moved_guesses == {0: {"k1": (0.0, 1e-3), "k2": (0.0, 1e-3), "k3": (0.0, 1e-3)}}
    assert "were moved inside" in batch.message[0] and "moved" not in batch.message[1]
    assert torch.equal(guesses["k1"], torch.tensor([0.0, 0.5], dtype=DT))  # the user's guesses untouched


def test_optimum_on_a_bound_named_per_sample():
    """Damping A >= 0.2 where the data say A = 0.1: that sample's estimate ends at the bound and
    its message names it; a sample whose optimum is inside does not."""
    t = torch.arange(14, dtype=DT) * 0.5
    ys = [torchql.simulate(LinearOscillator(A, 3.0), torch.tensor([0.0, 1.0], dtype=DT), t, rtol=1e-13,
                           atol=1e-15)[:, :1] for A in (0.1, 0.5)]
    data = torchql.Observations(t, torch.stack(ys), observe=["y"])
    x0 = torch.tensor([0.5, 0.5], dtype=DT)
    options = dict(bounds={"A": (0.2, None)})
    batch = torchql.fit_many(LinearOscillator(A=0.5, B=1.0), data, x0, **options)
    singles = [torchql.fit(LinearOscillator(A=0.5, B=1.0), data[b], x0, **options) for b in range(2)]
    for b in range(2):
        assert_sample_is_the_fit(batch[b], singles[b], rel=1e-7)
    assert "['A'] lie at their bounds" in batch.message[0] and "bounds" not in batch.message[1]
    assert 0.2 < float(batch.params["A"][0]) <= 0.2 * (1 + 1e-12)
    assert float(batch.params["A"][1]) == pytest.approx(0.5, rel=1e-8)


def test_sir_with_three_positive_bounds_batched():
    """SIR with beta, gamma and I(t0) bounded below by 0, from (3, 1, 0.5): the case whose capped
    steps once ended far from the optimum in ``fit`` (tests/test_bounds.py); batched, exact and
    noisy data reach the truth and what the single fit reaches. Not by the same path: a trial step to I(t0) = 40,
    whose model solution the batch integrates (its SSE is lower: accepted), is taken by ``fit`` for a
    blow-up (its grid solver's step budget is exceeded: rejected); measured 11 against 7 iterations
    on the exact data."""
    t = torch.arange(14, dtype=DT)
    x = torchql.simulate(SIR(), torch.tensor([762.0, 1.0, 0.0], dtype=DT), t, rtol=1e-12, atol=1e-12)
    noise = torch.randn(14, 1, generator=torch.Generator().manual_seed(0), dtype=DT)
    data = torchql.Observations(t, torch.stack([x[:, 1:2], x[:, 1:2] * (1 + 0.03 * noise)]), observe=["I"])
    x0 = torch.tensor([762.0, 0.5, 0.0], dtype=DT)
    bounds = {"beta": (0, None), "gamma": (0, None), "I": (0, None)}
    options = dict(fixed_x0=["S", "R"], bounds=bounds, max_iter=100)
    batch = torchql.fit_many(SIR(3.0, 1.0), data, x0, **options)
    assert_sample_is_the_fit(batch[1], torchql.fit(SIR(3.0, 1.0), data[1], x0, **options), rel=1e-7, same_path=False)
    assert batch.success.all(), batch.summary()
    assert torch.allclose(batch.estimates[0], torch.tensor([1.0, 1.66, 0.44], dtype=DT), rtol=1e-8, atol=0)


def test_bad_bounds_are_named_by_fit_many():
    t = torch.arange(5, dtype=DT)
    data = torchql.Observations(t, torch.ones(2, 5, 1, dtype=DT), observe=["y"])
    with pytest.raises(ValueError, match="`bounds` names unknown 'Q'"):
        torchql.fit_many(LinearOscillator(), data, torch.tensor([1.0, 0.0], dtype=DT), bounds={"Q": (0, 1)})
    with pytest.raises(ValueError, match=r"`bounds\['A'\]` needs lower < upper"):
        torchql.fit_many(LinearOscillator(), data, torch.tensor([1.0, 0.0], dtype=DT), bounds={"A": (1, 0)})
