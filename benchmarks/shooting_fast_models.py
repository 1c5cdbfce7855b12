"""Shooting on a model that outgrows the grid chosen at its guesses: a relaxation ``x' = -k (x - A cos t)``.

``x(0) = 0`` is known at ``t0 = 0``; ``k`` and ``A`` are fitted from ``k = 1``, ``A = 1.5`` to 20
values over ``[0.1, 2]`` (sigma 1e-4) simulated at ``A = 1`` and a true ``k`` of 30, 100, 1e3 and
1e4. The automatic storage grid is chosen for ``k = 1``; the transient of width ``1 / k`` after
``t0`` passes between two of its nodes, and past ``k`` of about 30 the grid solver's steps per
interval do not reach. For each ``k``: ``method="shooting"`` at its defaults, and with
``linear_solver="rodas5p"`` (the sensitivities integrated with every solution), against scipy's
``least_squares`` over ``solve_ivp`` (Radau, rtol 1e-11, the analytic Jacobian, ``k`` on the log
scale): status, iterations, time, the estimates' largest relative difference from scipy's, and
the sum of squares less scipy's (the SSE's integration error is about 3e-5).

Run (from the repository root)::

    python benchmarks/shooting_fast_models.py                  # k = 30, 100, 1e3, 1e4
    python benchmarks/shooting_fast_models.py --quick --out /tmp/b   # k = 30 only

Writes ``OUT/shooting_fast_models.md``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch
from scipy.integrate import solve_ivp
from scipy.optimize import least_squares

import torchql

DT = torch.float64
TIMES = np.linspace(0.1, 2.0, 20)
SIGMA = 1e-4


class Relaxation(torchql.ODEModel):
    """``x' = -k (x - A cos t)``."""

    state_names = ("x",)

    def __init__(self, k: float = 1.0, A: float = 1.5) -> None:
        super().__init__()
        self.register_buffer("k", torch.tensor(k, dtype=DT))
        self.register_buffer("A", torch.tensor(A, dtype=DT))

    def forward(self, t, x):
        return -self.k * (x - self.A * torch.cos(t))


def solution(k: float, A: float) -> np.ndarray:
    """``x`` at :data:`TIMES` from ``x(0) = 0`` (scipy Radau, rtol 1e-11)."""
    sol = solve_ivp(lambda t, x: -k * (x - A * np.cos(t)), (0.0, TIMES[-1]), [0.0], method="Radau", t_eval=TIMES,
                    rtol=1e-11, atol=1e-13, jac=lambda t, x: np.array([[-k]]))
    return sol.y[0]


def data(k: float) -> np.ndarray:
    return solution(k, 1.0) + SIGMA * np.random.default_rng(0).standard_normal(TIMES.size)


def scipy_optimum(y: np.ndarray, k: float) -> tuple[np.ndarray, float]:
    res = least_squares(lambda p: (solution(np.exp(p[0]), p[1]) - y) / SIGMA, [np.log(k), 1.0], xtol=1e-14,
                        ftol=1e-14, gtol=1e-14)
    return np.array([np.exp(res.x[0]), res.x[1]]), 2 * res.cost


def rows(k: float) -> list[str]:
    y = data(k)
    best, sse = scipy_optimum(y, k)
    obs = torchql.Observations(torch.tensor(TIMES, dtype=DT), torch.tensor(y, dtype=DT).unsqueeze(-1), observe=["x"],
                               sigma=SIGMA)
    out = []
    for label, options in (("defaults", {}), ('linear_solver="rodas5p"', {"linear_solver": "rodas5p"})):
        start = time.perf_counter()
        r = torchql.fit(Relaxation(), obs, torch.zeros(1, dtype=DT), method="shooting", params=["k", "A"], t0=0.0,
                        fixed_x0=["x"], **options)
        seconds = time.perf_counter() - start
        diff = float(np.max(np.abs(r.estimates.numpy() - best) / np.abs(best)))
        out.append(f"| {k:g} | {label} | {r.status.name} | {r.iterations} | {seconds:.2f} | {diff:.1e} | "
                   f"{r.sse - sse:+.1e} | {r.solver_options['solver']} |")
        print(out[-1], flush=True)
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="k = 30 only")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "output")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    torchql.fit(Relaxation(), torchql.Observations(torch.tensor(TIMES, dtype=DT), torch.tensor(data(2.0)).unsqueeze(-1),
                                                   observe=["x"], sigma=SIGMA),
                torch.zeros(1, dtype=DT), method="shooting", params=["k", "A"], t0=0.0, fixed_x0=["x"])  # warm-up
    lines = ["| true k | shooting | status | iterations | time (s) | estimates vs scipy | SSE - scipy's | solver |",
             "|---|---|---|---|---|---|---|---|"]
    for k in (30.0,) if args.quick else (30.0, 100.0, 1e3, 1e4):
        lines += rows(k)
    text = "\n".join(["# Shooting on a relaxation that outgrows its grid\n",
                      f"torch {torch.__version__}, one thread; guesses k = 1, A = 1.5; 20 values over [0.1, 2], "
                      "sigma 1e-4.\n", *lines, ""])
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "shooting_fast_models.md").write_text(text)


if __name__ == "__main__":
    sys.exit(main())
