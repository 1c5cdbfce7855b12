"""Models that become stiff during the fit: ``solver="auto"`` against ``solver="rodas5p"``.

``solver="auto"`` (the default) chooses the explicit DOP853 when the model is not stiff along the
data at the guesses. A relaxation rate guessed at 1 and fitted at 1e4 makes the model stiff only
where the iterates go; such a sample is found (the explicit pair's stiffness test, or the decay
rate times the span along an accepted iterate) and fitted again as a stiff model
(``torchql/engine_run.py``). The cases, each from the guesses ``k = 1`` (and ``a = 1.5``):

* ``lag``: ``x' = -k (x - y)``, ``y' = -a y``, both measured at 20 times over (0, 2], noise 1e-4,
  ``k = 1e4`` (``tests/test_engine_run.py``);
* ``relaxation``: ``x' = -k (x - cos t)``, measured at 40 times over [0.25, 10], noise 1e-4,
  ``k = 1e4``: at the fit's tolerance DOP853's steps there stay below its stiffness test's bound;
* ``lag, log times``: the lag measured at 30 log-spaced times over [1e-5, 10].

Reported for each: wall time (median of ``--repeats``), status, iterations, the solver the result
names, and the estimate of ``k``; ``auto`` and ``rodas5p`` are timed in turns.

Run (from the repository root)::

    python benchmarks/stiff_switch.py             # 3 repeats
    python benchmarks/stiff_switch.py --repeats 1
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

import torchql

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from testmodels import Lag, Relaxation, relaxation_solution  # noqa: E402

DT = torch.float64


def lag_case(times: torch.Tensor):
    x0 = torch.tensor([0.0, 1.0], dtype=DT)
    x = torchql.simulate(Lag(1e4, 1.0), x0, torch.cat([torch.zeros(1, dtype=DT), times]), solver="rodas5p",
                         rtol=1e-12, atol=1e-16)[1:]
    y = x + 1e-4 * torch.randn(x.shape, generator=torch.Generator().manual_seed(2), dtype=DT)
    data = torchql.Observations(times, y, observe=["x", "y"], sigma=1e-4)
    return lambda solver: torchql.fit(Lag(1.0, 1.5), data, x0, fixed_x0=["x", "y"], t0=0.0, solver=solver)


def relaxation_case():
    t = torch.linspace(0.25, 10.0, 40, dtype=DT)
    y = relaxation_solution(t, 0.0, 1e4).unsqueeze(-1)
    y = y + 1e-4 * torch.randn(y.shape, generator=torch.Generator().manual_seed(0), dtype=DT)
    data = torchql.Observations(t, y, observe=["x"], sigma=1e-4)
    x0 = torch.tensor([0.0], dtype=DT)
    return lambda solver: torchql.fit(Relaxation(1.0), data, x0, fixed_x0=["x"], t0=0.0, solver=solver)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(1)
    cases = {"lag": lag_case(torch.linspace(0.0, 2.0, 21, dtype=DT)[1:]), "relaxation": relaxation_case(),
             "lag, log times": lag_case(torch.logspace(-5, 1, 30, dtype=DT))}
    print(f"torch {torch.__version__}, 1 thread, median of {args.repeats}")
    print("| case | solver | time | status | iterations | solver used | k |")
    print("|---|---|---|---|---|---|---|")
    for name, fit in cases.items():
        times: dict = {"auto": [], "rodas5p": []}
        results = {}
        for _ in range(args.repeats):
            for solver in times:
                start = time.perf_counter()
                results[solver] = fit(solver)
                times[solver].append(time.perf_counter() - start)
        for solver, result in results.items():
            print(f"| {name} | {solver} | {statistics.median(times[solver]):.2f} s | {result.status.name} | "
                  f"{result.iterations} | {result.solver_options['solver']} | {float(result.params['k']):.8g} |")


if __name__ == "__main__":
    main()
