"""Stiff linear propagation: accuracy and time of every registered linear propagator.

The problem (scalar, closed form): ``w' = a(t) (w - g(t)) + g'(t)`` on ``[0, 2]`` with
``a(t) = -L (1 + t / 2)`` and ``g(t) = 1 + t / 2 - t^2 / 10``, so ``w(t) = g(t) + (w(0) - g(0)) e^{int a}``;
``a`` linear and ``b = g' - a g`` cubic, so the grid's Hermite interpolants are exact and every error
is the propagator's. Propagated from ``w(0) = 0`` with one homogeneous column, as ``fit`` does,
at ``fit``'s default tolerances (``rtol=1e-10``, ``atol=1e-12`` over the whole grid). ``h |lambda|``
ranges over ``[L h, 2 L h]``.

    PYTHONPATH=. python benchmarks/stiff_linear.py   # L = 1, 1e3, 1e6, 1e8; 100 and 1000 intervals
    PYTHONPATH=. python benchmarks/stiff_linear.py --repeats 5

Prints one table: the largest error at the nodes of the particular solution, the homogeneous
one's largest error, the propagator's count of evaluations (its own unit: series terms for
``taylor``, coefficient evaluations otherwise) and the median wall time, or why it failed.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from torchql.integrate import IntegrationError
from torchql.linearize import Linearization
from torchql.propagators import PROPAGATORS
from torchql.superposition import propagate_linear
from torchql.trajectory import LinearizedReference

DT = torch.float64


def problem(G: int, L: float):
    t = torch.linspace(0, 2, G + 1, dtype=DT)
    a, a_dot = -L * (1 + t / 2), torch.full_like(t, -L / 2)
    g, g_dot = 1 + t / 2 - t**2 / 10, 0.5 - t / 5
    b = g_dot - a * g
    b_dot = -0.2 - a_dot * g - a * g_dot
    lin = Linearization(f=b.unsqueeze(-1), jac=a.reshape(-1, 1, 1), f_dot=b_dot.unsqueeze(-1),
                        jac_dot=a_dot.reshape(-1, 1, 1))
    ref = LinearizedReference(t, torch.zeros(G + 1, 1, dtype=DT), torch.zeros(G + 1, 1, dtype=DT), lin)
    integral = -L * (t + t**2 / 4)
    exact = torch.stack([g - g[0] * torch.exp(integral), torch.exp(integral)], dim=-1)  # (G+1, 2)
    return ref, exact


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(1)
    w0 = torch.tensor([[0.0, 1.0]], dtype=DT)
    print(f"torch {torch.__version__}, float64, 1 thread, rtol=1e-10 atol=1e-12 (whole grid), median of {args.repeats}")
    print(f"{'L':>6} {'intervals':>9} {'h|lambda| max':>13} {'propagator':>13} {'err particular':>15} "
          f"{'err homogeneous':>15} {'evals':>8} {'time [s]':>9}")
    for L in (1.0, 1e3, 1e6, 1e8):
        for G in (100, 1000):
            ref, exact = problem(G, L)
            for name in PROPAGATORS:
                times, outcome = [], None
                for _ in range(args.repeats + 1):  # the first run warms up
                    start = time.perf_counter()
                    try:
                        W, evals = propagate_linear(ref, w0, rtol=1e-10, atol=1e-12, linear_solver=name,
                                                    max_steps=20_000)
                    except (IntegrationError, RuntimeError, AssertionError) as error:
                        outcome = f"failed: {type(error).__name__}: {str(error)[:60]}"
                        break
                    times.append(time.perf_counter() - start)
                if outcome is None:
                    err = (W[:, 0] - exact).abs().amax(dim=0)
                    outcome = (f"{err[0]:15.2e} {err[1]:15.2e} {evals:8d} "
                               f"{statistics.median(times[1:]):9.4f}")
                print(f"{L:6.0e} {G:9d} {2 * L * 2 / G:13.1e} {name:>13} {outcome}")


if __name__ == "__main__":
    main()
