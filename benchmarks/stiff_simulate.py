"""Stiff simulation: ``torchql.simulate(..., solver="rodas5p")`` against scipy's Radau and BDF.

For each stiff problem and tolerance, the same integration from the same start by

* torchql's default, ``solver="auto"`` (``torchql.simulate(model, x0, [t0, t_end])``: Rodas5P where
  the model is stiff at ``x0``, else DOP853, and Rodas5P again where DOP853 finds it stiff);
* torchql's Rodas5P (``torchql.simulate(model, x0, [t0, t_end], solver="rodas5p")``);
* ``scipy.integrate.solve_ivp`` with ``Radau`` and ``BDF``, given the analytic Jacobian (the
  peers' best case: without it they difference the right-hand side for their Jacobians);

reporting the wall time (best of ``--repeats``), the steps (accepted, then rejected), the
right-hand-side and Jacobian evaluations, and the error at the end against a reference solution
in the mixed norm ``max |y - ref| / (atol + rtol |ref|)`` (1 = one tolerance). Problems:

* Robertson to ``t = 1e5`` (reference: scipy Radau at ``rtol = 1e-13``; ``atol = 1e-6 rtol``);
* HIRES to ``t = 321.8122`` (reference: the IVP test set's, Mazzia and Magherini; ``atol = 1e-4 rtol``);
* van der Pol, ``mu = 1000``, from ``(2, 0)`` to ``t = 1000`` through the first jump (reference:
  scipy Radau at ``rtol = atol = 1e-13``; ``atol = rtol``).

It also times torchdiffeq's ``dopri5`` (``simulate``'s default before ``"auto"``) on Robertson to
``t = 1e3`` under a wall-clock cap, to show why an implicit solver is needed. Writes ``OUT/stiff_simulate.md``.

Run (from the repository root)::

    python benchmarks/stiff_simulate.py                        # rtol 1e-6 and 1e-8, 3 repeats
    python benchmarks/stiff_simulate.py --quick --out /tmp/b   # smoke run (seconds)
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import scipy
import torch
from scipy.integrate import solve_ivp

import torchql
from torchql.budget import TimeBudgetExceeded, time_budget
from torchql.integrate import CountedField, solve
from torchql.models import HIRES, Robertson, VanDerPol
from torchql.models.stiff import HIRES_REFERENCE
from torchql.solvers import rodas5p_solve

DT = torch.float64
#: Robertson at t = 1e5 from (1, 0, 0), scipy Radau at rtol = 1e-13, atol = 1e-22.
ROBERTSON_1E5 = (1.7865921142100227e-02, 7.2747514684365823e-08, 9.8213400611039237e-01)
HIRES_K = (1.71, 0.43, 8.32, 0.69, 0.035, 8.32, 280.0, 0.69, 0.69)
MU = 1000.0


def robertson_numpy(p: dict) -> tuple[Callable, Callable]:
    """Robertson's right-hand side and Jacobian in NumPy at coefficients ``p = {"k1", "k2", "k3"}``."""
    k1, k2, k3 = p["k1"], p["k2"], p["k3"]

    def f(t, y):
        return np.array([-k1 * y[0] + k3 * y[1] * y[2], k1 * y[0] - k3 * y[1] * y[2] - k2 * y[1] ** 2, k2 * y[1] ** 2])

    def jac(t, y):
        return np.array([[-k1, k3 * y[2], k3 * y[1]], [k1, -k3 * y[2] - 2 * k2 * y[1], -k3 * y[1]],
                         [0.0, 2 * k2 * y[1], 0.0]])
    return f, jac


robertson_f, robertson_jac = robertson_numpy({"k1": 0.04, "k2": 3e7, "k3": 1e4})


def hires_numpy(p: dict) -> tuple[Callable, Callable]:
    """HIRES's right-hand side and Jacobian in NumPy, at its rate constants with those of ``p``
    (any of ``"k1" .. "k9"``) in place of the defaults :data:`HIRES_K`."""
    k1, k2, k3, k4, k5, k6, k7, k8, k9 = (p.get(f"k{i + 1}", k) for i, k in enumerate(HIRES_K))

    def f(t, y):
        b, r = k7 * y[5] * y[7], (k2 + k8 + k9) * y[6]
        return np.array([-k1 * y[0] + k2 * y[1] + k6 * y[2] + 0.0007, k1 * y[0] - (k2 + k3) * y[1],
                         -(k6 + k1) * y[2] + k2 * y[3] + k5 * y[4], k3 * y[1] + k1 * y[2] - (k4 + k2) * y[3],
                         -(k5 + k1) * y[4] + k2 * (y[5] + y[6]), -b + k8 * y[3] + k1 * y[4] - k2 * y[5] + k8 * y[6],
                         b - r, -b + r])

    def jac(t, y):
        J = np.zeros((8, 8))
        J[0, :3] = -k1, k2, k6
        J[1, :2] = k1, -(k2 + k3)
        J[2, 2:5] = -(k6 + k1), k2, k5
        J[3, 1:4] = k3, k1, -(k4 + k2)
        J[4, 4:7] = -(k5 + k1), k2, k2
        J[5, 3:8] = k8, k1, -k7 * y[7] - k2, k8, -k7 * y[5]
        J[6, 5:8] = k7 * y[7], -(k2 + k8 + k9), k7 * y[5]
        J[7, 5:8] = -k7 * y[7], k2 + k8 + k9, -k7 * y[5]
        return J
    return f, jac


hires_f, hires_jac = hires_numpy({})


def vdp_numpy(p: dict) -> tuple[Callable, Callable]:
    """Van der Pol's right-hand side and Jacobian in NumPy at ``p = {"mu": ...}``."""
    mu = p["mu"]

    def f(t, y):
        return np.array([y[1], mu * (1 - y[0] ** 2) * y[1] - y[0]])

    def jac(t, y):
        return np.array([[0.0, 1.0], [-2 * mu * y[0] * y[1] - 1, mu * (1 - y[0] ** 2)]])
    return f, jac


vdp_f, vdp_jac = vdp_numpy({"mu": MU})


@dataclass
class Problem:
    name: str
    model: Callable[[], torchql.ODEModel]
    x0: tuple
    t_end: float
    atol_scale: float  # atol = atol_scale * rtol
    f: Callable
    jac: Callable
    reference: np.ndarray | None = None


def problems(quick: bool) -> list[Problem]:
    out = [Problem("Robertson, t = 1e5", Robertson, (1.0, 0.0, 0.0), 1e5, 1e-6, robertson_f, robertson_jac,
                   np.array(ROBERTSON_1E5)),
           Problem("HIRES, t = 321.8122", HIRES, (1, 0, 0, 0, 0, 0, 0, 0.0057), 321.8122, 1e-4, hires_f, hires_jac,
                   np.array(HIRES_REFERENCE))]
    if not quick:
        vdp = Problem("van der Pol mu = 1000, t = 1000", lambda: VanDerPol(MU), (2.0, 0.0), 1000.0, 1.0, vdp_f, vdp_jac)
        ref = solve_ivp(vdp_f, (0, vdp.t_end), vdp.x0, method="Radau", jac=vdp_jac, rtol=1e-13, atol=1e-13)
        vdp.reference = ref.y[:, -1]
        out.append(vdp)
    return out


def best_of(repeats: int, run: Callable[[], object]) -> tuple[float, object]:
    best, value = float("inf"), None
    for _ in range(repeats):
        start = time.perf_counter()
        value = run()
        best = min(best, time.perf_counter() - start)
    return best, value


def mixed_error(y: np.ndarray, ref: np.ndarray, rtol: float, atol: float) -> float:
    return float(np.max(np.abs(y - ref) / (atol + rtol * np.abs(ref))))


def rows_for(p: Problem, rtol: float, repeats: int) -> list[list[str]]:
    atol = p.atol_scale * rtol
    model, x0 = p.model(), torch.tensor(p.x0, dtype=DT)
    times = torch.tensor([0.0, p.t_end], dtype=DT)
    torchql.simulate(model, x0, times, solver="rodas5p", rtol=rtol, atol=atol)  # warm-up (torch.func's first call)
    seconds, y = best_of(repeats, lambda: torchql.simulate(model, x0, times, solver="rodas5p", rtol=rtol, atol=atol))
    _, sol = rodas5p_solve(model, x0, times, rtol=rtol, atol=atol)
    rows = [[p.name, f"{rtol:.0e}", "torchql rodas5p", f"{seconds:.3f}",
             f"{int(sol.n_accepted[0])} + {int(sol.n_rejected[0])}", str(sol.n_f), str(sol.n_jac),
             f"{mixed_error(y[-1].numpy(), p.reference, rtol, atol):.2g}"]]

    for method in ("Radau", "BDF"):
        seconds, s = best_of(repeats, lambda: solve_ivp(p.f, (0.0, p.t_end), p.x0, method=method, jac=p.jac,
                                                        rtol=rtol, atol=atol))
        rows.append([p.name, f"{rtol:.0e}", f"scipy {method}", f"{seconds:.3f}", f"{len(s.t) - 1}", str(s.nfev),
                     str(s.njev), f"{mixed_error(s.y[:, -1], p.reference, rtol, atol):.2g}"])
    return rows


def default_row(p: Problem, rtol: float, repeats: int) -> list[str]:
    """``torchql.simulate``'s default (``solver="auto"``) on ``p`` at ``rtol``: best time and error at the end."""
    atol = p.atol_scale * rtol
    model, x0 = p.model(), torch.tensor(p.x0, dtype=DT)
    times = torch.tensor([0.0, p.t_end], dtype=DT)
    seconds, y = best_of(repeats, lambda: torchql.simulate(model, x0, times, rtol=rtol, atol=atol))
    return ["default", p.name, f"{rtol:.0e}", f"{seconds:.3f}",
            f"{mixed_error(y[-1].numpy(), p.reference, rtol, atol):.2g}"]


def dopri5_on_robertson(cap: float) -> str:
    """``dopri5`` on Robertson to ``t = 1e3`` (rtol 1e-6) under a wall-clock cap of ``cap`` seconds."""
    field = CountedField(Robertson())
    times = torch.tensor([0.0, 1e3], dtype=DT)
    start = time.perf_counter()
    try:
        with time_budget(cap):
            solve(field, torch.tensor([1.0, 0.0, 0.0], dtype=DT), times, solver="dopri5", rtol=1e-6, atol=1e-12)
        outcome = "finished"
    except TimeBudgetExceeded:
        outcome = f"stopped at the {cap:g} s cap, unfinished"
    seconds = time.perf_counter() - start
    start = time.perf_counter()
    _, sol = rodas5p_solve(Robertson(), torch.tensor([1.0, 0.0, 0.0], dtype=DT), times, rtol=1e-6, atol=1e-12)
    stiff = time.perf_counter() - start
    return (f"Robertson to t = 1e3 at rtol 1e-6, atol 1e-12: torchql `dopri5` {outcome} after {seconds:.1f} s and "
            f"{field.n_evals} RHS evaluations; `rodas5p` {stiff:.2f} s, {int(sol.n_accepted[0])} steps, "
            f"{sol.n_f} RHS evaluations.")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--rtol", type=float, nargs="+", default=[1e-6, 1e-8])
    parser.add_argument("--dopri-cap", type=float, default=30.0, help="wall-clock cap of the dopri5 run, seconds")
    parser.add_argument("--quick", action="store_true", help="Robertson and HIRES at rtol 1e-6, one repeat")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "output")
    args = parser.parse_args(argv)
    if args.quick:
        args.repeats, args.rtol, args.dopri_cap = 1, [1e-6], 1.0
    torch.set_num_threads(1)
    load = os.getloadavg()
    header = ["problem", "rtol", "solver", "best time (s)", "steps (+ rejected)", "RHS evals", "Jacobians",
              "error (tolerances)"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for p in problems(args.quick):
        for rtol in args.rtol:
            for row in rows_for(p, rtol, args.repeats):
                lines.append("| " + " | ".join(row) + " |")
                print(lines[-1], flush=True)
    defaults = ["| simulate | problem | rtol | best time (s) | error (tolerances) |", "|---|---|---|---|---|"]
    for p in problems(args.quick):
        for rtol in args.rtol:
            defaults.append("| " + " | ".join(default_row(p, rtol, args.repeats)) + " |")
            print(defaults[-1], flush=True)
    dopri = dopri5_on_robertson(args.dopri_cap)
    print(dopri)
    text = "\n".join([
        f"# Stiff simulation: torchql rodas5p vs scipy Radau/BDF\n",
        f"torch {torch.__version__}, scipy {scipy.__version__}, numpy {np.__version__}, Python "
        f"{platform.python_version()}, one torch thread; load average before {load[0]:.2f}, after "
        f"{os.getloadavg()[0]:.2f}. Best of {args.repeats}. scipy gets the analytic Jacobian.\n",
        *lines, "", "torchql's default, `simulate(model, x0, t)` (`solver=\"auto\"`: Rodas5P where the model is "
        "stiff at x0, else DOP853, and Rodas5P again where DOP853 finds it stiff on the way):\n", *defaults, "",
        dopri, ""])
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "stiff_simulate.md").write_text(text)


if __name__ == "__main__":
    sys.exit(main())
