"""A bounded SIR fit from guesses three to four times off, against scipy's bounded ``least_squares``.

The epidemic (``N = 1000``, ``beta = 0.6``, ``gamma = 0.25``, ``I(0) = 5``; ``S(0) = N - I(0)``,
``R(0) = 0``) is measured in ``I`` at t = 0, 2, ..., 40 with noise of standard deviation 5 (``sigma
= 5``). ``I(0)``, ``beta`` and ``gamma`` are fitted from 10, 2.2969 and 0.6942, each bounded below
by 0 (``beta`` also above by 5 in the second setting), with ``torchql.fit``'s default options and
``method="shooting"``; the reference is scipy's ``least_squares`` (trf, the same bounds) over
``solve_ivp`` (DOP853, rtol 1e-11) from the same guesses. For each: status, iterations, the
model's evaluations (torchql's ``nfev``), the sum of squares and the time (one warm-up fit first,
untimed; one thread).

Far from the data the rates are driven toward their bound 0, into a stretch where no epidemic
spreads and the sum of squares is flat. A step toward a bound shrinks the distance at most
tenfold (``torchql.bounds.MAX_TOWARD_STEP``), and a Kantorovich trial that the model's own sum of
squares rejects is not propagated (``torchql.engine_steps``).

Run (from the repository root)::

    python benchmarks/sir_bounded.py
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from scipy.integrate import solve_ivp
from scipy.optimize import least_squares

import torchql

DT = torch.float64
N = 1000.0
GUESS = (10.0, 2.2969, 0.6942)  # I(0), beta, gamma


class SIR(torchql.ODEModel):
    """Susceptible-infected-recovered epidemic in a closed population of ``N``."""

    state_names = ("S", "I", "R")
    constants = ("N",)

    def __init__(self, beta: float, gamma: float) -> None:
        super().__init__()
        self.register_buffer("beta", torch.tensor(beta, dtype=DT))
        self.register_buffer("gamma", torch.tensor(gamma, dtype=DT))
        self.register_buffer("N", torch.tensor(N, dtype=DT))

    def forward(self, t, x):
        S, I = x[..., 0], x[..., 1]
        infection = self.beta * S * I / self.N
        return torch.stack([-infection, infection - self.gamma * I, self.gamma * I], -1)


def data() -> torchql.Observations:
    t = torch.arange(0.0, 41.0, 2.0, dtype=DT)
    x = torchql.simulate(SIR(0.6, 0.25), torch.tensor([995.0, 5.0, 0.0], dtype=DT), t)
    y = x[:, 1:2] + 5.0 * torch.randn(21, 1, generator=torch.Generator().manual_seed(2), dtype=DT)
    return torchql.Observations(t, y, observe=["I"], sigma=5.0)


def fit(observations: torchql.Observations, method: str, beta_max: float | None) -> tuple[torchql.FitResult, float]:
    start = time.perf_counter()
    result = torchql.fit(SIR(GUESS[1], GUESS[2]), observations, x0=torch.tensor([N - GUESS[0], GUESS[0], 0.0], dtype=DT),
                         params=["beta", "gamma"], fixed_x0=["R"], x0_expr={"S": lambda v: v["N"] - v["I"]},
                         bounds={"beta": (0, beta_max), "gamma": (0, None), "I": (0, None)}, method=method)
    return result, time.perf_counter() - start


def scipy_fit(observations: torchql.Observations, beta_max: float | None) -> tuple[float, float, int]:
    t, y = observations.t.numpy(), observations.y[:, 0].numpy()

    def residuals(u):
        I0, beta, gamma = u
        rhs = lambda _, v: [-beta * v[0] * v[1] / N, beta * v[0] * v[1] / N - gamma * v[1]]  # noqa: E731
        solution = solve_ivp(rhs, (0.0, 40.0), [N - I0, I0], t_eval=t, method="DOP853", rtol=1e-11, atol=1e-10)
        return (solution.y[1] - y) / 5.0
    start = time.perf_counter()
    upper = [np.inf, np.inf if beta_max is None else beta_max, np.inf]
    reference = least_squares(residuals, GUESS, bounds=([0, 0, 0], upper), xtol=1e-12, ftol=1e-12)
    return 2 * reference.cost, time.perf_counter() - start, reference.nfev


def main() -> None:
    torch.set_num_threads(1)
    observations = data()
    fit(observations, "kantorovich", None)  # warm-up
    print("| bounds on beta | method | status | iterations | evaluations | SSE | time |")
    print("|---|---|---|---|---|---|---|")
    for beta_max in (None, 5.0):
        bounds = f"(0, {beta_max:g})" if beta_max else "(0, None)"
        for method in ("kantorovich", "shooting"):
            result, seconds = fit(observations, method, beta_max)
            print(f"| {bounds} | torchql {method} | {result.status.name} | {result.iterations} | {result.nfev:,} | "
                  f"{result.sse:.8g} | {seconds:.2f} s |")
        sse, seconds, nfev = scipy_fit(observations, beta_max)
        print(f"| {bounds} | scipy least_squares | | | {nfev} solves | {sse:.8g} | {seconds:.2f} s |")


if __name__ == "__main__":
    argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args()  # (--help; no options)
    main()
