"""Throughput of batched fitting (``torchql.fit_many``) against loops of single fits and a vmapped JAX peer.

Two problem families, each sample with its own true coefficients and Gaussian noise:

* **coasting cars** (``torchql.models.CoastingCar``, the thesis' Sunbeam Alpine: frontal area
  17.3 ft^2, mass 80.43 slug), ``v' = -(rho A C_D / (2 m)) v^2 - mu g``, coefficients drawn
  around ``C_D = 0.45 +- 0.05``, ``mu = 0.015 +- 0.003``, initial speed ``117.3 +- 2`` ft/s,
  observed at ``t = 0, 5, ..., 40`` s (nine speeds, noise 0.3 ft/s; exact speeds from the
  closed-form solution). Unknowns ``v(t0)``, ``C_D``, ``mu``; start ``(v_1, 0.4, 0.02)`` with
  ``v_1`` the car's first measured speed. Batch sizes ``--sizes`` (default 10, 100, 1000, 10000);
* **linear oscillators** (``torchql.models.LinearOscillator``, ``y'' + A y' + B y = 0``, states
  ``(y, v = y')``), truths drawn around the thesis' ``(y0, v0, A, B) = (0, 1, 0.1, 3)``:
  ``y0 ~ 0 +- 0.05``, ``v0 ~ 1 +- 0.1``, ``A ~ 0.1 +- 0.02``, ``B ~ 3 +- 0.3``; position observed at
  ``t = 0, 0.5, ..., 6.5`` (14 points, noise 1e-3; exact positions from the closed form).
  Unknowns ``y(t0)``, ``v(t0)``, ``A``, ``B``; start: the thesis' ``(0.5, 0.5, 0.5, 1.0)``, each
  component of each sample times ``exp(0.2 z)``, ``z`` standard normal. Batch sizes
  ``--osc-sizes`` (default 1000).

Rows of each family's table, all in the same process, torch on one thread unless said:

* ``torchql fit_many`` (**the headline**): ``fit_many`` with its DEFAULT options (``grid="auto"``:
  each dataset's own storage intervals, ``rtol=1e-10``) on ``B`` datasets for every ``B``, given as
  one batched ``Observations`` (values ``(B, T, 1)``, validated once) with per-sample start states
  (``x0``) and coefficient guesses (``guesses=``), timed with that building, after one untimed
  warm-up on a small batch;
* ``torchql fit_many, tuned (grid=20)`` and ``tuned (rtol=1e-8)``: the largest ``B`` with one
  option changed (20 storage intervals; a looser integration tolerance), settings whose accuracy
  columns say what they cost; ``grid=1000 (the former fixed default)``: the storage grid every
  dataset had by default before ``grid="auto"``;
* ``torchql fit_many, N threads``: the largest ``B``, default options, torch on every core;
* ``JAX optimistix LM + diffrax, vmap`` (when ``jax``, ``diffrax`` and ``optimistix`` are
  installed: ``pip install "torchql[bench]"``): ``benchmarks/jax_peer.py``, one
  ``jax.jit(jax.vmap(fit_one))`` over the batch, float64, XLA on one thread; ``fit_one`` is
  ``optimistix.least_squares`` with ``LevenbergMarquardt(rtol=1e-8, atol=1e-8)`` (at most 200
  steps, ``throw=False``) over ``diffrax.diffeqsolve`` (``Dopri5``, ``PIDController(rtol=1e-10,
  atol=1e-12)``, ``SaveAt(ts=observation times)``, forward-mode ``ForwardMode`` Jacobians), from
  the same starts as torchql. Every ``B`` is compiled once for its shapes (``lower().compile()``,
  reported separately) and then timed (``block_until_ready``, inputs to and results from numpy);
* ``torchql fit, loop``: a Python loop of ``torchql.fit`` (default options) on the first
  ``--subset`` datasets, timed with the building of one ``Observations`` per dataset (once);
* ``scipy least_squares + solve_ivp ..., loop``: ``scipy.optimize.least_squares`` (``trf``,
  2-point differences, ``x_scale="jac"``, ``xtol=1e-12``, ``ftol=gtol=1e-14``) over
  ``scipy.integrate.solve_ivp`` (``rtol=1e-10``, ``atol=1e-12``, the settings of
  ``benchmarks/fit_speed.py``) on the same subset: ``DOP853`` and ``RK45`` for the cars, ``DOP853``
  for the oscillators. The faster scipy loop is the reference of ``/ scipy loop``.

Every fit_many row, every JAX size and the scipy loops are timed ``--repeat`` times (default 3)
and the fastest run counts; the torchql loop, the slowest, runs once. Ratios: fits/s of the row
over fits/s of the reference (``/ JAX``: the JAX row of the same ``B``). ``converged``: samples
whose fit succeeded (torchql: ``success``; JAX: optimistix' ``RESULTS.successful``); ``mean
iter``: torchql's iterations, JAX's Levenberg–Marquardt steps (accepted and rejected). The JAX
peer iterates each unknown as a multiple of its start (see ``benchmarks/jax_peer.py``); the
scipy loops start from the same starts as torchql and JAX.

Accuracy columns: ``max dSSE``, the largest relative excess of a row's sum of squares over the
best of all rows on the same dataset (every SSE recomputed from the closed-form solution);
``max diff``, the largest relative difference of a row's estimates from the default
``fit_many``'s on the same datasets (relative to the torchql estimate, or to 1% of that
unknown's largest magnitude in the batch where the estimate is smaller: the oscillators'
``y(t0)`` scatters around 0). The torchql loop's ``max diff`` is batched against single fits. A
note under each table gives how far the defaults' and the tuned rows' standard errors are from
those on the former fixed grid of 1,000 intervals (the largest relative difference).

Memory (``peak RSS``, fit_many and JAX rows): the process' peak resident set size during the
row's runs, libraries loaded included (Linux: the high-water mark is reset before each row
through ``/proc/self/clear_refs``; elsewhere the process' peak so far). The JAX rows of both
families run after every torchql and scipy row, so that JAX's memory is not in torchql's figures.

``--quick``: cars ``B = 4, 16``, oscillators ``B = 8``, loops on 4, one run each, no all-cores
row; the JAX rows when JAX is installed (their compilation is most of its time).

Run (from the repository root)::

    python benchmarks/batch.py                        # cars 10..10000, oscillators 1000; subset 100
    python benchmarks/batch.py --sizes 10 100 1000 --osc-sizes 100 1000 --subset 50
    python benchmarks/batch.py --no-jax               # torchql and scipy rows only
    python benchmarks/batch.py --quick --out /tmp/bench   # smoke run (JAX rows: if installed)

Writes ``OUT/batch.md`` (the tables) and ``OUT/batch.png`` (fits/s against ``B``).
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import platform
import re
import resource
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy
import torch
from scipy.integrate import solve_ivp
from scipy.optimize import least_squares

import torchql
from torchql.models import CoastingCar, LinearOscillator
from torchql.models.car import AIR_DENSITY, GRAVITY

DTYPE = torch.float64
AREA, MASS = 17.3, 80.43
#: Rows of other settings at the largest ``B``, each changing one option of the default fit: the
#: tuned ones (kind ``tuned``: faster, their accuracy columns say at what cost) and the former
#: fixed default grid of 1000 intervals (kind ``former``), for comparison.
TUNED = {"tuned (grid=20)": dict(grid=20), "tuned (rtol=1e-8)": dict(rtol=1e-8)}
FORMER = {"grid=1000 (the former fixed default)": dict(grid=1000)}
PEER_RTOL, PEER_ATOL = 1e-10, 1e-12
PEER_LSQ = dict(method="trf", jac="2-point", diff_step=1e-5, x_scale="jac", xtol=1e-12, ftol=1e-14, gtol=1e-14,
                max_nfev=2000)
#: Oscillators' start (y0, v0, A, B): the thesis', perturbed per sample by a factor exp(OSC_START_SPREAD z).
OSC_START, OSC_START_SPREAD = np.array([0.5, 0.5, 0.5, 1.0]), 0.2
#: Floor of the relative differences: this fraction of an unknown's largest magnitude in the batch.
REL_FLOOR = 1e-2
JAX_HINT = 'pip install "torchql[bench]"'


# ----------------------------------------------------------------------------------------------
# Problem families
# ----------------------------------------------------------------------------------------------

def exact_speed(t: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Cars' closed form ``v = sqrt(c/a) tan(atan(v0 sqrt(a/c)) - sqrt(a c) t)``, ft/s, ``(B, T)``.

    ``t (T,)`` s; ``p (B, 3)`` = ``(v0 ft/s, C_D, mu)``; ``a = rho A C_D / (2 m)``, ``c = mu g``.
    """
    v0, C_D, mu = p[:, 0], p[:, 1], p[:, 2]
    a = (0.5 * AIR_DENSITY * AREA * C_D / MASS)[:, None]
    c = (mu * GRAVITY)[:, None]
    with np.errstate(all="ignore"):
        return np.sqrt(c / a) * np.tan(np.arctan(v0[:, None] * np.sqrt(a / c)) - np.sqrt(a * c) * t[None, :])


def exact_position(t: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Oscillators' closed form ``y = exp(-A t/2) (y0 cos(w t) + (v0 + A y0/2) sin(w t)/w)``, ``(B, T)``.

    ``t (T,)``; ``p (B, 4)`` = ``(y0, v0, A, B)``; ``w = sqrt(B - A^2/4)`` (complex when overdamped).
    """
    y0, v0, A, B = (p[:, k, None] for k in range(4))
    w = np.sqrt((B - A**2 / 4).astype(complex))
    with np.errstate(all="ignore"):
        sin_over_w = t * np.sinc(w * t / np.pi)  # sin(w t) / w, also at w = 0
        return np.real(np.exp(-A * t / 2) * (y0 * np.cos(w * t) + (v0 + A * y0 / 2) * sin_over_w))


def _car_truth(rng: np.random.Generator, B: int) -> np.ndarray:
    v0 = 117.3 + 2.0 * rng.standard_normal(B)
    C_D = 0.45 + 0.05 * rng.standard_normal(B)
    mu = np.abs(0.015 + 0.003 * rng.standard_normal(B))
    return np.stack([v0, C_D, mu], axis=1)


def _car_starts(rng: np.random.Generator, y: np.ndarray) -> np.ndarray:
    B = y.shape[0]
    return np.stack([y[:, 0], np.full(B, 0.4), np.full(B, 0.02)], axis=1)


def _osc_truth(rng: np.random.Generator, B: int) -> np.ndarray:
    z = rng.standard_normal((B, 4))
    return np.array([0.0, 1.0, 0.1, 3.0]) + np.array([0.05, 0.1, 0.02, 0.3]) * z


def _osc_starts(rng: np.random.Generator, y: np.ndarray) -> np.ndarray:
    return OSC_START * np.exp(OSC_START_SPREAD * rng.standard_normal((y.shape[0], 4)))


def _car_rhs(t, x, C_D, mu):
    return [-0.5 * AIR_DENSITY * AREA * C_D / MASS * x[0] ** 2 - mu * GRAVITY]


def _osc_rhs(t, x, A, B):
    return [x[1], -A * x[1] - B * x[0]]


@dataclass(frozen=True)
class Family:
    """A problem family: model, observation times, truths, starts, closed form, scipy and JAX forms.

    Unknowns are the ``n_states`` initial states followed by ``coefficients``; state 0 is observed.
    """

    key: str
    title: str
    model: Callable[..., torchql.ODEModel]
    state_names: tuple[str, ...]
    coefficients: tuple[str, ...]
    times: np.ndarray
    noise: float
    truth: Callable[[np.random.Generator, int], np.ndarray]
    starts: Callable[[np.random.Generator, np.ndarray], np.ndarray]
    exact: Callable[[np.ndarray, np.ndarray], np.ndarray]
    scipy_rhs: Callable
    scipy_solvers: tuple[str, ...]
    peer: Callable

    @property
    def n_states(self) -> int:
        return len(self.state_names)


CARS = Family("cars", "Coasting cars", lambda **c: CoastingCar(AREA, MASS, **c), ("v",), ("C_D", "mu"),
              5.0 * np.arange(9), 0.3, _car_truth, _car_starts, exact_speed, _car_rhs, ("DOP853", "RK45"),
              lambda jp: jp.coasting_car(AREA, MASS, AIR_DENSITY, GRAVITY))
OSCILLATORS = Family("oscillators", "Linear oscillators", lambda **c: LinearOscillator(**c), ("y", "v"), ("A", "B"),
                     0.5 * np.arange(14), 1e-3, _osc_truth, _osc_starts, exact_position, _osc_rhs, ("DOP853",),
                     lambda jp: jp.linear_oscillator())


@dataclass
class Data:
    """``B`` datasets of a family: times ``t (T,)``, values ``y (B, T)``, ``truth (B, m)``, ``starts (B, m)``."""

    t: np.ndarray
    y: np.ndarray
    truth: np.ndarray
    starts: np.ndarray

    def head(self, n: int) -> "Data":
        """The first ``n`` datasets."""
        return Data(self.t, self.y[:n], self.truth[:n], self.starts[:n])


def make_data(family: Family, B: int, seed: int = 0, noise: float | None = None) -> Data:
    """``B`` datasets of ``family``: exact values plus Gaussian noise (``noise``, default the family's)."""
    rng = np.random.default_rng(seed)
    truth = family.truth(rng, B)
    t = np.asarray(family.times, dtype=float)
    y = family.exact(t, truth) + (family.noise if noise is None else noise) * rng.standard_normal((B, t.size))
    return Data(t, y, truth, family.starts(rng, y))


# ----------------------------------------------------------------------------------------------
# The methods
# ----------------------------------------------------------------------------------------------

def run_fit_many(family: Family, data: Data, **options) -> tuple[torchql.BatchFitResult, float]:
    """``fit_many`` on ``data`` (``options`` as given, else defaults), timed with its batched Observations."""
    start = time.perf_counter()
    obs = torchql.Observations(torch.tensor(data.t, dtype=DTYPE), torch.tensor(data.y, dtype=DTYPE).unsqueeze(-1),
                               observe=[family.state_names[0]])
    n = family.n_states
    x0 = torch.tensor(data.starts[:, :n], dtype=DTYPE)
    guesses = {name: torch.tensor(data.starts[:, n + k], dtype=DTYPE) for k, name in enumerate(family.coefficients)}
    result = torchql.fit_many(family.model(), obs, x0, guesses=guesses, **options)
    return result, time.perf_counter() - start


def run_single_loop(family: Family, data: Data) -> tuple[np.ndarray, list[str], int, float]:
    """A loop of ``torchql.fit`` (defaults) over ``data``: estimates ``(B, m)``, statuses, successes, seconds."""
    start = time.perf_counter()
    tt = torch.tensor(data.t, dtype=DTYPE)
    n = family.n_states
    estimates, status, success = [], [], 0
    for row, guess in zip(data.y, data.starts):
        obs = torchql.Observations(tt, torch.tensor(row, dtype=DTYPE).unsqueeze(-1), observe=[family.state_names[0]])
        model = family.model(**dict(zip(family.coefficients, guess[n:].tolist())))
        r = torchql.fit(model, obs, torch.tensor(guess[:n], dtype=DTYPE))
        estimates.append(r.estimates.numpy())
        status.append(r.status.name)
        success += bool(r.success)
    return np.array(estimates), status, success, time.perf_counter() - start


def run_scipy_loop(family: Family, data: Data, solver: str) -> tuple[np.ndarray, float]:
    """A loop of ``least_squares`` over ``solve_ivp`` (``solver``) on ``data``: estimates ``(B, m)``, seconds."""
    start = time.perf_counter()
    t, n = data.t, family.n_states
    estimates = []
    for row, guess in zip(data.y, data.starts):
        def residuals(u, row=row):
            sol = solve_ivp(family.scipy_rhs, (t[0], t[-1]), u[:n], method=solver, t_eval=t, args=tuple(u[n:]),
                            rtol=PEER_RTOL, atol=PEER_ATOL)
            if not sol.success or sol.y.shape[1] != t.size:
                return np.full(t.size, 1e10)
            return sol.y[0] - row
        estimates.append(least_squares(residuals, guess, **PEER_LSQ).x)
    return np.array(estimates), time.perf_counter() - start


def best_of(repeat: int, run: Callable[[], tuple]) -> tuple:
    """``run()`` ``repeat`` times (each returns a tuple ending with its seconds): the fastest run's tuple."""
    return min((run() for _ in range(repeat)), key=lambda r: r[-1])


def reset_peak_rss() -> None:
    """Reset the process' peak resident set size (Linux >= 4.0; elsewhere nothing)."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass


def peak_rss_mb() -> float:
    """The process' peak resident set size since the last reset, MB (``VmHWM``; else ``ru_maxrss``)."""
    try:
        with open("/proc/self/status") as f:
            return int(re.search(r"VmHWM:\s+(\d+)", f.read()).group(1)) / 1024
    except (OSError, AttributeError):
        kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return kb / 1024 if sys.platform != "darwin" else kb / 1024**2


# ----------------------------------------------------------------------------------------------
# Rows
# ----------------------------------------------------------------------------------------------

@dataclass
class Row:
    """One row of a family's table: ``B`` datasets (the first ``B``), estimates ``(B, m)``, wall seconds.

    ``kind``: ``fit_many`` (default options), ``tuned``, ``former`` (the former default grid),
    ``threads``, ``jax``, ``loop`` (torchql fit) or ``scipy``. ``dsse`` and ``diff`` are filled by :func:`score_rows`.
    """

    label: str
    kind: str
    B: int
    seconds: float
    estimates: np.ndarray
    converged: int | None = None
    iterations: float | None = None
    rss: float | None = None
    extra: dict = field(default_factory=dict)
    dsse: float = float("nan")
    diff: float = float("nan")

    @property
    def rate(self) -> float:
        return self.B / self.seconds


def torchql_row(label: str, kind: str, result: torchql.BatchFitResult, seconds: float, rss: float | None = None,
                **extra) -> Row:
    """A row from a ``fit_many`` result."""
    return Row(label, kind, len(result), seconds, result.estimates.numpy(), int(result.success.sum()),
               float(result.iterations.double().mean()), rss, dict(extra, result=result))


def fit_many_rows(family: Family, data: Data, sizes: list[int], repeat: int, all_cores: bool = True) -> list[Row]:
    """The headline (default options) at every ``B``; the tuned and (``all_cores``) all-cores rows at the largest."""
    rows = []
    for B in sorted(sizes):
        print(f"... {family.key}: fit_many B = {B}", file=sys.stderr, flush=True)
        reset_peak_rss()
        result, seconds = best_of(repeat, lambda: run_fit_many(family, data.head(B)))
        rows.append(torchql_row("torchql fit_many", "fit_many", result, seconds, peak_rss_mb()))
    B = max(sizes)
    for kind, settings in (("tuned", TUNED), ("former", FORMER)):
        for name, options in settings.items():
            print(f"... {family.key}: fit_many B = {B}, {name}", file=sys.stderr, flush=True)
            result, seconds = best_of(repeat, lambda: run_fit_many(family, data.head(B), **options))
            rows.append(torchql_row(f"torchql fit_many, {name}", kind, result, seconds))
    if not all_cores:
        return rows
    threads = os.cpu_count() or 1
    print(f"... {family.key}: fit_many B = {B}, {threads} threads", file=sys.stderr, flush=True)
    torch.set_num_threads(threads)
    try:
        result, seconds = best_of(repeat, lambda: run_fit_many(family, data.head(B)))
    finally:
        torch.set_num_threads(1)
    rows.append(torchql_row(f"torchql fit_many, {threads} threads", "threads", result, seconds))
    return rows


def jax_rows(family: Family, data: Data, sizes: list[int], repeat: int, peer) -> list[Row]:
    """The JAX peer at every ``B`` (compiled per shape; the compile time in ``extra``)."""
    rows = []
    problem = family.peer(peer)
    for B in sorted(sizes):
        print(f"... {family.key}: JAX B = {B}", file=sys.stderr, flush=True)
        reset_peak_rss()
        d = data.head(B)
        r = peer.fit_batch(problem, d.t, d.y, d.starts, repeat=repeat)
        rows.append(Row("JAX optimistix LM + diffrax, vmap", "jax", B, r.seconds, r.estimates, int(r.success.sum()),
                        float(np.mean(r.steps)), peak_rss_mb(),
                        dict(compile=r.compile_seconds, cores=r.cpu_seconds / r.seconds, max_steps=int(r.steps.max()))))
    return rows


def loop_rows(family: Family, data: Data, subset: int, repeat: int) -> list[Row]:
    """The torchql ``fit`` loop (once) and the scipy loops (best of ``repeat``) on the first ``subset``."""
    d = data.head(subset)
    print(f"... {family.key}: loops on the subset of {subset}", file=sys.stderr, flush=True)
    estimates, status, success, seconds = run_single_loop(family, d)
    rows = [Row("torchql fit, loop", "loop", subset, seconds, estimates, success, extra=dict(status=status))]
    for solver in family.scipy_solvers:
        estimates, seconds = best_of(repeat, lambda: run_scipy_loop(family, d, solver))
        rows.append(Row(f"scipy least_squares + solve_ivp {solver}, loop", "scipy", subset, seconds, estimates,
                        extra=dict(solver=solver)))
    return rows


def standard_errors(result: torchql.BatchFitResult) -> np.ndarray:
    """The standard errors ``(B, m)`` of a ``fit_many`` result, from its covariances."""
    return np.sqrt(np.diagonal(result.covariance.numpy(), axis1=1, axis2=2))


def relative_difference(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``|a - b|`` relative to ``|b|``, or to ``REL_FLOOR`` times each column's largest ``|b|`` where larger."""
    floor = REL_FLOOR * np.max(np.abs(b), axis=0, keepdims=True)
    return np.abs(a - b) / np.maximum(np.abs(b), np.maximum(floor, 1e-300))


def score_rows(family: Family, data: Data, rows: list[Row]) -> None:
    """Fill every row's ``dsse`` (SSE excess over the best row, per dataset) and ``diff`` (from fit_many)."""
    sse = [np.sum((family.exact(data.t, r.estimates) - data.y[:r.B]) ** 2, axis=1) for r in rows]
    n = max(r.B for r in rows)
    best = np.full(n, np.inf)
    for s in sse:
        best[:s.size] = np.fmin(best[:s.size], s)
    reference = max((r for r in rows if r.kind == "fit_many"), key=lambda r: r.B).estimates
    for r, s in zip(rows, sse):
        r.dsse = float(np.max((s - best[:r.B]) / best[:r.B]))
        m = min(r.B, len(reference))
        if r.kind != "fit_many":
            r.diff = float(np.max(relative_difference(r.estimates[:m], reference[:m])))


#: The order of the rows in a table.
ROW_ORDER = ("fit_many", "tuned", "former", "threads", "jax", "loop", "scipy")


def benchmark_family(family: Family, sizes: list[int], subset: int, repeat: int, seed: int,
                     all_cores: bool = True) -> dict:
    """The torchql and scipy rows of one family's table (the JAX rows come later: :func:`add_jax_rows`)."""
    data = make_data(family, max(sizes + [subset]), seed)
    run_fit_many(family, data.head(4))  # warm-up (imports, first calls), untimed
    rows = fit_many_rows(family, data, sizes, repeat, all_cores) + loop_rows(family, data, subset, repeat)
    return dict(family=family, rows=rows, data=data, sizes=sizes, repeat=repeat, subset=subset)


def add_jax_rows(res: dict, peer) -> None:
    """Add the JAX rows to a family's result (after every torchql row, so that JAX's memory is not in theirs)."""
    res["rows"] += jax_rows(res["family"], res["data"], res["sizes"], res["repeat"], peer)


def finish(res: dict) -> None:
    """Order a family's rows and score them."""
    res["rows"].sort(key=lambda r: ROW_ORDER.index(r.kind))
    score_rows(res["family"], res["data"], res["rows"])


# ----------------------------------------------------------------------------------------------
# Report
# ----------------------------------------------------------------------------------------------

def _ratio(x: float) -> str:
    if not np.isfinite(x):
        return ""
    return f"{x:.0f}x" if x >= 10 else f"{x:.2g}x"


def _num(x: float | None, fmt: str) -> str:
    return "" if x is None or not np.isfinite(x) else format(x, fmt)


HEADER = ("| method | datasets | wall time | fits / s | / scipy loop | / torchql loop | / JAX | converged | mean iter "
          "| max dSSE | max diff | peak RSS |")


def table_lines(res: dict) -> list[str]:
    """The Markdown table of one family's rows."""
    rows = res["rows"]
    scipy_rate = max(r.rate for r in rows if r.kind == "scipy")
    loop_rate = next(r.rate for r in rows if r.kind == "loop")
    jax_rate = {r.B: r.rate for r in rows if r.kind == "jax"}
    lines = [HEADER, "|" + "---|" * (HEADER.count("|") - 1)]
    for r in rows:
        vs_jax = r.rate / jax_rate[r.B] if r.kind in ("fit_many", "tuned", "former", "threads") and r.B in jax_rate else np.nan
        vs_scipy = _ratio(r.rate / scipy_rate)
        lines.append(
            f"| {r.label} | {r.B} | {r.seconds:.2f} s | {r.rate:.1f} | "
            f"{f'**{vs_scipy}**' if r.kind == 'fit_many' else vs_scipy} | {_ratio(r.rate / loop_rate)} | "
            f"{f'**{_ratio(vs_jax)}**' if r.kind == 'fit_many' and np.isfinite(vs_jax) else _ratio(vs_jax)} | "
            f"{'' if r.converged is None else f'{r.converged}/{r.B}'} | {_num(r.iterations, '.2f')} | "
            f"{_num(r.dsse, '.1e')} | {_num(r.diff, '.1e')} | {_num(r.rss, '.0f')}{' MB' if r.rss else ''} |")
    return lines


def notes(res: dict) -> list[str]:
    """The notes under one family's table."""
    rows, fam = res["rows"], res["family"]
    scipy_best = max((r for r in rows if r.kind == "scipy"), key=lambda r: r.rate)
    loop = next(r for r in rows if r.kind == "loop")
    largest = max((r for r in rows if r.kind == "fit_many"), key=lambda r: r.B)
    n = min(loop.B, largest.B)
    same = all(largest.extra["result"].status[i].name == loop.extra["status"][i] for i in range(n))
    truth_err = np.median(relative_difference(largest.estimates, res["data"].truth[:largest.B]), axis=0)
    out = [
        f"`/ scipy loop`: against the faster scipy loop ({scipy_best.extra['solver']}); loops on the first "
        f"{res['subset']} datasets. fit_many rows, JAX rows and scipy loops: the fastest of {res['repeat']} "
        f"run(s); the torchql loop: one run.",
        f"Batched against single torchql fits (default options, first {n} datasets): statuses identical: "
        f"{'yes' if same else 'NO'}; `max diff` of the `torchql fit, loop` row.",
        f"Median relative error of fit_many's estimates against the true values (noise {fam.noise:g}): " + ", ".join(
            f"{name} {e:.1e}" for name, e in zip(largest.extra["result"].unknown_names, truth_err)) + ".",
    ]
    tuned = [r for r in rows if r.kind == "tuned" and r.B == largest.B]
    if tuned:
        best = max(tuned, key=lambda r: r.rate)
        out.append(f"Defaults against the fastest tuned row at B = {largest.B} ({best.label.split(', ', 1)[1]}): "
                   f"{largest.rate / best.rate:.2g}x its fits/s.")
    former = next((r for r in rows if r.kind == "former" and r.B == largest.B), None)
    if former is not None:
        errors = standard_errors(former.extra["result"])
        others = [largest] + [r for r in rows if r.kind == "tuned" and r.B == largest.B]
        out.append(f"Standard errors (the reported covariance's) against those on the fixed 1,000-interval grid, "
                   f"largest relative difference at B = {largest.B}: " + ", ".join(
                       f"{'defaults' if r is largest else r.label.split(', ', 1)[1]} "
                       f"{np.nanmax(np.abs(standard_errors(r.extra['result']) - errors) / errors):.1e}" for r in others)
                   + " (a storage grid's interpolation error reaches the sensitivities the final pass integrates "
                   "on it).")
    jax = [r for r in rows if r.kind == "jax"]
    if jax:
        out.append("JAX: compile time per batch size (tracing and XLA compilation of `jit(vmap(fit_one))` for "
                   "its shapes, not in the wall time): " + ", ".join(f"B={r.B} {r.extra['compile']:.1f} s" for r in jax)
                   + "; cores used in the timed call (CPU time / wall time): "
                   + ", ".join(f"{r.extra['cores']:.2f}" for r in jax)
                   + "; LM steps per sample (accepted and rejected): largest "
                   + ", ".join(str(r.extra["max_steps"]) for r in jax)
                   + " (the vmapped loop runs every sample until the last one stops). `converged`: samples that "
                   "optimistix reports successful.")
    return out


def environment(load: tuple[float, float], peer) -> str:
    """Versions, thread settings and machine load, for the header."""
    jax_part = peer.versions() if peer is not None else f"JAX rows skipped ({JAX_HINT})"
    return (f"torch {torch.__version__} (1 thread unless a row says otherwise), {jax_part}, scipy {scipy.__version__}, "
            f"numpy {np.__version__}, Python {platform.python_version()}, {platform.machine()}, {os.cpu_count()} "
            f"CPUs; load average {load[0]:.2f} before, {load[1]:.2f} after")


def markdown(results: list[dict], load: tuple[float, float], peer) -> str:
    """The report: environment line, then per family its table and notes."""
    parts = [environment(load, peer) + "."]
    for res in results:
        fam = res["family"]
        parts.append(f"## {fam.title}\n\nUnknowns: " + ", ".join(res["rows"][0].extra["result"].unknown_names)
                     + f"; {fam.times.size} observations per dataset.\n\n" + "\n".join(table_lines(res)) + "\n\n"
                     + "\n".join(f"* {n}" for n in notes(res)))
    return "\n\n".join(parts) + "\n"


def plot(results: list[dict], path: Path) -> None:
    """fits/s against ``B`` per family: fit_many and JAX as lines, the loops as horizontal lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(results), figsize=(6 * len(results), 5), squeeze=False)
    for ax, res in zip(axes[0], results):
        rows = res["rows"]
        for kind, label, style in (("fit_many", "torchql fit_many (default)", "o-"), ("jax", "JAX LM + diffrax", "s-"),
                                   ("tuned", "torchql fit_many, tuned", "^"),
                                   ("former", "torchql fit_many, grid=1000 (former default)", "x")):
            pts = sorted((r.B, r.rate) for r in rows if r.kind == kind)
            if pts:
                ax.loglog(*zip(*pts), style, label=label)
        for k, r in enumerate(r for r in rows if r.kind in ("loop", "scipy")):
            ax.axhline(r.rate, color=f"C{3 + k}", ls="--" if r.kind == "loop" else ":", label=r.label)
        ax.set_xlabel("datasets in the batch, B")
        ax.set_ylabel("fits per second")
        ax.set_title(f"{res['family'].title}: batched fitting throughput")
        ax.grid(True, which="both", alpha=0.3)
        # below the axes: inside them it hid a marker (the oscillators' single-B rows share one x)
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# ----------------------------------------------------------------------------------------------
# Command line
# ----------------------------------------------------------------------------------------------

def load_peer(disabled: bool):
    """The ``jax_peer`` module when jax, diffrax and optimistix are importable (else None, with one line)."""
    if disabled:
        print("JAX rows skipped (--no-jax).", flush=True)
        return None
    missing = [m for m in ("jax", "diffrax", "optimistix") if importlib.util.find_spec(m) is None]
    if missing:
        print(f"JAX rows skipped: {', '.join(missing)} not installed ({JAX_HINT}).", flush=True)
        return None
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import jax_peer

    return jax_peer


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[10, 100, 1000, 10000],
                        help="batch sizes B of the cars (default 10 100 1000 10000)")
    parser.add_argument("--osc-sizes", type=int, nargs="+", default=[1000],
                        help="batch sizes B of the oscillators (default 1000)")
    parser.add_argument("--subset", type=int, default=100, help="datasets fitted by the loops (default 100)")
    parser.add_argument("--repeat", type=int, default=3,
                        help="runs of each fit_many row, JAX size and scipy loop; the fastest counts (default 3)")
    parser.add_argument("--no-jax", action="store_true", help="leave out the JAX rows even when JAX is installed")
    parser.add_argument("--quick", action="store_true",
                        help="smoke run: cars 4 and 16, oscillators 8, subset 4, one run each, no all-cores row")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "output",
                        help="output folder (default benchmarks/output)")
    args = parser.parse_args(argv)
    if args.quick:
        args.sizes, args.osc_sizes, args.subset, args.repeat = [4, 16], [8], 4, 1
    if min(args.sizes + args.osc_sizes) < 1 or args.subset < 1 or args.repeat < 1:
        parser.error("--sizes, --osc-sizes, --subset and --repeat must be positive")
    return args


def main(argv=None) -> None:
    args = parse_args(argv)
    torch.set_num_threads(1)
    peer = load_peer(args.no_jax)
    load_before = os.getloadavg()[0]
    results = [benchmark_family(family, list(sizes), args.subset, args.repeat, seed, all_cores=not args.quick)
               for seed, (family, sizes) in enumerate(((CARS, args.sizes), (OSCILLATORS, args.osc_sizes)))]
    for res in results:
        if peer is not None:
            add_jax_rows(res, peer)
        finish(res)
    report = markdown(results, (load_before, os.getloadavg()[0]), peer)
    print(report)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "batch.md").write_text("# batch: torchql.fit_many against loops of single fits and JAX\n\n" + report)
    plot(results, args.out / "batch.png")


if __name__ == "__main__":
    main()
