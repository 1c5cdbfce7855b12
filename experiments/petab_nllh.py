"""The PEtab benchmark problems' likelihood at the published best fit: torchql against the reference.

For Boehm_JProteomeRes2014, Bruno_JExpBot2016 and Fiedler_BMCSystBiol2016 (``../shared/petab``,
written as torchql models in ``experiments/petab/``), the negative log-likelihood at the nominal
parameters is computed three ways:

* ``reference``: ``reference.nllh`` of the problem's JSON (AMICI's benchmark value);
* ``torchql``: trajectories by :func:`torchql.simulate` with the problem's solver (``rodas5p`` for the
  stiff Boehm model, ``dopri5`` otherwise) at ``rtol = 1e-8``, ``atol = 1e-10``;
* ``scipy``: trajectories by :func:`scipy.integrate.solve_ivp` at the same tolerances, ``Radau`` for
  Boehm (with the Jacobian of the same right-hand side by ``torch.func.jacrev``), ``RK45`` (the
  Dormand-Prince pair of ``dopri5``) otherwise. Its right-hand side is the same hand-written torch
  model, called on numpy arrays, so that this column checks the integration and not the formulas.

Wall times are of one likelihood evaluation after a first, warm-up one (2 shared cores; they depend on
the machine and its load). The stiffness column is ``max |eigenvalue of df/dx| * time span`` over the
nominal trajectory (481 points per condition; Jacobians by ``torch.func.jacrev``): the number of steps
an explicit solver's stability would need, within a small factor.

Run (from the repository root; about 10 s)::

    python experiments/petab_nllh.py              # prints the table, writes experiments/output/petab_nllh.md
    python experiments/petab_nllh.py --out DIR    # writes DIR/petab_nllh.md
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch
from scipy.integrate import solve_ivp

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import torchql  # noqa: E402
from experiments.petab import (PROBLEMS, PetabProblem, Simulator, load_problem, negative_log_likelihood,  # noqa: E402
                               nominal_values, setup_condition)

RTOL, ATOL = 1e-8, 1e-10
SCIPY_METHOD = {"rodas5p": "Radau", "dopri5": "RK45"}


def scipy_simulator(method: str, rtol: float, atol: float) -> Simulator:
    """A simulator by ``solve_ivp(method)`` over the torch model's right-hand side (and Jacobian)."""
    def simulate(model, x0, times, t0):
        def f(t, x):
            return model(torch.tensor(t, dtype=torch.float64), torch.from_numpy(x)).numpy()

        def jac(t, x):
            tt = torch.tensor(t, dtype=torch.float64)
            return torch.func.jacrev(lambda y: model(tt, y))(torch.from_numpy(x)).numpy()

        t_eval = times.numpy()
        sol = solve_ivp(f, (t0, float(t_eval[-1])), x0.numpy(), method=method, t_eval=t_eval, rtol=rtol, atol=atol,
                        **({"jac": jac} if method in ("Radau", "BDF", "LSODA") else {}))
        if not sol.success:
            raise RuntimeError(f"solve_ivp ({method}): {sol.message}")
        return torch.from_numpy(sol.y.T.copy())
    return simulate


def stiffness(problem: PetabProblem, points: int = 481) -> tuple[float, str]:
    """``max |eigenvalue| * time span`` over the nominal trajectories of every condition, and where."""
    values, worst, where = nominal_values(problem), 0.0, ""
    for condition in problem.conditions:
        setup = setup_condition(problem, condition, values)
        span = float(setup.times[-1]) - setup.t0
        t = torch.linspace(setup.t0, float(setup.times[-1]), points, dtype=torch.float64)
        x = torchql.simulate(setup.model, setup.x0, t, t0=setup.t0, solver="rodas5p", rtol=RTOL, atol=ATOL)
        jac = torch.func.vmap(torch.func.jacrev(setup.model, argnums=1))(t, x)  # (points, n, n)
        largest = torch.linalg.eigvals(jac).abs().amax(dim=-1)
        k = int(largest.argmax())
        if float(largest[k]) * span > worst:
            worst = float(largest[k]) * span
            where = f"{condition}, t = {float(t[k]):.3g}, max |lambda| = {float(largest[k]):.3g}"
    return worst, where


def _timed(function):
    function()  # warm-up: first calls build torch's kernels and the solvers' caches
    start = time.perf_counter()
    value = function()
    return value, time.perf_counter() - start


def rows() -> list[dict]:
    out = []
    for name, spec in PROBLEMS.items():
        problem = load_problem(spec)
        values = nominal_values(problem)
        mine, mine_s = _timed(lambda: negative_log_likelihood(problem, values))
        method = SCIPY_METHOD[spec.solver]
        theirs, theirs_s = _timed(lambda: negative_log_likelihood(problem, values, scipy_simulator(method, RTOL, ATOL)))
        ratio, where = stiffness(problem)
        out.append(dict(name=name, reference=problem.reference_nllh, torchql=mine, solver=spec.solver, seconds=mine_s,
                        scipy=theirs, scipy_method=method, scipy_seconds=theirs_s, stiffness=ratio, where=where,
                        data=len(problem.measurements), conditions=len(problem.conditions)))
    return out


def report(results: list[dict]) -> str:
    lines = [
        "# PEtab benchmark problems: negative log-likelihood at the published best fit",
        "",
        "`python experiments/petab_nllh.py` (problems from `../shared/petab`, written as torchql models in",
        f"`experiments/petab/`); both integrators at rtol {RTOL:g}, atol {ATOL:g}; wall time of one evaluation after",
        "a warm-up (2 shared cores, machine-dependent).",
        "",
        "| problem | conditions | data | reference NLL | torchql NLL | \\|torchql - ref\\| | solver | wall time "
        "| scipy NLL | \\|scipy - ref\\| | scipy method | scipy wall time | max \\|lambda\\| x span |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        lines.append(f"| {r['name']} | {r['conditions']} | {r['data']} | {r['reference']:.6f} | {r['torchql']:.6f} "
                     f"| {abs(r['torchql'] - r['reference']):.1e} | {r['solver']} | {r['seconds']:.2f} s "
                     f"| {r['scipy']:.6f} | {abs(r['scipy'] - r['reference']):.1e} | {r['scipy_method']} "
                     f"| {r['scipy_seconds']:.2f} s | {r['stiffness']:.2g} |")
    lines += ["", "Largest eigenvalue of the Jacobian along the nominal trajectories:", ""]
    lines += [f"* {r['name']}: {r['where']}" for r in results]
    off = [r["name"] for r in results if not abs(r["torchql"] - r["reference"]) < 1e-3]
    lines += ["", ("Every torchql value is within 1e-3 of the reference" if not off else
                   f"Further than 1e-3 from the reference: {', '.join(off)}")
              + " (the tolerance that `tests/experiments/test_petab.py` asserts)."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "output")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    text = report(rows())
    print(text)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "petab_nllh.md").write_text(text)


if __name__ == "__main__":
    main()
