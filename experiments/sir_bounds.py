"""SIR (N = 763, beta = 1.66, gamma = 0.44, I0 = 1; 14 daily values of I; S(t0) = N - 1, R(t0) = 0 fixed)
fitted from beta = 3, gamma = 1, I0 = 0.5 with and without ``beta, gamma, I >= 0``, by both methods, on
exact and 3 %-noise data: iterations, estimates and SSE.

    python experiments/sir_bounds.py
"""

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
torch.set_num_threads(1)

from test_bounds import SIR, SIR_POSITIVE, _fit_sir  # noqa: E402

import torchql  # noqa: E402

argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args()  # (--help; no options)
DT = torch.float64
t = torch.arange(14, dtype=DT)
x = torchql.simulate(SIR(), torch.tensor([762.0, 1.0, 0.0], dtype=DT), t, rtol=1e-12, atol=1e-12)
noise = torch.randn(14, 1, generator=torch.Generator().manual_seed(0), dtype=DT)
for kind, y in (("exact", x[:, 1:2]), ("noisy", x[:, 1:2] * (1 + 0.03 * noise))):
    data = torchql.Observations(t, y, observe=["I"])
    for method in ("kantorovich", "shooting"):
        for name, bounds in (("none", None), ("all", SIR_POSITIVE)):
            r = _fit_sir(data, (3.0, 1.0, 0.5), bounds, method)
            est = ", ".join(f"{n} = {v:.10g}" for n, v in zip(r.unknown_names, r.estimates.tolist()))
            print(f"{kind:5s} {method:11s} bounds={name:4s} {r.status.name:10s} {r.iterations:3d} it  {est}  SSE = {r.sse:.10g}")
