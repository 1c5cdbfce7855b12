"""Quasilinearization against gradient-based fitting: iterations, RHS evaluations, wall time, accuracy.

Problems (all float64):

* (a) the thesis' linear oscillator ``y'' + A y' + B y = 0`` and (b) nonlinear oscillator
  ``y'' + A y' + B y + C y'^3 + D y^3 = 0``; y at t = 0, 0.5, ..., 6.5 (14 points) from the
  truth (y0 = 0, y0' = 1, A = 0.1, B = 3, C = 0.2, D = 4), rounded to 6 and to 2 significant
  digits; the thesis' guesses (0.5, 0.5, 0.5, 1.0) and (0.5, 0.5, 0.5, 2.0, 0.5, 2.0);
* (c) the thesis' three coasting cars (C_D, mu and v0 from nine measured velocities; guesses
  C_D = 0.4, mu = 0.02, v0 = the first measurement);
* (d) a model not in the thesis with noisy data: FitzHugh-Nagumo ``V' = c (V - V^3/3 + R)``,
  ``R' = -(V - a + b R) / c``, a = b = 0.2, c = 3, V0 = -1, R0 = 1, both states observed every
  0.5 on [0, 20] with Gaussian noise of sd 0.05 (seed 0, sigma given); guess a = b = 0.25,
  c = 2.5, initial state from the first observations.

Methods: torchql ``fit`` (kantorovich and shooting; default tolerances), ``adjoint_fit`` with
Adam and with L-BFGS (adjoint gradients, torchdiffeq's default rtol 1e-7; budgets below), and
``scipy.optimize.least_squares(method="lm")`` over ``scipy.integrate.solve_ivp`` (DOP853, rtol
1e-10, atol 1e-12, central-difference Jacobian).

Recorded per method: iterations, right-hand-side evaluations, wall time, parameter error
(against the truth for the 6-digit data; against the lowest-SSE estimate found by any method
otherwise) and the SSE reached (every method's final estimate re-evaluated the same way, at
rtol 1e-12); traces of error and SSE against iteration and wall time.

Run (from the repository root)::

    python experiments/vs_gradient.py              # writes experiments/output/vs_gradient.{md,png}
    python experiments/vs_gradient.py --quick      # one problem, tiny budgets (< 1 minute)
    python experiments/vs_gradient.py --out DIR
"""

from __future__ import annotations

import argparse
import copy
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from scipy.integrate import solve_ivp  # noqa: E402
from scipy.optimize import least_squares  # noqa: E402

import torchql  # noqa: E402
from torchql.baselines import adjoint_fit  # noqa: E402
from torchql.models import CoastingCar, LinearOscillator, NonlinearOscillator  # noqa: E402

DT = torch.float64
#: Budgets of the gradient runs (full run; --quick uses QUICK_BUDGETS).
BUDGETS = {"adam": dict(max_steps=3000, max_time=15.0), "lbfgs": dict(max_steps=500, max_time=15.0)}
QUICK_BUDGETS = {"adam": dict(max_steps=15, max_time=5.0), "lbfgs": dict(max_steps=40, max_time=6.0)}
SCIPY_RTOL, SCIPY_ATOL = 1e-10, 1e-12
METHOD_LABELS = {"kantorovich": "torchql kantorovich", "shooting": "torchql shooting", "adam": "adjoint + Adam",
                 "lbfgs": "adjoint + L-BFGS", "scipy": "scipy LM + solve_ivp"}
COLORS = {"kantorovich": "C0", "shooting": "C1", "adam": "C3", "lbfgs": "C2", "scipy": "C4"}

CAR_TIMES = tuple(5.0 * k for k in range(9))
CARS = (
    ("Sunbeam Alpine", 17.3, 80.43, (117.3, 104.9, 95.3, 87.3, 79.2, 71.9, 65.7, 59.8, 54.0)),
    ("Porsche 911", 18.4, 76.39, (117.3, 108.4, 100.9, 93.9, 88.0, 82.1, 76.3, 70.5, 65.4)),
    ("XKE Jaguar", 18.2, 105.59, (117.3, 108.5, 101.2, 94.6, 88.6, 82.1, 76.4, 71.6, 66.0)),
)


class FitzHughNagumo(torchql.ODEModel):
    """``V' = c (V - V^3/3 + R)``, ``R' = -(V - a + b R) / c``."""

    state_names = ("V", "R")

    def __init__(self, a: float = 0.2, b: float = 0.2, c: float = 3.0) -> None:
        super().__init__()
        for name, value in (("a", a), ("b", b), ("c", c)):
            self.register_buffer(name, torch.tensor(float(value), dtype=DT))

    def forward(self, t, x):
        V, R = x.unbind(-1)
        return torch.stack((self.c * (V - V**3 / 3 + R), -(V - self.a + self.b * R) / self.c), dim=-1)


@dataclass
class Problem:
    name: str
    model: torchql.ODEModel  # at the guesses
    data: torchql.Observations
    x0: torch.Tensor | None
    truth: torch.Tensor | None  # unknowns in unknown_names order, when the reference is the truth
    note: str = ""


@dataclass
class Run:
    method: str
    status: str
    iterations: int
    nfev: int
    wall: float
    estimates: torch.Tensor
    trace_est: list = field(default_factory=list)  # estimates per iteration
    trace_sse: list = field(default_factory=list)
    trace_time: list = field(default_factory=list)
    sse: float = float("nan")
    error: float = float("nan")
    trace_err: list = field(default_factory=list)


# ----------------------------------------------------------------------------------------------
def round_significant(values: torch.Tensor, digits: int) -> torch.Tensor:
    return torch.tensor([float(f"{v:.{digits - 1}e}") for v in values.tolist()], dtype=values.dtype)


def oscillator_problems(nonlinear: bool, digits_list) -> list[Problem]:
    t = torch.arange(14, dtype=DT) * 0.5
    truth_model = NonlinearOscillator() if nonlinear else LinearOscillator()
    y = torchql.simulate(truth_model, torch.tensor([0.0, 1.0], dtype=DT), t, rtol=1e-13, atol=1e-15)[:, 0]
    truth = torch.tensor([0.0, 1.0, 0.1, 3.0, 0.2, 4.0] if nonlinear else [0.0, 1.0, 0.1, 3.0], dtype=DT)
    out = []
    for d in digits_list:
        data = torchql.Observations(t, round_significant(y, d).unsqueeze(-1), observe=["y"])
        model = NonlinearOscillator(0.5, 2.0, 0.5, 2.0) if nonlinear else LinearOscillator(0.5, 1.0)
        kind = "nonlinear" if nonlinear else "linear"
        out.append(Problem(f"{kind} oscillator, {d}-digit data", model, data, torch.tensor([0.5, 0.5], dtype=DT),
                           truth if d >= 6 else None))
    return out


def car_problems() -> list[Problem]:
    t = torch.tensor(CAR_TIMES, dtype=DT)
    return [Problem(f"car: {name}", CoastingCar(area, mass), torchql.Observations(t, torch.tensor(v, dtype=DT),
                                                                                    observe=["v"]), None, None)
            for name, area, mass, v in CARS]


def fhn_problem() -> Problem:
    t = torch.arange(41, dtype=DT) * 0.5
    x = torchql.simulate(FitzHughNagumo(), torch.tensor([-1.0, 1.0], dtype=DT), t, rtol=1e-13, atol=1e-15)
    gen = torch.Generator().manual_seed(0)
    y = x + 0.05 * torch.randn(x.shape, generator=gen, dtype=DT)
    data = torchql.Observations(t, y, observe=["V", "R"], sigma=0.05)
    return Problem("FitzHugh-Nagumo, noisy (sd 0.05)", FitzHughNagumo(0.25, 0.25, 2.5), data, None, None,
                   note="truth V0 = -1, R0 = 1, a = b = 0.2, c = 3")


# ----------------------------------------------------------------------------------------------
def unknowns_of(record: torchql.IterationRecord, names: list[str], state_names) -> torch.Tensor:
    values = []
    for name in names:
        if name.endswith("(t0)") and name[:-4] in state_names:
            values.append(record.x0[list(state_names).index(name[:-4])])
        else:
            values.append(record.params[name].reshape(()))
    return torch.stack(values).detach()


def run_torchql(problem: Problem, method: str) -> tuple[Run, list[str]]:
    times = []
    start = time.perf_counter()
    result = torchql.fit(problem.model, problem.data, x0=problem.x0, method=method,
                         callback=lambda rec: times.append(time.perf_counter() - start))
    wall = time.perf_counter() - start
    states = problem.model.state_names
    hist = result.history[: len(times)]
    run = Run(method, result.status.name, result.iterations, result.nfev, wall, result.estimates.clone(),
              [unknowns_of(r, result.unknown_names, states) for r in hist], [r.sse for r in hist], times)
    return run, result.unknown_names


def run_gradient(problem: Problem, optimizer: str, budgets) -> Run:
    times, est, sses = [], [], []
    start = time.perf_counter()

    def cb(step, sse, estimates):
        times.append(time.perf_counter() - start)
        est.append(estimates)
        sses.append(sse)

    result = adjoint_fit(problem.model, problem.data, x0=problem.x0, optimizer=optimizer, callback=cb,
                         **budgets[optimizer])
    wall = time.perf_counter() - start
    return Run(optimizer, result.status.name, result.iterations, result.nfev, wall, result.estimates.clone(), est,
               sses, times)


class _ScipyProblem:
    """Residuals ``(y - h(x(t))) / sigma`` of the model integrated by solve_ivp; counts RHS calls."""

    def __init__(self, problem: Problem, names: list[str]):
        model = problem.model
        self.states = list(model.state_names)
        self.names = names
        self.param_names = [n for n in names if not (n.endswith("(t0)") and n[:-4] in self.states)]
        self.buffers = {k: float(v) for k, v in model.named_buffers()}
        data = problem.data
        self.t = data.t.numpy()
        self.y = data.y.numpy()
        self.w = 1.0 / data.sigma.numpy()
        self.observe = [self.states.index(s) for s in data.observe]
        self.nfev = 0
        self.rhs = self._make_rhs(model)

    def _make_rhs(self, model):
        kind = type(model).__name__

        def rhs(t, x, p):
            self.nfev += 1
            if kind == "LinearOscillator":
                return [x[1], -p["A"] * x[1] - p["B"] * x[0]]
            if kind == "NonlinearOscillator":
                return [x[1], -p["A"] * x[1] - p["B"] * x[0] - p["C"] * x[1] ** 3 - p["D"] * x[0] ** 3]
            if kind == "CoastingCar":
                drag = 0.5 * p["rho"] * p["frontal_area"] * p["C_D"] / p["mass"]
                return [-drag * x[0] ** 2 - p["mu"] * p["g"]]
            if kind == "FitzHughNagumo":
                V, R = x
                return [p["c"] * (V - V**3 / 3 + R), -(V - p["a"] + p["b"] * R) / p["c"]]
            raise NotImplementedError(kind)

        return rhs

    def split(self, u: np.ndarray):
        p = dict(self.buffers)
        x0 = np.zeros(len(self.states))
        for name, value in zip(self.names, u):
            if name in self.param_names:
                p[name] = value
            else:
                x0[self.states.index(name[:-4])] = value
        return x0, p

    def residuals(self, u: np.ndarray) -> np.ndarray:
        x0, p = self.split(u)
        sol = solve_ivp(self.rhs, (self.t[0], self.t[-1]), x0, method="DOP853", t_eval=self.t, args=(p,),
                        rtol=SCIPY_RTOL, atol=SCIPY_ATOL)
        if not sol.success or sol.y.shape[1] != len(self.t):
            return np.full(self.y.size, 1e6)
        pred = sol.y[self.observe].T
        return ((self.y - pred) * self.w).ravel()

    def jacobian(self, u: np.ndarray) -> np.ndarray:
        """Central differences, step 1e-4 max(|u_i|, 0.1)."""
        cols = []
        for i in range(len(u)):
            h = 1e-4 * max(abs(u[i]), 0.1)
            up, dn = u.copy(), u.copy()
            up[i] += h
            dn[i] -= h
            cols.append((self.residuals(up) - self.residuals(dn)) / (2 * h))
        return np.stack(cols, axis=1)


def run_scipy(problem: Problem, names: list[str], u0: torch.Tensor) -> Run:
    sp = _ScipyProblem(problem, names)
    times, est, sses = [], [], []
    start = time.perf_counter()

    def jac(u):  # called once per accepted iterate: the trace
        r = sp.residuals(u)
        times.append(time.perf_counter() - start)
        est.append(torch.tensor(u, dtype=DT))
        sses.append(float(r @ r))
        return sp.jacobian(u)

    out = least_squares(sp.residuals, u0.numpy(), jac=jac, method="lm", xtol=1e-12, ftol=1e-12, gtol=1e-12)
    wall = time.perf_counter() - start
    status = "CONVERGED" if out.success else "FAILED"
    return Run("scipy", f"{status} ({out.status})", int(out.njev), sp.nfev, wall, torch.tensor(out.x, dtype=DT),
               est, sses, times)


# ----------------------------------------------------------------------------------------------
def sse_at(problem: Problem, names: list[str], u: torch.Tensor) -> float:
    """Weighted SSE of the model at unknowns ``u``, integrated at rtol 1e-12 (the common yardstick)."""
    if not torch.isfinite(u).all():
        return float("nan")
    states = list(problem.model.state_names)
    model = copy.deepcopy(problem.model)
    x0 = problem.x0.clone() if problem.x0 is not None else problem.data.y[0].clone()
    for name, value in zip(names, u):
        if name.endswith("(t0)") and name[:-4] in states:
            x0[states.index(name[:-4])] = value
        else:
            model._buffers[name] = value.clone().reshape(())
    try:
        x = torchql.simulate(model, x0, problem.data.t, rtol=1e-12, atol=1e-14)
    except torchql.IntegrationError:
        return float("nan")
    idx = [states.index(s) for s in problem.data.observe]
    r = (problem.data.y - x[:, idx]) / problem.data.sigma
    return float((r[~torch.isnan(r)] ** 2).sum())


def param_error(u: torch.Tensor, ref: torch.Tensor) -> float:
    """Largest relative error; absolute where the reference is below 0.01 in magnitude."""
    if not torch.isfinite(u).all():
        return float("nan")
    scale = torch.where(ref.abs() >= 1e-2, ref.abs(), torch.ones_like(ref))
    return float(((u - ref).abs() / scale).max())


def solve_problem(problem: Problem, budgets) -> tuple[list[Run], list[str], torch.Tensor, str]:
    runs = []
    for method in ("kantorovich", "shooting"):
        run, names = run_torchql(problem, method)
        runs.append(run)
        print(f"  {METHOD_LABELS[method]:22s} {run.status:18s} it {run.iterations:5d}  {run.wall:7.2f} s", flush=True)
    guess = runs[0].trace_est[0]
    for optimizer in ("adam", "lbfgs"):
        run = run_gradient(problem, optimizer, budgets)
        runs.append(run)
        print(f"  {METHOD_LABELS[optimizer]:22s} {run.status:18s} it {run.iterations:5d}  {run.wall:7.2f} s", flush=True)
    run = run_scipy(problem, names, guess)
    runs.append(run)
    print(f"  {METHOD_LABELS['scipy']:22s} {run.status:18s} it {run.iterations:5d}  {run.wall:7.2f} s", flush=True)
    for run in runs:
        run.sse = sse_at(problem, names, run.estimates)
    if problem.truth is not None:
        ref, ref_name = problem.truth, "the truth"
    else:
        finite = [r for r in runs if math.isfinite(r.sse)]
        best = min(finite, key=lambda r: r.sse)
        ref, ref_name = best.estimates, f"the lowest-SSE estimate ({METHOD_LABELS[best.method]})"
    for run in runs:
        run.error = param_error(run.estimates, ref)
        run.trace_err = [param_error(u, ref) for u in run.trace_est]
    return runs, names, ref, ref_name


# ----------------------------------------------------------------------------------------------
def table(runs: list[Run]) -> list[str]:
    lines = ["| method | status | iterations | RHS evals | wall time (s) | param. error | SSE |",
             "|---|---|---|---|---|---|---|"]
    for r in runs:
        lines.append(f"| {METHOD_LABELS[r.method]} | {r.status} | {r.iterations} | {r.nfev} | {r.wall:.2f} | "
                     f"{r.error:.2e} | {r.sse:.4g} |")
    return lines


def findings(results) -> list[str]:
    out = []
    for problem, runs, names, ref, ref_name in results:
        by = {r.method: r for r in runs}
        best_ql = min((by["kantorovich"], by["shooting"]), key=lambda r: r.error if math.isfinite(r.error) else 1e9)
        tol = max(10 * best_ql.error, 1e-6) if math.isfinite(best_ql.error) else float("nan")
        parts = []
        for m in ("lbfgs", "adam", "scipy"):
            r = by[m]
            if math.isfinite(r.error) and r.error <= tol:
                ratio = r.wall / max(best_ql.wall, 1e-9)
                parts.append(f"{METHOD_LABELS[m]} matches it ({r.error:.1e}) in {r.wall:.2g} s ({ratio:.2g}x the time, "
                             f"{r.nfev / max(best_ql.nfev, 1):.1f}x the RHS evaluations)")
            else:
                parts.append(f"{METHOD_LABELS[m]} stops at error {r.error:.1e} ({r.status}, {r.iterations} iterations, "
                             f"{r.wall:.2g} s)")
        out.append(f"* **{problem.name}**: {METHOD_LABELS[best_ql.method]} reaches error {best_ql.error:.1e} in "
                   f"{best_ql.iterations} iterations and {best_ql.wall:.2g} s; " + "; ".join(parts) + ".")
    return out


def summary(results) -> list[str]:
    """Counts over the problems: who reached the best torchql accuracy (10x), and the median wall times."""
    n = len(results)
    reached = {m: 0 for m in ("kantorovich", "shooting", "adam", "lbfgs", "scipy")}
    walls = {m: [] for m in reached}
    for problem, runs, names, ref, ref_name in results:
        by = {r.method: r for r in runs}
        best = min(r.error for r in (by["kantorovich"], by["shooting"]) if math.isfinite(r.error))
        for m, r in by.items():
            walls[m].append(r.wall)
            if math.isfinite(r.error) and r.error <= max(10 * best, 1e-6):
                reached[m] += 1
    lines = ["Over the problems: reached the better torchql error (within 10x, or 1e-6): " + ", ".join(
        f"{METHOD_LABELS[m]} {reached[m]}/{n}" for m in reached) + ". Median wall time: " + ", ".join(
        f"{METHOD_LABELS[m]} {float(np.median(walls[m])):.2g} s" for m in walls) + "."]
    return lines


def write_markdown(results, path: Path, budgets, total: float, quick: bool) -> None:
    lines = ["# torchql against gradient-based fitting", ""]
    lines += [
        "Generated by `experiments/vs_gradient.py`" + (" --quick" if quick else "") + f" in {total:.0f} s "
        "(2 shared CPU cores, one torch thread).", "",
        "Methods: torchql `fit` (`kantorovich`, `shooting`; default rtol 1e-10); `torchql.baselines.adjoint_fit` "
        "with Adam (lr 1e-2 in the normalized space) and with L-BFGS (strong-Wolfe line search), gradients "
        "by `torchdiffeq.odeint_adjoint` at torchdiffeq's default rtol 1e-7 / atol 1e-9; "
        "`scipy.optimize.least_squares(method=\"lm\")` over `solve_ivp` (DOP853, rtol 1e-10, atol 1e-12, "
        "central-difference Jacobian).", "",
        f"**Budgets of the gradient runs**: Adam at most {budgets['adam']['max_steps']} steps and "
        f"{budgets['adam']['max_time']:g} s of wall time per problem; L-BFGS at most {budgets['lbfgs']['max_steps']} "
        f"steps and {budgets['lbfgs']['max_time']:g} s. A run that stops on its budget says `MAX_ITER`.", "",
        "Columns: *iterations* are updates (torchql), optimizer steps (Adam, L-BFGS; an L-BFGS step may "
        "evaluate the loss several times in its line search) and Jacobian evaluations = accepted iterates "
        "(scipy LM); *RHS evals* counts calls of the model's right-hand side (for the adjoint runs forward and "
        "backward solves; for torchql the batched calls of its linearized systems; for scipy including the "
        "finite-difference Jacobian); *param. error* is the largest relative error of the unknowns (absolute "
        "where the reference is below 0.01) against the reference named under each table; *SSE* is every "
        "method's final estimate re-integrated at rtol 1e-12 (weighted by 1/sigma for the noisy problem).", "",
    ]
    for problem, runs, names, ref, ref_name in results:
        lines += [f"## {problem.name}", ""]
        lines += [f"Unknowns {', '.join(names)}; reference: {ref_name} = "
                  f"({', '.join(f'{v:.6g}' for v in ref.tolist())})." + (f" ({problem.note})" if problem.note else ""),
                  ""]
        lines += table(runs) + [""]
    lines += ["## Findings", ""] + findings(results) + [""]
    lines += summary(results) + [""]
    path.write_text("\n".join(lines))


def plot(results, path: Path) -> None:
    n = len(results)
    fig, axes = plt.subplots(n, 4, figsize=(18, 3.2 * n + 0.6), squeeze=False)
    for row, (problem, runs, names, ref, ref_name) in enumerate(results):
        for run in runs:
            k = np.arange(len(run.trace_err))
            err = np.array(run.trace_err, dtype=float)
            sse = np.array(run.trace_sse, dtype=float)
            tt = np.array(run.trace_time, dtype=float)
            style = dict(color=COLORS[run.method], label=METHOD_LABELS[run.method], lw=1.3,
                         marker="o" if len(k) < 60 else None, ms=3)
            axes[row, 0].plot(k, err, **style)
            axes[row, 1].plot(tt, err, **style)
            axes[row, 2].plot(k, sse, **style)
            axes[row, 3].plot(tt, sse, **style)
        for col, (xl, yl) in enumerate((("iteration", "param. error"), ("wall time (s)", "param. error"),
                                        ("iteration", "SSE"), ("wall time (s)", "SSE"))):
            ax = axes[row, col]
            ax.set_yscale("log")
            if col in (0, 2):
                ax.set_xscale("symlog", linthresh=10)
            ax.set_xlabel(xl)
            ax.set_ylabel(yl)
            ax.grid(alpha=0.3)
        axes[row, 0].set_title(problem.name, loc="left", fontsize=10)
    axes[0, 3].legend(fontsize=8)
    fig.suptitle("Parameter error and SSE against iteration and wall time (log scales)")
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="one problem, tiny budgets (< 1 minute)")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "output")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    args.out.mkdir(parents=True, exist_ok=True)
    budgets = QUICK_BUDGETS if args.quick else BUDGETS
    if args.quick:
        problems = oscillator_problems(False, (6,))
    else:
        problems = (oscillator_problems(False, (6, 2)) + oscillator_problems(True, (6, 2)) + car_problems()
                    + [fhn_problem()])
    run_torchql(problems[0], "kantorovich")  # untimed: a process' first torch.func derivative costs about 1 s
    start = time.perf_counter()
    results = []
    for problem in problems:
        print(problem.name, flush=True)
        runs, names, ref, ref_name = solve_problem(problem, budgets)
        results.append((problem, runs, names, ref, ref_name))
    total = time.perf_counter() - start
    write_markdown(results, args.out / "vs_gradient.md", budgets, total, args.quick)
    plot(results, args.out / "vs_gradient.png")
    print(f"wrote {args.out / 'vs_gradient.md'} and {args.out / 'vs_gradient.png'} in {total:.0f} s")


if __name__ == "__main__":
    main()
