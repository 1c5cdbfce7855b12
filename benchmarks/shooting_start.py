"""Shooting from the integrated guesses against shooting from the data, on ``fit_speed.py``'s problems.

``method="shooting"`` iterates on the model's own solutions. With ``initial_trajectory="integrate"``
(its ``"auto"``) the first one is the model integrated from the guesses; with ``"data"`` it is the
model integrated from the coefficients matched to the data's slopes and the data's own initial
states (the data-built start of Kantorovich's iteration, then one integration). For each of
``fit_speed.py``'s problems (the linear oscillator on 14 exact points, the nonlinear one on 66,
the thesis' three coasting cars, each from ``fit_speed.py``'s guesses), both fits at the default
options otherwise, timed ``--repeats`` times after one untimed run (median), one thread. Columns:
status, iterations, median time, the sum of squares reached, and the ratio of the times.

Run (from the repository root)::

    python benchmarks/shooting_start.py              # writes benchmarks/output/shooting_start.md
    python benchmarks/shooting_start.py --repeats 3 --out /tmp/bench
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import torch

import torchql

sys.path.insert(0, str(Path(__file__).resolve().parent))
import fit_speed  # noqa: E402  (the problems)

STARTS = ("integrate", "data")


def timed(problem, start: str, repeats: int) -> tuple[torchql.FitResult, float]:
    """The shooting fit of ``problem`` from ``start`` and its median time over ``repeats`` runs."""
    def run():
        return torchql.fit(problem.guess_model(), problem.data, problem.x0, method="shooting",
                           initial_trajectory=start)
    run()
    times = []
    for _ in range(repeats):
        begin = time.perf_counter()
        result = run()
        times.append(time.perf_counter() - begin)
    return result, statistics.median(times)


def markdown(rows: list[tuple], repeats: int, load: tuple[float, float]) -> str:
    lines = [f"Median of {repeats} runs after one untimed run; torch {torch.__version__} (1 thread); "
             f"load average {load[0]:.2f} before, {load[1]:.2f} after.", "",
             "| problem | start | status | iterations | median time | SSE | time / integrated start |",
             "|---|---|---|---|---|---|---|"]
    for name, start, result, seconds, ratio in rows:
        lines.append(f"| {name} | {start} | {result.status.name} | {result.iterations} | {1000 * seconds:.0f} ms | "
                     f"{result.sse:.6g} | {ratio:.2f} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "output")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    load = os.getloadavg()[0]
    rows = []
    for problem in fit_speed.make_problems(False):
        base = None
        for start in STARTS:
            result, seconds = timed(problem, start, args.repeats)
            base = seconds if base is None else base
            rows.append((problem.name, start, result, seconds, seconds / base))
            print(f"... {problem.name}, {start}: {1000 * seconds:.0f} ms", file=sys.stderr, flush=True)
    report = markdown(rows, args.repeats, (load, os.getloadavg()[0]))
    print(report)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "shooting_start.md").write_text("# shooting_start: shooting from the guesses and from the data\n\n"
                                                + report)


if __name__ == "__main__":
    main()
