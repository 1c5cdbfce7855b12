"""Wall time of torchql fits against a SciPy peer, measured side by side in one process.

For each problem (the thesis' linear and nonlinear oscillators with exact data, the three
coasting cars of Table 4.6), this fits the same unknowns from the same start with

* torchql ``method="kantorovich"`` and ``method="shooting"``, at the default tolerances
  (``rtol=1e-10``) and at ``rtol=1e-8``;
* the peer: ``scipy.optimize.least_squares`` (trust-region reflective, finite-difference
  Jacobian) over ``scipy.integrate.solve_ivp`` with ``RK45`` and with ``DOP853`` at
  ``rtol=1e-10``, ``atol=1e-12`` (torchql's defaults).

Every configuration is warmed up once (not timed), then timed ``--repeats`` times, the
configurations of a problem interleaved round-robin so that load changes hit them alike; the
median is reported. It prints a Markdown table and writes it to ``OUT/fit_speed.md``.

Run (from the repository root)::

    python benchmarks/fit_speed.py                 # 5 repeats, writes benchmarks/output/fit_speed.md
    python benchmarks/fit_speed.py --repeats 9
    python benchmarks/fit_speed.py --quick --out /tmp/bench   # one problem, one repeat (smoke test)

See ``benchmarks/README.md`` for what each column means.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import scipy
import torch
from scipy.integrate import solve_ivp
from scipy.optimize import least_squares

import torchql
from torchql.models import CoastingCar, LinearOscillator, NonlinearOscillator

DTYPE = torch.float64
#: Tolerances that make the "exact" oscillator data.
DATA_RTOL, DATA_ATOL = 1e-13, 1e-15
#: The peer's integrator tolerances: torchql's float64 defaults.
PEER_RTOL, PEER_ATOL = 1e-10, 1e-12
#: The peer's least-squares settings (chosen so that it reaches the same accuracy as torchql on
#: the exact-data problems: relative step of the finite differences ~ sqrt(rtol) balances
#: truncation and integration noise; tight xtol/ftol so it does not stop early).
PEER_LSQ = dict(method="trf", jac="2-point", diff_step=1e-5, x_scale="jac", xtol=1e-12, ftol=1e-14, gtol=1e-14,
                max_nfev=2000)
#: Common targets: parameter error (exact data), SSE relative to the best SSE (cars).
TARGET_PARAM_ERROR = 1e-6
TARGET_SSE_EXCESS = 1e-6

# The thesis' cars (experiments/thesis.py, Table 4.6): name, frontal area (ft^2), mass (slug), velocities.
CAR_TIMES = tuple(5.0 * k for k in range(9))
CARS = (
    ("Sunbeam Alpine", 17.3, 80.43, (117.3, 104.9, 95.3, 87.3, 79.2, 71.9, 65.7, 59.8, 54.0)),
    ("Porsche 911", 18.4, 76.39, (117.3, 108.4, 100.9, 93.9, 88.0, 82.1, 76.3, 70.5, 65.4)),
    ("XKE Jaguar", 18.2, 105.59, (117.3, 108.5, 101.2, 94.6, 88.6, 82.1, 76.4, 71.6, 66.0)),
)


# ----------------------------------------------------------------------------------------------
# Problems
# ----------------------------------------------------------------------------------------------
@dataclass
class Problem:
    """One fitting problem, in torchql's and in SciPy's terms (unknowns in torchql's order)."""

    name: str
    guess_model: Callable[[], torchql.ODEModel]  # model holding the coefficient guesses
    data: torchql.Observations
    x0: torch.Tensor | None  # torchql's x0 argument (None: taken from the data)
    start: np.ndarray  # the same start as a vector of unknowns [x0..., coefficients...]
    rhs: Callable  # numpy right-hand side rhs(t, x, *coefficients)
    n_states: int
    observed: int  # index of the observed state
    truth: np.ndarray | None = None  # exact-data problems only
    model_of: Callable[[np.ndarray], torchql.ODEModel] = None  # model holding the coefficients of a vector
    best_sse: float = math.nan  # filled in after all fits (cars)
    timings: dict = field(default_factory=dict)


def _linear_rhs(t, x, A, B):
    y, v = x
    return [v, -A * v - B * y]


def _nonlinear_rhs(t, x, A, B, C, D):
    y, v = x
    return [v, -A * v - B * y - C * v**3 - D * y**3]


def _car_rhs_factory(area, mass, rho=0.00238, g=32.2):
    def rhs(t, x, C_D, mu):
        return [-0.5 * rho * area * C_D / mass * x[0] ** 2 - mu * g]
    return rhs


def exact_data(model, dt, n) -> torchql.Observations:
    t = torch.arange(n, dtype=DTYPE) * dt
    X = torchql.simulate(model, torch.tensor([0.0, 1.0], dtype=DTYPE), t, rtol=DATA_RTOL, atol=DATA_ATOL)
    return torchql.Observations(t, X[:, :1], observe=["y"])


def make_problems(quick: bool) -> list[Problem]:
    problems = [Problem(
        "linear oscillator, 14 exact points", lambda: LinearOscillator(0.5, 1.0),
        exact_data(LinearOscillator(), 0.5, 14), torch.tensor([0.5, 0.5], dtype=DTYPE),
        np.array([0.5, 0.5, 0.5, 1.0]), _linear_rhs, 2, 0, truth=np.array([0.0, 1.0, 0.1, 3.0]),
        model_of=lambda p: LinearOscillator(*p))]
    if quick:
        return problems
    problems.append(Problem(
        "nonlinear oscillator, 66 exact points", lambda: NonlinearOscillator(0.5, 2.0, 0.5, 2.0),
        exact_data(NonlinearOscillator(), 0.1, 66), torch.tensor([0.5, 0.5], dtype=DTYPE),
        np.array([0.5, 0.5, 0.5, 2.0, 0.5, 2.0]), _nonlinear_rhs, 2, 0,
        truth=np.array([0.0, 1.0, 0.1, 3.0, 0.2, 4.0]), model_of=lambda p: NonlinearOscillator(*p)))
    for name, area, mass, v in CARS:
        data = torchql.Observations(torch.tensor(CAR_TIMES, dtype=DTYPE), torch.tensor(v, dtype=DTYPE).unsqueeze(-1),
                                    observe=["v"])
        problems.append(Problem(
            f"car: {name}", (lambda a=area, m=mass: CoastingCar(a, m)), data, None,
            np.array([v[0], 0.4, 0.02]), _car_rhs_factory(area, mass), 1, 0,
            model_of=(lambda p, a=area, m=mass: CoastingCar(a, m, *p))))
    return problems


# ----------------------------------------------------------------------------------------------
# Runners: each returns a dict with the estimates, iterations, RHS evaluations, SSE and status
# ----------------------------------------------------------------------------------------------
def torchql_runner(problem: Problem, method: str, rtol: float | None):
    def run():
        r = torchql.fit(problem.guess_model(), problem.data, problem.x0, method=method, rtol=rtol)
        return dict(estimates=r.estimates.numpy().copy(), iterations=r.iterations, rhs=r.nfev, sse=r.sse,
                    status=r.status.name, ok=r.success)
    return run


class _CountingRHS:
    def __init__(self, f):
        self.f, self.calls = f, 0

    def __call__(self, t, x, *p):
        self.calls += 1
        return self.f(t, x, *p)


def peer_residuals(problem: Problem, solver: str, counter: _CountingRHS):
    t = problem.data.t.numpy()
    y = problem.data.y[:, 0].numpy()
    n = problem.n_states

    def residuals(u):
        sol = solve_ivp(counter, (t[0], t[-1]), u[:n], method=solver, t_eval=t, args=tuple(u[n:]),
                        rtol=PEER_RTOL, atol=PEER_ATOL)
        if not sol.success or sol.y.shape[1] != t.size:
            return np.full(t.size, 1e10)
        return sol.y[problem.observed] - y
    return residuals


def scipy_runner(problem: Problem, solver: str):
    def run():
        counter = _CountingRHS(problem.rhs)
        r = least_squares(peer_residuals(problem, solver, counter), problem.start, **PEER_LSQ)
        return dict(estimates=r.x.copy(), iterations=r.njev, rhs=counter.calls, sse=float(2 * r.cost),
                    status=f"status {r.status}", ok=r.status > 0, solves=r.nfev + r.njev * r.x.size)
    return run


def torchql_solve_runner(problem: Problem, estimate: np.ndarray, rtol: float | None):
    model = problem.model_of(estimate[problem.n_states:])
    x0 = torch.tensor(estimate[:problem.n_states], dtype=DTYPE)
    t = problem.data.t

    def run():
        torchql.simulate(model, x0, t, rtol=rtol)
    return run


def scipy_solve_runner(problem: Problem, estimate: np.ndarray, solver: str):
    t = problem.data.t.numpy()
    n = problem.n_states

    def run():
        solve_ivp(problem.rhs, (t[0], t[-1]), estimate[:n], method=solver, t_eval=t, args=tuple(estimate[n:]),
                  rtol=PEER_RTOL, atol=PEER_ATOL)
    return run


def time_interleaved(runners: dict, repeats: int) -> dict:
    """Warm each runner up once (untimed), then time them round-robin; returns name -> (times, last output)."""
    out = {name: ([], run()) for name, run in runners.items()}
    for _ in range(repeats):
        for name, run in runners.items():
            start = time.perf_counter()
            value = run()
            out[name][0].append(time.perf_counter() - start)
            out[name] = (out[name][0], value)
    return out


# ----------------------------------------------------------------------------------------------
# Accuracy and formatting
# ----------------------------------------------------------------------------------------------
def parameter_error(estimates: np.ndarray, truth: np.ndarray) -> float:
    """Largest error over the unknowns: relative, absolute where the truth is zero."""
    scale = np.where(truth == 0, 1.0, np.abs(truth))
    return float(np.max(np.abs(estimates - truth) / scale))


def reference_sse(problem: Problem, estimates: np.ndarray) -> float:
    """SSE of the model with ``estimates`` integrated tightly (DOP853, rtol 1e-13): the one yardstick
    for every method (each method's own SSE carries its own integration error, ~1e-6 relative at rtol 1e-8)."""
    t = problem.data.t.numpy()
    n = problem.n_states
    sol = solve_ivp(problem.rhs, (t[0], t[-1]), estimates[:n], method="DOP853", t_eval=t, args=tuple(estimates[n:]),
                    rtol=DATA_RTOL, atol=DATA_ATOL)
    return float(np.sum((sol.y[problem.observed] - problem.data.y[:, 0].numpy()) ** 2))


def accuracy(problem: Problem, value: dict) -> tuple[float, str, bool]:
    if problem.truth is not None:
        err = parameter_error(value["estimates"], problem.truth)
        return err, f"err {err:.1e}", err <= TARGET_PARAM_ERROR
    excess = (reference_sse(problem, value["estimates"]) - problem.best_sse) / problem.best_sse
    return excess, f"dSSE {excess:.1e}", excess <= TARGET_SSE_EXCESS


def fmt_time(seconds: float) -> str:
    return f"{seconds * 1e3:.0f} ms" if seconds >= 0.1 else f"{seconds * 1e3:.1f} ms"


CONFIGS = (
    ("torchql kantorovich", "rtol 1e-10 (default)", "kantorovich", None),
    ("torchql kantorovich", "rtol 1e-8", "kantorovich", 1e-8),
    ("torchql shooting", "rtol 1e-10 (default)", "shooting", None),
    ("torchql shooting", "rtol 1e-8", "shooting", 1e-8),
)
PEERS = (("scipy RK45", "RK45"), ("scipy DOP853", "DOP853"))


def benchmark(problems: list[Problem], repeats: int, configs=CONFIGS, peers=PEERS) -> list[dict]:
    rows = []
    for problem in problems:
        print(f"... {problem.name}", file=sys.stderr, flush=True)
        runners = {}
        for label, setting, method, rtol in configs:
            runners[(label, setting)] = torchql_runner(problem, method, rtol)
        for label, solver in peers:
            runners[(label, f"rtol 1e-10, {solver}")] = scipy_runner(problem, solver)
        measured = time_interleaved(runners, repeats)
        finite = [v[1]["estimates"] for v in measured.values() if np.isfinite(v[1]["estimates"]).all()]
        by_sse = sorted(((reference_sse(problem, e), i) for i, e in enumerate(finite)), key=lambda pair: pair[0])
        problem.best_sse = by_sse[0][0]

        # one forward solve of the same model over the same span at the same tolerance, at the truth
        # (exact-data problems) or at the best fit (cars)
        best = problem.truth if problem.truth is not None else finite[by_sse[0][1]]
        solve_runners = {}
        rtols = sorted({rtol for *_, rtol in configs}, key=lambda r: -1 if r is None else r)
        for rtol in rtols:
            solve_runners[("torchql", rtol)] = torchql_solve_runner(problem, best, rtol)
        for _, solver in peers:
            solve_runners[("scipy", solver)] = scipy_solve_runner(problem, best, solver)
        solves = time_interleaved(solve_runners, max(repeats, 5))
        solve_time = {k: statistics.median(v[0]) for k, v in solves.items()}

        peer_time = {}
        for label, solver in peers:
            times, _ = measured[(label, f"rtol 1e-10, {solver}")]
            peer_time[solver] = statistics.median(times)
        for (label, setting), (times, value) in measured.items():
            median = statistics.median(times)
            _, acc_text, reached = accuracy(problem, value)
            if label.startswith("torchql"):
                rtol = next(r for lab, s, _, r in configs if (lab, s) == (label, setting))
                one_solve = solve_time[("torchql", rtol)]
                ratios = {solver: median / peer_time[solver] for solver in peer_time}
            else:
                solver = setting.split(", ")[1]
                one_solve = solve_time[("scipy", solver)]
                ratios = {}
            rows.append(dict(problem=problem.name, method=label, setting=setting, status=value["status"],
                             ok=value["ok"], iterations=value["iterations"], rhs=value["rhs"], accuracy=acc_text,
                             reached=reached, median=median, spread=(min(times), max(times)), ratios=ratios,
                             one_solve=one_solve, equivalents=median / one_solve))
    return rows


def markdown(rows: list[dict], repeats: int, peers=PEERS, load=None) -> str:
    headers = ["problem", "method", "setting", "status", "iter", "RHS evals", "accuracy", "target",
               "median time"] + [f"/ {label}" for label, _ in peers] + ["one solve", "fit / solve"]
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    for r in rows:
        ratio_cells = [f"{r['ratios'][solver]:.2f}" if solver in r["ratios"] else "—" for _, solver in peers]
        cells = [r["problem"], r["method"], r["setting"], r["status"], str(r["iterations"]), str(r["rhs"]),
                 r["accuracy"], "yes" if r["reached"] else "**no**", fmt_time(r["median"])] + ratio_cells + [
                 fmt_time(r["one_solve"]), f"{r['equivalents']:.0f}"]
        lines.append("| " + " | ".join(cells) + " |")
    env = (f"torch {torch.__version__} ({torch.get_num_threads()} thread), torchdiffeq, scipy {scipy.__version__}, "
           f"numpy {np.__version__}, Python {platform.python_version()}, {platform.machine()}, "
           f"{os.cpu_count()} CPUs")
    load_text = "" if load is None else f"; load average {load[0]:.2f} before, {load[1]:.2f} after"
    return (f"Median over {repeats} repeat(s) after one untimed warm-up, configurations interleaved; "
            f"{env}{load_text}.\n\n" + "\n".join(lines) + "\n")


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5, help="timed repeats per configuration (default 5)")
    parser.add_argument("--quick", action="store_true",
                        help="smoke run: linear oscillator only, 1 repeat, default-tolerance torchql and DOP853")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "output",
                        help="output folder (default benchmarks/output)")
    return parser.parse_args(argv)


def main(argv=None) -> None:
    args = parse_args(argv)
    torch.set_num_threads(1)
    repeats = 1 if args.quick else args.repeats
    configs = (CONFIGS[0], CONFIGS[2]) if args.quick else CONFIGS
    peers = PEERS[1:] if args.quick else PEERS
    load_before = os.getloadavg()[0]
    rows = benchmark(make_problems(args.quick), repeats, configs, peers)
    table = markdown(rows, repeats, peers, (load_before, os.getloadavg()[0]))
    print(table)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "fit_speed.md").write_text("# fit_speed: torchql against scipy least_squares + solve_ivp\n\n" + table)


if __name__ == "__main__":
    main()
