"""A solution with its sensitivities for a model that is not stiff: DOP853's steps differentiated
(:mod:`torchql.dopri_sensitivity`) against Rodas5P's (:mod:`torchql.solvers.sensitivity`).

The final pass integrates the sensitivities with the solution where the storage grid misses a
change of the model (and for a second Gauss–Newton step on the model). The problem: a lightly
damped oscillator ``y'' + A y' + B y = 0`` with ``A = 0.1``, ``B = 400`` (20 rad/s), unknowns
``y(0), y'(0), A, B`` (columns scaled by their magnitudes, as the engine scales them), at
``fit``'s tolerances (``rtol=1e-10``, ``atol=1e-12``):

* one sample over ``[0, 100]`` (318 periods), 301 nodes;
* 50 samples (``B`` from 400 to 401) over ``[0, 10]`` (32 periods), 301 nodes.

For each: the median wall time of each method (1 thread, interleaved, after an untimed warm-up),
their ratio, and the largest difference of their columns relative to the columns' scale (both are
the derivatives of their own computed solutions, each within the tolerance of the exact one).

    python benchmarks/final_sensitivities.py              # 3 repeats
    python benchmarks/final_sensitivities.py --quick      # smoke run: spans 3 and 1, 1 repeat
    python benchmarks/final_sensitivities.py --fit        # also a whole fit of such an oscillator

``--fit`` times ``torchql.fit`` of one oscillator (``A = 0.01``, ``B = 400``) from 300 noisy
positions (sd 0.005) over ``[0, 100]``, from integrated guesses ``A = 0.012``, ``B = 400.02``: its
final pass takes second Gauss–Newton steps on the model with the sensitivities integrated.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

import torchql
from torchql.dopri import dopri_batch
from torchql.dopri_sensitivity import explicit_sensitivities
from torchql.model import AugmentedSystem
from torchql.models import LinearOscillator
from torchql.solvers.sensitivity import rodas5p_sensitivities

DT = torch.float64
RTOL, ATOL = 1e-10, 1e-12
CASES = (("one oscillator, 318 periods", 1, 100.0), ("50 oscillators, 32 periods", 50, 10.0))


def case(samples: int, span: float):
    """The system, starts ``(S, 4)``, columns ``(S, 4, 4)`` and grid ``(301,)`` of a case."""
    system = AugmentedSystem(LinearOscillator(A=0.1, B=400.0), ["A", "B"], DT, torch.device("cpu"))
    z0 = torch.tensor([[1.0, 0.5, 0.1, 400.0]], dtype=DT).repeat(samples, 1)
    z0[:, 3] += torch.linspace(0, 1, samples, dtype=DT)
    return system, z0, torch.diag_embed(z0.abs()), torch.linspace(0, span, 301, dtype=DT)


def methods(system, z0, columns, grid) -> dict:
    """Each method as a call returning its columns ``(S, G, M, m)``."""
    return {"DOP853 steps": lambda: explicit_sensitivities(system, z0, columns, grid, rtol=RTOL, atol=ATOL)[1],
            "Rodas5P steps": lambda: rodas5p_sensitivities(system, z0, columns, grid, rtol=RTOL, atol=ATOL)[2]}


def whole_fit() -> None:
    """Print the time, status, iterations and estimates of the ``--fit`` case."""
    system, _, _, _ = case(1, 100.0)
    t = torch.linspace(0, 100, 300, dtype=DT)
    truth = torch.tensor([[1.0, 0.0, 0.01, 400.0]], dtype=DT)
    x = dopri_batch(system, truth, t, rtol=1e-12, atol=1e-14, method="dop853")[0][0, :, :1]
    noise = 0.005 * torch.randn(300, 1, generator=torch.Generator().manual_seed(0), dtype=DT)
    data = torchql.Observations(t, x + noise, observe=["y"])
    start = time.perf_counter()
    result = torchql.fit(LinearOscillator(A=0.012, B=400.02), data, torch.tensor([1.0, 0.0], dtype=DT),
                         initial_trajectory="integrate")
    print(f"whole fit: {time.perf_counter() - start:.1f} s, {result.status.name}, {result.iterations} iterations, "
          f"A = {float(result.params['A']):.10g}, B = {float(result.params['B']):.12g}, SSE {result.sse:.6g}")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="spans 3 and 1, 1 repeat (a smoke run)")
    parser.add_argument("--fit", action="store_true", help="also time a whole fit (about 25 s)")
    args = parser.parse_args(argv)
    cases = [(label, samples, span / 33 if args.quick else span) for label, samples, span in CASES]
    repeats = 1 if args.quick else args.repeats
    torch.set_num_threads(1)
    print("| case | DOP853 steps (s) | Rodas5P steps (s) | speed-up | max column difference / scale |")
    print("|---|---|---|---|---|")
    for label, samples, span in cases:
        calls = methods(*case(samples, span))
        columns = {name: call() for name, call in calls.items()}  # warm-up, and the values compared
        times: dict = {name: [] for name in calls}
        for _ in range(repeats):
            for name, call in calls.items():
                start = time.perf_counter()
                call()
                times[name].append(time.perf_counter() - start)
        a, b = (statistics.median(times[name]) for name in calls)
        V, W = columns.values()
        difference = float((V - W).abs().max() / W.abs().max())
        label = f"{label} (span {span:g})" if args.quick else label
        print(f"| {label} | {a:.2f} | {b:.2f} | {b / a:.1f}x | {difference:.1e} |")
    if args.fit:
        whole_fit()


if __name__ == "__main__":
    main()
