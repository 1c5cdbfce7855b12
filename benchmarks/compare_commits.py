"""Single fits of ``benchmarks/fit_speed.py``'s problems by two versions of torchql, interleaved in one process.

The working tree's ``torchql`` and another revision's, exported from git (``git archive``) under
the package name ``torchql_base`` (the package imports itself relatively, so the copy is
independent), fit the same exact data with their default options: the linear oscillator (14
points), the nonlinear oscillator (66 points) and the three coasting cars of the thesis, each
model and dataset built from the version's own classes. For each problem and method the two fits
alternate ``--repeats`` times after two untimed warm-ups of each, so that the machine's load
hits them alike; the table gives the median times, their ratio (``< 1``: the working tree is
faster), the iterations and the largest difference of the estimates.

With ``--batches B ...`` it compares ``fit_many`` instead, at its default options, on
``benchmarks/batch.py``'s families (``B`` coasting cars and ``B`` linear oscillators, its data of
seed 0, each batch given as one batched ``Observations`` with per-sample starts), interleaved alike.

Run (from the repository root)::

    python benchmarks/compare_commits.py --base HEAD~3                 # Kantorovich, 9 repeats
    python benchmarks/compare_commits.py --base v0 --methods kantorovich shooting --repeats 3
    python benchmarks/compare_commits.py --base HEAD~3 --batches 1000 --repeats 5
    python benchmarks/compare_commits.py --base HEAD~3 --batches 100 --linear-solver rk4_doubling
"""

from __future__ import annotations

import argparse
import importlib
import statistics
import subprocess
import sys
import tarfile
import tempfile
from collections.abc import Callable
from io import BytesIO
from pathlib import Path

import torch

import torchql

sys.path.insert(0, str(Path(__file__).resolve().parent))
import batch as bb  # noqa: E402  (the batch families' data)
import fit_speed as fs  # noqa: E402  (the problems' data)

DTYPE = torch.float64
ROOT = Path(__file__).resolve().parents[1]


def export(revision: str, folder: Path):
    """``torchql`` at ``revision``, importable as ``torchql_base`` from ``folder``."""
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", revision, "torchql"], check=True,
                             capture_output=True).stdout
    with tarfile.open(fileobj=BytesIO(archive)) as tar:
        try:
            tar.extractall(folder, filter="data")
        except TypeError:  # Python without extraction filters (before 3.10.12 / 3.11.4)
            tar.extractall(folder)
    (folder / "torchql").rename(folder / "torchql_base")
    sys.path.insert(0, str(folder))
    return importlib.import_module("torchql_base")


def problems(pkg) -> list[tuple]:
    """``(name, model factory, data, x0)`` of fit_speed's problems, in the classes of package ``pkg``."""
    models = importlib.import_module(f"{pkg.__name__}.models")
    out = []
    for name, model, dt, n in (("linear oscillator", models.LinearOscillator, 0.5, 14),
                               ("nonlinear oscillator", models.NonlinearOscillator, 0.1, 66)):
        t = torch.arange(n, dtype=DTYPE) * dt
        x = pkg.simulate(model(), torch.tensor([0.0, 1.0], dtype=DTYPE), t, rtol=fs.DATA_RTOL, atol=fs.DATA_ATOL)
        guess = (0.5, 1.0) if n == 14 else (0.5, 2.0, 0.5, 2.0)
        out.append((name, lambda m=model, g=guess: m(*g), pkg.Observations(t, x[:, :1], observe=["y"]),
                    torch.tensor([0.5, 0.5], dtype=DTYPE)))
    for name, area, mass, v in fs.CARS:
        data = pkg.Observations(torch.tensor(fs.CAR_TIMES, dtype=DTYPE), torch.tensor(v, dtype=DTYPE).unsqueeze(-1),
                                observe=["v"])
        out.append((f"car: {name}", lambda a=area, m=mass: models.CoastingCar(a, m), data, None))
    return out


def batch_problems(pkg, B: int, options: dict) -> list[tuple]:
    """``(name, run)`` of ``fit_many`` on ``B`` datasets of each of batch.py's families, in package ``pkg``,
    with ``options`` (keywords of ``fit_many``)."""
    models = importlib.import_module(f"{pkg.__name__}.models")
    out = []
    for family, make in ((bb.CARS, lambda: models.CoastingCar(bb.AREA, bb.MASS)),
                         (bb.OSCILLATORS, lambda: models.LinearOscillator())):
        data = bb.make_data(family, B, seed=0)
        n = family.n_states
        obs = pkg.Observations(torch.tensor(data.t, dtype=DTYPE), torch.tensor(data.y, dtype=DTYPE).unsqueeze(-1),
                               observe=[family.state_names[0]])
        x0 = torch.tensor(data.starts[:, :n], dtype=DTYPE)
        guesses = {name: torch.tensor(data.starts[:, n + k], dtype=DTYPE) for k, name in enumerate(family.coefficients)}
        out.append((f"{family.key}, B = {B}", lambda make=make, obs=obs, x0=x0, g=guesses: pkg.fit_many(
            make(), obs, x0, guesses=g, **options)))
    return out


def timed_row(label: str, run_a: Callable, run_b: Callable, repeats: int, seconds: Callable[[float], str],
              iterations: Callable) -> str:
    """One table row: ``run_a`` (the base) and ``run_b`` (the working tree) timed interleaved, their
    medians (formatted by ``seconds``), iterations (``iterations`` of a result), ratio and the
    largest difference of their estimates."""
    timed = fs.time_interleaved({"base": run_a, "working": run_b}, repeats)
    (times_a, a), (times_b, b) = timed["base"], timed["working"]
    ma, mb = statistics.median(times_a), statistics.median(times_b)
    diff = float((a.estimates - b.estimates).abs().max())
    row = (f"| {label} | {seconds(ma)} | {iterations(a)} | {seconds(mb)} | {iterations(b)} | **{mb / ma:.2f}** | "
           f"{diff:.1e} |")
    print(row, flush=True)
    return row


def compare_batches(base, sizes: list[int], repeats: int, options: dict) -> list[str]:
    lines = ["| problem | base: median | base: mean iterations | working tree: median | working tree: mean "
             "iterations | working / base | estimates differ by |", "|---|---|---|---|---|---|---|"]
    for B in sizes:
        for (name, run_a), (_, run_b) in zip(batch_problems(base, B, options), batch_problems(torchql, B, options)):
            lines.append(timed_row(name, run_a, run_b, repeats, lambda s: f"{s:.3f} s",
                                   lambda r: f"{float(r.iterations.double().mean()):.2f}"))
    return lines


def compare(base, methods: list[str], repeats: int, options: dict) -> list[str]:
    lines = ["| problem | method | base: median | base: iterations | working tree: median | working tree: "
             "iterations | working / base | estimates differ by |", "|---|---|---|---|---|---|---|---|"]
    for method in methods:
        for (name, make_a, data_a, x_a), (_, make_b, data_b, x_b) in zip(problems(base), problems(torchql)):
            run_a = lambda: base.fit(make_a(), data_a, x_a, method=method, **options)  # noqa: E731
            run_b = lambda: torchql.fit(make_b(), data_b, x_b, method=method, **options)  # noqa: E731
            run_a(), run_b()  # the first untimed warm-up; time_interleaved's is the second
            lines.append(timed_row(f"{name} | {method}", run_a, run_b, repeats, lambda s: f"{1000 * s:.1f} ms",
                                   lambda r: r.iterations))
    return lines


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--base", required=True, help="the git revision to compare with (a commit, tag or branch)")
    parser.add_argument("--methods", nargs="+", default=["kantorovich"], choices=["kantorovich", "shooting"])
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--batches", type=int, nargs="+", default=None, metavar="B",
                        help="compare fit_many on B cars and B oscillators (batch.py's data) instead of single fits")
    parser.add_argument("--linear-solver", default=None,
                        help="the linear_solver of every fit (default: the default of each version)")
    parser.add_argument("--out", type=Path, default=None, help="also write the table to OUT/compare_commits.md")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    options = {} if args.linear_solver is None else {"linear_solver": args.linear_solver}
    revision = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", args.base], check=True,
                              capture_output=True, text=True).stdout.strip()
    with tempfile.TemporaryDirectory() as folder:
        base = export(args.base, Path(folder))
        header = (f"Working tree against {args.base} ({revision}), interleaved in one process, median of "
                  f"{args.repeats} repeats, torch {torch.__version__}, 1 thread"
                  + (f", linear_solver={args.linear_solver!r}." if args.linear_solver else "."))
        print(header)
        lines = (compare(base, args.methods, args.repeats, options) if args.batches is None
                 else compare_batches(base, args.batches, args.repeats, options))
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "compare_commits.md").write_text("# compare_commits\n\n" + header + "\n\n" + "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
