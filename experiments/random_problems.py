"""Seeded random fitting problems: torchql against scipy ``least_squares`` from the same guesses.

Every problem is drawn from a seed, so a failure found here can be rerun alone
(``make_problem(family, seed, noise)``). Five families (all float64):

* ``linear``: ``x' = K x`` with 2-4 states, ``K = -(Q diag(lam) Q^-1)``, ``lam`` uniform in
  [0.2, 2] and ``Q`` Gaussian with condition number below 10; 1 to n-1 states observed at 51 times
  on [0, 10]. Unknowns: 1 to n entries of ``K`` (each a scalar buffer ``kij``, the others held at
  the truth) and every initial state.
* ``oscillator``: ``y'' + c y' + k y = 0`` (``torchql.models.LinearOscillator``, A = c, B = k) or
  the Duffing-type ``y'' + c y' + k y + d y^3 = 0``, drawn with equal odds; the position alone
  observed at 51 times on [0, 10]. Unknowns: the coefficients and both initial states.
* ``logistic``: ``x' = r x (1 - x / K)``; unknowns r, K, x0; 31 times from 0 to 3/r past the midpoint.
* ``lotka_volterra``: ``x' = a x - b x y``, ``y' = c x y - d y``, both states observed at 61 times
  over two periods; unknowns a, b, c, d and both initial states.
* ``michaelis_menten``: ``S' = -V S / (Km + S)``, S0 in [1, 5] Km; unknowns V, Km, S0; 31 times
  until S falls to 5 % of S0.

Data: the truth integrated by ``solve_ivp`` (DOP853, rtol 1e-13, atol 1e-15), plus Gaussian noise of
sd ``noise * scale`` (``scale``: each observed column's largest |value|), noise 0, 1e-3 or 1e-1.
Each drawn problem must be identifiable: the Jacobian of the residuals at the truth (forward
sensitivities), its columns scaled to unit norm, has full rank and a condition number below
``MAX_COND`` = 1e6; otherwise the problem is drawn again from the same random stream.

Guesses: every coefficient times a factor log-uniform in [0.3, 3]; an observed initial state is the
first observation, an unobserved one the truth times such a factor.

Methods, from the same guess, with no sigma given (both minimize the plain sum of squares):

* ``torchql.fit`` with its default options (Kantorovich, DOP853, rtol 1e-10, atol 1e-12), only
  ``max_time`` passed (``--max-time``; passed only where ``torchql.fit`` accepts it);
* ``scipy.optimize.least_squares(method="trf")`` with its default options (xtol = ftol = gtol =
  1e-8, ``x_scale`` 1, ``max_nfev`` 100 m) over ``scipy.integrate.solve_ivp`` with DOP853 at the same
  rtol 1e-10 / atol 1e-12. DOP853 rather than LSODA: none of these problems is stiff, and at these
  tight tolerances the eighth-order explicit method takes far fewer steps than LSODA's Adams
  method (each step a Python call); it is the integrator of the other experiment scripts. The
  Jacobian is passed (``jac=``), integrated alongside the model as its forward sensitivity
  equations: finite differences through an adaptive integrator are noisy, and a reference that
  stops early for that reason would make torchql look better than it is. The same wall-time
  budget applies (checked at every right-hand-side evaluation; reported as ``MAX_TIME``).

Verdicts: both estimates' SSE is re-evaluated with one accurate integrator (DOP853, rtol 1e-12,
atol 1e-14). The best SSE is the lower of the two; a method *reaches* the optimum when its SSE is at
most ``best * (1 + 1e-6) + floor``, the floor ``L * (1e-8 * scale)^2`` (L values, ``scale`` the
largest column scale): exact data are fitted to the integrators' accuracy only (RMS residuals of
1e-10 to 1e-9 of the signal), so on exact data an absolute floor like 1e-20 would declare whichever
method's integrator happened to be more accurate the only one to reach the optimum; with noise
1e-3 the floor is 1e-10 of the SSE, negligible. A *wrong diagnosis* is a torchql result with
``success=True`` that does not reach the best SSE (a false claim of convergence), or
``NOT_IDENTIFIABLE`` on a problem whose Jacobian at scipy's optimum is well conditioned
(column-scaled condition number below ``MAX_COND``).

Run (from the repository root)::

    python experiments/random_problems.py                      # 45 problems; prints the report
    python experiments/random_problems.py --write              # also writes experiments/output/random_problems.md
    python experiments/random_problems.py --n 15 --families logistic linear --max-time 60 --workers 2

The printed report holds wall times, which depend on the machine and its load. Each process first
fits one small problem with both methods, untimed, and the report gives that warm-up apart: the first
``torch.func`` derivative in a process imports ``torch._dynamo`` (about 1 s, once), a cost of the
process and not of any one fit, as scipy's first call pays its own imports.
"""

from __future__ import annotations

import argparse
import inspect
import math
import sys
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from scipy.integrate import solve_ivp
from scipy.optimize import least_squares

import torchql
from torchql.models import LinearOscillator

DTYPE = torch.float64
FAMILIES = ("linear", "oscillator", "logistic", "lotka_volterra", "michaelis_menten")
NOISES = (0.0, 1e-3, 1e-1)
#: Integrator of the data and of the SSE re-evaluation; of the scipy fits (torchql's float64 defaults).
DATA_RTOL, DATA_ATOL = 1e-13, 1e-15
EVAL_RTOL, EVAL_ATOL = 1e-12, 1e-14
FIT_RTOL, FIT_ATOL = 1e-10, 1e-12
#: Identifiability: the column-scaled Jacobian's largest condition number.
MAX_COND = 1e6
#: Guess factors: log-uniform in [GUESS_LOW, GUESS_HIGH].
GUESS_LOW, GUESS_HIGH = 0.3, 3.0
#: Reaching the optimum: relative SSE tolerance and the floor's RMS residual relative to the scale.
SSE_RTOL, FLOOR_REL = 1e-6, 1e-8
MAX_DRAWS = 200


# ----------------------------------------------------------------------------------------------
# torch models (torchql) -- each mirrors a numpy right-hand side below
def _scalar(value: float) -> torch.Tensor:
    return torch.tensor(float(value), dtype=DTYPE)


class LinearSystem(torchql.ODEModel):
    """``x' = K x``: ``K = K_fixed + sum_j k_j E_j``; the free entries are scalar buffers ``kij``."""

    constants = ("K_fixed", "E")

    def __init__(self, K_fixed: np.ndarray, free: Sequence[tuple[int, int]], values: Sequence[float]):
        super().__init__()
        n = K_fixed.shape[0]
        self.state_names = tuple(f"x{i + 1}" for i in range(n))
        self.free_names = tuple(f"k{i + 1}{j + 1}" for i, j in free)
        E = np.zeros((len(free), n, n))
        K = K_fixed.copy()
        for e, (i, j) in enumerate(free):
            E[e, i, j] = 1.0
            K[i, j] = 0.0
        self.register_buffer("K_fixed", torch.tensor(K, dtype=DTYPE))
        self.register_buffer("E", torch.tensor(E, dtype=DTYPE))
        for name, value in zip(self.free_names, values):
            self.register_buffer(name, _scalar(value))

    def forward(self, t, x):
        k = torch.stack([getattr(self, name) for name in self.free_names])
        K = self.K_fixed + torch.einsum("e,eij->ij", k, self.E)
        return torch.einsum("ij,...j->...i", K, x)


class Duffing(torchql.ODEModel):
    """``y'' + c y' + k y + d y^3 = 0``: states ``(y, v)``."""

    state_names = ("y", "v")

    def __init__(self, c: float, k: float, d: float):
        super().__init__()
        for name, value in (("c", c), ("k", k), ("d", d)):
            self.register_buffer(name, _scalar(value))

    def forward(self, t, x):
        y, v = x.unbind(-1)
        return torch.stack((v, -self.c * v - self.k * y - self.d * y**3), dim=-1)


class Logistic(torchql.ODEModel):
    """``x' = r x (1 - x / K)``."""

    state_names = ("x",)

    def __init__(self, r: float, K: float):
        super().__init__()
        self.register_buffer("r", _scalar(r))
        self.register_buffer("K", _scalar(K))

    def forward(self, t, x):
        return self.r * x * (1 - x / self.K)


class LotkaVolterra(torchql.ODEModel):
    """``x' = a x - b x y``, ``y' = c x y - d y``."""

    state_names = ("x", "y")

    def __init__(self, a: float, b: float, c: float, d: float):
        super().__init__()
        for name, value in (("a", a), ("b", b), ("c", c), ("d", d)):
            self.register_buffer(name, _scalar(value))

    def forward(self, t, z):
        x, y = z.unbind(-1)
        return torch.stack((self.a * x - self.b * x * y, self.c * x * y - self.d * y), dim=-1)


class MichaelisMenten(torchql.ODEModel):
    """``S' = -V S / (Km + S)``."""

    state_names = ("S",)

    def __init__(self, V: float, Km: float):
        super().__init__()
        self.register_buffer("V", _scalar(V))
        self.register_buffer("Km", _scalar(Km))

    def forward(self, t, x):
        return -self.V * x / (self.Km + x)


# ----------------------------------------------------------------------------------------------
# numpy right-hand sides with their Jacobians in the state (n, n) and the coefficients (n, P)
def _linear_fns(K_fixed: np.ndarray, free: Sequence[tuple[int, int]]):
    E = np.zeros((len(free), *K_fixed.shape))
    K0 = K_fixed.copy()
    for e, (i, j) in enumerate(free):
        E[e, i, j] = 1.0
        K0[i, j] = 0.0

    def K(p):
        return K0 + np.tensordot(p, E, axes=1)

    return (lambda t, x, p: K(p) @ x), (lambda t, x, p: K(p)), (lambda t, x, p: (E @ x).T)


def _osc_f(t, x, p):
    y, v = x
    return np.array([v, -p[0] * v - p[1] * y])


def _osc_fx(t, x, p):
    return np.array([[0.0, 1.0], [-p[1], -p[0]]])


def _osc_fp(t, x, p):
    y, v = x
    return np.array([[0.0, 0.0], [-v, -y]])


def _duffing_f(t, x, p):
    y, v = x
    return np.array([v, -p[0] * v - p[1] * y - p[2] * y**3])


def _duffing_fx(t, x, p):
    y, _ = x
    return np.array([[0.0, 1.0], [-p[1] - 3 * p[2] * y**2, -p[0]]])


def _duffing_fp(t, x, p):
    y, v = x
    return np.array([[0.0, 0.0, 0.0], [-v, -y, -y**3]])


def _logistic_f(t, x, p):
    return p[0] * x * (1 - x / p[1])


def _logistic_fx(t, x, p):
    return np.array([[p[0] * (1 - 2 * x[0] / p[1])]])


def _logistic_fp(t, x, p):
    return np.array([[x[0] * (1 - x[0] / p[1]), p[0] * x[0] ** 2 / p[1] ** 2]])


def _lv_f(t, z, p):
    x, y = z
    a, b, c, d = p
    return np.array([a * x - b * x * y, c * x * y - d * y])


def _lv_fx(t, z, p):
    x, y = z
    a, b, c, d = p
    return np.array([[a - b * y, -b * x], [c * y, c * x - d]])


def _lv_fp(t, z, p):
    x, y = z
    return np.array([[x, -x * y, 0.0, 0.0], [0.0, 0.0, x * y, -y]])


def _mm_f(t, x, p):
    return -p[0] * x / (p[1] + x)


def _mm_fx(t, x, p):
    return np.array([[-p[0] * p[1] / (p[1] + x[0]) ** 2]])


def _mm_fp(t, x, p):
    return np.array([[-x[0] / (p[1] + x[0]), p[0] * x[0] / (p[1] + x[0]) ** 2]])


# ----------------------------------------------------------------------------------------------
@dataclass
class Problem:
    """One drawn problem. Unknowns ``u = (x0 (every state), p)``; ``observed`` indexes the states."""

    family: str
    seed: int
    noise: float
    variant: str
    state_names: tuple[str, ...]
    coef_names: tuple[str, ...]
    truth_x0: np.ndarray
    truth_p: np.ndarray
    guess_x0: np.ndarray
    guess_p: np.ndarray
    observed: list[int]
    t: np.ndarray
    y: np.ndarray  # (T, K)
    scale: np.ndarray  # (K,)
    rhs: Callable = field(repr=False)
    jac_x: Callable = field(repr=False)
    jac_p: Callable = field(repr=False)
    make_model: Callable = field(repr=False)  # p -> torchql.ODEModel
    cond_truth: float = math.nan

    @property
    def truth(self) -> np.ndarray:
        return np.concatenate([self.truth_x0, self.truth_p])

    @property
    def guess(self) -> np.ndarray:
        return np.concatenate([self.guess_x0, self.guess_p])

    @property
    def unknown_names(self) -> list[str]:
        return [f"{s}(t0)" for s in self.state_names] + list(self.coef_names)

    @property
    def floor(self) -> float:
        """Absolute SSE floor: RMS residuals of ``FLOOR_REL`` times the largest column scale."""
        return self.y.size * (FLOOR_REL * float(self.scale.max())) ** 2

    def data(self) -> torchql.Observations:
        return torchql.Observations(torch.tensor(self.t, dtype=DTYPE), torch.tensor(self.y, dtype=DTYPE),
                                    observe=[self.state_names[i] for i in self.observed])

    def trajectory(self, u: np.ndarray, rtol: float = EVAL_RTOL, atol: float = EVAL_ATOL) -> np.ndarray | None:
        """The states ``(T, n)`` at the observation times from unknowns ``u``; None if the solve fails."""
        n = len(self.state_names)
        with np.errstate(all="ignore"):
            sol = solve_ivp(self.rhs, (self.t[0], self.t[-1]), u[:n], method="DOP853", t_eval=self.t,
                            args=(u[n:],), rtol=rtol, atol=atol)
        if not sol.success or sol.y.shape[1] != len(self.t) or not np.isfinite(sol.y).all():
            return None
        return sol.y.T

    def sse(self, u) -> float:
        """SSE at ``u`` with the accurate integrator (NaN if ``u`` or its solve is not finite)."""
        if u is None or not np.isfinite(u).all():
            return math.nan
        x = self.trajectory(np.asarray(u, dtype=float))
        return math.nan if x is None else float(np.sum((self.y - x[:, self.observed]) ** 2))

    def residuals_and_jacobian(self, u, rtol=FIT_RTOL, atol=FIT_ATOL, check: Callable | None = None):
        """Residuals ``y - h(x)`` (time-major) and their Jacobian in ``u`` (forward sensitivities);
        None if the solve fails. ``check`` is called at every right-hand-side evaluation."""
        n, m = len(self.state_names), len(u)
        p = u[n:]

        def f(t, zs):
            if check is not None:
                check()
            x, S = zs[:n], zs[n:].reshape(n, m)
            dS = self.jac_x(t, x, p) @ S
            dS[:, n:] += self.jac_p(t, x, p)
            return np.concatenate([np.atleast_1d(self.rhs(t, x, p)), dS.ravel()])

        z0 = np.concatenate([u[:n], np.eye(n, m).ravel()])
        with np.errstate(all="ignore"):
            sol = solve_ivp(f, (self.t[0], self.t[-1]), z0, method="DOP853", t_eval=self.t, rtol=rtol, atol=atol)
        if not sol.success or sol.y.shape[1] != len(self.t) or not np.isfinite(sol.y).all():
            return None
        x = sol.y[:n].T
        S = sol.y[n:].T.reshape(len(self.t), n, m)
        r = (self.y - x[:, self.observed]).ravel()
        J = (-S[:, self.observed, :]).reshape(-1, m)
        return r, J


def scaled_condition(J: np.ndarray) -> tuple[int, float]:
    """Rank and condition number of ``J`` with its columns scaled to unit norm."""
    norms = np.linalg.norm(J, axis=0)
    if not np.all(norms > 0) or not np.isfinite(J).all():
        return int(np.sum(norms > 0)), math.inf
    s = np.linalg.svd(J / norms, compute_uv=False)
    rank = int(np.sum(s > s[0] * max(J.shape) * np.finfo(float).eps))
    return rank, float(s[0] / s[-1]) if s[-1] > 0 else math.inf


def _log_uniform(rng, low, high, size=None):
    return np.exp(rng.uniform(math.log(low), math.log(high), size))


def _draw(family: str, rng: np.random.Generator) -> dict:
    """One candidate: the model's pieces, truth and times (no data, no guesses)."""
    if family == "linear":
        n = int(rng.integers(2, 5))
        while True:
            Q = rng.standard_normal((n, n))
            if np.linalg.cond(Q) < 10:
                break
        lam = rng.uniform(0.2, 2.0, n)
        K = -(Q @ np.diag(lam) @ np.linalg.inv(Q))
        n_obs = int(rng.integers(1, n))
        observed = sorted(rng.choice(n, n_obs, replace=False).tolist())
        n_free = int(rng.integers(1, n + 1))
        cells = [(i, j) for i in range(n) for j in range(n)]
        free = [cells[c] for c in sorted(rng.choice(len(cells), n_free, replace=False).tolist())]
        x0 = rng.uniform(0.5, 1.5, n) * rng.choice([-1.0, 1.0], n)
        f, fx, fp = _linear_fns(K, free)
        return dict(variant=f"n={n}, observed {[i + 1 for i in observed]}, free {len(free)}",
                    state_names=tuple(f"x{i + 1}" for i in range(n)),
                    coef_names=tuple(f"k{i + 1}{j + 1}" for i, j in free), truth_x0=x0,
                    truth_p=np.array([K[i, j] for i, j in free]), observed=observed, t=np.linspace(0, 10, 51),
                    rhs=f, jac_x=fx, jac_p=fp, make_model=lambda p, K=K, free=free: LinearSystem(K, free, p))
    if family == "oscillator":
        x0 = np.array([rng.uniform(0.5, 1.5) * rng.choice([-1.0, 1.0]), rng.uniform(-1.0, 1.0)])
        c, k = rng.uniform(0.1, 0.6), rng.uniform(1.0, 4.0)
        common = dict(state_names=("y", "v"), truth_x0=x0, observed=[0], t=np.linspace(0, 10, 51))
        if rng.random() < 0.5:
            return dict(variant="linear", coef_names=("A", "B"), truth_p=np.array([c, k]), rhs=_osc_f,
                        jac_x=_osc_fx, jac_p=_osc_fp, make_model=lambda p: LinearOscillator(*p), **common)
        d = rng.uniform(0.5, 2.0)
        return dict(variant="Duffing", coef_names=("c", "k", "d"), truth_p=np.array([c, k, d]), rhs=_duffing_f,
                    jac_x=_duffing_fx, jac_p=_duffing_fp, make_model=lambda p: Duffing(*p), **common)
    if family == "logistic":
        r, K, u = rng.uniform(0.5, 2.0), rng.uniform(1.0, 10.0), rng.uniform(0.02, 0.2)
        t_end = (math.log((1 - u) / u) + 3.0) / r
        return dict(variant="", state_names=("x",), coef_names=("r", "K"), truth_x0=np.array([u * K]),
                    truth_p=np.array([r, K]), observed=[0], t=np.linspace(0, t_end, 31), rhs=_logistic_f,
                    jac_x=_logistic_fx, jac_p=_logistic_fp, make_model=lambda p: Logistic(*p))
    if family == "lotka_volterra":
        a, b, c, d = rng.uniform(0.5, 1.5), rng.uniform(0.2, 1.0), rng.uniform(0.2, 1.0), rng.uniform(0.5, 1.5)
        while True:
            f = _log_uniform(rng, 0.4, 2.5, 2)
            if np.all(np.abs(np.log(f)) > 0.2):
                break
        period = 2 * math.pi / math.sqrt(a * d)
        return dict(variant="", state_names=("x", "y"), coef_names=("a", "b", "c", "d"),
                    truth_x0=np.array([d / c, a / b]) * f, truth_p=np.array([a, b, c, d]), observed=[0, 1],
                    t=np.linspace(0, 2 * period, 61), rhs=_lv_f, jac_x=_lv_fx, jac_p=_lv_fp,
                    make_model=lambda p: LotkaVolterra(*p))
    if family == "michaelis_menten":
        V, Km = rng.uniform(0.5, 2.0), rng.uniform(0.5, 5.0)
        S0 = Km * rng.uniform(1.0, 5.0)
        t_end = (Km * math.log(20.0) + 0.95 * S0) / V
        return dict(variant="", state_names=("S",), coef_names=("V", "Km"), truth_x0=np.array([S0]),
                    truth_p=np.array([V, Km]), observed=[0], t=np.linspace(0, t_end, 31), rhs=_mm_f,
                    jac_x=_mm_fx, jac_p=_mm_fp, make_model=lambda p: MichaelisMenten(*p))
    raise ValueError(f"unknown family {family!r}; expected one of {FAMILIES}")


def make_problem(family: str, seed: int, noise: float) -> Problem:
    """Draw an identifiable problem of ``family`` from ``seed`` with noise ``noise`` (relative sd).

    The truth and the guesses depend on ``(family, seed)`` only: the same seed at another noise level
    is the same problem with other data."""
    rng = np.random.default_rng([seed, FAMILIES.index(family)])
    for _ in range(MAX_DRAWS):
        spec = _draw(family, rng)
        problem = Problem(family=family, seed=seed, noise=noise, guess_x0=np.empty(0), guess_p=np.empty(0),
                          y=np.empty((0, 0)), scale=np.empty(0), **spec)
        x = problem.trajectory(problem.truth, DATA_RTOL, DATA_ATOL)
        if x is None:
            continue
        exact = x[:, problem.observed]
        problem.y = exact
        problem.scale = np.abs(exact).max(axis=0)
        rj = problem.residuals_and_jacobian(problem.truth, DATA_RTOL, DATA_ATOL)
        if rj is None:
            continue
        rank, cond = scaled_condition(rj[1])
        if rank < len(problem.truth) or cond >= MAX_COND:
            continue
        problem.cond_truth = cond
        break
    else:
        raise RuntimeError(f"no identifiable {family} problem in {MAX_DRAWS} draws (seed {seed})")
    # guesses and noise from their own streams: the same at every noise level
    guess_rng = np.random.default_rng([seed, FAMILIES.index(family), 1])
    problem.guess_p = problem.truth_p * _log_uniform(guess_rng, GUESS_LOW, GUESS_HIGH, len(problem.truth_p))
    x0_factors = _log_uniform(guess_rng, GUESS_LOW, GUESS_HIGH, len(problem.truth_x0))
    noise_rng = np.random.default_rng([seed, FAMILIES.index(family), 2])
    problem.y = exact + noise * problem.scale * noise_rng.standard_normal(exact.shape)
    guess_x0 = problem.truth_x0 * x0_factors
    guess_x0[problem.observed] = problem.y[0]
    problem.guess_x0 = guess_x0
    return problem


# ----------------------------------------------------------------------------------------------
class _OverBudget(Exception):
    pass


def run_torchql(problem: Problem, max_time: float | None) -> dict:
    kwargs = {}
    if max_time is not None and "max_time" in inspect.signature(torchql.fit).parameters:
        kwargs["max_time"] = max_time
    model = problem.make_model(problem.guess_p)
    start = time.perf_counter()
    try:
        result = torchql.fit(model, problem.data(), x0=torch.tensor(problem.guess_x0, dtype=DTYPE), **kwargs)
    except Exception as exc:  # noqa: BLE001 -- a crash is a finding, recorded as such
        return dict(status="EXCEPTION", success=False, message=f"{type(exc).__name__}: {exc}", sse=math.nan,
                    iterations=-1, wall=time.perf_counter() - start, estimates=None)
    wall = time.perf_counter() - start
    x0 = result.x0.detach().numpy()
    p = np.array([float(result.params[name]) for name in problem.coef_names])
    return dict(status=result.status.name, success=bool(result.success), message=result.message,
                sse=float(result.sse), iterations=int(result.iterations), wall=wall,
                estimates=np.concatenate([x0, p]))


def run_scipy(problem: Problem, max_time: float | None) -> dict:
    start = time.perf_counter()
    cache: dict = {}
    solves = [0]

    def check():
        if max_time is not None and time.perf_counter() - start > max_time:
            raise _OverBudget

    def solve(u):
        key = u.tobytes()
        if key not in cache:
            cache.clear()
            solves[0] += 1
            rj = problem.residuals_and_jacobian(u, check=check)
            cache[key] = rj if rj is not None else (np.full(problem.y.size, 1e6), np.zeros((problem.y.size, len(u))))
        return cache[key]

    try:
        out = least_squares(lambda u: solve(u)[0], problem.guess, jac=lambda u: solve(u)[1], method="trf")
    except _OverBudget:
        return dict(status="MAX_TIME", success=False, message="time budget", sse=math.nan, nfev=solves[0],
                    wall=time.perf_counter() - start, estimates=None)
    status = {-1: "IMPROPER_INPUT", 0: "MAX_NFEV", 1: "GTOL", 2: "FTOL", 3: "XTOL", 4: "FTOL_XTOL"}[out.status]
    return dict(status=status, success=bool(out.success), message=out.message, sse=float(2 * out.cost),
                nfev=int(out.nfev), wall=time.perf_counter() - start, estimates=out.x.copy())


_WARM_UP: dict[str, float] = {}


def warm_up() -> dict[str, float]:
    """Once per process: fit a small problem with both methods, untimed in the study; their wall times."""
    if not _WARM_UP:
        problem = make_problem("logistic", 0, 0.0)
        _WARM_UP.update(torchql=run_torchql(problem, None)["wall"], scipy=run_scipy(problem, None)["wall"])
    return dict(_WARM_UP)


def run_problem(job: tuple[str, int, float, float | None]) -> dict:
    """Fit one problem with both methods; the record of :func:`study`."""
    torch.set_num_threads(1)
    warm = warm_up()
    family, seed, noise, max_time = job
    problem = make_problem(family, seed, noise)
    tq, sp = run_torchql(problem, max_time), run_scipy(problem, max_time)
    tq["sse_eval"], sp["sse_eval"] = problem.sse(tq["estimates"]), problem.sse(sp["estimates"])
    finite = [s for s in (tq["sse_eval"], sp["sse_eval"]) if math.isfinite(s)]
    best = min(finite) if finite else math.nan
    for r in (tq, sp):
        r["reached"] = bool(math.isfinite(r["sse_eval"]) and r["sse_eval"] <= best * (1 + SSE_RTOL) + problem.floor)
    cond_opt = math.nan
    if sp["estimates"] is not None:
        rj = problem.residuals_and_jacobian(sp["estimates"], EVAL_RTOL, EVAL_ATOL)
        if rj is not None:
            cond_opt = scaled_condition(rj[1])[1]
    wrong = None
    if tq["success"] and not tq["reached"]:
        wrong = "claims convergence above the best SSE"
    elif tq["status"] == "NOT_IDENTIFIABLE" and cond_opt < MAX_COND:
        wrong = f"NOT_IDENTIFIABLE, condition number at scipy's optimum {cond_opt:.3g}"
    sse_truth = problem.sse(problem.truth)
    return dict(family=family, seed=seed, noise=noise, variant=problem.variant, names=problem.unknown_names,
                truth=problem.truth, guess=problem.guess, best=best, floor=problem.floor, sse_truth=sse_truth,
                local=bool(best > 2 * sse_truth + problem.floor),
                cond_truth=problem.cond_truth, cond_opt=cond_opt, torchql=tq, scipy=sp, wrong=wrong, warm_up=warm)


def jobs_for(n: int, seed: int, families: Sequence[str], max_time: float | None) -> list[tuple]:
    """``n`` problems spread evenly: problem ``i`` has family ``i mod F`` and noise ``(i // F) mod 3``;
    its seed ``seed + i``."""
    F = len(families)
    return [(families[i % F], seed + i, NOISES[(i // F) % len(NOISES)], max_time) for i in range(n)]


def study(jobs: Sequence[tuple], workers: int = 1, progress: Callable[[dict], None] | None = None) -> list[dict]:
    records = []
    if workers <= 1:
        for job in jobs:
            records.append(run_problem(job))
            if progress:
                progress(records[-1])
        return records
    with ProcessPoolExecutor(workers) as pool:
        for record in pool.map(run_problem, jobs):
            records.append(record)
            if progress:
                progress(record)
    return records


# ----------------------------------------------------------------------------------------------
def _fmt(values) -> str:
    return "-" if values is None else "[" + ", ".join(f"{v:.6g}" for v in values) + "]"


def _count(records, key, method) -> str:
    groups: dict = {}
    for r in records:
        groups.setdefault(r[key], []).append(r[method]["reached"])
    return ", ".join(f"{k:g}: {sum(v)}/{len(v)}" if isinstance(k, float) else f"{k}: {sum(v)}/{len(v)}"
                     for k, v in groups.items())


def report(records: Sequence[dict], args_line: str) -> str:
    N = len(records)
    tq_wall = np.array([r["torchql"]["wall"] for r in records])
    sp_wall = np.array([r["scipy"]["wall"] for r in records])
    ratios = tq_wall / sp_wall
    worst = int(np.argmax(ratios))
    warm = {method: max(r["warm_up"][method] for r in records) for method in ("torchql", "scipy")}
    local = ", ".join(f"{r['family']} seed {r['seed']} noise {r['noise']:g}" for r in records if r["local"]) or "none"
    lines = [
        "# Random problems: torchql against scipy least_squares",
        "",
        f"`{args_line}`; torchql {torchql.__version__}, torch {torch.__version__}; wall times on this machine "
        "(single-threaded; they depend on the machine and its load).",
        "",
        "## Summary",
        "",
        f"- reaching the best SSE: torchql {sum(r['torchql']['reached'] for r in records)}/{N}, "
        f"scipy {sum(r['scipy']['reached'] for r in records)}/{N}",
        f"- torchql by family: {_count(records, 'family', 'torchql')}",
        f"- scipy by family: {_count(records, 'family', 'scipy')}",
        f"- torchql by noise: {_count(records, 'noise', 'torchql')}",
        f"- scipy by noise: {_count(records, 'noise', 'scipy')}",
        f"- median wall time: torchql {np.median(tq_wall):.3g} s, scipy {np.median(sp_wall):.3g} s, "
        f"ratio of medians {np.median(tq_wall) / np.median(sp_wall):.3g}, median per-problem ratio "
        f"{np.median(ratios):.3g}",
        f"- worst per-problem torchql/scipy time ratio: {ratios[worst]:.3g} ({records[worst]['family']} seed "
        f"{records[worst]['seed']} noise {records[worst]['noise']:g}: {tq_wall[worst]:.3g} s against "
        f"{sp_wall[worst]:.3g} s)",
        f"- warm-up fit of each process, not counted above: torchql {warm['torchql']:.3g} s, scipy "
        f"{warm['scipy']:.3g} s (the first `torch.func` derivative imports `torch._dynamo` once)",
        f"- wrong diagnoses: {sum(r['wrong'] is not None for r in records)}",
        f"- best SSE above twice the truth's plus the floor (both methods in a local optimum): {local}",
        "",
        "## torchql not reaching the best SSE",
        "",
    ]
    missed = [r for r in records if not r["torchql"]["reached"]]
    lines += [f"- {r['family']} ({r['variant'] or '-'}) seed {r['seed']} noise {r['noise']:g}: "
              f"{r['torchql']['status']}, SSE {r['torchql']['sse_eval']:.6g} against best {r['best']:.6g} "
              f"(truth {r['sse_truth']:.6g}; condition number at scipy's optimum {r['cond_opt']:.3g}); "
              f"{r['torchql']['message']!r}" for r in missed] or ["- none"]
    lines += ["", "## Wrong diagnoses", ""]
    lines += [f"- {r['family']} seed {r['seed']} noise {r['noise']:g}: {r['wrong']} ({r['torchql']['status']})"
              for r in records if r["wrong"]] or ["- none"]
    lines += ["", "## scipy not reaching the best SSE", ""]
    lines += [f"- {r['family']} ({r['variant'] or '-'}) seed {r['seed']} noise {r['noise']:g}: "
              f"{r['scipy']['status']}, SSE {r['scipy']['sse_eval']:.6g} against best {r['best']:.6g}"
              for r in records if not r["scipy"]["reached"]] or ["- none"]
    lines += ["", "## Per problem", "",
              "| family | variant | seed | noise | torchql status | torchql SSE | iter | torchql s | scipy status | "
              "scipy SSE | nfev | scipy s | reached (tq/sp) | truth's SSE | cond. at scipy's optimum |",
              "| --- | --- | ---: | ---: | --- | ---: | ---: | ---: | --- | ---: | ---: | ---: | --- | ---: | ---: |"]
    for r in records:
        tq, sp = r["torchql"], r["scipy"]
        lines.append(f"| {r['family']} | {r['variant']} | {r['seed']} | {r['noise']:g} | {tq['status']} | "
                     f"{tq['sse_eval']:.6g} | {tq['iterations']} | {tq['wall']:.3g} | {sp['status']} | "
                     f"{sp['sse_eval']:.6g} | {sp['nfev']} | {sp['wall']:.3g} | "
                     f"{'yes' if tq['reached'] else 'no'}/{'yes' if sp['reached'] else 'no'} | {r['sse_truth']:.6g} | "
                     f"{r['cond_opt']:.3g} |")
    lines += ["", "## Estimates", "", "Unknowns: initial states, then coefficients.", ""]
    for r in records:
        lines.append(f"- {r['family']} seed {r['seed']} noise {r['noise']:g} {r['names']}: truth "
                     f"{_fmt(r['truth'])}, guess {_fmt(r['guess'])}, torchql {_fmt(r['torchql']['estimates'])}, "
                     f"scipy {_fmt(r['scipy']['estimates'])}")
    return "\n".join(lines) + "\n"


def _count(text: str) -> int:
    """A positive whole number of the command line (argparse's error names the option otherwise)."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1; received {value}")
    return value


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=_count, default=45,
                        help="number of problems (default 45 = 5 families x 3 noises x 3)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the first problem (problem i has seed + i)")
    parser.add_argument("--families", nargs="+", choices=FAMILIES, default=list(FAMILIES))
    parser.add_argument("--max-time", type=float, default=None, help="per-fit wall-time budget, s (both methods)")
    parser.add_argument("--workers", type=_count, default=1, help="worker processes (default 1)")
    parser.add_argument("--write", action="store_true", help="write the report to OUT/random_problems.md")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "output")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    jobs = jobs_for(args.n, args.seed, args.families, args.max_time)
    start = time.perf_counter()

    def progress(r):
        tq, sp = r["torchql"], r["scipy"]
        print(f"{r['family']:>16} seed {r['seed']:>3} noise {r['noise']:<6g} torchql {tq['status']:<16} "
              f"{tq['wall']:7.2f} s {'reached' if tq['reached'] else 'MISSED '}  scipy {sp['status']:<9} "
              f"{sp['wall']:7.2f} s {'reached' if sp['reached'] else 'MISSED'}", file=sys.stderr, flush=True)

    records = study(jobs, args.workers, progress)
    argv_line = " ".join(["python experiments/random_problems.py", *(argv if argv is not None else sys.argv[1:])])
    text = report(records, argv_line)
    print(text)
    print(f"total wall time {time.perf_counter() - start:.1f} s", file=sys.stderr)
    if args.write:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "random_problems.md").write_text(text)


if __name__ == "__main__":
    main()
