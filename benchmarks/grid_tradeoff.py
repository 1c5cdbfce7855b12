"""What tuning ``fit_many``'s storage grid or tolerance buys in time and costs in accuracy.

``fit_many``'s defaults (``grid="auto"``: each dataset's own storage intervals, from the fourth
derivative of its first trajectory; ``rtol=1e-10``) against settings a user may try for speed:
a fixed number of uniform storage intervals (``grid=``), a looser tolerance (``rtol=1e-8``), or the
quintic storage (``linear_solver="taylor_quintic"``, with its own automatic grid or 20 intervals).
On ``benchmarks/batch.py``'s families (the same truths, noise and starts), ``--size`` datasets
each, torch on one thread. Every row is timed ``--repeat`` times (the fastest counts) after one
untimed warm-up on a small batch.

Columns: the time, fits per second, the defaults' time over the row's (above 1: faster than the
defaults), and the row's accuracy against the reference, ``grid=1000`` (the former fixed
default, the finest storage here): the largest relative difference of the estimates and of their
standard errors over the batch (relative to the reference's value, or to 1% of that unknown's
largest magnitude in the batch where the value is smaller, as ``batch.py`` measures), and the
datasets whose fit succeeded.

Run (from the repository root)::

    python benchmarks/grid_tradeoff.py                  # both families, 1,000 datasets each
    python benchmarks/grid_tradeoff.py --families oscillators --size 200 --repeat 2
    python benchmarks/grid_tradeoff.py --quick --out /tmp/bench    # smoke run: 8 datasets, one run

Writes ``OUT/grid_tradeoff.md``.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import batch  # noqa: E402  (the families, their data and the fit_many runner)

#: The rows: a label and the options given to ``fit_many`` (none: its defaults).
SETTINGS = (("defaults", {}), ("grid=20", {"grid": 20}), ("grid=50", {"grid": 50}), ("grid=100", {"grid": 100}),
            ("rtol=1e-8", {"rtol": 1e-8}))
#: The quintic storage's rows, in a table of their own below each family's (same columns and reference).
QUINTIC = (('linear_solver="taylor_quintic"', {"linear_solver": "taylor_quintic"}),
           ('linear_solver="taylor_quintic", grid=20', {"linear_solver": "taylor_quintic", "grid": 20}))
#: The reference of the accuracy columns.
REFERENCE = ("grid=1000 (reference)", {"grid": 1000})


def measure(family: batch.Family, data: batch.Data, repeat: int) -> list[tuple]:
    """``(label, seconds, result)`` of every setting and of the reference, fastest of ``repeat`` runs."""
    batch.run_fit_many(family, data.head(min(8, len(data.y))))  # warm-up
    rows = []
    for label, options in (*SETTINGS, REFERENCE, *QUINTIC):
        result, seconds = batch.best_of(repeat, lambda: batch.run_fit_many(family, data, **options))
        rows.append((label, seconds, result))
        print(f"... {family.key}: {label} {seconds:.3f} s", file=sys.stderr, flush=True)
    return rows


def table(family: batch.Family, size: int, rows: list[tuple]) -> str:
    """The markdown tables of one family's rows: the settings and the reference (the last of them),
    then the quintic storage's (:data:`QUINTIC`) in a table of their own."""
    main, quintic = rows[:len(SETTINGS) + 1], rows[len(SETTINGS) + 1:]
    reference = main[-1][2]
    estimates, errors = reference.estimates.numpy(), batch.standard_errors(reference)
    defaults = main[0][1]
    head = ["| setting | time | fits/s | speed-up over defaults | estimates: max rel. diff | "
            "standard errors: max rel. diff | converged |", "|---|---|---|---|---|---|---|"]
    lines = [f"## {family.title}, B = {size}", "", *head]
    for row in [*main, None, *quintic]:
        if row is None:
            lines += ["", "### The quintic storage (tuned: not the default), against the defaults and reference above", "",
                      "| quintic storage | time | fits/s | speed-up over the defaults | estimates: max rel. diff | "
                      "standard errors: max rel. diff | converged |", head[1]]
            continue
        label, seconds, result = row
        d_est = float(np.max(batch.relative_difference(result.estimates.numpy(), estimates)))
        d_se = float(np.max(batch.relative_difference(batch.standard_errors(result), errors)))
        lines.append(f"| {label} | {seconds:.3f} s | {size / seconds:,.0f} | {defaults / seconds:.2f} | {d_est:.1e} | "
                     f"{d_se:.1e} | {int(result.success.sum())}/{size} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--families", nargs="+", choices=("cars", "oscillators"), default=["oscillators", "cars"])
    parser.add_argument("--size", type=int, default=1000)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true", help="8 datasets, one run each")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "output")
    args = parser.parse_args(argv)
    size, repeat = (8, 1) if args.quick else (args.size, args.repeat)
    torch.set_num_threads(1)
    families = {"cars": batch.CARS, "oscillators": batch.OSCILLATORS}
    load = os.getloadavg()[0]
    parts = []
    for name in args.families:
        family = families[name]
        parts.append(table(family, size, measure(family, batch.make_data(family, size, seed=args.seed), repeat)))
    header = (f"Fastest of {repeat} run(s) after a warm-up; torch {torch.__version__} (1 thread); load average "
              f"{load:.2f} before, {os.getloadavg()[0]:.2f} after. Accuracy against `grid=1000`.\n")
    report = header + "\n" + "\n".join(parts)
    print(report)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "grid_tradeoff.md").write_text("# grid_tradeoff: fit_many's defaults against tuned settings\n\n"
                                               + report)


if __name__ == "__main__":
    main()
