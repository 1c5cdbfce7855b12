"""Cubic against quintic storage of the reference: how far each grid's Kantorovich fixed point is
from the model's optimum, and what that does to whole fits.

The storage grid holds the reference ``z``, ``h f`` and ``h A`` between its nodes as Hermite
interpolants: cubic for ``linear_solver="taylor"`` (the default), quintic for ``"taylor_quintic"``
(:mod:`torchql.propagators.quintic`; ``h A``'s from the second time derivative of ``A``). Their
error moves the Kantorovich fixed point off the model's optimum; the final pass's Gauss–Newton
steps on the model then remove it, each at the cost of a new integration. With ``grid="auto"``
each storage counts its own intervals (the quintic fewer, for the same interpolation error).

Two tables, on the seeded random problems of ``experiments/random_problems.py`` (noise 1e-3):

* **Fixed points** (the final pass's steps off, ``POLISH_STEPS = 0``): the largest relative
  difference of each grid's estimates from those on 2,000 intervals, for 50, 100 and 200 uniform
  intervals (and the observation times), on the nonlinear problems (Duffing oscillators,
  Lotka–Volterra, logistic, Michaelis–Menten);
* **Whole fits** at the defaults otherwise (the automatic grid, the final pass on): status,
  iterations (the final pass's steps included) and wall time of each storage on every problem of
  the five families.

Run (from the repository root)::

    python experiments/quintic_storage.py            # 15 problems; writes experiments/output/quintic_storage.md
    python experiments/quintic_storage.py --quick    # 5 problems, no file
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import random_problems as rp  # noqa: E402

import torchql  # noqa: E402
import torchql.engine_final as engine_final  # noqa: E402

SOLVERS = ("taylor", "taylor_quintic")
GRIDS = (50, 100, 200)
REFERENCE_GRID = 2000
NOISE = 1e-3


def problems(n: int) -> list:
    """The first ``n`` problems of the five families, seeds 0, 1, ..., noise :data:`NOISE`."""
    return [rp.make_problem(rp.FAMILIES[i % len(rp.FAMILIES)], i, NOISE) for i in range(n)]


def _fit(problem, **options):
    model = problem.make_model(problem.guess_p)
    return torchql.fit(model, problem.data(), x0=torch.tensor(problem.guess_x0, dtype=torch.float64), **options)


def label(problem) -> str:
    """``family (variant) seed k``, the variant where the family has one."""
    variant = f" ({problem.variant})" if problem.variant else ""
    return f"{problem.family}{variant} seed {problem.seed}"


def _nonlinear(problem) -> bool:
    return problem.family != "linear" and (problem.family != "oscillator" or problem.variant == "Duffing")


def fixed_point_rows(items: list) -> list[str]:
    """The fixed points' offsets from the fine grid's, the final pass's steps off."""
    rows = []
    saved = engine_final.POLISH_STEPS
    engine_final.POLISH_STEPS = 0
    try:
        for problem in items:
            if not _nonlinear(problem):
                continue
            reference = _fit(problem, grid=REFERENCE_GRID).estimates
            cells = []
            for grid in GRIDS:
                offsets = []
                for solver in SOLVERS:
                    estimates = _fit(problem, grid=grid, linear_solver=solver).estimates
                    offsets.append(float(((estimates - reference).abs() / reference.abs().clamp(min=1e-12)).max()))
                cells.append(f"{offsets[0]:.1e} / {offsets[1]:.1e} ({offsets[0] / max(offsets[1], 1e-300):.0f}x)")
            rows.append(f"| {label(problem)} | " + " | ".join(cells) + " |")
    finally:
        engine_final.POLISH_STEPS = saved
    return rows


def whole_fit_rows(items: list, repeats: int) -> tuple[list[str], list[float]]:
    """Whole fits with each storage: rows, and the per-problem time ratios quintic / cubic."""
    rows, ratios = [], []
    for problem in items:
        cells, times = [], []
        for solver in SOLVERS:
            _fit(problem, linear_solver=solver)  # warm
            best = float("inf")
            for _ in range(repeats):
                start = time.perf_counter()
                result = _fit(problem, linear_solver=solver)
                best = min(best, time.perf_counter() - start)
            times.append(best)
            cells.append(f"{result.status.name} {result.iterations} it {best * 1e3:.0f} ms")
        ratios.append(times[1] / times[0])
        rows.append(f"| {label(problem)} | " + " | ".join(cells)
                    + f" | {ratios[-1]:.2f} |")
    return rows, ratios


def report(n: int, repeats: int) -> str:
    items = problems(n)
    fixed = fixed_point_rows(items)
    whole, ratios = whole_fit_rows(items, repeats)
    lines = [
        "# Cubic against quintic storage of the reference",
        "",
        f"`python experiments/quintic_storage.py`: {n} random problems (noise {NOISE}), torch "
        f"{torch.__version__} (1 thread). Wall times depend on the machine and its load.",
        "",
        "## Kantorovich fixed points (the final pass's steps off)",
        "",
        f"Largest relative difference of the estimates from those on {REFERENCE_GRID} intervals: "
        "cubic / quintic (their ratio).",
        "",
        "| problem | " + " | ".join(f"{g} intervals" for g in GRIDS) + " |",
        "|---|" + "---|" * len(GRIDS),
        *fixed,
        "",
        "## Whole fits (defaults otherwise: automatic grid, final pass on)",
        "",
        f"Status, iterations (the final pass's steps included) and the best of {repeats} wall times.",
        "",
        "| problem | taylor (cubic) | taylor_quintic | time quintic / cubic |",
        "|---|---|---|---|",
        *whole,
        "",
        f"Median per-problem time ratio quintic / cubic: {statistics.median(ratios):.2f} "
        f"(range {min(ratios):.2f} to {max(ratios):.2f}).",
        "",
    ]
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="5 problems, one timing each, no file")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "output")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    text = report(5 if args.quick else 15, 1 if args.quick else 3)
    print(text)
    if not args.quick:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "quintic_storage.md").write_text(text)


if __name__ == "__main__":
    main()
