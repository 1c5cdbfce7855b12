"""Wall time to parameter error 1e-6: torchql against adjoint + Adam, on the thesis' oscillators.

For the linear oscillator (14 exact points, ``t = 0, 0.5, ..., 6.5``) and the nonlinear
oscillator (66 exact points, ``t = 0, 0.1, ..., 6.5``), from the thesis' starts, this measures

* torchql ``fit(method="kantorovich")`` at its defaults: the wall time of the whole fit (median
  over ``--repeats`` after one untimed warm-up), and the parameter error it returns;
* ``torchql.baselines.adjoint_fit`` with Adam at its defaults (learning rate 1e-2 in the
  normalized space, gradients through ``torchdiffeq.odeint_adjoint`` at rtol 1e-7), with its
  own stopping rule switched off (``tol = gtol = 1e-15``) so that it runs its whole step
  budget (``--steps``, default 20,000) or wall-time budget (``--max-time``): after every step,
  the wall time and the parameter error.

The parameter error is the largest relative error of the unknowns ``(y0, v0, A, B[, C, D])``
against the truth (absolute where the truth is below 0.01 in magnitude, i.e. for ``y0 = 0``).
The table gives the step and wall time at which Adam first reaches the target; where it never
does, the smallest error it reached, its error over the last tenth of the run (where it stalls)
and a lower bound on the ratio (Adam's whole run over torchql's fit). ``--backprop`` takes
gradients by backpropagation through ``odeint`` instead (``adjoint=False``): the same
optimizer path to the integration tolerance at a third of the cost per step, for the long
20,000-step runs. Writes ``OUT/vs_adam.md`` and ``OUT/vs_adam.png`` (error against wall time).

Run (from the repository root)::

    python benchmarks/vs_adam.py                              # 20,000 Adam steps per problem (hours)
    python benchmarks/vs_adam.py --max-time 900               # each Adam run stops after 15 minutes
    python benchmarks/vs_adam.py --backprop --problems linear # the 20,000 steps, backpropagation
    python benchmarks/vs_adam.py --quick --out /tmp/bench     # smoke run (seconds)
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import torch

import torchql
from torchql.baselines import adjoint_fit
from torchql.models import LinearOscillator, NonlinearOscillator

DTYPE = torch.float64
TARGET = 1e-6
#: Tolerances that make the "exact" data.
DATA_RTOL, DATA_ATOL = 1e-13, 1e-15


@dataclass
class Problem:
    key: str
    title: str
    truth_model: torchql.ODEModel
    guess_model: torchql.ODEModel
    times: torch.Tensor
    truth: torch.Tensor  # (y0, v0, coefficients...) in torchql's unknown order

    def data(self) -> torchql.Observations:
        X = torchql.simulate(self.truth_model, self.truth[:2], self.times, rtol=DATA_RTOL, atol=DATA_ATOL)
        return torchql.Observations(self.times, X[:, :1], observe=["y"])


def problems() -> dict[str, Problem]:
    return {
        "linear": Problem("linear", "linear oscillator, 14 exact points", LinearOscillator(),
                          LinearOscillator(0.5, 1.0), torch.arange(14, dtype=DTYPE) * 0.5,
                          torch.tensor([0.0, 1.0, 0.1, 3.0], dtype=DTYPE)),
        "nonlinear": Problem("nonlinear", "nonlinear oscillator, 66 exact points", NonlinearOscillator(),
                             NonlinearOscillator(0.5, 2.0, 0.5, 2.0), torch.arange(66, dtype=DTYPE) * 0.1,
                             torch.tensor([0.0, 1.0, 0.1, 3.0, 0.2, 4.0], dtype=DTYPE)),
    }


X0_GUESS = (0.5, 0.5)


def param_error(estimates: torch.Tensor, truth: torch.Tensor) -> float:
    """Largest relative error; absolute where the truth is below 0.01 in magnitude."""
    scale = torch.where(truth.abs() < 0.01, torch.ones_like(truth), truth.abs())
    return float(((estimates - truth).abs() / scale).max())


def time_torchql(problem: Problem, data, repeats: int) -> dict:
    x0 = torch.tensor(X0_GUESS, dtype=DTYPE)
    torchql.fit(problem.guess_model, data, x0=x0)  # warm-up (first-call costs of vmap/jacrev)
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = torchql.fit(problem.guess_model, data, x0=x0)
        times.append(time.perf_counter() - start)
    return dict(status=result.status.name, iterations=result.iterations, wall=statistics.median(times),
                error=param_error(result.estimates, problem.truth))


def run_adam(problem: Problem, data, steps: int, max_time: float | None, adjoint: bool) -> dict:
    trace = []  # (step, seconds since start, parameter error)
    start = time.perf_counter()

    def callback(step, sse, estimates):
        trace.append((step, time.perf_counter() - start, param_error(estimates, problem.truth)))

    result = adjoint_fit(problem.guess_model, data, x0=torch.tensor(X0_GUESS, dtype=DTYPE), optimizer="adam",
                         max_steps=steps, max_time=max_time, tol=1e-15, gtol=1e-15, adjoint=adjoint,
                         callback=callback)
    wall = time.perf_counter() - start
    reached = next(((s, t) for s, t, e in trace if e <= TARGET), None)
    errors = [e for _, _, e in trace]
    tail = errors[-max(1, len(errors) // 10):]
    return dict(status=result.status.name, steps=result.iterations, wall=wall, trace=trace, reached=reached,
                best=min(errors), tail_min=min(tail), tail_max=max(tail), final=errors[-1],
                per_step=wall / max(result.iterations, 1))


def write_report(path: Path, rows, args, total: float) -> None:
    grad = "backpropagation through `odeint`" if args.backprop else "`odeint_adjoint`"
    lines = [
        "# Wall time to parameter error 1e-6: torchql against adjoint + Adam", "",
        f"Generated by `python benchmarks/vs_adam.py {' '.join(args.argv)}`".rstrip() + f" in {total:.0f} s; "
        f"torch {torch.__version__} (1 thread), Python {platform.python_version()}, {platform.machine()}.", "",
        f"torchql: `fit(method=\"kantorovich\")` at its defaults, median of {args.repeats} after a warm-up. "
        f"Adam: `adjoint_fit(optimizer=\"adam\")` at its defaults (lr 1e-2 in the normalized space, "
        f"rtol 1e-7), gradients by {grad}, stopping rule off (`tol = gtol = 1e-15`), at most "
        f"{args.steps} steps" + (f" and {args.max_time:g} s" if args.max_time else "") + " per problem.", "",
        "| problem | torchql iterations | torchql wall (s) | torchql error | Adam steps run | Adam s/step | "
        "Adam reaches 1e-6 at | Adam best error | Adam error, last tenth | wall-time ratio Adam/torchql |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for problem, tq, adam in rows:
        if adam["reached"] is not None:
            step, t = adam["reached"]
            reach, ratio = f"step {step}, {t:.0f} s", f"{t / tq['wall']:.0f}"
        else:
            reach = "not reached"
            ratio = f"> {adam['wall'] / tq['wall']:.0f} (Adam not there after {adam['wall']:.0f} s)"
        lines.append(
            f"| {problem.title} | {tq['iterations']} ({tq['status']}) | {tq['wall']:.2f} | {tq['error']:.1e} | "
            f"{adam['steps']} ({adam['status']}) | {adam['per_step']:.3f} | {reach} | {adam['best']:.1e} | "
            f"{adam['tail_min']:.1e} .. {adam['tail_max']:.1e} | {ratio} |")
    lines += ["", "*Adam error, last tenth*: the smallest and largest parameter error over the last tenth "
              "of its steps, where a stalled run stays.", ""]
    path.write_text("\n".join(lines))
    print("\n".join(lines))


def plot(path: Path, rows) -> None:
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib is not installed: no plot")
        return
    fig, axes = plt.subplots(1, len(rows), figsize=(6 * len(rows), 4.2), squeeze=False)
    for ax, (problem, tq, adam) in zip(axes[0], rows):
        _, t, e = zip(*adam["trace"])
        ax.loglog([max(x, 1e-3) for x in t], e, label="adjoint + Adam")
        ax.loglog([tq["wall"]], [max(tq["error"], 1e-16)], "o", color="C3", label="torchql kantorovich (whole fit)")
        ax.axhline(TARGET, color="gray", ls="--", lw=0.8)
        ax.set(title=problem.title, xlabel="wall time (s)", ylabel="parameter error")
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "output")
    parser.add_argument("--problems", nargs="+", choices=["linear", "nonlinear"], default=["linear", "nonlinear"])
    parser.add_argument("--steps", type=int, default=20000, help="Adam's step budget (default 20000)")
    parser.add_argument("--max-time", type=float, default=None, help="Adam's wall-time budget per problem (s)")
    parser.add_argument("--repeats", type=int, default=3, help="timed torchql fits (median)")
    parser.add_argument("--backprop", action="store_true", help="Adam's gradients by backpropagation, not adjoint")
    parser.add_argument("--quick", action="store_true", help="linear oscillator, 20 Adam steps, 1 repeat")
    args = parser.parse_args(argv)
    args.argv = [] if argv is None else list(argv)
    if argv is None:
        import sys
        args.argv = sys.argv[1:]
    if args.quick:
        args.problems, args.steps, args.repeats = ["linear"], 20, 1
    torch.set_num_threads(1)
    args.out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    rows = []
    catalogue = problems()
    for key in args.problems:
        problem = catalogue[key]
        data = problem.data()
        tq = time_torchql(problem, data, args.repeats)
        print(f"{problem.title}: torchql {tq['wall']:.2f} s, error {tq['error']:.1e}", flush=True)
        adam = run_adam(problem, data, args.steps, args.max_time, adjoint=not args.backprop)
        print(f"{problem.title}: Adam {adam['steps']} steps in {adam['wall']:.0f} s, best error {adam['best']:.1e}",
              flush=True)
        rows.append((problem, tq, adam))
    write_report(args.out / "vs_adam.md", rows, args, time.perf_counter() - start)
    plot(args.out / "vs_adam.png", rows)


if __name__ == "__main__":
    main()
