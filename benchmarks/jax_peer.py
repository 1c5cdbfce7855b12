"""The JAX peer of ``benchmarks/batch.py``: optimistix Levenberg–Marquardt over diffrax, vmapped over a batch.

Each dataset is fitted by ``optimistix.least_squares`` with ``optimistix.LevenbergMarquardt`` (QR
solve of the damped Gauss–Newton step, optimistix' trust-region update of the damping); its
residuals are the model's observed state at the observation times minus the data, integrated by
``diffrax.diffeqsolve`` with ``Dopri5`` (the Dormand–Prince pair of torchql's ``dopri5``) under a
``PIDController(rtol=1e-10, atol=1e-12)`` (torchql's default tolerances), saved at the observation
times (``SaveAt(ts=...)``), differentiated in forward mode (``diffrax.ForwardMode``, the Jacobian
of the residuals by ``jax.jacfwd``, optimistix' default for least squares). The unknowns are the
initial states followed by the coefficients, iterated as multiples of each sample's start
(``p = |start| * u``, ``u`` starting at ±1), so that the damping sees unknowns of one size.

One ``jax.jit(jax.vmap(fit_one))`` fits the whole batch: every sample runs the same compiled
loops, masked, until the last one stops. Float64 (``jax_enable_x64``), on the CPU, XLA on one
thread (``XLA_FLAGS`` gains ``--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1``
unless it already sets the first), as torch is in ``batch.py``'s rows. ``throw=False``: a sample
that fails (step limit, non-finite values) keeps its last iterate and is counted as unsuccessful.

This module is imported only when ``jax``, ``diffrax`` and ``optimistix`` are installed
(``pip install "torchql[bench]"``); it does not import torch or torchql.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

#: XLA's thread settings for the peer (one thread, as torch's rows of ``batch.py``).
XLA_ONE_THREAD = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
os.environ.setdefault("JAX_PLATFORMS", "cpu")
if "xla_cpu_multi_thread_eigen" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + XLA_ONE_THREAD).strip()

import diffrax  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import optimistix as optx  # noqa: E402

jax.config.update("jax_enable_x64", True)

#: Integration tolerances (torchql's defaults) and the most steps of one integration.
ODE_RTOL, ODE_ATOL, ODE_MAX_STEPS = 1e-10, 1e-12, 16384
#: Levenberg–Marquardt's stopping tolerances (on the scaled unknowns and on the residuals) and step limit.
LM_RTOL, LM_ATOL, LM_MAX_STEPS = 1e-8, 1e-8, 200


@dataclass(frozen=True)
class PeerProblem:
    """A model for the peer: ``rhs(t, x (n,), coef (k,)) -> dx/dt (n,)``; unknowns ``(x(t0) (n,), coef (k,))``.

    ``observed`` is the index of the measured state.
    """

    name: str
    rhs: Callable
    n_states: int
    observed: int = 0


def coasting_car(area: float, mass: float, rho: float, g: float) -> PeerProblem:
    """``v' = -(rho A C_D / (2 m)) v^2 - mu g`` (ft/s; ``A`` ft^2, ``m`` slug); unknowns ``(v(t0), C_D, mu)``."""
    def rhs(t, x, coef):
        C_D, mu = coef[0], coef[1]
        return -0.5 * rho * area * C_D / mass * x**2 - mu * g

    return PeerProblem("coasting car", rhs, n_states=1)


def linear_oscillator() -> PeerProblem:
    """``y'' + A y' + B y = 0``, states ``(y, y')``, ``y`` observed; unknowns ``(y(t0), y'(t0), A, B)``."""
    def rhs(t, x, coef):
        A, B = coef[0], coef[1]
        return jnp.stack([x[1], -A * x[1] - B * x[0]])

    return PeerProblem("linear oscillator", rhs, n_states=2)


def observed_path(problem: PeerProblem, ts: jax.Array, p: jax.Array) -> jax.Array:
    """The observed state ``(T,)`` at the times ``ts (T,)`` for the unknowns ``p (n + k,)``, from ``ts[0]``."""
    n = problem.n_states
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(lambda t, x, coef: problem.rhs(t, x, coef)), diffrax.Dopri5(), t0=ts[0], t1=ts[-1],
        dt0=None, y0=p[:n], args=p[n:], saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=diffrax.PIDController(rtol=ODE_RTOL, atol=ODE_ATOL), adjoint=diffrax.ForwardMode(),
        max_steps=ODE_MAX_STEPS, throw=False)
    return sol.ys[:, problem.observed]


def make_fit_one(problem: PeerProblem) -> Callable:
    """``fit_one(ts (T,), data (T,), start (m,)) -> (estimates (m,), success (), steps ())`` for one dataset."""
    solver = optx.LevenbergMarquardt(rtol=LM_RTOL, atol=LM_ATOL)

    def fit_one(ts, data, start):
        scale = jnp.where(start != 0, jnp.abs(start), 1.0)

        def residuals(u, args):
            return observed_path(problem, ts, scale * u) - data

        sol = optx.least_squares(residuals, solver, start / scale, max_steps=LM_MAX_STEPS, throw=False)
        return scale * sol.value, sol.result == optx.RESULTS.successful, sol.stats["num_steps"]

    return fit_one


@dataclass
class PeerResult:
    """The peer's fits of ``B`` datasets: estimates ``(B, m)``, success ``(B,)``, LM steps ``(B,)``.

    ``seconds``: the fastest timed call (inputs to device, fit, results back to numpy);
    ``compile_seconds``: tracing and compiling for these shapes (``jit(...).lower(...).compile()``);
    ``cpu_seconds``: the process' CPU time during that fastest call (``cpu_seconds / seconds``: cores used).
    """

    estimates: np.ndarray
    success: np.ndarray
    steps: np.ndarray
    seconds: float
    compile_seconds: float
    cpu_seconds: float


def compile_batch(problem: PeerProblem, ts: np.ndarray, data: np.ndarray, starts: np.ndarray):
    """``jit(vmap(fit_one))`` compiled for ``ts (T,)``, ``data (B, T)``, ``starts (B, m)``, and its compile seconds."""
    start = time.perf_counter()
    batched = jax.jit(jax.vmap(make_fit_one(problem), in_axes=(None, 0, 0)))
    compiled = batched.lower(jnp.asarray(ts), jnp.asarray(data), jnp.asarray(starts)).compile()
    return compiled, time.perf_counter() - start


def _timed_call(compiled, ts: np.ndarray, data: np.ndarray, starts: np.ndarray) -> tuple:
    """One call of the compiled batch fit: numpy results, wall seconds and process CPU seconds."""
    wall, cpu = time.perf_counter(), time.process_time()
    out = compiled(jnp.asarray(ts), jnp.asarray(data), jnp.asarray(starts))
    jax.block_until_ready(out)
    estimates, success, steps = (np.asarray(a) for a in out)
    return estimates, success, steps, time.perf_counter() - wall, time.process_time() - cpu


def fit_batch(problem: PeerProblem, ts: np.ndarray, data: np.ndarray, starts: np.ndarray,
              repeat: int = 1) -> PeerResult:
    """Fit the datasets ``data (B, T)`` at the shared times ``ts (T,)`` from ``starts (B, m)``.

    Compiles once (untimed in ``seconds``, reported as ``compile_seconds``), then runs the
    compiled batch ``repeat`` times; the fastest run counts.
    """
    ts, data, starts = (np.asarray(a, dtype=np.float64) for a in (ts, data, starts))
    compiled, compile_seconds = compile_batch(problem, ts, data, starts)
    runs = [_timed_call(compiled, ts, data, starts) for _ in range(repeat)]
    estimates, success, steps, seconds, cpu_seconds = min(runs, key=lambda r: r[3])
    return PeerResult(estimates, success.astype(bool), steps, seconds, compile_seconds, cpu_seconds)


def versions() -> str:
    """The peer's versions and thread settings, for a table header."""
    from importlib.metadata import version

    return (f"jax {jax.__version__}, diffrax {version('diffrax')}, optimistix {version('optimistix')} "
            f"(float64, {jax.default_backend()}, XLA_FLAGS=\"{os.environ.get('XLA_FLAGS', '')}\")")


if __name__ == "__main__":
    raise SystemExit("benchmarks/jax_peer.py is the JAX peer that benchmarks/batch.py measures; run "
                     "`python benchmarks/batch.py --help`")
