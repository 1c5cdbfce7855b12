"""Fit the PEtab benchmark problem Bruno_JExpBot2016 with torchql: from its nominal parameters (the
published best fit), and from starts perturbed by a factor 1.2 up or down (random signs, i.e. +-20 %
on the log scale) in every one of its 13 estimated parameters. Prints and writes
``experiments/output/petab_fit.md``: status, iterations, the negative log-likelihood against the
reference, the largest relative difference of the estimates from the nominal fit's, and the time.

    python experiments/petab_fit.py [--starts 8]

Boehm_JProteomeRes2014 (stiff; its three noise sigmas are estimated) and Fiedler_BMCSystBiol2016
(per-gel scalings of the observables, replicates at equal times, ten noise parameters) are not
fitted here: see the problem-structure issue's notes.
"""

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
torch.set_num_threads(1)

from experiments.petab import PROBLEMS, load_problem, nominal_values  # noqa: E402
from experiments.petab.bruno_fit import fit_bruno  # noqa: E402


def perturbed(problem, values: dict, seed: int) -> dict:
    """``values`` with every estimated parameter multiplied by 1.2 or divided by it (random signs)."""
    g = torch.Generator().manual_seed(seed)
    start = dict(values)
    for name in problem.estimated:
        start[name] = values[name] * (1.2 if float(torch.rand(1, generator=g)) < 0.5 else 1 / 1.2)
    return start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--starts", type=int, default=8, help="perturbed starts (default 8)")
    args = parser.parse_args()
    problem = load_problem(PROBLEMS["Bruno_JExpBot2016"])
    values = nominal_values(problem)
    lines = ["# Bruno_JExpBot2016 fitted by torchql", "",
             f"Reference negative log-likelihood at the nominal parameters: {problem.reference_nllh:.6f}.", "",
             "| start | status | iterations | NLL | NLL - reference | max rel. diff. of estimates | time (s) |",
             "|---|---|---|---|---|---|---|"]
    start = time.perf_counter()
    best = fit_bruno(problem, values)
    elapsed = time.perf_counter() - start
    lines.append(f"| nominal | {best.status.name} | {best.iterations} | {best.nll:.6f} | "
                 f"{best.nll - problem.reference_nllh:+.1e} | 0 | {elapsed:.1f} |")
    print(lines[-1])
    returned = 0
    for seed in range(args.starts):
        start = time.perf_counter()
        result = fit_bruno(problem, perturbed(problem, values, seed))
        elapsed = time.perf_counter() - start
        diff = float(((result.estimates - best.estimates).abs() / best.estimates.abs()).max())
        back = result.success and abs(result.nll - problem.reference_nllh) < 1e-3
        returned += back
        lines.append(f"| +-20 % seed {seed} | {result.status.name} | {result.iterations} | {result.nll:.6f} | "
                     f"{result.nll - problem.reference_nllh:+.1e} | {diff:.1e} | {elapsed:.1f} |")
        print(lines[-1])
    lines += ["", f"{returned} of {args.starts} perturbed starts returned to the reference (|NLL - reference| < 1e-3).",
              "", "Command: `python experiments/petab_fit.py" + (f" --starts {args.starts}`" if args.starts != 8 else "`")]
    out = Path(__file__).resolve().parent / "output" / "petab_fit.md"
    out.write_text("\n".join(lines) + "\n")
    print(lines[-3])
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
