"""Basin of attraction: how often each method reaches the global optimum from poor guesses.

Settings (all float64):

* **FitzHugh-Nagumo** ``V' = c (V - V^3/3 + R)``, ``R' = -(V - a + b R) / c`` (the catalogue's
  ``FitzHughNagumo``), truth a = b = 0.2, c = 3, (V0, R0) = (-1, 1); both states observed every
  0.05 on [0, 20] (401 times) with Gaussian noise of sd 0.05 (seed 0; ``sigma=0.05`` given).
* **Linear oscillator, 2-digit data** ``y'' + A y' + B y = 0`` (the thesis' eq. 4.2), truth
  A = 0.1, B = 3, (y0, y0') = (0, 1); y alone at t = 0, 0.5, ..., 6.5 (14 times), rounded to two
  significant digits (the thesis' Table 4.1 data).

Starts: the coefficients drawn log-uniform in [0.1x, 10x] of the truth (seed 2024, the same
draws for every method). Initial states: the first observation for observed states; the
oscillator's unobserved velocity from the first divided difference ``(y1 - y0) / (t1 - t0)``.
``kantorovich (data)`` builds its first trajectory from the data (``initial_trajectory="data"``);
every other method starts from the same initial state.

Methods: torchql ``fit`` with ``method="kantorovich"`` (first trajectory from the data, and
integrated from the guesses) and ``method="shooting"``; ``scipy.optimize.least_squares`` over
``scipy.integrate.solve_ivp`` (DOP853, rtol 1e-10, atol 1e-12, the Jacobian from the forward
sensitivity equations integrated alongside: "lm", or "trf" with the same positivity bounds as
torchql when torchql accepts ``bounds``); ``torchql.baselines.adjoint_fit`` with Adam. Shooting (one
integration of the variational equations per update and per step halving, stepping onto all 401
FitzHugh-Nagumo observation times), Adam, and Kantorovich from an integrated first trajectory
(from a poor guess it integrates a stiff or exploding model first) are expensive: they run on the
first 10, 5 and 30 starts only, Adam within a step and time budget. Every fit also has a wall-time budget
(``budget`` in ``FULL``/``QUICK``, 120 s in the full study; a fit stopped by it is recorded as ``TIME_BUDGET``).
The fits check it between iterations, so one long integration can overrun it: the limit is made hard by
running every fit in a worker process (``run_supervised``, for any ``--workers``) that is killed when the fit
has run ``FIT_GRACE_S`` past its budget (Adam: past its time budget); that fit is recorded as ``TIME_BUDGET``
too, with its wall time up to the kill, and a worker that dies on its own (a crash) as ``WORKER_DIED``.

Reaching the global optimum: each final estimate's weighted SSE is re-evaluated with one common
accurate integrator (DOP853, rtol 1e-12); the global optima are the distinct estimates whose SSE
is within 1e-6 relative of the lowest over every method and start, each polished by one torchql
shooting fit started there (which gives its standard errors too): usually one, but the
oscillator's samples every 0.5 s cannot tell its frequency from an alias (B = 3 and B = 204.4
give the same SSE). A run reaches the global optimum when its SSE is within 1e-6 relative of the
lowest and every estimate within 0.1 standard errors of one of them.

Run (from the repository root)::

    python experiments/basin.py                # writes experiments/output/basin.{md,png,csv}
    python experiments/basin.py --quick        # a handful of starts, small budgets (< 1 minute)
    python experiments/basin.py --workers 4    # 4 worker processes (single-threaded each; default 1)
    python experiments/basin.py --out DIR --starts 100 --integrate-starts 30 --shooting-starts 10 --adam-starts 5

Only torchql's public API is used (plus scipy for the reference method).
"""

from __future__ import annotations

import argparse
import csv
import math
import multiprocessing
import multiprocessing.connection
import signal
import subprocess
import sys
import time
import traceback
from collections import Counter, deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
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
from torchql.models import FitzHughNagumo, LinearOscillator  # noqa: E402

DT = torch.float64
START_SEED, NOISE_SEED = 2024, 0
#: Success criterion (see the module docstring).
SSE_RTOL, SE_TOL = 1e-6, 0.1
#: Common yardstick for every final estimate.
EVAL_RTOL, EVAL_ATOL = 1e-12, 1e-14
SCIPY_RTOL, SCIPY_ATOL = 1e-10, 1e-12
#: torchql settings for every fit: iteration cap and per-integration solver step budget.
TORCHQL_MAX_ITER, TORCHQL_MAX_STEPS = 30, 5000
METHODS = ("kantorovich-data", "kantorovich-integrate", "shooting", "scipy", "adam", "kantorovich-auto")
LABELS = {"kantorovich-data": "torchql kantorovich (data)", "kantorovich-integrate": "torchql kantorovich (integrate)",
          "kantorovich-auto": "torchql kantorovich (default, auto)",
          "shooting": "torchql shooting", "scipy": "scipy least_squares + solve_ivp", "adam": "adjoint + Adam"}
FULL = dict(starts=100, integrate_starts=30, shooting_starts=10, adam_starts=5, budget=120.0, adam_steps=2000,
            adam_time=10.0)
QUICK = dict(starts=1, integrate_starts=1, shooting_starts=1, adam_starts=1, budget=20.0, adam_steps=3, adam_time=1.0)
#: The methods that run on the first starts only, and their key in FULL/QUICK.
FEWER_STARTS = {"kantorovich-integrate": "integrate_starts", "shooting": "shooting_starts", "adam": "adam_starts"}
#: Seconds a fit may run past its wall-time budget before its worker process is killed: the in-fit
#: watchdogs stop most fits at the budget, the kill is the backstop for one long integration.
FIT_GRACE_S = 10.0
#: Seconds a terminated worker process gets to exit before it is killed.
TERMINATE_WAIT_S = 5.0


class _OverBudget(Exception):
    """Raised from a callback when a fit exceeds its wall-time budget."""


# ----------------------------------------------------------------------------------------------
@dataclass
class Setting:
    """One basin problem: data, truth, what torchql and scipy need to fit it."""

    key: str
    title: str
    coef_names: tuple[str, ...]
    truth_coefs: np.ndarray
    truth_x0: np.ndarray
    data: torchql.Observations
    x0_guess: np.ndarray  # (n_states,) the data-driven initial state every method starts from
    observed: list[int]  # state index of each data column
    model_cls: type
    rhs: object  # numpy f(t, x, p) -> (n,)
    jac_x: object  # numpy df/dx (n, n)
    jac_p: object  # numpy df/dp (n, P), columns in coef_names order

    def model(self, coefs) -> torchql.ODEModel:
        return self.model_cls(**{n: float(v) for n, v in zip(self.coef_names, coefs)})

    @property
    def unknown_names(self) -> list[str]:
        return [f"{s}(t0)" for s in self.model_cls.state_names] + list(self.coef_names)


def fhn_setting() -> Setting:
    t = torch.arange(401, dtype=DT) * 0.05
    x = torchql.simulate(FitzHughNagumo(), torch.tensor([-1.0, 1.0], dtype=DT), t, rtol=1e-13, atol=1e-15)
    gen = torch.Generator().manual_seed(NOISE_SEED)
    y = x + 0.05 * torch.randn(x.shape, generator=gen, dtype=DT)
    data = torchql.Observations(t, y, observe=["V", "R"], sigma=0.05)

    def rhs(t, x, p):
        a, b, c = p
        V, R = x
        return np.array([c * (V - V**3 / 3 + R), -(V - a + b * R) / c])

    def jac_x(t, x, p):
        a, b, c = p
        V, R = x
        return np.array([[c * (1 - V**2), c], [-1 / c, -b / c]])

    def jac_p(t, x, p):
        a, b, c = p
        V, R = x
        return np.array([[0.0, 0.0, V - V**3 / 3 + R], [1 / c, -R / c, (V - a + b * R) / c**2]])

    return Setting("fhn", "FitzHugh-Nagumo, noisy (sd 0.05, 401 times)", ("a", "b", "c"), np.array([0.2, 0.2, 3.0]),
                   np.array([-1.0, 1.0]), data, y[0].numpy().copy(), [0, 1], FitzHughNagumo, rhs, jac_x, jac_p)


def oscillator_setting() -> Setting:
    t = torch.arange(14, dtype=DT) * 0.5
    y = torchql.simulate(LinearOscillator(), torch.tensor([0.0, 1.0], dtype=DT), t, rtol=1e-13, atol=1e-15)[:, 0]
    y = torch.tensor([float(f"{v:.1e}") for v in y.tolist()], dtype=DT)
    data = torchql.Observations(t, y.unsqueeze(-1), observe=["y"])
    x0 = np.array([y[0].item(), ((y[1] - y[0]) / (t[1] - t[0])).item()])

    def rhs(t, x, p):
        A, B = p
        return np.array([x[1], -A * x[1] - B * x[0]])

    def jac_x(t, x, p):
        A, B = p
        return np.array([[0.0, 1.0], [-B, -A]])

    def jac_p(t, x, p):
        return np.array([[0.0, 0.0], [-x[1], -x[0]]])

    return Setting("oscillator", "Linear oscillator, 2-digit data (14 times, y only)", ("A", "B"), np.array([0.1, 3.0]),
                   np.array([0.0, 1.0]), data, x0, [0], LinearOscillator, rhs, jac_x, jac_p)


SETTINGS = {"fhn": fhn_setting, "oscillator": oscillator_setting}


def draw_starts(setting: Setting, n: int) -> np.ndarray:
    """``(n, P)`` factors, log-uniform in [0.1, 10], one row per start (same for every method)."""
    rng = np.random.default_rng([START_SEED, list(SETTINGS).index(setting.key)])
    return 10.0 ** rng.uniform(-1.0, 1.0, size=(n, len(setting.coef_names)))


# ----------------------------------------------------------------------------------------------
def bounds_supported(setting: Setting) -> bool:
    """Whether ``torchql.fit`` accepts ``bounds`` (it raised NotImplementedError before they existed)."""
    try:
        torchql.fit(setting.model(setting.truth_coefs), setting.data, x0=torch.tensor(setting.x0_guess),
                    bounds={setting.coef_names[0]: (0.0, None)}, max_iter=0)
    except NotImplementedError:
        return False
    return True


def run_torchql(setting: Setting, coefs, method: str, bounds: bool, budget: float) -> dict:
    kind, _, init = method.partition("-")
    kwargs = dict(method=kind, max_iter=TORCHQL_MAX_ITER, max_steps=TORCHQL_MAX_STEPS)
    if kind == "kantorovich":
        kwargs["initial_trajectory"] = init
        kwargs["grid"] = setting.data.n_times - 1 if setting.data.n_times > 100 else None
    if bounds:
        kwargs["bounds"] = {name: (0.0, None) for name in setting.coef_names}
    start = time.perf_counter()

    def watchdog(record):
        if time.perf_counter() - start > budget:
            raise _OverBudget

    try:
        result = torchql.fit(setting.model(coefs), setting.data, x0=torch.tensor(setting.x0_guess), callback=watchdog,
                             **kwargs)
    except _OverBudget:
        return dict(status="TIME_BUDGET", iterations=-1, wall=time.perf_counter() - start, estimates=None)
    return dict(status=result.status.name, iterations=result.iterations, wall=time.perf_counter() - start,
                estimates=result.estimates.numpy().copy())


class _ScipyProblem:
    """Weighted residuals of the model integrated by solve_ivp, and their Jacobian from the
    forward sensitivity equations (one solve gives both; cached by the point)."""

    def __init__(self, setting: Setting, budget: float, start: float):
        self.s, self.budget, self.start = setting, budget, start
        self.t = setting.data.t.numpy()
        self.y = setting.data.y.numpy()
        self.w = 1.0 / setting.data.sigma.numpy()
        self.n, self.P = len(setting.truth_x0), len(setting.coef_names)
        self._key, self._value = None, None

    def _solve(self, u: np.ndarray):
        key = u.tobytes()
        if key == self._key:
            return self._value
        if time.perf_counter() - self.start > self.budget:
            raise _OverBudget
        n, P, s = self.n, self.P, self.s
        p = u[n:]
        m = n + P

        def f(t, zs):
            x, S = zs[:n], zs[n:].reshape(n, m)
            dS = s.jac_x(t, x, p) @ S
            dS[:, n:] += s.jac_p(t, x, p)
            return np.concatenate([s.rhs(t, x, p), dS.ravel()])

        z0 = np.concatenate([u[:n], np.eye(n, m).ravel()])
        with np.errstate(all="ignore"):
            sol = solve_ivp(f, (self.t[0], self.t[-1]), z0, method="DOP853", t_eval=self.t, rtol=SCIPY_RTOL,
                            atol=SCIPY_ATOL)
        if not sol.success or sol.y.shape[1] != len(self.t) or not np.isfinite(sol.y).all():
            r = np.full(self.y.size, 1e6)
            J = np.zeros((self.y.size, m))
        else:
            x = sol.y[:n].T  # (T, n)
            S = sol.y[n:].T.reshape(len(self.t), n, m)
            idx = self.s.observed
            r = ((self.y - x[:, idx]) * self.w).ravel()
            J = (-S[:, idx, :] * self.w[:, :, None]).reshape(-1, m)
        self._key, self._value = key, (r, J)
        return r, J

    def fun(self, u):
        return self._solve(u)[0]

    def jac(self, u):
        return self._solve(u)[1]


def run_scipy(setting: Setting, coefs, bounds: bool, budget: float) -> dict:
    start = time.perf_counter()
    sp = _ScipyProblem(setting, budget, start)
    u0 = np.concatenate([setting.x0_guess, coefs])
    n = len(setting.x0_guess)
    if bounds:
        lower = np.concatenate([np.full(n, -np.inf), np.zeros(len(coefs))])
        kwargs = dict(method="trf", bounds=(lower, np.full(len(u0), np.inf)))
    else:
        kwargs = dict(method="lm")
    try:
        out = least_squares(sp.fun, u0, jac=sp.jac, xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=200, **kwargs)
    except _OverBudget:
        return dict(status="TIME_BUDGET", iterations=-1, wall=time.perf_counter() - start, estimates=None)
    status = {-1: "IMPROPER_INPUT", 0: "MAX_NFEV"}.get(out.status, "CONVERGED")
    iterations = int(out.njev) if out.njev is not None else int(out.nfev)
    return dict(status=f"{status} ({out.status})", iterations=iterations, wall=time.perf_counter() - start,
                estimates=out.x.copy())


def run_adam(setting: Setting, coefs, steps: int, max_time: float) -> dict:
    start = time.perf_counter()
    result = adjoint_fit(setting.model(coefs), setting.data, x0=torch.tensor(setting.x0_guess), optimizer="adam",
                         max_steps=steps, max_time=max_time)
    return dict(status=result.status.name, iterations=result.iterations, wall=time.perf_counter() - start,
                estimates=result.estimates.numpy().copy())


def sse_at(setting: Setting, u) -> float:
    """Weighted SSE at unknowns ``u`` (initial states, then coefficients), integrated accurately."""
    if u is None or not np.isfinite(u).all():
        return math.nan
    n = len(setting.truth_x0)
    with np.errstate(all="ignore"):
        sol = solve_ivp(setting.rhs, (setting.data.t[0].item(), setting.data.t[-1].item()), u[:n], method="DOP853",
                        t_eval=setting.data.t.numpy(), args=(u[n:],), rtol=EVAL_RTOL, atol=EVAL_ATOL)
    if not sol.success or sol.y.shape[1] != setting.data.n_times or not np.isfinite(sol.y).all():
        return math.nan
    r = (setting.data.y.numpy() - sol.y[setting.observed].T) / setting.data.sigma.numpy()
    return float(np.sum(r**2))


# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class JobFailure:
    """A job without a result: ``TIME_BUDGET`` (its worker was killed past the job's limit) or
    ``WORKER_DIED`` (its worker exited on its own, e.g. a crash); ``wall``: seconds it ran."""

    status: str
    wall: float


@dataclass
class _Worker:
    """A persistent worker process, the parent's end of its pipe, and the job it runs (if ``busy``)."""

    process: multiprocessing.process.BaseProcess
    conn: multiprocessing.connection.Connection
    ready: bool = False
    busy: bool = False
    job: object = None
    started: float = 0.0
    limit: float = 0.0


def _worker_main(conn: multiprocessing.connection.Connection, func: Callable,
                 initializer: Callable[[], None] | None) -> None:
    """Worker process: run each job received on ``conn`` and send back ``("ok", result)`` or
    ``("error", traceback)``, until the parent closes its end. Ctrl-C is left to the parent, which
    stops the workers."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if initializer is not None:
        initializer()
    conn.send(("ready", None))
    while True:
        try:
            job = conn.recv()
        except EOFError:
            return
        try:
            reply = ("ok", func(job))
        except Exception:
            reply = ("error", traceback.format_exc())
        conn.send(reply)


def _start_worker(ctx: multiprocessing.context.BaseContext, func: Callable,
                  initializer: Callable[[], None] | None) -> _Worker:
    """Start a worker process; it is not ``ready`` for jobs until it says so (after its imports)."""
    parent, child = ctx.Pipe()
    process = ctx.Process(target=_worker_main, args=(child, func, initializer), daemon=True)
    process.start()
    child.close()
    return _Worker(process, parent)


def _stop_worker(worker: _Worker) -> None:
    """Terminate the worker's process, kill it if it does not exit, and close its pipe."""
    worker.conn.close()
    worker.process.terminate()
    worker.process.join(TERMINATE_WAIT_S)
    if worker.process.exitcode is None:
        worker.process.kill()
        worker.process.join()


def _receive(worker: _Worker) -> tuple[str, object] | None:
    """The worker's next message, ``("died", None)`` when its process is gone, None when neither."""
    try:
        if not worker.conn.poll():
            return None if worker.process.exitcode is None else ("died", None)
        return worker.conn.recv()
    except (EOFError, OSError):
        return "died", None


def run_supervised(jobs: Sequence, func: Callable, workers: int, limit_of: Callable[[object], float],
                   on_result: Callable[[object, object], None],
                   initializer: Callable[[], None] | None = None) -> None:
    """Run ``func(job)`` for every job in ``workers`` persistent spawned processes, with a hard
    wall-time limit per job.

    ``on_result(job, result)`` is called here as each job ends (in completion order) with
    ``func(job)``'s return value, or with a :class:`JobFailure` when the job ran ``limit_of(job)``
    seconds (its worker is killed: a check inside the job cannot interrupt, e.g., one long
    integration) or its worker died. Only such a worker is replaced (while jobs remain), so imports
    and per-process caches are paid once per worker; the clock of a job starts when a ready worker
    receives it. An exception raised by ``func`` is raised here as RuntimeError. No worker outlives
    the call (normal return, exception, Ctrl-C). ``func`` and ``initializer`` must be top-level
    functions that the spawned processes can import.
    """
    if workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    ctx = multiprocessing.get_context("spawn")
    pending = deque(jobs)
    pool: list[_Worker] = []
    try:
        for _ in range(min(workers, len(pending))):
            pool.append(_start_worker(ctx, func, initializer))
        while pending or any(w.busy for w in pool):
            for w in pool:
                if w.ready and not w.busy and pending:
                    w.job = pending.popleft()
                    w.busy, w.started, w.limit = True, time.perf_counter(), limit_of(w.job)
                    try:
                        w.conn.send(w.job)
                    except OSError:
                        pass  # the worker is gone: its job is recorded as WORKER_DIED below
            deadlines = [w.started + w.limit for w in pool if w.busy]
            timeout = max(0.0, min(deadlines) - time.perf_counter()) if deadlines else None
            multiprocessing.connection.wait([w.conn for w in pool] + [w.process.sentinel for w in pool], timeout)
            for w in list(pool):
                message = _receive(w)
                elapsed = time.perf_counter() - w.started
                if message is None:
                    if not (w.busy and elapsed >= w.limit):
                        continue
                    failure = JobFailure("TIME_BUDGET", elapsed)
                elif message[0] == "ready":
                    w.ready = True
                    continue
                elif message[0] == "ok":
                    w.busy = False
                    on_result(w.job, message[1])
                    continue
                elif message[0] == "error":
                    raise RuntimeError(f"a job raised in a worker process:\n{message[1]}")
                elif not w.ready:
                    raise RuntimeError(f"a worker process exited while starting (exit code {w.process.exitcode})")
                else:
                    failure = JobFailure("WORKER_DIED", elapsed)
                _stop_worker(w)
                pool.remove(w)
                if pending:
                    pool.append(_start_worker(ctx, func, initializer))
                if w.busy:
                    on_result(w.job, failure)
    finally:
        for w in pool:
            _stop_worker(w)


# ----------------------------------------------------------------------------------------------
_WORKER_SETTINGS: dict = {}


def _init_worker() -> None:
    torch.set_num_threads(1)


def _job(args) -> dict:
    key, index, coefs, method, bounds, cfg = args
    if key not in _WORKER_SETTINGS:
        _WORKER_SETTINGS[key] = SETTINGS[key]()
    setting = _WORKER_SETTINGS[key]
    if method == "scipy":
        out = run_scipy(setting, coefs, bounds, cfg["budget"])
    elif method == "adam":
        out = run_adam(setting, coefs, cfg["adam_steps"], cfg["adam_time"])
    else:
        out = run_torchql(setting, coefs, method, bounds, cfg["budget"])
    out.update(setting=key, start=index, method=method, factors=coefs / setting.truth_coefs,
               sse=sse_at(setting, out["estimates"]))
    return out


def _job_limit(job) -> float:
    """Hard wall-time limit of a ``_job``: its budget (Adam's time budget) plus ``FIT_GRACE_S``."""
    method, cfg = job[3], job[5]
    return (cfg["adam_time"] if method == "adam" else cfg["budget"]) + FIT_GRACE_S


def failed_row(setting: Setting, job, failure: JobFailure) -> dict:
    """The row of a ``_job`` that the supervisor stopped or lost: ``_job``'s fields, without estimates."""
    key, index, coefs, method, _, _ = job
    return dict(status=failure.status, iterations=-1, wall=failure.wall, estimates=None, setting=key, start=index,
                method=method, factors=coefs / setting.truth_coefs, sse=math.nan)


@dataclass
class Optimum:
    """One global optimum: estimates (initial states, then coefficients), weighted SSE, standard errors."""

    u: np.ndarray
    sse: float
    se: np.ndarray


def global_optima(setting: Setting, rows: list[dict]) -> list[Optimum]:
    """The distinct optima whose SSE equals the best any run reached (within ``SSE_RTOL``), best first.

    Each is a run's estimate polished by one torchql shooting fit started there (which gives its
    standard errors). Sampled data may not tell several optima apart: y sampled every 0.5 s
    cannot distinguish the oscillator's frequency ``w`` from ``w + 4 pi`` (``B = 3`` from
    ``B = 204.4``, the same SSE to rounding), so every run that reaches one of them reaches the
    global optimum. Runs within ``SE_TOL`` standard errors of an optimum already found are the
    same optimum.
    """
    finite = sorted((r for r in rows if np.isfinite(r["sse"])), key=lambda r: r["sse"])
    if not finite:
        raise RuntimeError(f"no fit of the {setting.title} setting ended with a finite SSE: there is no optimum "
                           "to compare the starts with (give the fits more time: --starts, budgets)")
    best_sse = finite[0]["sse"]
    n = len(setting.truth_x0)
    optima: list[Optimum] = []
    for r in finite:
        if r["sse"] > best_sse * (1 + SSE_RTOL):
            break
        u = r["estimates"]
        if any(np.max(np.abs(u - o.u) / o.se) <= SE_TOL for o in optima):
            continue
        result = torchql.fit(setting.model(u[n:]), setting.data, x0=torch.tensor(u[:n]), method="shooting")
        polished = result.estimates.numpy()
        sse_pol = sse_at(setting, polished)
        if result.success and sse_pol <= r["sse"]:
            u, sse = polished, sse_pol
        else:
            sse = r["sse"]
        optima.append(Optimum(u, sse, np.array([result.stderr[name] for name in result.unknown_names])))
    return sorted(optima, key=lambda o: o.sse)


def classify(rows: list[dict], optima: list[Optimum]) -> None:
    """Mark each run ``reached`` when it ends at one of the global ``optima``; ``se_dev``: its distance to the nearest."""
    best_sse = min(o.sse for o in optima)
    for r in rows:
        u = r["estimates"]
        if u is None or not np.isfinite(r["sse"]):
            r["se_dev"], r["reached"] = math.nan, False
            continue
        r["se_dev"] = float(min(np.max(np.abs(u - o.u) / o.se) for o in optima))
        r["reached"] = bool(r["sse"] <= best_sse * (1 + SSE_RTOL) and r["se_dev"] <= SE_TOL)


def failure_mode(r: dict) -> str:
    if r["reached"]:
        return ""
    status = r["status"].split(" ")[0]
    if status in ("CONVERGED", "CONVERGED_SSE") and np.isfinite(r["sse"]):
        return "converged elsewhere"
    return status


# ----------------------------------------------------------------------------------------------
def summarize(rows: list[dict]) -> list[dict]:
    out = []
    for method in METHODS:
        rs = [r for r in rows if r["method"] == method]
        if not rs:
            continue
        reached = [r for r in rs if r["reached"]]
        its = [r["iterations"] for r in rs if r["iterations"] >= 0]
        out.append(dict(method=method, n=len(rs), reached=len(reached), fraction=len(reached) / len(rs),
                        med_iter=float(np.median(its)) if its else math.nan,
                        med_iter_reached=float(np.median([r["iterations"] for r in reached])) if reached else math.nan,
                        med_wall=float(np.median([r["wall"] for r in rs])),
                        med_wall_reached=float(np.median([r["wall"] for r in reached])) if reached else math.nan,
                        failures=Counter(failure_mode(r) for r in rs if not r["reached"])))
    return out


def _fmt(v, spec="g") -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, spec)


def library_version() -> str:
    root = Path(torchql.__file__).resolve().parents[1]
    try:
        head = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--", "torchql"], capture_output=True,
                               text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return f"torchql {torchql.__version__}"
    if not head:
        return f"torchql {torchql.__version__} from {root}"
    return f"torchql {torchql.__version__}, git {head}" + (" with uncommitted changes under torchql/" if dirty else "")


def write_markdown(path: Path, settings, rows, refs, cfg, bounds, quick: bool, total: float, workers: int,
                   command: str = "python experiments/basin.py") -> None:
    lines = ["# Basin of attraction from poor guesses", ""]
    if quick:
        lines += ["**--quick run: a handful of starts and tiny budgets; not the study's figures.**", ""]
    lines += [
        f"Generated by `{command}`"
        f" ({library_version()}; total wall time {total / 60:.1f} min with {workers} worker process(es),"
        " each single-threaded; wall times are per fit on a shared 2-core machine).", "",
        "Starts: coefficients drawn log-uniform in [0.1x, 10x] of the truth (seed "
        f"{START_SEED}, the same draws for every method; the expensive ones on the first starts only: kantorovich "
        f"(integrate) {cfg['integrate_starts']}, shooting {cfg['shooting_starts']}, Adam {cfg['adam_starts']}). Initial states "
        "from the first observation (the oscillator's unobserved velocity from the first divided difference); "
        "`kantorovich (data)` takes its first trajectory from the data (`initial_trajectory=\"data\"`).", "",
        "**Reaching the global optimum**: the run's final estimate, re-evaluated with one accurate integrator "
        f"(DOP853, rtol {EVAL_RTOL:g}), has a weighted SSE within {SSE_RTOL:g} relative of the best SSE any method "
        f"reached from any start (polished by one shooting fit), and every estimate (initial states and "
        f"coefficients) lies within {SE_TOL:g} standard errors of a global optimum: a best estimate, or another "
        "with the same SSE (to that tolerance) where the data cannot tell several apart.", "",
        "Budgets: torchql `max_iter={}`, `max_steps={}` (solver steps per integration), kantorovich storage grid = "
        "the observation times for FitzHugh-Nagumo (400 intervals), the default for the oscillator (`grid=\"auto\"`: "
        "each fit's uniform intervals chosen from its first reference); scipy "
        "`max_nfev=200`; every torchql and scipy fit is stopped after {:g} s of wall time (`TIME_BUDGET`), "
        "checked between iterations. Adam: `adjoint_fit(optimizer=\"adam\")`, default learning rate, at most {} "
        "steps or {:g} s, on the first {} starts. The limit is hard: each fit runs in a worker process, killed "
        "{:g} s past the fit's budget (Adam: its time budget) when, e.g., one long integration overruns it; such "
        "a fit is `TIME_BUDGET` too, with its wall time up to the kill.".format(
            TORCHQL_MAX_ITER, TORCHQL_MAX_STEPS, cfg["budget"], cfg["adam_steps"], cfg["adam_time"],
            cfg["adam_starts"], FIT_GRACE_S), "",
        "Bounds: " + ("`torchql.fit` accepts `bounds`: the torchql runs use positivity bounds (0, None) on every "
                      "coefficient, and scipy uses method \"trf\" with the same bounds."
                      if bounds else "`torchql.fit(..., bounds=...)` raised NotImplementedError: every torchql run is "
                      "unbounded, and scipy uses method \"lm\" (unbounded)."), "",
        "Iterations: torchql updates; scipy Jacobian evaluations (`njev`); Adam steps. Medians over every "
        "start of the method (failed ones included, except `TIME_BUDGET` and `WORKER_DIED`), and over those "
        "that reached the optimum.", "",
    ]
    for setting in settings:
        optima = refs[setting.key]
        truth = np.concatenate([setting.truth_x0, setting.truth_coefs])
        rs = [r for r in rows if r["setting"] == setting.key]
        described = [f"SSE {o.sse:.10g}; " + ", ".join(
            f"{n} = {v:.6g} ± {s:.2g} (truth {t:g})" for n, v, s, t in zip(setting.unknown_names, o.u, o.se, truth))
            for o in optima]
        if len(optima) == 1:
            header = [f"Global optimum: {described[0]}.", ""]
        else:
            counts = [sum(1 for r in rs if r["reached"] and np.max(np.abs(r["estimates"] - o.u) / o.se) <= SE_TOL)
                      for o in optima]
            header = [f"{len(optima)} global optima, with the same SSE to within {SSE_RTOL:g} (the data cannot tell "
                      "them apart; a run that reaches any of them reaches the global optimum):", ""]
            header += [f"{k + 1}. {d} ({c} runs)" for k, (d, c) in enumerate(zip(described, counts))] + [""]
        lines += [f"## {setting.title}", "", *header,
                  "| method | starts | reached optimum | fraction | median iterations (all / reached) | "
                  "median wall s (all / reached) | failure modes (count) |",
                  "|---|---|---|---|---|---|---|"]
        for s in summarize(rs):
            modes = ", ".join(f"{k} {v}" for k, v in s["failures"].most_common()) or "none"
            lines.append(f"| {LABELS[s['method']]} | {s['n']} | {s['reached']} | {s['fraction']:.2f} | "
                         f"{_fmt(s['med_iter'])} / {_fmt(s['med_iter_reached'])} | "
                         f"{_fmt(s['med_wall'], '.2f')} / {_fmt(s['med_wall_reached'], '.2f')} | {modes} |")
        lines.append("")
    lines += ["Failure modes: a torchql `Status` name (its message says what it means), `TIME_BUDGET` "
              "(stopped by the wall-time budget), `WORKER_DIED` (the fit's worker process exited during the fit: "
              "a crash), `converged elsewhere` (the method reported convergence, but "
              "to another stationary point than the optimum), scipy's `MAX_NFEV`; Adam's `MAX_ITER` is the end "
              "of its step or time budget.", "",
              "Every start and outcome: `basin.csv`. Figure: `basin.png` (each start's coefficient factors, "
              "green when it reached the optimum).", ""]
    path.write_text("\n".join(lines))


def write_csv(path: Path, settings, rows) -> None:
    width = max(len(s.unknown_names) for s in settings)
    pwidth = max(len(s.coef_names) for s in settings)
    fields = (["setting", "method", "start"] + [f"factor_{i}" for i in range(pwidth)]
              + ["status", "reached", "failure_mode", "iterations", "wall_s", "sse", "se_deviation"]
              + [f"estimate_{i}" for i in range(width)] + ["unknown_names"])
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        for r in rows:
            setting = next(s for s in settings if s.key == r["setting"])
            row = dict(setting=r["setting"], method=r["method"], start=r["start"], status=r["status"],
                       reached=int(r["reached"]), failure_mode=failure_mode(r), iterations=r["iterations"],
                       wall_s=f"{r['wall']:.3f}", sse=f"{r['sse']:.12g}", se_deviation=f"{r['se_dev']:.4g}",
                       unknown_names=" ".join(setting.unknown_names))
            for i, v in enumerate(r["factors"]):
                row[f"factor_{i}"] = f"{v:.6g}"
            if r["estimates"] is not None:
                for i, v in enumerate(r["estimates"]):
                    row[f"estimate_{i}"] = f"{v:.12g}"
            w.writerow(row)


def plot(path: Path, settings, rows) -> None:
    methods = [m for m in METHODS if any(r["method"] == m for r in rows)]
    fig, axes = plt.subplots(len(settings), len(methods), figsize=(3.3 * len(methods), 3.3 * len(settings)),
                             squeeze=False)
    for i, setting in enumerate(settings):
        names = setting.coef_names
        ix, iy = (0, 2) if len(names) == 3 else (0, 1)
        for j, method in enumerate(methods):
            ax = axes[i, j]
            rs = [r for r in rows if r["setting"] == setting.key and r["method"] == method]
            for ok, color, label in ((True, "tab:green", "reached"), (False, "tab:red", "not reached")):
                pts = np.array([r["factors"] for r in rs if r["reached"] == ok]).reshape(-1, len(names))
                ax.scatter(pts[:, ix], pts[:, iy], s=14, c=color, label=label, alpha=0.8)
            n_ok = sum(r["reached"] for r in rs)
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlim(0.08, 12.5)
            ax.set_ylim(0.08, 12.5)
            ax.axvline(1, color="0.8", lw=0.8, zorder=0)
            ax.axhline(1, color="0.8", lw=0.8, zorder=0)
            ax.set_title(f"{LABELS[method]}\n{n_ok}/{len(rs)} reached", fontsize=9)
            ax.set_xlabel(f"{names[ix]} start / truth", fontsize=8)
            if j == 0:
                ax.set_ylabel(f"{setting.title.split(',')[0]}\n{names[iy]} start / truth", fontsize=8)
    axes[0, 0].legend(fontsize=7, loc="lower left")
    fig.suptitle("Starts (coefficient factors, log scale) coloured by whether the method reached the optimum")
    fig.tight_layout(rect=(0, 0, 1, 0.96))
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "output")
    parser.add_argument("--quick", action="store_true", help="a handful of starts and small budgets (< 1 minute)")
    parser.add_argument("--starts", type=int, default=None, help="starts per setting (default 100; --quick 1)")
    parser.add_argument("--integrate-starts", type=int, default=None,
                        help="starts for torchql kantorovich (integrate) (default 30; --quick 1)")
    parser.add_argument("--shooting-starts", type=int, default=None,
                        help="starts for torchql shooting (default 10; --quick 1)")
    parser.add_argument("--adam-starts", type=int, default=None, help="starts for Adam (default 5; --quick 1)")
    parser.add_argument("--workers", type=int, default=1,
                        help="worker processes, each killing fits past their budget (default 1)")
    parser.add_argument("--settings", nargs="+", choices=list(SETTINGS), default=list(SETTINGS))
    parser.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS[:-1]),
                        help="methods to run (default all but kantorovich-auto, torchql's default start: from "
                             "the data on both settings, so it repeats kantorovich-data)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    cfg = dict(QUICK if args.quick else FULL)
    if args.starts is not None:
        cfg["starts"] = args.starts
    for key in FEWER_STARTS.values():
        if getattr(args, key) is not None:
            cfg[key] = getattr(args, key)
        cfg[key] = min(cfg[key], cfg["starts"])
    args.out.mkdir(parents=True, exist_ok=True)

    t_start = time.perf_counter()
    settings = [SETTINGS[key]() for key in args.settings]
    bounds = bounds_supported(settings[0])
    print(f"bounds supported by torchql.fit: {bounds}", flush=True)
    jobs = []
    for setting in settings:
        for index, factors in enumerate(draw_starts(setting, cfg["starts"])):
            coefs = setting.truth_coefs * factors
            for method in args.methods:
                if method in FEWER_STARTS and index >= cfg[FEWER_STARTS[method]]:
                    continue
                jobs.append((setting.key, index, coefs, method, bounds, cfg))
    by_key = {setting.key: setting for setting in settings}
    rows = []

    def collect(job, result) -> None:
        if isinstance(result, JobFailure):
            result = failed_row(by_key[job[0]], job, result)
        rows.append(result)
        _progress(len(rows) - 1, len(jobs), result, t_start)

    run_supervised(jobs, _job, args.workers, _job_limit, collect, initializer=_init_worker)
    rows.sort(key=lambda r: (args.settings.index(r["setting"]), METHODS.index(r["method"]), r["start"]))

    refs = {}
    for setting in settings:
        rs = [r for r in rows if r["setting"] == setting.key]
        refs[setting.key] = global_optima(setting, rs)
        classify(rs, refs[setting.key])
    total = time.perf_counter() - t_start
    given = list(sys.argv[1:] if argv is None else argv)
    kept = [a for k, a in enumerate(given)  # without --out DIR / --out=DIR (the place, not the experiment)
            if a != "--out" and not a.startswith("--out=") and not (k and given[k - 1] == "--out")]
    command = " ".join(["python experiments/basin.py", *kept])
    write_markdown(args.out / "basin.md", settings, rows, refs, cfg, bounds, args.quick, total, args.workers, command)
    write_csv(args.out / "basin.csv", settings, rows)
    plot(args.out / "basin.png", settings, rows)
    for setting in settings:
        print(f"\n{setting.title}")
        for s in summarize([r for r in rows if r["setting"] == setting.key]):
            print(f"  {LABELS[s['method']]:34s} {s['reached']:3d}/{s['n']:3d} reached  median it {_fmt(s['med_iter'])}"
                  f"  median wall {s['med_wall']:.2f} s  failures {dict(s['failures'])}")
    print(f"\nwrote {args.out / 'basin.md'}, basin.png, basin.csv in {total / 60:.1f} min")


def _progress(k: int, n: int, row: dict, t_start: float) -> None:
    if (k + 1) % 10 == 0 or k + 1 == n:
        print(f"  {k + 1}/{n} fits done ({time.perf_counter() - t_start:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
