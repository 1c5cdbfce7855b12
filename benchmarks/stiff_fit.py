"""Stiff fits: torchql ``fit`` and ``fit_many`` against scipy ``least_squares`` over ``solve_ivp(Radau)``.

Two problems of the stiff-model issue, each fitted from guesses 0.3-3x the truth:

* Robertson kinetics (k1 = 0.04, k2 = 3e7, k3 = 1e4 unknown, positive), all three states
  observed at 28 log-spaced times from 1e-4 to 1e5 with 1 % multiplicative noise (sigma = 1 % of
  each true value); the initial state (1, 0, 0) known;
* van der Pol with mu = 1000 (mu unknown), y observed at 40 times over two relaxation periods
  (t to 3000) with noise 0.01; the initial state known.

torchql runs with ``solver="rodas5p"`` and ``linear_solver="radau"`` (the stiff path: an implicit
Rosenbrock solver for every nonlinear pass, Radau IIA collocation for the linear transfers, early
geometric grid nodes), its tolerances ``rtol=1e-8``; scipy runs ``least_squares`` (trust-region
reflective, bounds 0 < k, finite differences, ``x_scale="jac"``) over ``solve_ivp(method="Radau")``
at the same ``rtol=1e-8`` with the model's analytic Jacobian. ``fit_many`` fits the same dataset
with ``B`` different guesses in one call (per-fit time = total / B).

Reported: wall time (best of ``--repeats``), the optimum's SSE (sum of squared weighted
residuals, both evaluated by torchql's ``simulate`` at tight tolerance) and the largest relative
difference of the estimates from scipy's.

Run (from the repository root)::

    python benchmarks/stiff_fit.py               # writes benchmarks/output/stiff_fit.md
    python benchmarks/stiff_fit.py --quick       # Robertson only, one repeat (smoke test)
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
from scipy.integrate import solve_ivp
from scipy.optimize import least_squares

import torchql
from torchql.models import Robertson, VanDerPol

DT = torch.float64
RTOL, ATOL_ROBERTSON, ATOL_VDP = 1e-8, 1e-14, 1e-10


def robertson_problem():
    t = torch.logspace(-4, 5, 28, dtype=DT)
    x0 = torch.tensor([1.0, 0.0, 0.0], dtype=DT)
    x = torchql.simulate(Robertson(), x0, torch.cat([torch.zeros(1, dtype=DT), t]), solver="rodas5p",
                         rtol=1e-11, atol=1e-16)[1:]
    noise = torch.randn(x.shape, generator=torch.Generator().manual_seed(0), dtype=DT)
    sigma = (0.01 * x).clamp(min=1e-30)
    data = torchql.Observations(t, x + sigma * noise, observe=["y1", "y2", "y3"], sigma=sigma)
    truth = {"k1": 0.04, "k2": 3e7, "k3": 1e4}
    guesses = [{"k1": 0.08, "k2": 1.5e7, "k3": 2e4}, {"k1": 0.012, "k2": 9e7, "k3": 3e3},
               {"k1": 0.12, "k2": 1e7, "k3": 3e4}, {"k1": 0.02, "k2": 6e7, "k3": 5e3}]
    return dict(name="Robertson (k1, k2, k3)", model=Robertson, data=data, x0=x0, truth=truth, guesses=guesses,
                atol=ATOL_ROBERTSON)


def vdp_problem():
    t = torch.linspace(30.0, 3000.0, 40, dtype=DT)
    x0 = torch.tensor([2.0, 0.0], dtype=DT)
    x = torchql.simulate(VanDerPol(1000.0), x0, torch.cat([torch.zeros(1, dtype=DT), t]), solver="rodas5p",
                         rtol=1e-11, atol=1e-13)[1:]
    noise = torch.randn(40, 1, generator=torch.Generator().manual_seed(1), dtype=DT)
    data = torchql.Observations(t, x[:, :1] + 0.01 * noise, observe=["y"], sigma=0.01)
    guesses = [{"mu": 700.0}, {"mu": 1400.0}, {"mu": 600.0}, {"mu": 2000.0}]
    return dict(name="van der Pol mu = 1000 (mu)", model=VanDerPol, data=data, x0=x0, truth={"mu": 1000.0},
                guesses=guesses, atol=ATOL_VDP)


def torchql_fit(problem, guess):
    model = problem["model"](**guess)
    bounds = {name: (0.0, None) for name in guess}
    return torchql.fit(model, problem["data"], problem["x0"], params=list(guess), fixed_x0=list(model.state_names),
                       t0=0.0, bounds=bounds, solver="rodas5p", linear_solver="radau", rtol=RTOL,
                       atol=problem["atol"])


def torchql_fit_many(problem):
    guesses = problem["guesses"]
    names = list(guesses[0])
    B = len(guesses)
    model = problem["model"](**guesses[0])
    per_sample = {name: torch.tensor([g[name] for g in guesses], dtype=DT) for name in names}
    return torchql.fit_many(model, [problem["data"]] * B, problem["x0"], params=names, guesses=per_sample,
                            fixed_x0=list(model.state_names), t0=0.0, bounds={n: (0.0, None) for n in names},
                            solver="rodas5p", linear_solver="radau", rtol=RTOL, atol=problem["atol"])


def scipy_fit(problem, guess):
    """least_squares in log parameters (positive) over solve_ivp(Radau) with the analytic Jacobian."""
    names = list(guess)
    data = problem["data"]
    t = data.t.numpy()
    y = data.y.numpy()
    sigma = data.sigma.numpy()
    x0 = problem["x0"].numpy()
    n = x0.size
    observed = [list(problem["model"]().state_names).index(s) for s in data.observe]
    template = problem["model"]()

    def rhs_and_jac(p):
        model = problem["model"](**dict(zip(names, p.tolist())))

        def f(tt, x):
            with torch.no_grad():
                return model(torch.tensor(tt, dtype=DT), torch.as_tensor(x, dtype=DT)).numpy()

        def jac(tt, x):
            return torch.func.jacrev(lambda z: model(torch.tensor(tt, dtype=DT), z))(
                torch.as_tensor(x, dtype=DT)).numpy()
        return f, jac

    def residuals(q):
        f, jac = rhs_and_jac(np.exp(q))
        sol = solve_ivp(f, (0.0, float(t[-1])), x0, method="Radau", t_eval=t, rtol=RTOL, atol=problem["atol"],
                        jac=jac)
        if not sol.success or sol.y.shape[1] != t.size:
            return np.full(y.size, 1e10)
        return ((sol.y.T[:, observed] - y) / sigma).ravel()

    del template, n
    q0 = np.log([guess[k] for k in names])
    out = least_squares(residuals, q0, method="trf", x_scale="jac", xtol=1e-10, ftol=1e-10)
    return dict(zip(names, np.exp(out.x).tolist())), out.nfev


def sse_of(problem, estimates):
    model = problem["model"](**estimates)
    data = problem["data"]
    x = torchql.simulate(model, problem["x0"], torch.cat([torch.zeros(1, dtype=DT), data.t]), solver="rodas5p",
                         rtol=1e-11, atol=problem["atol"] * 1e-2)[1:]
    index = [list(model.state_names).index(s) for s in data.observe]
    return float((((x[:, index] - data.y) / data.sigma) ** 2).sum())


def best_time(run, repeats):
    best, out = math.inf, None
    for _ in range(repeats):
        start = time.perf_counter()
        out = run()
        best = min(best, time.perf_counter() - start)
    return best, out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--quick", action="store_true", help="Robertson, first guess, one repeat")
    parser.add_argument("--only", choices=("robertson", "vdp"), help="one problem only")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "output")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    problems = [robertson_problem()] if args.quick else [robertson_problem(), vdp_problem()]
    if args.only:
        problems = [robertson_problem() if args.only == "robertson" else vdp_problem()]
    repeats = 1 if args.quick else args.repeats
    lines = ["| problem | start | torchql fit (s) | status, iterations | scipy Radau (s) | scipy nfev | "
             "SSE torchql | SSE scipy | max rel. diff. | ratio scipy/torchql |", "|---|---|---|---|---|---|---|---|---|---|"]
    for problem in problems:
        guesses = problem["guesses"][:1] if args.quick else problem["guesses"]
        for k, guess in enumerate(guesses):
            t_ql, result = best_time(lambda: torchql_fit(problem, guess), repeats)
            t_sp, (est_sp, nfev) = best_time(lambda: scipy_fit(problem, guess), repeats)
            est_ql = {name: float(result.params[name]) for name in guess}
            diff = max(abs(est_ql[n] - est_sp[n]) / abs(est_sp[n]) for n in guess)
            lines.append(f"| {problem['name']} | {k} | {t_ql:.2f} | {result.status.name}, {result.iterations} | "
                         f"{t_sp:.2f} | {nfev} | {sse_of(problem, est_ql):.6g} | {sse_of(problem, est_sp):.6g} | "
                         f"{diff:.1e} | {t_sp / t_ql:.2f} |")
            print(lines[-1], flush=True)
        if not args.quick:
            t_b, batch = best_time(lambda: torchql_fit_many(problem), repeats)
            B = len(problem["guesses"])
            lines.append(f"| {problem['name']} | fit_many, B = {B} | {t_b / B:.2f} per fit | "
                         f"{int(batch.success.sum())}/{B} converged | | | "
                         f"{float(batch.sse.nanmean()):.6g} (mean) | | | |")
            print(lines[-1], flush=True)
    text = "\n".join(lines) + "\n"
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "stiff_fit.md").write_text(
        "# Stiff fits: torchql against scipy least_squares over solve_ivp(Radau)\n\n"
        f"`python benchmarks/stiff_fit.py` (torch {torch.__version__}, 1 thread, best of {repeats})\n\n" + text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
