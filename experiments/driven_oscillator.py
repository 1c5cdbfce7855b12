"""A driven oscillator y'' + c y' + k y = u(t) with a measured force u: fit c, k and the initial state
from noisy positions, then validate on a second, independent force signal (fit percentage, NRMSE).

The data come from the true system (c = 0.3 1/s, k = 4 1/s^2) driven by a random force held between
samples every 0.25 s (zero-order hold), positions every 0.3 s with noise sigma = 0.02. The user code
is the block between the markers; the rest makes the data and prints.

    python experiments/driven_oscillator.py [--plot]   # --plot writes experiments/output/driven_oscillator.png
"""

import argparse
import time
from pathlib import Path

import torch

import torchql
from torchql.models import DrivenOscillator

PARSER = argparse.ArgumentParser(description=__doc__.splitlines()[0])
PARSER.add_argument("--plot", action="store_true", help="write experiments/output/driven_oscillator.png")
ARGS = PARSER.parse_args()

DT = torch.float64
TRUTH = DrivenOscillator(c=0.3, k=4.0)
X0 = torch.tensor([0.5, 0.0], dtype=DT)


def experiment(seed: int, x0: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """A random held force (times, values) and the noisy positions it causes (times, values)."""
    g = torch.Generator().manual_seed(seed)
    t_u = torch.linspace(0, 12, 49, dtype=DT)
    u = torch.randn(49, generator=g, dtype=DT)
    t = torch.linspace(0, 12, 41, dtype=DT)
    force = torchql.Inputs(t_u, u, names="u", kind="zoh")
    y = torchql.simulate(TRUTH, x0, t, inputs=force, rtol=1e-12, atol=1e-14)[:, :1]
    return t_u, u, t, y + 0.02 * torch.randn(y.shape, generator=g, dtype=DT)


t_u, u, t, y = experiment(1, X0)
t_u2, u2, t2, y2 = experiment(4, X0)
start = time.perf_counter()
# ---- user code: 6 lines ----------------------------------------------------------------------------
force = torchql.Inputs(t_u, u, names="u", kind="zoh")
data = torchql.Observations(t, y, observe=["y"], sigma=0.02, inputs=force)
result = torchql.fit(DrivenOscillator(c=0.5, k=2.0), data, x0=torch.zeros(2, dtype=DT))
validation = torchql.Observations(t2, y2, observe=["y"], inputs=torchql.Inputs(t_u2, u2, names="u", kind="zoh"))
comparison = torchql.compare(result, validation)
print(result.report(iterations=False))
# -----------------------------------------------------------------------------------------------------
elapsed = time.perf_counter() - start
intervals = result.confidence_intervals(0.95)
for name in ("c", "k"):
    low, high = intervals[name]
    truth = float(getattr(TRUTH, name))
    print(f"{name}: estimate {float(result.params[name]):.5f}, 95% interval [{low:.5f}, {high:.5f}], truth {truth} "
          f"({'inside' if low < truth < high else 'OUTSIDE'})")
print(f"validation on a second force signal: fit {float(comparison.fit_percent[0]):.2f}% (NRMSE)")
print(f"fit and compare: {elapsed:.2f} s")
if ARGS.plot:
    import matplotlib

    matplotlib.use("Agg")
    fig, _ = comparison.plot()
    out = Path(__file__).resolve().parent / "output" / "driven_oscillator.png"
    fig.savefig(out, dpi=120, bbox_inches="tight")
    print(f"wrote {out}")
