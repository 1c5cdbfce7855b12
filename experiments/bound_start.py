"""Starting guesses on a bound: iterations from a guess on the bound against guesses inside.

``torchql.fit`` moves a guess that lies on its bound (or outside it) strictly inside before
iterating: ``bound + 1e-3 * max(1, |bound|)`` for a one-sided bound, ``1e-3`` of the width
inside the nearer of two (``torchql.bounds.START_OFFSET``). This script measures what that
costs: for each problem the fit from the guess on the bound is run beside fits from guesses
strictly inside, both near the bound (``1e-10`` and ``1e-6`` above it, kept as given, which shows
what a smaller offset would cost) and at a generic inside guess. Every fit's data are exact
(``torchql.simulate`` at rtol 1e-13), so every start that converges must reach the truth.

Problems (float64):

* kinetics: ``A -k1-> B -k2-> C`` and ``A -k3-> C`` (k = 0.9, 0.4, 0.25), A, B and C observed
  at t = 0, 0.5, ..., 10 from (1, 0, 0), the initial state estimated; the rates bounded
  ``(0, None)`` and guessed 0 (as the COPS kinetics benchmarks start);
* slow kinetics: ``torchql.models.FirstOrderReactions`` (k1 = 5e-5, k2 = 2e-4 1/s), A, B, C
  observed every 500 s up to 1e4 s from (100, 0, 0), rates bounded ``(0, None)``;
* two-sided: the linear oscillator ``y'' + A y' + B y = 0`` (A = 0.1, B = 3), y observed at t =
  0, 0.5, ..., 6.5, A bounded ``(0, 1)`` and guessed on its lower and on its upper bound
  (B guessed 1).

Columns: start, the guesses' distance from the bound (``on`` = on it, moved by the fit), method,
status, iterations, the largest relative error of the estimates against the truth, SSE.

Run (from the repository root; about 10 s, prints only, writes nothing)::

    PYTHONPATH=. python experiments/bound_start.py
"""

from __future__ import annotations

import argparse

import torch

import torchql
from torchql.models import BranchedReactions, FirstOrderReactions, LinearOscillator

DT = torch.float64




def _exact(model, x0, t, observe):
    x = torchql.simulate(model, x0, t, rtol=1e-13, atol=1e-15)
    return torchql.Observations(t, x[:, [model.state_names.index(s) for s in observe]], observe=list(observe))


def problems():
    """``(name, truth (dict), make_model(guess dict), data, x0, bounds, starts)`` per problem."""
    truth = dict(k1=0.9, k2=0.4, k3=0.25)
    x0 = torch.tensor([1.0, 0.0, 0.0], dtype=DT)
    data = _exact(BranchedReactions(**truth), x0, torch.arange(21, dtype=DT) * 0.5, ("A", "B", "C"))
    starts = [("on the bound", "on", dict(k1=0.0, k2=0.0, k3=0.0)),
              ("near the bound", "1e-6", dict(k1=1e-6, k2=1e-6, k3=1e-6)),
              ("near the bound", "1e-10", dict(k1=1e-10, k2=1e-10, k3=1e-10)),
              ("inside", "-", dict(k1=0.5, k2=0.5, k3=0.5))]
    yield ("kinetics", truth, lambda g: BranchedReactions(**g), data, x0,
           {"k1": (0.0, None), "k2": (0.0, None), "k3": (0.0, None)}, starts)

    truth = dict(k1=5e-5, k2=2e-4)
    x0 = torch.tensor([100.0, 0.0, 0.0], dtype=DT)
    data = _exact(FirstOrderReactions(**truth), x0, torch.arange(21, dtype=DT) * 500.0, ("A", "B", "C"))
    starts = [("on the bound", "on", dict(k1=0.0, k2=0.0)),
              ("near the bound", "1e-10", dict(k1=1e-10, k2=1e-10)),
              ("inside", "-", dict(k1=1e-4, k2=1e-4))]
    yield ("slow kinetics", truth, lambda g: FirstOrderReactions(**g), data, x0,
           {"k1": (0.0, None), "k2": (0.0, None)}, starts)

    truth = dict(A=0.1, B=3.0)
    x0 = torch.tensor([0.0, 1.0], dtype=DT)
    data = _exact(LinearOscillator(**truth), x0, torch.arange(14, dtype=DT) * 0.5, ("y",))
    starts = [("on the lower bound", "on", dict(A=0.0, B=1.0)),
              ("on the upper bound", "on", dict(A=1.0, B=1.0)),
              ("near the lower bound", "1e-10", dict(A=1e-10, B=1.0)),
              ("inside", "-", dict(A=0.5, B=1.0))]
    yield ("two-sided", truth, lambda g: LinearOscillator(**g), data, x0, {"A": (0.0, 1.0)}, starts)


def main() -> None:
    header = f"{'problem':<14} {'start':<21} {'dist':>5} {'method':<12} {'status':<14} {'iter':>4} " \
             f"{'max rel err':>11} {'SSE':>9}"
    print(header)
    print("-" * len(header))
    for name, truth, make, data, x0, bounds, starts in problems():
        for label, dist, guess in starts:
            for method in torchql.METHODS:
                r = torchql.fit(make(guess), data, x0, method=method, bounds=bounds)
                err = max(abs(r.params[k].item() - v) / abs(v) for k, v in truth.items())
                print(f"{name:<14} {label:<21} {dist:>5} {method:<12} {r.status.name:<14} {r.iterations:>4} "
                      f"{err:>11.1e} {r.sse:>9.1e}")
    print("\n'on': the guess lies on its bound and the fit moved it inside (result.moved_guesses).")


if __name__ == "__main__":
    argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args()  # (--help; no options)
    main()
