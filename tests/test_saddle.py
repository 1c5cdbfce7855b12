"""Leaving a saddle (torchql/saddle.py): a fit that ended where the data could not separate some unknowns
is made again from a step along those unknowns when the sum of squares falls there."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchql

from testmodels import Product

DT = torch.float64


class TwoDecays(torchql.ODEModel):
    """``x1' = -k1 x1``, ``x2' = -k2 x2``: observed only as ``x1 + x2``, symmetric in swapping them."""

    state_names = ("x1", "x2")

    def __init__(self, k1=1.0, k2=1.0):
        super().__init__()
        self.register_buffer("k1", torch.tensor(k1, dtype=DT))
        self.register_buffer("k2", torch.tensor(k2, dtype=DT))

    def forward(self, t, x):
        return torch.stack((-self.k1 * x[..., 0], -self.k2 * x[..., 1]), -1)


X0 = torch.tensor([1.0, 1.0], dtype=DT)


def _sum_of_decays(seed: int = 0) -> torchql.Observations:
    """``x1 + x2`` of :class:`TwoDecays` (``k1 = 1``, ``k2 = 0.2``) at 21 times with noise 0.02."""
    t = torch.linspace(0, 5, 21, dtype=DT)
    y = torchql.simulate(TwoDecays(1.0, 0.2), X0, t).sum(-1, keepdim=True)
    y = y + 0.02 * torch.tensor(np.random.default_rng(seed).standard_normal((21, 1)))
    return torchql.Observations(t, y, observe=torch.tensor([[1.0, 1.0]], dtype=DT))


@pytest.mark.parametrize("method", ["kantorovich", "shooting"])
def test_a_fit_started_on_the_symmetry_leaves_its_saddle(method):
    """Guessed with equal rates, every iterate keeps them equal (their columns coincide) and the fit
    ended NOT_IDENTIFIABLE with its sum of squares 30 times the optimum's. A step along the null
    direction lowers it, and the fit made from there reaches the optimum that a guess off the
    symmetry reaches (scipy's least_squares from the symmetric guess: the same, its finite
    differences breaking the tie)."""
    data = _sum_of_decays()
    kw = dict(x0=X0, fixed_x0=["x1", "x2"], method=method)
    reference = torchql.fit(TwoDecays(0.6, 0.4), data, **kw)
    assert reference.status is torchql.Status.CONVERGED
    fit = torchql.fit(TwoDecays(0.5, 0.5), data, **kw)
    assert fit.success, fit.message
    assert "saddle" in fit.message and "NOT_IDENTIFIABLE (SSE 0.158" in fit.message
    assert fit.sse == pytest.approx(reference.sse, rel=1e-9)
    # (the fits started apart: their estimates agree to their tolerance, 1e-8 of the stderr's 0.02)
    assert sorted(fit.estimates.tolist()) == pytest.approx(sorted(reference.estimates.tolist()), abs=1e-7)
    guesses = {"k1": torch.tensor([0.5, 0.6], dtype=DT), "k2": torch.tensor([0.5, 0.4], dtype=DT)}
    batch = torchql.fit_many(TwoDecays(), [data, data], X0.expand(2, 2), fixed_x0=["x1", "x2"], method=method,
                             guesses=guesses)
    assert batch[0].message == fit.message and batch[1].message == reference.message
    assert torch.allclose(batch.estimates[0], fit.estimates, rtol=1e-8, atol=0)
    assert torch.allclose(batch.estimates[1], reference.estimates, rtol=1e-8, atol=0)


def test_a_product_stays_not_identifiable_without_a_second_fit():
    """Along the null direction of a product ``a b`` the sum of squares rises (the valley curves):
    no second fit is made, and the result says only that the product is what the data read."""
    t = torch.linspace(0, 3, 16, dtype=DT)
    y = torchql.simulate(Product(0.5, 2.0), torch.tensor([1.0], dtype=DT), t)
    data = torchql.Observations(t, y + 0.01 * torch.tensor(np.random.default_rng(1).standard_normal((16, 1))),
                                observe=["y"])
    fit = torchql.fit(Product(1.0, 1.5), data, x0=torch.tensor([1.0], dtype=DT), fixed_x0=["y"])
    assert fit.status is torchql.Status.NOT_IDENTIFIABLE
    assert "saddle" not in fit.message and "{a, b}" in fit.message


class ThreeDecays(torchql.ODEModel):
    """Three decays from 1, observed as their sum: symmetric in any permutation of its rates."""

    state_names = ("x1", "x2", "x3")

    def __init__(self, k1=1.0, k2=1.0, k3=1.0):
        super().__init__()
        for name, value in dict(k1=k1, k2=k2, k3=k3).items():
            self.register_buffer(name, torch.tensor(value, dtype=DT))

    def forward(self, t, x):
        return torch.stack((-self.k1 * x[..., 0], -self.k2 * x[..., 1], -self.k3 * x[..., 2]), -1)


@pytest.mark.parametrize("rates, seed, guess, method", [
    ((2.0, 0.7, 0.15), 3, (0.5, 0.5, 0.5), "kantorovich"),  # a threefold saddle, then a twofold one
    ((2.0, 0.7, 0.15), 3, (0.5, 0.5, 0.5), "shooting"),
    ((1.0, 0.3, 0.1), 5, (1.0, 0.5, 0.5), "shooting"),  # two rates met at 0.18, far from their guess 0.5
])
def test_three_decays_leave_every_saddle(rates, seed, guess, method):
    """Guessed with three equal rates, the first fit ended on the threefold saddle (SSE 1.52) and its
    step off it separated one rate; the second ended on the saddle where the other two met (SSE
    0.029, 32 times the optimum), and each such end is now tried again. Two rates met at 0.18 from
    guesses of 0.5: a step sized by the guesses (20 % of the estimates) rose the sum of squares by
    26 %, and the steps are now sized by the estimates, at three lengths. Each ends at the optimum
    that a guess off the symmetry reaches (scipy's least_squares: the same)."""
    t = torch.linspace(0, 6, 31, dtype=DT)
    x0 = torch.ones(3, dtype=DT)
    y = torchql.simulate(ThreeDecays(*rates), x0, t).sum(-1, keepdim=True)
    y = y + 0.005 * torch.tensor(np.random.default_rng(seed).standard_normal((31, 1)))
    data = torchql.Observations(t, y, observe=torch.ones(1, 3, dtype=DT))
    kw = dict(x0=x0, fixed_x0=["x1", "x2", "x3"], method=method)
    reference = torchql.fit(ThreeDecays(*(1.2 * r for r in rates)), data, **kw)
    fit = torchql.fit(ThreeDecays(*guess), data, **kw)
    assert reference.status is torchql.Status.CONVERGED and fit.success, fit.message
    assert "saddle" in fit.message
    assert fit.sse == pytest.approx(reference.sse, rel=1e-9)
    assert sorted(fit.estimates.tolist()) == pytest.approx(sorted(reference.estimates.tolist()), rel=1e-6)


def test_data_met_to_the_integrations_accuracy_are_on_no_saddle(monkeypatch):
    """A product ``a b`` fitted to exact data ends NOT_IDENTIFIABLE at SSE ~1e-20: no step lowers what the
    integration cannot resolve, and the steps are not tried (a FitzHugh–Nagumo fit of exact data spent a
    quarter of its time on them)."""
    import torchql.saddle

    def untried(null):
        raise AssertionError("a saddle step was tried")
    monkeypatch.setattr(torchql.saddle, "directions", untried)
    t = torch.linspace(0, 3, 16, dtype=DT)
    data = torchql.Observations(t, torchql.simulate(Product(0.5, 2.0), torch.tensor([1.0], dtype=DT), t),
                                observe=["y"])
    fit = torchql.fit(Product(1.0, 1.5), data, x0=torch.tensor([1.0], dtype=DT), fixed_x0=["y"])
    assert fit.status is torchql.Status.NOT_IDENTIFIABLE and fit.sse < 1e-15
