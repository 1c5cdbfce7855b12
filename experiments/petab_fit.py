"""Fit the PEtab benchmark problem Bruno_JExpBot2016 with torchql: from its nominal parameters (the
published best fit), and from starts perturbed by a factor 1.2 up or down (random signs, i.e. +-20 %
on the log scale) in every one of its 13 estimated parameters. Prints and writes
``experiments/output/petab_fit.md``: status, iterations, the negative log-likelihood against the
reference, the largest relative difference of the estimates from the nominal fit's, and the time.

    python experiments/petab_fit.py [--starts 8] [--factor 1.2] [--scale lin|log10]

``--factor 3`` starts three times off (up or down) in every parameter; ``--scale log10`` iterates every
unknown on the log scale, as PEtab estimates them, the bounds applying to the logarithm (other
options than the defaults write ``experiments/output/petab_fit_<scale>_x<factor>.md``).

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


def perturbed(problem, values: dict, seed: int, factor: float = 1.2) -> dict:
    """``values`` with every estimated parameter multiplied by ``factor`` or divided by it (random signs)."""
    g = torch.Generator().manual_seed(seed)
    start = dict(values)
    for name in problem.estimated:
        start[name] = values[name] * (factor if float(torch.rand(1, generator=g)) < 0.5 else 1 / factor)
    return start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--starts", type=int, default=8, help="perturbed starts (default 8)")
    parser.add_argument("--factor", type=float, default=1.2, help="perturbation factor (default 1.2: +-20 %%)")
    parser.add_argument("--scale", choices=("lin", "log10"), default="lin",
                        help="iterate the unknowns on the linear scale (default) or on PEtab's log10 scale")
    parser.add_argument("--max-time", type=float, default=None, help="wall-clock budget of each fit, s (default none)")
    args = parser.parse_args()
    label = f"x{args.factor:g}"
    problem = load_problem(PROBLEMS["Bruno_JExpBot2016"])
    values = nominal_values(problem)
    lines = ["# Bruno_JExpBot2016 fitted by torchql", "",
             f"Reference negative log-likelihood at the nominal parameters: {problem.reference_nllh:.6f}.", "",
             "| start | status | iterations | NLL | NLL - reference | max rel. diff. of estimates | time (s) |",
             "|---|---|---|---|---|---|---|"]
    start = time.perf_counter()
    best = fit_bruno(problem, values, scale=args.scale, max_time=args.max_time)
    elapsed = time.perf_counter() - start
    lines.append(f"| nominal | {best.status.name} | {best.iterations} | {best.nll:.6f} | "
                 f"{best.nll - problem.reference_nllh:+.1e} | 0 | {elapsed:.1f} |")
    print(lines[-1])
    returned = 0
    for seed in range(args.starts):
        start = time.perf_counter()
        result = fit_bruno(problem, perturbed(problem, values, seed, args.factor), scale=args.scale,
                           max_time=args.max_time)
        elapsed = time.perf_counter() - start
        diff = float(((result.estimates - best.estimates).abs() / best.estimates.abs()).max())
        back = result.success and abs(result.nll - problem.reference_nllh) < 1e-3
        returned += back
        lines.append(f"| {label} seed {seed} | {result.status.name} | {result.iterations} | {result.nll:.6f} | "
                     f"{result.nll - problem.reference_nllh:+.1e} | {diff:.1e} | {elapsed:.1f} |")
        print(lines[-1], flush=True)
    flags = "".join(f" --{k} {v}" for k, v, default in (("starts", args.starts, 8), ("factor", f"{args.factor:g}", "1.2"),
                                                           ("scale", args.scale, "lin"),
                                                           ("max-time", args.max_time, None)) if v != default)
    lines += ["", f"{returned} of {args.starts} perturbed starts returned to the reference (|NLL - reference| < 1e-3).",
              "", f"Unknowns iterated on the {args.scale} scale. Command: `python experiments/petab_fit.py{flags}`"]
    name = "petab_fit.md" if not flags else f"petab_fit_{args.scale}_{label}.md"
    out = Path(__file__).resolve().parent / "output" / name
    out.write_text("\n".join(lines) + "\n")
    print(lines[-3])
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
