"""The engine's flat-minimum test (MINPACK's ``ftol`` test on accepted damped steps), on hand-made
iterates: the linear problem ``C alpha ~ d`` with weights ``w``, the merits before and after; and
each stiff sample's own trial tolerance in a batch."""

from types import SimpleNamespace

import pytest
import torch

import torchql
from torchql.damping import LevenbergMarquardt, Undamped
from torchql.engine import FLAT_DAMPING, Engine

DT = torch.float64


def _flat(damping, merit_new, alpha, *, filters=True, exact=False, accept=True, rejected=1):
    """``Engine._flat`` for one sample: ``|d|^2 = 2`` (w = 1), C the identity on two rows, merit 1 -> ``merit_new``;
    ``rejected`` trials at the iterate (what damped the step)."""
    C = torch.eye(2, dtype=DT).unsqueeze(0)
    d = torch.tensor([[1.0, 1.0]], dtype=DT)
    cur = {"C": C, "d": d, "w": torch.ones(1, 2, dtype=DT), "merit": torch.tensor([1.0], dtype=DT)}
    st = SimpleNamespace(cur=cur, damping=torch.tensor([damping], dtype=DT), rejected=torch.tensor([rejected]))
    spec = SimpleNamespace(ftol=1e-6, has_exact=exact, damping=LevenbergMarquardt() if filters else Undamped())
    engine = SimpleNamespace(spec=spec)
    trial = {"merit": torch.tensor([merit_new], dtype=DT)}
    alpha = torch.tensor([alpha], dtype=DT)
    return bool(Engine._flat(engine, st, torch.tensor([0]), trial, torch.tensor([accept]), alpha)[0])


def test_a_damped_step_that_changes_nothing_ends_the_fit():
    # predicted decrease |d|^2 - |d - alpha|^2 = 2 - 2 (1 - 1e-7)^2 ~ 4e-7 <= 1e-6, actual 5e-7
    assert _flat(1e-4, 1.0 - 5e-7, [1e-7, 1e-7])


def test_the_flat_test_needs_every_condition():
    assert not _flat(1e-4, 1.0 - 5e-7, [1e-3, 1e-3])  # the linear model promises more: 4e-3
    assert not _flat(1e-4, 1.0 - 5e-6, [1e-7, 1e-7])  # the merit changed by more than ftol
    assert not _flat(0.0, 1.0 - 5e-7, [1e-7, 1e-7])  # undamped steps: Engine._converged's tests
    assert not _flat(10 * FLAT_DAMPING, 1.0 - 5e-7, [1e-7, 1e-7])  # too damped: short steps promise little
    assert not _flat(1e-4, 1.0 - 5e-7, [1e-7, 1e-7], accept=False)
    assert not _flat(1e-4, 1.0 - 5e-7, [1e-7, 1e-7], filters=False)
    assert not _flat(1e-4, 1.0 - 5e-7, [1e-7, 1e-7], exact=True)
    # damped after a poor gain, not by rejections: the undamped step after it is tested instead
    assert not _flat(1e-4, 1.0 - 5e-7, [1e-7, 1e-7], rejected=0)


def test_a_stiff_batchs_samples_each_take_the_trial_tolerance_of_their_own_step():
    """On the stiff path a trial's transfers are integrated at a tolerance that follows its step
    (inexact Newton). Each sample has its own: taken from the batch's longest step, a sample near
    its optimum (k from 990) got the loose transfers of another's long step (from 300), which the
    convergence test does not accept, and took 6 iterations in the batch against 3 alone."""
    from testmodels import Relaxation

    t = torch.logspace(-4, 0.5, 30, dtype=DT)
    x = torchql.simulate(Relaxation(k=1e3), torch.tensor([2.0], dtype=DT), torch.cat([torch.zeros(1, dtype=DT), t]),
                         solver="rodas5p", rtol=1e-12, atol=1e-14)[1:]
    data, x0 = torchql.Observations(t, x, observe=["x"]), torch.tensor([2.0], dtype=DT)
    options = dict(t0=0.0, params=["k"], fixed_x0=["x"], solver="rodas5p", rtol=1e-8, atol=1e-12)
    guesses = [990.0, 300.0, 3000.0]
    batch = torchql.fit_many(Relaxation(), [data] * 3, x0, guesses={"k": torch.tensor(guesses, dtype=DT)}, **options)
    for i, k in enumerate(guesses):
        single = torchql.fit(Relaxation(k=k), data, x0, **options)
        assert single.success and batch[i].success, (single.message, batch[i].message)
        assert batch[i].iterations == single.iterations
        assert batch[i].params["k"].item() == pytest.approx(single.params["k"].item(), rel=1e-12)
        assert single.params["k"].item() == pytest.approx(1e3, rel=1e-8)


def test_a_stiff_re_anchoring_propagates_at_the_tolerance_of_the_iterate_it_replaces(monkeypatch):
    """Re-anchoring replaces an iterate whose step was rejected by one about the model's own
    solution, to try the step again; on the stiff path that iterate's transfers were integrated at
    the inexact tolerance of its step (INEXACT_FACTOR), and so are the replacement's. At the fit's
    tolerance they took 5.5 times the Radau substeps: on HIRES (8 states, 3 rates) six re-anchorings
    took half of a 108 s fit, now 72 s. Robertson's exact data from 2x off re-anchor early, at 1e-6."""
    from torchql.engine import Engine
    from torchql.models import Robertson

    t = torch.logspace(-5, 4, 30, dtype=DT)
    x0 = torch.tensor([1.0, 0.0, 0.0], dtype=DT)
    x = torchql.simulate(Robertson(), x0, torch.cat([torch.zeros(1, dtype=DT), t]), solver="rodas5p", rtol=1e-12,
                         atol=1e-18)[1:]
    seen, inside = [], []
    reanchor, propagate = Engine._reanchor, Engine._propagate

    def recorded_reanchor(self, st, rejected):
        inside.append(st.cur["rtol"][rejected].clone())
        try:
            return reanchor(self, st, rejected)
        finally:
            inside.pop()

    def recorded_propagate(self, idx, z, z_dot, lin, w0, rtol=None, coefficients=None):
        if inside:
            seen.append((rtol, inside[-1]))
        return propagate(self, idx, z, z_dot, lin, w0, rtol, coefficients)

    monkeypatch.setattr(Engine, "_reanchor", recorded_reanchor)
    monkeypatch.setattr(Engine, "_propagate", recorded_propagate)
    guess = {"k1": 0.08, "k2": 1.5e7, "k3": 2e4}
    r = torchql.fit(Robertson(**guess), torchql.Observations(t, x, observe=["y1", "y2", "y3"]), x0,
                    fixed_x0=["y1", "y2", "y3"], t0=0.0, bounds={k: (0.0, None) for k in guess})
    assert r.success, r.message
    assert max(abs(r.params[k].item() - v) / v for k, v in {"k1": 0.04, "k2": 3e7, "k3": 1e4}.items()) < 1e-6
    assert any(float(replaced.max()) > r.solver_options["rtol"] for _, replaced in seen)  # an early, loose one
    for rtol, replaced in seen:
        assert rtol == pytest.approx(float(replaced.max()), rel=1e-12)
