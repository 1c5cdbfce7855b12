"""The core's acceptance figures: exact-data recovery, iteration counts and Table 3.2's xi.

Run: ``python experiments/core_figures.py``. Prints, for the thesis oscillators with exact data
(made at rtol 1e-13), each method's status, iteration count, the error of the iterate after 8
updates and of the final estimate (relative, absolute where the truth is 0), and the wall time
(the first fit includes torch.func's one-time warm-up).
"""

import argparse, time, math, torch, torchql
from torchql.models import LinearOscillator, NonlinearOscillator, HarmonicOscillator
argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args()  # (--help; no options)
torch.set_num_threads(1)
DT=torch.float64
def data(model, dt, n):
    t = torch.arange(n, dtype=DT)*dt
    X = torchql.simulate(model, torch.tensor([0.0,1.0],dtype=DT), t, rtol=1e-13, atol=1e-15)
    return torchql.Observations(t, X[:, :1], observe=["y"])
def relerr(est, truth):
    s = torch.where(truth==0, torch.ones_like(truth), truth.abs()); return ((est-truth).abs()/s).max().item()
lin = data(LinearOscillator(), 0.5, 14); non = data(NonlinearOscillator(), 0.1, 66)
LT = torch.tensor([0,1,0.1,3.0],dtype=DT); NT=torch.tensor([0,1,.1,3,.2,4.0],dtype=DT)
for m in torchql.METHODS:
    t1=time.perf_counter(); r = torchql.fit(LinearOscillator(0.5,1.0), lin, x0=torch.tensor([0.5,0.5],dtype=DT), method=m); dt=time.perf_counter()-t1
    h8 = r.history[min(8, r.iterations)]
    e8 = relerr(torch.cat([h8.x0, h8.params["A"].reshape(1), h8.params["B"].reshape(1)]), LT)
    print(f"linear 14 pts {m}: {r.status.name}, iterations {r.iterations}, error after 8 updates {e8:.1e}, final error {relerr(r.estimates, LT):.1e}, {dt:.2f} s")
    t1=time.perf_counter(); r = torchql.fit(NonlinearOscillator(0.5,2.0,0.5,2.0), non, x0=torch.tensor([0.5,0.5],dtype=DT), method=m); dt=time.perf_counter()-t1
    print(f"nonlinear 66 pts {m}: {r.status.name}, iterations {r.iterations}, final error {relerr(r.estimates, NT):.1e}, {dt:.2f} s")
t = torch.tensor([0.0,0.25,0.5],dtype=DT)
r = torchql.fit(HarmonicOscillator(1.0), torchql.Observations(t, torch.cos(math.pi*t), observe=["x"]), x0=torch.tensor([1.0,1.0],dtype=DT), initial_trajectory="data")
print(f"Table 3.2: xi - pi^2 = {r.params['xi'].item()-math.pi**2:.1e} after {r.iterations} iterations")
