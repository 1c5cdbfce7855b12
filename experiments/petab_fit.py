"""Fit a PEtab benchmark problem with torchql: Bruno_JExpBot2016 (default), Fiedler_BMCSystBiol2016 or
Boehm_JProteomeRes2014, from its nominal parameters (the published best fit), and from starts perturbed
by a factor 1.2 up or down (random signs, i.e. +-20 % on the log scale) in every one of its estimated
parameters (13, 22 and 9).
Prints and writes ``experiments/output/petab_fit.md`` (``--out`` another folder; Bruno with the defaults; otherwise a name with
the problem and options): status, iterations, the negative log-likelihood against the reference, the
largest relative difference of the estimates from the nominal fit's, and the time.

    python experiments/petab_fit.py [--problem Bruno|Fiedler|Boehm] [--starts 8] [--factor 1.2] [--scale lin|log10]

``--factor 3`` starts three times off (up or down) in every parameter; ``--scale log10`` iterates every
unknown on the log scale, as PEtab estimates them, the bounds applying to the logarithm (other
options than the defaults write ``experiments/output/petab_fit_<scale>_x<factor>.md``).

Fiedler's noise is proportional to each gel's scaling, ``sigma = s * sigma_obs``, both unknown: its
fit maximizes the likelihood with a ``sigma(p)`` function (:mod:`torchql.sigma_function`); its default
scale is PEtab's log10. Boehm_JProteomeRes2014 is stiff, and its three noise sigmas are estimated
(``sigma="estimate"``); each of its fits takes minutes.
"""

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
torch.set_num_threads(1)

from experiments.petab import PROBLEMS, load_problem, nominal_values  # noqa: E402
from experiments.petab.boehm_fit import fit_boehm  # noqa: E402
from experiments.petab.bruno_fit import fit_bruno  # noqa: E402
from experiments.petab.fiedler_fit import fit_fiedler  # noqa: E402

#: The fitted problems: PEtab name, fit function and default scale, by short name.
FITS = {"Bruno": ("Bruno_JExpBot2016", fit_bruno, "lin"), "Fiedler": ("Fiedler_BMCSystBiol2016", fit_fiedler, "log10"),
        "Boehm": ("Boehm_JProteomeRes2014", fit_boehm, "lin")}


def perturbed(problem, values: dict, seed: int, factor: float = 1.2) -> dict:
    """``values`` with every estimated parameter multiplied by ``factor`` or divided by it (random signs)."""
    g = torch.Generator().manual_seed(seed)
    start = dict(values)
    for name in problem.estimated:
        start[name] = values[name] * (factor if float(torch.rand(1, generator=g)) < 0.5 else 1 / factor)
    return start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--problem", choices=tuple(FITS), default="Bruno", help="the problem (default Bruno)")
    parser.add_argument("--starts", type=int, default=8, help="perturbed starts (default 8)")
    parser.add_argument("--factor", type=float, default=1.2, help="perturbation factor (default 1.2: +-20 %%)")
    parser.add_argument("--scale", choices=("lin", "log10"), default=None,
                        help="iterate the unknowns on the linear scale or on PEtab's log10 scale (default: lin for "
                             "Bruno, log10 for Fiedler)")
    parser.add_argument("--max-time", type=float, default=None, help="wall-clock budget of each fit, s (default none)")
    parser.add_argument("--max-iter", type=int, default=None, help="iterations of each fit (default torchql's)")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "output",
                        help="folder of the table (default experiments/output)")
    args = parser.parse_args()
    name, fit, default_scale = FITS[args.problem]
    scale = args.scale or default_scale
    options = {k: v for k, v in (("max_time", args.max_time), ("max_iter", args.max_iter)) if v is not None}
    label = f"x{args.factor:g}"
    problem = load_problem(PROBLEMS[name])
    values = nominal_values(problem)
    lines = [f"# {name} fitted by torchql", "",
             f"Reference negative log-likelihood at the nominal parameters: {problem.reference_nllh:.6f}.", "",
             "| start | status | iterations | NLL | NLL - reference | max rel. diff. of estimates | time (s) |",
             "|---|---|---|---|---|---|---|"]
    start = time.perf_counter()
    best = fit(problem, values, scale=scale, **options)
    elapsed = time.perf_counter() - start
    lines.append(f"| nominal | {best.status.name} | {best.iterations} | {best.nll:.6f} | "
                 f"{best.nll - problem.reference_nllh:+.1e} | 0 | {elapsed:.1f} |")
    print(lines[-1], flush=True)
    returned = reached = 0
    for seed in range(args.starts):
        start = time.perf_counter()
        result = fit(problem, perturbed(problem, values, seed, args.factor), scale=scale, **options)
        elapsed = time.perf_counter() - start
        diff = float(((result.estimates - best.estimates).abs() / best.estimates.abs()).max())
        close = abs(result.nll - problem.reference_nllh) < 1e-3
        returned += result.success and close
        reached += close
        lines.append(f"| {label} seed {seed} | {result.status.name} | {result.iterations} | {result.nll:.6f} | "
                     f"{result.nll - problem.reference_nllh:+.1e} | {diff:.1e} | {elapsed:.1f} |")
        print(lines[-1], flush=True)
    flags = "".join(f" --{k} {v}" for k, v, default in (("problem", args.problem, "Bruno"),
                                                           ("starts", args.starts, 8), ("factor", f"{args.factor:g}", "1.2"),
                                                           ("scale", args.scale, None),
                                                           ("max-time", args.max_time, None),
                                                           ("max-iter", args.max_iter, None)) if v != default)
    lines += ["", f"{returned} of {args.starts} perturbed starts returned to the reference (|NLL - reference| < 1e-3) "
              f"and converged; {reached} reached it.", "",
              f"Unknowns iterated on the {scale} scale. Command: `python experiments/petab_fit.py{flags}`"]
    prefix = "petab_fit" if args.problem == "Bruno" else f"petab_fit_{args.problem.lower()}"
    out_name = "petab_fit.md" if not flags else f"{prefix}_{scale}_{label}.md"
    args.out.mkdir(parents=True, exist_ok=True)
    out = args.out / out_name
    out.write_text("\n".join(lines) + "\n")
    print(lines[-3])
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
