"""Throughput of batched fitting (``torchql.fit_many``) against loops of single fits, in one run.

Problem: a fleet of coasting cars (``torchql.models.CoastingCar``, the thesis' Sunbeam Alpine:
frontal area 17.3 ft^2, mass 80.43 slug), each with its own coefficients drawn around
``C_D = 0.45 +- 0.05``, ``mu = 0.015 +- 0.003`` and initial speed ``117.3 +- 2`` ft/s, observed
at ``t = 0, 5, ..., 40`` s (nine speeds) with Gaussian noise of 0.3 ft/s. The exact speeds come
from the model's closed-form solution. Unknowns per car: ``v(t0)``, ``C_D``, ``mu``; start
``C_D = 0.4``, ``mu = 0.02``, ``v(t0)`` = the car's first measured speed.

Compared, in the same process:

* ``torchql.fit_many`` on ``B`` datasets for every ``B`` in ``--sizes`` (after one untimed
  warm-up on a small batch), given as one batched ``Observations`` (values ``(B, 9, 1)``,
  validated once) and timed with its building; once more at the largest ``B`` with
  ``rtol=1e-8`` (every other row: the default ``rtol=1e-10``), a faster setting whose accuracy
  is reported beside the others', and once with torch on every core (the other rows and the
  loops run on one thread);
* a Python loop of ``torchql.fit`` on the first ``--subset`` datasets (same settings), timed
  with the building of one ``Observations`` per dataset;
* a Python loop of ``scipy.optimize.least_squares`` over ``scipy.integrate.solve_ivp`` on the
  same subset, with the settings of ``benchmarks/fit_speed.py`` (``trf``, 2-point differences,
  ``rtol=1e-10``, ``atol=1e-12``), with ``DOP853`` and with ``RK45``; the faster of the two is the
  reference of the ratios.

Loops are timed on the subset only (their throughput does not depend on the batch size); the
ratio at size ``B`` is ``fits/s of fit_many at B`` over ``fits/s of the loop``. Every fit_many row
and both scipy loops are timed ``--repeat`` times (default 3) and the fastest run counts, on both
sides of each ratio alike (the torchql loop, the slowest, runs once).

torchql's settings: ``grid=GRID`` storage intervals (the default is 1000, far finer than nine
smooth samples need; both torchql variants use the same grid, so batched and single fits are
the same computation). The accuracy columns say what that costs: the largest relative
difference of the batched estimates from single fits with the default grid, and the largest
relative excess of their SSE over the better of torchql's and scipy's (the target of
``fit_speed.py`` is ``1e-6``).

Memory: the process' peak resident set size after each batch (``resource``; it only grows, and
the batches run in increasing size, so each figure is the peak up to and including that batch).

Run (from the repository root)::

    python benchmarks/batch.py                      # sizes 10,100,1000,10000; subset 100
    python benchmarks/batch.py --sizes 10 100 1000 --subset 50
    python benchmarks/batch.py --quick --out /tmp/bench   # smoke run (seconds)

Writes ``OUT/batch.md`` (the table) and ``OUT/batch.png`` (fits/s against ``B``).
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import sys
import time
from pathlib import Path

import numpy as np
import scipy
import torch
from scipy.integrate import solve_ivp
from scipy.optimize import least_squares

import torchql
from torchql.models import CoastingCar
from torchql.models.car import AIR_DENSITY, GRAVITY

DTYPE = torch.float64
AREA, MASS = 17.3, 80.43
TIMES = tuple(5.0 * k for k in range(9))
NOISE = 0.3
GRID = 20
GUESS = dict(C_D=0.4, mu=0.02)
#: A looser integration tolerance for one extra fit_many row (its accuracy is reported beside it).
FAST_RTOL = 1e-8
PEER_RTOL, PEER_ATOL = 1e-10, 1e-12
PEER_LSQ = dict(method="trf", jac="2-point", diff_step=1e-5, x_scale="jac", xtol=1e-12, ftol=1e-14, gtol=1e-14,
                max_nfev=2000)


def exact_speed(t: np.ndarray, v0: np.ndarray, C_D: np.ndarray, mu: np.ndarray) -> np.ndarray:
    """Closed form of ``v' = -a v^2 - c``: ``v = sqrt(c/a) tan(atan(v0 sqrt(a/c)) - sqrt(a c) t)``, ``(B, T)``."""
    a = (0.5 * AIR_DENSITY * AREA * C_D / MASS)[:, None]
    c = (mu * GRAVITY)[:, None]
    return np.sqrt(c / a) * np.tan(np.arctan(v0[:, None] * np.sqrt(a / c)) - np.sqrt(a * c) * t[None, :])


def make_data(B: int, seed: int = 0):
    """``B`` noisy datasets: the times ``(T,)``, speeds ``(B, T)`` and the true ``(v0, C_D, mu)`` ``(B, 3)``."""
    rng = np.random.default_rng(seed)
    v0 = 117.3 + 2.0 * rng.standard_normal(B)
    C_D = 0.45 + 0.05 * rng.standard_normal(B)
    mu = np.abs(0.015 + 0.003 * rng.standard_normal(B))
    t = np.array(TIMES)
    v = exact_speed(t, v0, C_D, mu) + NOISE * rng.standard_normal((B, t.size))
    return t, v, np.stack([v0, C_D, mu], axis=1)


def batch_observations(t: np.ndarray, v: np.ndarray) -> torchql.Observations:
    """The datasets ``v (B, T)`` at times ``t (T,)`` as one batched Observations, values ``(B, T, 1)``."""
    return torchql.Observations(torch.tensor(t, dtype=DTYPE), torch.tensor(v, dtype=DTYPE).unsqueeze(-1),
                                observe=["v"])


def run_fit_many(t, v, grid=GRID, rtol=None) -> tuple[torchql.BatchFitResult, float]:
    """``fit_many`` on the datasets ``v (B, T)``, timed with the building of their batched Observations."""
    start = time.perf_counter()
    data = batch_observations(t, v)
    x0 = torch.tensor(v[:, :1], dtype=DTYPE)
    result = torchql.fit_many(CoastingCar(AREA, MASS, **GUESS), data, x0, grid=grid, rtol=rtol)
    return result, time.perf_counter() - start


def run_single_loop(t, v, grid=GRID) -> tuple[np.ndarray, np.ndarray, list[str], float]:
    """A loop of ``torchql.fit`` on the datasets ``v (B, T)``, timed with the building of their Observations."""
    start = time.perf_counter()
    tt = torch.tensor(t, dtype=DTYPE)
    estimates, sse, status = [], [], []
    model = CoastingCar(AREA, MASS, **GUESS)
    for row in v:
        d = torchql.Observations(tt, torch.tensor(row, dtype=DTYPE).unsqueeze(-1), observe=["v"])
        r = torchql.fit(model, d, torch.tensor(row[:1], dtype=DTYPE), grid=grid)
        estimates.append(r.estimates.numpy())
        sse.append(r.sse)
        status.append(r.status.name)
    return np.array(estimates), np.array(sse), status, time.perf_counter() - start


def _car_rhs(t, x, C_D, mu):
    return [-0.5 * AIR_DENSITY * AREA * C_D / MASS * x[0] ** 2 - mu * GRAVITY]


def run_scipy_loop(t, v, solver: str) -> tuple[np.ndarray, np.ndarray, float]:
    start = time.perf_counter()
    estimates, sse = [], []
    for row in v:
        def residuals(u, row=row):
            sol = solve_ivp(_car_rhs, (t[0], t[-1]), u[:1], method=solver, t_eval=t, args=tuple(u[1:]),
                            rtol=PEER_RTOL, atol=PEER_ATOL)
            if not sol.success or sol.y.shape[1] != t.size:
                return np.full(t.size, 1e10)
            return sol.y[0] - row
        r = least_squares(residuals, np.array([row[0], GUESS["C_D"], GUESS["mu"]]), **PEER_LSQ)
        estimates.append(r.x)
        sse.append(2 * r.cost)
    return np.array(estimates), np.array(sse), time.perf_counter() - start


def reference_sse(t, v, estimates) -> np.ndarray:
    """SSE of each estimate from the closed-form solution (the yardstick for every method)."""
    fitted = exact_speed(t, estimates[:, 0], estimates[:, 1], estimates[:, 2])
    return np.sum((fitted - v) ** 2, axis=1)


def peak_rss_mb() -> float:
    kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kb / 1024 if sys.platform != "darwin" else kb / 1024**2


def best_of(repeat: int, run):
    """``run()`` ``repeat`` times: the last result with the shortest wall time (its last element)."""
    runs = [run() for _ in range(repeat)]
    return min(runs, key=lambda r: r[-1])[:-1] + (min(r[-1] for r in runs),)


def benchmark(sizes: list[int], subset: int, seed: int = 0, repeat: int = 3) -> dict:
    t, v, truth = make_data(max(sizes + [subset]), seed)
    run_fit_many(t, v[:4])  # warm-up (imports, first calls), untimed
    batched = {}
    for B in sorted(sizes):
        print(f"... fit_many B = {B}", file=sys.stderr, flush=True)
        result, seconds = best_of(repeat, lambda: run_fit_many(t, v[:B]))
        batched[B] = dict(result=result, seconds=seconds, rate=B / seconds, rss=peak_rss_mb(),
                          converged=int(result.success.sum()), iterations=float(result.iterations.double().mean()))
    B = max(sizes)
    print(f"... fit_many B = {B}, rtol = {FAST_RTOL}", file=sys.stderr, flush=True)
    fast, seconds = best_of(repeat, lambda: run_fit_many(t, v[:B], rtol=FAST_RTOL))
    fast_row = dict(B=B, seconds=seconds, rate=B / seconds, converged=int(fast.success.sum()),
                    iterations=float(fast.iterations.double().mean()))
    threads = os.cpu_count() or 1
    print(f"... fit_many B = {B}, {threads} threads", file=sys.stderr, flush=True)
    torch.set_num_threads(threads)
    try:
        wide, seconds = best_of(repeat, lambda: run_fit_many(t, v[:B]))
    finally:
        torch.set_num_threads(1)
    wide_row = dict(B=B, seconds=seconds, rate=B / seconds, converged=int(wide.success.sum()),
                    iterations=float(wide.iterations.double().mean()), threads=threads,
                    diff=float(((wide.estimates - batched[B]["result"].estimates).abs()
                                / batched[B]["result"].estimates.abs()).nan_to_num(0.0).max()))
    print(f"... loops on the subset of {subset}", file=sys.stderr, flush=True)
    ts, vs = t, v[:subset]
    single_est, single_sse, single_status, single_seconds = run_single_loop(ts, vs)
    default_est, _, _, _ = run_single_loop(ts, vs, grid=None)
    peers = {}
    for solver in ("DOP853", "RK45"):
        est, sse, seconds = best_of(repeat, lambda: run_scipy_loop(ts, vs, solver))
        peers[solver] = dict(estimates=est, sse=sse, seconds=seconds, rate=subset / seconds)
    largest = batched[max(sizes)]["result"]
    n_cmp = min(subset, max(sizes))
    batch_est = largest.estimates[:n_cmp].numpy()
    diff = np.abs(batch_est - single_est[:n_cmp]) / np.maximum(np.abs(single_est[:n_cmp]), 1e-300)
    sse_diff = np.abs(largest.sse[:n_cmp].numpy() - single_sse[:n_cmp]) / single_sse[:n_cmp]
    grid_cost = np.abs(batch_est - default_est[:n_cmp]) / np.abs(default_est[:n_cmp])
    candidates = [reference_sse(ts, vs[:n_cmp], e[:n_cmp]) for e in (
        batch_est, fast.estimates[:n_cmp].numpy(), default_est, peers["DOP853"]["estimates"],
        peers["RK45"]["estimates"])]
    best = np.min(np.stack(candidates), axis=0)
    excess = {name: float(np.max((c - best) / best)) for name, c in
              zip(("fit_many", f"fit_many rtol={FAST_RTOL:g}", "fit (default grid)", "scipy DOP853", "scipy RK45"),
                  candidates)}
    statuses_agree = all(largest.status[i].name == single_status[i] for i in range(n_cmp))
    return dict(batched=batched, fast=fast_row, wide=wide_row, single=dict(seconds=single_seconds, rate=subset / single_seconds),
                peers=peers, repeat=repeat,
                subset=subset, n_cmp=n_cmp, max_diff=float(diff.max()), max_sse_diff=float(sse_diff.max()),
                grid_cost=float(grid_cost.max()), excess=excess, statuses_agree=statuses_agree,
                truth_error=float(np.median(np.abs(batch_est - truth[:n_cmp]) / np.abs(truth[:n_cmp]))))


def _ratio(x: float) -> str:
    return f"{x:.0f}x" if x >= 10 else f"{x:.2g}x"


def markdown(res: dict, load) -> str:
    peer_name = max(res["peers"], key=lambda k: res["peers"][k]["rate"])
    peer_rate = res["peers"][peer_name]["rate"]
    single_rate = res["single"]["rate"]
    lines = ["| method | datasets | wall time | fits / s | / scipy loop | / torchql loop | converged | mean iter "
             "| peak RSS |", "|---|---|---|---|---|---|---|---|---|"]
    for B, r in sorted(res["batched"].items()):
        lines.append(f"| torchql fit_many | {B} | {r['seconds']:.2f} s | {r['rate']:.0f} | "
                     f"**{_ratio(r['rate'] / peer_rate)}** | {_ratio(r['rate'] / single_rate)} | {r['converged']}/{B} | "
                     f"{r['iterations']:.2f} | {r['rss']:.0f} MB |")
    f = res["fast"]
    lines.append(f"| torchql fit_many, rtol={FAST_RTOL:g} | {f['B']} | {f['seconds']:.2f} s | {f['rate']:.0f} | "
                 f"{_ratio(f['rate'] / peer_rate)} | {_ratio(f['rate'] / single_rate)} | {f['converged']}/{f['B']} | "
                 f"{f['iterations']:.2f} | |")
    w = res["wide"]
    lines.append(f"| torchql fit_many, {w['threads']} threads | {w['B']} | {w['seconds']:.2f} s | {w['rate']:.0f} | "
                 f"{_ratio(w['rate'] / peer_rate)} | {_ratio(w['rate'] / single_rate)} | {w['converged']}/{w['B']} | "
                 f"{w['iterations']:.2f} | |")
    S = res["subset"]
    lines.append(f"| torchql fit, loop | {S} | {res['single']['seconds']:.2f} s | {single_rate:.1f} | "
                 f"{single_rate / peer_rate:.2f}x | 1x | | | |")
    for name, p in res["peers"].items():
        lines.append(f"| scipy least_squares + solve_ivp {name}, loop | {S} | {p['seconds']:.2f} s | {p['rate']:.1f} | "
                     f"{p['rate'] / peer_rate:.2f}x | | | | |")
    env = (f"torch {torch.__version__} ({torch.get_num_threads()} thread), scipy {scipy.__version__}, numpy "
           f"{np.__version__}, Python {platform.python_version()}, {platform.machine()}, {os.cpu_count()} CPUs; "
           f"load average {load[0]:.2f} before, {load[1]:.2f} after")
    acc = res["excess"]
    notes = [
        f"Ratios are against the faster scipy loop ({peer_name}); loops are timed on the first {S} datasets. "
        f"Every fit_many row and both scipy loops are the best of {res['repeat']} runs (the torchql loop: one "
        f"run), so that a busy moment of the machine does not decide a ratio.",
        f"Every row runs torch on 1 thread except `{w['threads']} threads` (torch's default on this machine: "
        f"every core; the loops use one); its estimates differ from the 1-thread row's by at most "
        f"{w['diff']:.1e} (relative).",
        f"Batched vs single torchql fits (same grid, first {res['n_cmp']} datasets of the largest batch): largest "
        f"relative difference of the estimates {res['max_diff']:.1e}, of the SSE {res['max_sse_diff']:.1e}; "
        f"statuses identical: {'yes' if res['statuses_agree'] else 'NO'}.",
        f"Cost of `grid={GRID}` against the default grid (1000): largest relative difference of the estimates "
        f"{res['grid_cost']:.1e}.",
        "Largest relative SSE excess over the best of the methods (closed-form solution): " + ", ".join(
            f"{k} {v:.1e}" for k, v in acc.items()) + ".",
        f"Median relative error of the estimates against the true coefficients (noise {NOISE} ft/s): "
        f"{res['truth_error']:.1e}.",
    ]
    return (f"{env}.\n\n" + "\n".join(lines) + "\n\n" + "\n".join(f"* {n}" for n in notes) + "\n")


def plot(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sizes = sorted(res["batched"])
    rates = [res["batched"][B]["rate"] for B in sizes]
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.loglog(sizes, rates, "o-", label="torchql fit_many")
    ax.axhline(res["single"]["rate"], color="C1", ls="--", label="torchql fit, Python loop")
    for k, (name, p) in enumerate(res["peers"].items()):
        ax.axhline(p["rate"], color=f"C{2 + k}", ls=":", label=f"scipy {name}, Python loop")
    ax.set_xlabel("datasets in the batch, B")
    ax.set_ylabel("fits per second")
    ax.set_title("Coasting cars: batched fitting throughput (1 CPU thread)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[10, 100, 1000, 10000],
                        help="batch sizes B (default 10 100 1000 10000)")
    parser.add_argument("--subset", type=int, default=100, help="datasets fitted by the loops (default 100)")
    parser.add_argument("--repeat", type=int, default=3,
                        help="runs of each fit_many row and scipy loop; the fastest counts (default 3)")
    parser.add_argument("--quick", action="store_true", help="smoke run: sizes 4 and 16, subset 4, one run each")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "output",
                        help="output folder (default benchmarks/output)")
    args = parser.parse_args(argv)
    if args.quick:
        args.sizes, args.subset, args.repeat = [4, 16], 4, 1
    if any(B < 1 for B in args.sizes) or args.subset < 1 or args.repeat < 1:
        parser.error("--sizes, --subset and --repeat must be positive")
    return args


def main(argv=None) -> None:
    args = parse_args(argv)
    torch.set_num_threads(1)
    load_before = os.getloadavg()[0]
    res = benchmark(list(args.sizes), args.subset, repeat=args.repeat)
    table = markdown(res, (load_before, os.getloadavg()[0]))
    print(table)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "batch.md").write_text("# batch: torchql.fit_many against loops of single fits\n\n" + table)
    plot(res, args.out / "batch.png")


if __name__ == "__main__":
    main()
