"""``torchql.fit_many`` against a loop of ``torchql.fit`` on batches of small random problems.

The problems are those of ``experiments/random_problems.py`` (each drawn from its seed: an
identifiable truth, guesses 0.3 to 3 times it, observation times of its own), three families:

* ``logistic``: ``x' = r x (1 - x / K)``, unknowns ``x(t0)``, ``r``, ``K``, 31 times;
* ``michaelis_menten``: ``S' = -V S / (Km + S)``, unknowns ``S(t0)``, ``V``, ``Km``, 31 times;
* ``lotka_volterra``: ``x' = a x - b x y``, ``y' = c x y - d y``, both states observed, unknowns
  both initial states and ``a, b, c, d``, 61 times over two periods.

For each family and batch size ``B`` (``--sizes``, default 8, 100 and 1000), datasets of seeds
``0 .. B - 1`` with noise ``--noise`` (default 1e-3 of each series' scale): ``fit_many`` with its
DEFAULT options on all ``B`` (one batched ``Observations`` with per-sample times, per-sample
guesses; timed with its building, after one untimed warm-up), against a Python loop of
``torchql.fit`` (default options) on the first ``min(B, --loop)`` of them (default 100; fits per
second extrapolate to ``B``). Both on one thread. Columns: fits per second of each, their ratio
(``> 1``: the batch is faster), the loop's time per fit, fit_many's successes, the largest
difference of the batch's estimates from the loop's (relative, or absolute below 1e-3) and
whether every status agrees.

Run (from the repository root)::

    python benchmarks/batch_families.py                       # writes benchmarks/output/batch_families.md
    python benchmarks/batch_families.py --sizes 8 100 --loop 20 --out /tmp/bench
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

import torchql

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))
import random_problems as rp  # noqa: E402  (the problems' generator)

FAMILIES = ("logistic", "michaelis_menten", "lotka_volterra")
DTYPE = torch.float64


def problems(family: str, B: int, noise: float) -> list:
    """The ``B`` problems of ``family`` with seeds ``0 .. B - 1``."""
    return [rp.make_problem(family, seed, noise) for seed in range(B)]


def run_batch(batch: list) -> tuple[torchql.BatchFitResult, float]:
    """``fit_many`` with default options on the problems of ``batch``, timed with building its data."""
    start = time.perf_counter()
    first = batch[0]
    t = torch.tensor(np.stack([p.t for p in batch]), dtype=DTYPE)
    y = torch.tensor(np.stack([p.y for p in batch]), dtype=DTYPE)
    data = torchql.Observations(t, y, observe=[first.state_names[i] for i in first.observed])
    x0 = torch.tensor(np.stack([p.guess_x0 for p in batch]), dtype=DTYPE)
    guesses = {name: torch.tensor([p.guess_p[k] for p in batch], dtype=DTYPE) for k, name in enumerate(first.coef_names)}
    result = torchql.fit_many(first.make_model(first.guess_p), data, x0, guesses=guesses)
    return result, time.perf_counter() - start


def run_loop(batch: list) -> tuple[list, float]:
    """A loop of ``torchql.fit`` (default options) over ``batch``: results and seconds."""
    start = time.perf_counter()
    results = [torchql.fit(p.make_model(p.guess_p), p.data(), torch.tensor(p.guess_x0, dtype=DTYPE)) for p in batch]
    return results, time.perf_counter() - start


def row(family: str, B: int, loop: int, noise: float) -> dict:
    batch = problems(family, B, noise)
    run_batch(batch[:2])  # warm-up, untimed
    result, seconds = run_batch(batch)
    singles, loop_seconds = run_loop(batch[:min(B, loop)])
    n = len(singles)
    diff = max(float(((result[i].estimates - s.estimates).abs()
                      / s.estimates.abs().clamp(min=1e-3)).max()) for i, s in enumerate(singles))
    same = all(result[i].status == s.status for i, s in enumerate(singles))
    return dict(family=family, B=B, rate=B / seconds, seconds=seconds, loop_rate=n / loop_seconds,
                per_fit=loop_seconds / n, n_loop=n, success=int(result.success.sum()), diff=diff, same=same)


def markdown(rows: list[dict], noise: float, load: tuple[float, float]) -> str:
    lines = [f"torch {torch.__version__} (1 thread), Python {platform.python_version()}, {platform.machine()}, "
             f"{os.cpu_count()} CPUs; load average {load[0]:.2f} before, {load[1]:.2f} after. Noise {noise:g}; "
             "default options throughout.", "",
             "| family | B | fit_many wall time | fit_many fits / s | loop of fit: fits / s (datasets) | "
             "fit_many / loop | loop: time per fit | fit_many converged | max diff | statuses agree |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['family']} | {r['B']} | {r['seconds']:.2f} s | {r['rate']:.1f} | "
                     f"{r['loop_rate']:.1f} ({r['n_loop']}) | **{r['rate'] / r['loop_rate']:.2g}x** | "
                     f"{1000 * r['per_fit']:.0f} ms | {r['success']}/{r['B']} | {r['diff']:.1e} | "
                     f"{'yes' if r['same'] else 'NO'} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[8, 100, 1000])
    parser.add_argument("--loop", type=int, default=100, help="datasets fitted by the loop (default 100)")
    parser.add_argument("--noise", type=float, default=1e-3)
    parser.add_argument("--families", nargs="+", default=list(FAMILIES), choices=FAMILIES)
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "output")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    load = os.getloadavg()[0]
    rows = []
    for family in args.families:
        for B in args.sizes:
            print(f"... {family} B = {B}", file=sys.stderr, flush=True)
            rows.append(row(family, B, args.loop, args.noise))
    report = markdown(rows, args.noise, (load, os.getloadavg()[0]))
    print(report)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "batch_families.md").write_text("# batch_families: fit_many against a loop of fit on small problems\n\n"
                                                + report)


if __name__ == "__main__":
    main()
