"""Stiff fits: torchql ``fit`` and ``fit_many`` against scipy ``least_squares`` over ``solve_ivp(Radau)``.

Three problems, each fitted from guesses 0.3-3x the truth:

* Robertson kinetics (k1 = 0.04, k2 = 3e7, k3 = 1e4 unknown, positive), all three states
  observed at 28 log-spaced times from 1e-4 to 1e5 with 1 % multiplicative noise (sigma = 1 % of
  each true value); the initial state (1, 0, 0) known;
* van der Pol with mu = 1000 (mu unknown), y observed at 40 times over (0, 700] with noise 0.01,
  the initial state (2, 0) known: the slow drift from y = 2 towards the first relaxation jump
  (at t = 807), which sets mu (the drift's time scale is mu). The sum of squares in mu has
  spurious minima where a smaller mu's jumps fall between the data (mu ~ 290-410 here; over two
  periods, t to 3000, also at 337-565), so a local method started there stays there;
* HIRES (8 states; k1 = 1.71, k7 = 280 and k8 = 0.69 unknown, positive, the other rates known),
  all eight states observed at 25 times over [1, 321.8122] with 1 % multiplicative noise, the
  initial state of the IVP test set known: a mildly stiff network (the Jacobian's eigenvalues
  from -4e-5 to -210 along the solution, -8.3 and -10.5 throughout), where a grid interval's
  transfer must follow every mode that its intervals (0.8 wide) do not leave decayed, and
  scipy's error control on the solution alone follows only the slow ones.

torchql runs with its defaults (``solver="auto"`` detects the stiffness and takes Rodas5P for
every nonlinear pass and Radau IIA collocation for the linear transfers; a stiff model's first
reference is integrated from the guesses; for van der Pol a labelled row builds it from the data,
``initial_trajectory="data"``) and positivity bounds, at ``rtol=1e-8`` as scipy; scipy runs
``least_squares`` (trust-region reflective in log parameters, finite differences,
``x_scale="jac"``) over ``solve_ivp(method="Radau")`` at the same ``rtol`` and ``atol``, with the
right-hand side and its analytic Jacobian written in NumPy (the fair peer: a torch-evaluated
right-hand side costs scipy about 4x). ``fit_many`` fits the same dataset with ``B`` different
guesses in one call (per-fit time = total / B).

Reported: wall time (best of ``--repeats``), status and iterations, the optimum's SSE (sum of
squared weighted residuals; both methods' estimates evaluated by torchql's ``simulate`` at tight
tolerance) and whether it is within 1e-6 relative of the best SSE either method found.

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
from torchql.models import HIRES, Robertson, VanDerPol

sys.path.insert(0, str(Path(__file__).resolve().parent))
from stiff_simulate import hires_numpy, robertson_numpy, vdp_numpy  # noqa: E402  (the models in NumPy, for scipy)

DT = torch.float64
RTOL, ATOL_ROBERTSON, ATOL_VDP, ATOL_HIRES = 1e-8, 1e-14, 1e-10, 1e-12


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
    return dict(name="Robertson (k1, k2, k3)", model=Robertson, numpy=robertson_numpy, data=data, x0=x0,
                truth=truth, guesses=guesses, atol=ATOL_ROBERTSON, variants={"defaults": {}})


def vdp_problem():
    t = torch.linspace(17.5, 700.0, 40, dtype=DT)
    x0 = torch.tensor([2.0, 0.0], dtype=DT)
    x = torchql.simulate(VanDerPol(1000.0), x0, torch.cat([torch.zeros(1, dtype=DT), t]), solver="rodas5p",
                         rtol=1e-11, atol=1e-13)[1:]
    noise = torch.randn(40, 1, generator=torch.Generator().manual_seed(1), dtype=DT)
    data = torchql.Observations(t, x[:, :1] + 0.01 * noise, observe=["y"], sigma=0.01)
    guesses = [{"mu": 300.0}, {"mu": 700.0}, {"mu": 1400.0}, {"mu": 3000.0}]
    return dict(name="van der Pol mu = 1000 (mu)", model=VanDerPol, numpy=vdp_numpy, data=data, x0=x0,
                truth={"mu": 1000.0}, guesses=guesses, atol=ATOL_VDP,
                variants={"defaults": {}, "initial_trajectory='data'": {"initial_trajectory": "data"}})


def hires_problem():
    t = torch.linspace(1.0, 321.8122, 25, dtype=DT)
    x0 = torch.tensor([1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0057], dtype=DT)
    x = torchql.simulate(HIRES(), x0, torch.cat([torch.zeros(1, dtype=DT), t]), solver="rodas5p",
                         rtol=1e-11, atol=1e-16)[1:]
    noise = torch.randn(x.shape, generator=torch.Generator().manual_seed(2), dtype=DT)
    sigma = (0.01 * x).clamp(min=1e-30)
    data = torchql.Observations(t, x + sigma * noise, observe=list(HIRES().state_names), sigma=sigma)
    guesses = [{"k1": 2.0, "k7": 350.0, "k8": 0.55}, {"k1": 0.855, "k7": 560.0, "k8": 1.38},
               {"k1": 5.13, "k7": 93.3, "k8": 0.23}, {"k1": 0.57, "k7": 840.0, "k8": 2.07}]
    return dict(name="HIRES (k1, k7, k8)", model=HIRES, numpy=hires_numpy, data=data, x0=x0,
                truth={"k1": 1.71, "k7": 280.0, "k8": 0.69}, guesses=guesses, atol=ATOL_HIRES,
                variants={"defaults": {}})


PROBLEMS = {"robertson": robertson_problem, "vdp": vdp_problem, "hires": hires_problem}


def _options(problem, names):
    """torchql's options here: the defaults, positivity bounds and scipy's tolerances."""
    model = problem["model"]()
    return dict(params=list(names), fixed_x0=list(model.state_names), t0=0.0,
                bounds={name: (0.0, None) for name in names}, rtol=RTOL, atol=problem["atol"])


def torchql_fit(problem, guess, **extra):
    return torchql.fit(problem["model"](**guess), problem["data"], problem["x0"], **_options(problem, guess), **extra)


def torchql_fit_many(problem, **extra):
    guesses = problem["guesses"]
    names = list(guesses[0])
    per_sample = {name: torch.tensor([g[name] for g in guesses], dtype=DT) for name in names}
    return torchql.fit_many(problem["model"](**guesses[0]), [problem["data"]] * len(guesses), problem["x0"],
                            guesses=per_sample, **_options(problem, names), **extra)


def scipy_fit(problem, guess):
    """least_squares in log parameters (positive) over solve_ivp(Radau), NumPy right-hand side and Jacobian."""
    names = list(guess)
    data = problem["data"]
    t, y, sigma = data.t.numpy(), data.y.numpy(), data.sigma.numpy()
    x0 = problem["x0"].numpy()
    observed = [list(problem["model"]().state_names).index(s) for s in data.observe]

    def residuals(q):
        f, jac = problem["numpy"](dict(zip(names, np.exp(q).tolist())))
        try:
            sol = solve_ivp(f, (0.0, float(t[-1])), x0, method="Radau", t_eval=t, rtol=RTOL, atol=problem["atol"],
                            jac=jac)
        except (ValueError, ArithmeticError, np.linalg.LinAlgError):  # a solution that overflowed: a failure
            return np.full(y.size, 1e10)
        if not sol.success or sol.y.shape[1] != t.size:
            return np.full(y.size, 1e10)
        return ((sol.y.T[:, observed] - y) / sigma).ravel()

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


def _reached(sse, best):
    return "yes" if sse <= best * (1 + 1e-6) + 1e-9 else "no"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--quick", action="store_true", help="Robertson, first guess, one repeat")
    parser.add_argument("--only", choices=tuple(PROBLEMS), help="one problem only")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "output")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    problems = [PROBLEMS[key]() for key in (("robertson",) if args.quick else (args.only,) if args.only else PROBLEMS)]
    repeats = 1 if args.quick else args.repeats
    torchql_fit(problems[0], problems[0]["guesses"][0])  # warm-up: the first torch.func derivative of a process
    lines = ["| problem | start | torchql options | torchql (s) | status, iterations | SSE torchql | reached | "
             "scipy Radau (s) | nfev | SSE scipy | reached | time scipy/torchql |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for problem in problems:
        guesses = problem["guesses"][:1] if args.quick else problem["guesses"]
        rows = []
        for guess in guesses:
            t_sp, (est_sp, nfev) = best_time(lambda: scipy_fit(problem, guess), repeats)
            sse_sp = sse_of(problem, est_sp)
            for label, extra in problem["variants"].items():
                t_ql, result = best_time(lambda: torchql_fit(problem, guess, **extra), repeats)
                sse_ql = sse_of(problem, {name: float(result.params[name]) for name in guess})
                rows.append((guess, label, t_ql, result, sse_ql, t_sp, nfev, sse_sp))
                print(guess, label, round(t_ql, 2), result.status.name, sse_ql, round(t_sp, 2), sse_sp, flush=True)
        best = min(min(r[4], r[7]) for r in rows)
        for guess, label, t_ql, result, sse_ql, t_sp, nfev, sse_sp in rows:
            start = ", ".join(f"{n} = {v:g}" for n, v in guess.items())
            lines.append(f"| {problem['name']} | {start} | {label} | {t_ql:.2f} | {result.status.name}, "
                         f"{result.iterations} | {sse_ql:.6g} | {_reached(sse_ql, best)} | {t_sp:.2f} | {nfev} | "
                         f"{sse_sp:.6g} | {_reached(sse_sp, best)} | {t_sp / t_ql:.2f} |")
        if not args.quick:
            B = len(problem["guesses"])
            for label, extra in problem["variants"].items():
                t_b, batch = best_time(lambda: torchql_fit_many(problem, **extra), repeats)
                sse_b = [sse_of(problem, {n: float(batch.params[n][i]) for n in problem["guesses"][0]})
                         for i in range(B)]
                reached = sum(_reached(v, best) == "yes" for v in sse_b)
                lines.append(f"| {problem['name']} | fit_many, B = {B} (the starts above) | {label} | "
                             f"{t_b / B:.2f} per fit | {int(batch.success.sum())}/{B} converged | "
                             f"{max(sse_b):.6g} (largest) | {reached}/{B} | | | | | |")
        print("\n".join(lines), flush=True)
    text = "\n".join(lines) + "\n"
    args.out.mkdir(parents=True, exist_ok=True)
    if not args.quick and not args.only:
        (args.out / "stiff_fit.md").write_text(
            "# Stiff fits: torchql against scipy least_squares over solve_ivp(Radau)\n\n"
            f"`python benchmarks/stiff_fit.py` (torch {torch.__version__}, 1 thread, best of {repeats}; "
            "torchql at its defaults with positivity bounds and scipy's tolerances; scipy with a NumPy right-hand "
            "side and analytic Jacobian). 'reached': the SSE within 1e-6 relative of the best either method "
            "found on that problem.\n\n" + text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
