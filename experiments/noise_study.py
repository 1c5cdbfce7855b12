"""Monte Carlo study of noise and observation density for the thesis' oscillators.

G. A. Zupp's thesis (1968), chapters IV and V, fits the linear oscillator ``y'' + A y' + B y = 0``
and the nonlinear one ``y'' + A y' + B y + C y'^3 + D y^3 = 0`` to one dataset per setting: the
true response rounded to 6, 4 or 2 significant digits, at 8, 14 or 66 times over 0-6.5 s. From
these single fits it concludes that there is an "optimum" density of observations beyond which
more points of the same accuracy do not improve the estimates.

A single rounded dataset is one draw: its error says little about how the error scales. This
script repeats every setting on many datasets and measures, for every estimate, the bias, the
spread, the RMS error, the mean reported standard error and the empirical coverage of the 95 %
Wald intervals (``FitResult.confidence_intervals``), at 8, 14, 27, 66 and 131 points.

Noise settings (design in ``DESIGN`` below, repeated in the report):

* Gaussian, sd 0.01 and 0.001 (absolute; |y| <= 0.56): independent draws, seeded;
* rounding to 6, 4 and 2 significant digits, two ways:
  - *fixed*: the thesis' own data (truth y0 = 0, y0' = 1), rounded once, one fit per density;
  - *replicated*: rounding is deterministic, so repeated datasets come from repeated
    *experiments*: each replicate starts with its own initial velocity y0' ~ U(0.9, 1.1)
    (the true A, B, C, D unchanged), and its response is rounded. The rounding error stays
    a deterministic function of the signal, as in a real measurement, but differs between
    replicates. The same replicates (the same y0') are used at every density and digit count.

Run (from the repository root)::

    python experiments/noise_study.py            # writes experiments/output/noise_study.{md,png,csv}
    python experiments/noise_study.py --out DIR  # writes DIR/
    python experiments/noise_study.py --quick    # tiny setting (linear model, 2 densities, 3 datasets)

All datasets of one setting (model, noise, density; for rounding, the fixed dataset too) share
the times, the guesses and the fit options, so they are fitted with one ``torchql.fit_many``
call: each dataset runs ``torchql.fit``'s Kantorovich iteration on its own (same estimates,
statuses and standard errors). Single ``torchql.fit`` calls remain where no batch exists or
``fit_many`` cannot serve: the numerical check (one dataset per fit setting) and the
independent-noise theory (it needs ``FitResult.jacobian``, which a batch result does not keep).

Only torchql's public API is used; everything is float64 and single-threaded. Runtime of the
full study: about 70 s on one free CPU core with the batched fits (350 s with one
``torchql.fit`` per dataset; longer on a busy machine); ``--quick``: ~15 s.
"""

from __future__ import annotations

import argparse
import csv
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

import torchql  # noqa: E402
from torchql.models import LinearOscillator, NonlinearOscillator  # noqa: E402

DTYPE = torch.float64
#: Tolerances of the integration that makes the "exact" data (as experiments/thesis.py).
DATA_RTOL, DATA_ATOL = 1e-13, 1e-15
#: Fit settings: a coarser Kantorovich storage grid and, for noisy data, a looser integrator
#: (checked against the defaults at run time, see ``numerical_check``).
FIT_GRID = 200
FIT_RTOL_NOISY = 1e-8
#: 6-digit data need the default tolerance: their estimation errors are ~1e-7.
FIT_RTOL_PRECISE = None
FIT_MAX_STEPS = 400
LEVEL = 0.95

#: All observation times are taken from this grid (0, 0.01, ..., 6.5), so every density is a
#: subset of the same integrated trajectory.
FINE_STEP, FINE_N = 0.01, 651
#: Densities: number of points over 0-6.5 s -> indices into the fine grid.
DENSITIES: dict[int, list[int]] = {
    8: [0, 100, 200, 300, 400, 500, 600, 650],  # t = 0, 1, ..., 6, 6.5 (as experiments/thesis.py)
    14: list(range(0, 651, 50)),  # step 0.5
    27: list(range(0, 651, 25)),  # step 0.25
    66: list(range(0, 651, 10)),  # step 0.1
    131: list(range(0, 651, 5)),  # step 0.05
    651: list(range(0, 651)),  # step 0.01: extension, 2-digit rounding only (see EXTENSION)
}

NAMES = {"linear": ("y0", "y0'", "A", "B"), "nonlinear": ("y0", "y0'", "A", "B", "C", "D")}
TRUTH = {"linear": (0.0, 1.0, 0.1, 3.0), "nonlinear": (0.0, 1.0, 0.1, 3.0, 0.2, 4.0)}
#: Start of every fit: about 10 % from the truth (this study is about noise, not basins).
GUESS = {"linear": (0.05, 0.9, 0.11, 2.7), "nonlinear": (0.05, 0.9, 0.11, 2.7, 0.22, 3.6)}
#: The coefficient shown in the figure and the key table, per model.
KEY = {"linear": "B", "nonlinear": "D"}
#: Replicated rounding: initial velocity of each replicate ~ U(1 - W, 1 + W).
AMPLITUDE_HALF_WIDTH = 0.1

#: Thesis' printed estimates (experiments/thesis.py, Tables 4.1-4.5): (model, digits, points) -> values.
THESIS = {
    ("linear", 6, 14): (0.0, 1.00002, 0.099999, 3.00015),
    ("linear", 4, 14): (0.0, 1.00001, 0.100030, 3.00015),
    ("linear", 2, 14): (-0.001870, 1.00012, 0.102050, 3.00104),
    ("linear", 2, 66): (-0.000550, 0.996580, 0.0985520, 3.00177),
    ("nonlinear", 6, 14): (-0.000001, 1.00002, 0.100027, 3.00015, 0.199912, 4.00063),
    ("nonlinear", 4, 14): (0.000010, 0.999846, 0.100171, 2.99986, 0.199583, 4.00348),
    ("nonlinear", 2, 14): (-0.001527, 1.02469, 0.059754, 2.99733, 0.303364, 4.03972),
    ("nonlinear", 2, 66): (-0.000498, 1.00487, 0.089051, 3.00770, 0.224580, 3.94190),
    ("nonlinear", 6, 8): (0.0, 1.000037, 0.099978, 3.00024, 0.200023, 4.00037),
    ("nonlinear", 2, 8): (-0.000134, 1.09951, -0.070835, 0.667966, 0.667966, 3.23572),
}


@dataclass(frozen=True)
class Noise:
    """One noise setting: ``kind`` 'gauss' (level = sd) or 'round' (level = significant digits)."""

    kind: str
    level: float

    @property
    def label(self) -> str:
        return f"Gaussian sd {self.level:g}" if self.kind == "gauss" else f"rounded {int(self.level)} digits"

    @property
    def rtol(self) -> float | None:
        return FIT_RTOL_PRECISE if (self.kind == "round" and self.level >= 6) else FIT_RTOL_NOISY


NOISES = (Noise("gauss", 0.01), Noise("gauss", 0.001), Noise("round", 6), Noise("round", 4), Noise("round", 2))
#: Beyond the thesis' densities: where would correlated rounding errors show? Near each extremum
#: the signal stays within one 2-digit rounding step for ~0.1 s, so at a 0.01 s step about ten
#: neighbouring points share one rounding error. Only 2-digit data, at 651 points.
EXTENSION = ((NOISES[4], 651),)


@dataclass(frozen=True)
class Config:
    models: tuple[str, ...]
    densities: tuple[int, ...]
    #: Datasets per (model, noise kind).
    n_datasets: dict[tuple[str, str], int]
    #: Extra (noise, points) settings run for every model.
    extension: tuple[tuple[Noise, int], ...] = ()


FULL = Config(("linear", "nonlinear"), (8, 14, 27, 66, 131),
              {("linear", "gauss"): 30, ("linear", "round"): 12,
               ("nonlinear", "gauss"): 8, ("nonlinear", "round"): 6}, EXTENSION)
QUICK = Config(("linear",), (14, 66), {("linear", "gauss"): 3, ("linear", "round"): 3})


# ----------------------------------------------------------------------------------------------
# Data
# ----------------------------------------------------------------------------------------------
def fine_times() -> torch.Tensor:
    return torch.arange(FINE_N, dtype=DTYPE) * FINE_STEP


def oscillator(model: str, coeffs: Sequence[float]) -> torchql.ODEModel:
    return LinearOscillator(*coeffs) if model == "linear" else NonlinearOscillator(*coeffs)


def true_response(model: str, ydot0: float) -> torch.Tensor:
    """y(t) on the fine grid for the true coefficients, y0 = 0 and y0' = ``ydot0``."""
    truth = TRUTH[model]
    x = torchql.simulate(oscillator(model, truth[2:]), torch.tensor([0.0, ydot0], dtype=DTYPE), fine_times(),
                         rtol=DATA_RTOL, atol=DATA_ATOL)
    return x[:, 0]


def round_significant(values: torch.Tensor, digits: int) -> torch.Tensor:
    """Round every element to ``digits`` significant decimal digits (0 stays 0), as thesis.py."""
    return torch.tensor([float(f"{v:.{digits - 1}e}") for v in values.tolist()], dtype=values.dtype)


class Truths:
    """The true responses: y0' = 1 (Gaussian and fixed-rounding data) and the replicates' y0'."""

    def __init__(self, model: str, n_replicates: int) -> None:
        rng = np.random.default_rng(20240 + len(model))
        self.amplitudes = 1.0 + AMPLITUDE_HALF_WIDTH * (2.0 * rng.random(n_replicates) - 1.0)
        self.base = true_response(model, 1.0)
        if model == "linear":  # y is linear in the initial state: scale, no new integration
            self.replicates = [float(a) * self.base for a in self.amplitudes]
        else:
            self.replicates = [true_response(model, float(a)) for a in self.amplitudes]


# ----------------------------------------------------------------------------------------------
# Fits and statistics
# ----------------------------------------------------------------------------------------------
@dataclass
class FitOutcome:
    """One fit: status, errors (estimate - truth), reported standard errors, 95 % coverage.

    ``seconds``: wall time of the fit; for a fit made in a batch, its share of the batch's time.
    """

    status: str
    success: bool
    errors: np.ndarray | None = None
    stderr: np.ndarray | None = None
    covered: np.ndarray | None = None
    seconds: float = 0.0


def outcome(result: torchql.FitResult, truth: Sequence[float],
            seconds: float) -> FitOutcome:
    """The :class:`FitOutcome` of a fit: a ``FitResult``, or one sample of a ``BatchFitResult``."""
    if not result.success:
        return FitOutcome(result.status.name, False, seconds=seconds)
    est = np.array(result.estimates.tolist())
    truth_arr = np.array(truth, dtype=float)
    se = np.array([result.stderr[n] for n in result.unknown_names])
    ci = result.confidence_intervals(LEVEL)
    lo = np.array([ci[n][0] for n in result.unknown_names])
    hi = np.array([ci[n][1] for n in result.unknown_names])
    covered = np.where(np.isfinite(se), (lo <= truth_arr) & (truth_arr <= hi), np.nan)
    return FitOutcome(result.status.name, True, est - truth_arr, se, covered, seconds)


def fit_once(model: str, t: torch.Tensor, y: torch.Tensor, truth: Sequence[float], rtol: float | None,
             grid: int | None = FIT_GRID) -> FitOutcome:
    """One ``torchql.fit`` of the values ``y (T,)`` at times ``t (T,)`` from :data:`GUESS`."""
    guess = GUESS[model]
    start = time.perf_counter()
    try:
        result = torchql.fit(oscillator(model, guess[2:]), torchql.Observations(t, y, observe=["y"]),
                             x0=torch.tensor(guess[:2], dtype=DTYPE), method="kantorovich", grid=grid, rtol=rtol,
                             max_steps=FIT_MAX_STEPS)
    except Exception as exc:  # noqa: BLE001 - counted as a failure, never dropped silently
        return FitOutcome(f"EXCEPTION {type(exc).__name__}", False, seconds=time.perf_counter() - start)
    return outcome(result, truth, time.perf_counter() - start)


def fit_datasets(model: str, t: torch.Tensor, ys: torch.Tensor, truths: Sequence[Sequence[float]],
                 rtol: float | None) -> list[FitOutcome]:
    """The datasets ``ys (B, T)`` of one setting (shared times ``t (T,)``, guesses and options) fitted at once.

    One ``torchql.fit_many`` call: each sample runs ``torchql.fit``'s Kantorovich iteration with
    the options of :func:`fit_once` (grid, rtol, max_steps: all supported by ``fit_many``), so
    each outcome is the one ``fit_once`` gives that dataset (estimates equal to the convergence
    tolerance, same statuses). ``truths``: the true unknowns of each dataset, ``B`` rows.
    """
    guess = GUESS[model]
    B = ys.shape[0]
    start = time.perf_counter()
    try:
        batch = torchql.fit_many(oscillator(model, guess[2:]), torchql.Observations(t, ys.unsqueeze(-1), observe=["y"]),
                                 x0=torch.tensor(guess[:2], dtype=DTYPE), grid=FIT_GRID, rtol=rtol,
                                 max_steps=FIT_MAX_STEPS)
    except Exception as exc:  # noqa: BLE001 - every dataset counted as a failure, never dropped silently
        seconds = (time.perf_counter() - start) / B
        return [FitOutcome(f"EXCEPTION {type(exc).__name__}", False, seconds=seconds) for _ in range(B)]
    seconds = (time.perf_counter() - start) / B
    return [outcome(sample, truth, seconds) for sample, truth in zip(batch, truths)]


@dataclass
class Cell:
    """All fits of one (model, noise, density) setting."""

    model: str
    noise: Noise
    n_points: int
    outcomes: list[FitOutcome] = field(default_factory=list)
    fixed: FitOutcome | None = None  # rounding only: the thesis' own (un-replicated) data
    theory: np.ndarray | None = None  # linearized sd per unknown (see theory_sd)

    @property
    def ok(self) -> list[FitOutcome]:
        return [o for o in self.outcomes if o.success]

    @property
    def n(self) -> int:
        return len(self.outcomes)

    @property
    def failures(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for o in self.outcomes:
            if not o.success:
                out[o.status] = out.get(o.status, 0) + 1
        return out

    def errors(self) -> np.ndarray:
        return np.array([o.errors for o in self.ok]).reshape(len(self.ok), len(NAMES[self.model]))

    def stat(self, name: str) -> dict[str, float]:
        """bias, sd, rms (+ its standard error), mean stderr, coverage (+ binomial se), for one unknown."""
        i = NAMES[self.model].index(name)
        nan = float("nan")
        if not self.ok:
            return dict(bias=nan, sd=nan, rms=nan, rms_se=nan, mean_se=nan, coverage=nan, coverage_se=nan, m=0,
                        theory=nan if self.theory is None else float(self.theory[i]))
        e = self.errors()[:, i]
        m = len(e)
        rms = float(np.sqrt(np.mean(e**2)))
        # delta method: se(mean e^2) = sd(e^2)/sqrt(m), d rms = d(mean e^2) / (2 rms)
        rms_se = float(np.std(e**2, ddof=1) / math.sqrt(m) / (2 * rms)) if m > 1 and rms > 0 else nan
        se = np.array([o.stderr[i] for o in self.ok])
        cov = np.array([o.covered[i] for o in self.ok], dtype=float)
        cov = cov[np.isfinite(cov)]
        return dict(
            bias=float(np.mean(e)), sd=float(np.std(e, ddof=1)) if m > 1 else nan, rms=rms, rms_se=rms_se,
            mean_se=float(np.nanmean(se)) if np.isfinite(se).any() else nan,
            coverage=float(np.mean(cov)) if len(cov) else nan,
            # binomial standard error at the nominal level: how far chance alone moves the coverage
            coverage_se=math.sqrt(LEVEL * (1 - LEVEL) / len(cov)) if len(cov) else nan, m=m,
            theory=nan if self.theory is None else float(self.theory[i]),
        )


def run_cell(model: str, noise: Noise, n_points: int, n_datasets: int, truths: Truths) -> Cell:
    """All fits of one setting, in one :func:`fit_datasets` call (rounding: the fixed dataset last)."""
    idx = DENSITIES[n_points]
    t = fine_times()[idx]
    cell = Cell(model, noise, n_points)
    key_model, key_noise = ("linear", "nonlinear").index(model), NOISES.index(noise)
    if noise.kind == "gauss":
        gen = torch.Generator().manual_seed(1_000_000 * (key_model + 1) + 10_000 * key_noise + n_points)
        exact = truths.base[idx]
        ys = torch.stack([exact + noise.level * torch.randn(len(idx), generator=gen, dtype=DTYPE)
                          for _ in range(n_datasets)])
        cell.outcomes = fit_datasets(model, t, ys, [TRUTH[model]] * n_datasets, noise.rtol)
    else:
        digits = int(noise.level)
        ys, truth_rows = [], []
        for a, response in zip(truths.amplitudes[:n_datasets], truths.replicates):
            truth = list(TRUTH[model])
            truth[1] = float(a)
            ys.append(round_significant(response[idx], digits))
            truth_rows.append(truth)
        ys.append(round_significant(truths.base[idx], digits))  # the thesis' own data, fitted alike
        truth_rows.append(TRUTH[model])
        *cell.outcomes, cell.fixed = fit_datasets(model, t, torch.stack(ys), truth_rows, noise.rtol)
    return cell


def theory_sd(model: str, truths: Truths, n_points: int) -> dict[Noise, np.ndarray]:
    """Linearized sd of every estimate at the truth (y0' = 1), per noise setting, from the Jacobian.

    Gaussian: ``sd * sqrt(diag((J^T J)^-1))``. Rounding to d digits, modelled as independent
    uniform errors of variance ``q_i^2 / 12`` (``q_i`` the rounding step at ``y_i``): the sandwich
    ``G J^T diag(q^2 / 12) J G`` with ``G = (J^T J)^-1`` (least squares is unweighted). This is
    what the estimates' spread would be if rounding acted like independent noise.
    """
    idx = DENSITIES[n_points]
    t, y = fine_times()[idx], truths.base[idx]
    truth = TRUTH[model]
    result = torchql.fit(oscillator(model, truth[2:]), torchql.Observations(t, y, observe=["y"]),
                         x0=torch.tensor(truth[:2], dtype=DTYPE), grid=FIT_GRID)
    J = result.jacobian.numpy()
    G = np.linalg.inv(J.T @ J)
    y_np = y.numpy()
    out = {}
    for noise in NOISES:
        if noise.kind == "gauss":
            out[noise] = noise.level * np.sqrt(np.diag(G))
        else:
            with np.errstate(divide="ignore"):
                q = np.where(y_np != 0, 10.0 ** (np.floor(np.log10(np.abs(y_np))) - int(noise.level) + 1), 0.0)
            out[noise] = np.sqrt(np.diag(G @ (J.T * (q**2 / 12.0)) @ J @ G))
    return out


def numerical_check(model: str, truths: Truths) -> list[str]:
    """The fast fit settings against torchql's defaults, on one noisy dataset and one 6-digit one."""
    idx = DENSITIES[66]
    t = fine_times()[idx]
    gen = torch.Generator().manual_seed(7)
    lines = []
    cases = (("Gaussian sd 0.001", truths.base[idx] + 0.001 * torch.randn(len(idx), generator=gen, dtype=DTYPE),
              FIT_RTOL_NOISY),
             ("rounded 6 digits", round_significant(truths.base[idx], 6), FIT_RTOL_PRECISE))
    for label, y, rtol in cases:
        fast = fit_once(model, t, y, TRUTH[model], rtol)
        default = fit_once(model, t, y, TRUTH[model], None, grid=None)
        if fast.success and default.success:
            diff = np.abs(fast.errors - default.errors)
            rel = float(np.max(diff / np.maximum(np.abs(np.array(TRUTH[model])), 0.1)))
            ratio = float(np.max(diff / np.maximum(np.abs(default.errors), 1e-300)))
            lines.append(f"{model}, 66 points, {label}: grid={FIT_GRID}, rtol={rtol or 'default'} changes the "
                         f"estimates by at most {rel:.1e} relative to their size (to max(|truth|, 0.1)), i.e. "
                         f"by at most {ratio:.1e} times their own estimation error.")
        else:
            lines.append(f"{model}, 66 points, {label}: check fit failed ({fast.status} / {default.status}).")
    return lines


# ----------------------------------------------------------------------------------------------
# Report
# ----------------------------------------------------------------------------------------------
class Report:
    def __init__(self) -> None:
        self.parts: list[str] = []

    def add(self, text: str) -> None:
        self.parts.append(text)

    def table(self, headers: Sequence[str], rows: Sequence[Sequence[str]]) -> None:
        lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
        lines += ["| " + " | ".join(row) + " |" for row in rows]
        self.add("\n".join(lines) + "\n")

    def write(self, path: Path) -> None:
        path.write_text("\n".join(self.parts))


def g(value: float, digits: int = 2) -> str:
    return "—" if value is None or not math.isfinite(value) else f"{value:.{digits}g}"


def e(value: float, digits: int = 1) -> str:
    return "—" if value is None or not math.isfinite(value) else f"{value:.{digits}e}"


def slope(cells: Sequence[Cell], name: str, key: str = "rms") -> tuple[float, float]:
    """Least-squares slope (and its standard error) of log ``key`` ('rms' or 'theory') against log(points)."""
    pts = []
    for c in cells:
        v = c.stat(name)[key]
        if math.isfinite(v) and v > 0:
            pts.append((math.log(c.n_points), math.log(v)))
    if len(pts) < 2:
        return float("nan"), float("nan")
    x, y = np.array(pts).T
    X = np.vstack([x, np.ones_like(x)]).T
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    if len(pts) > 2:
        s2 = float(np.sum((y - X @ coef) ** 2)) / (len(pts) - 2)
        se = math.sqrt(s2 / float(np.sum((x - x.mean()) ** 2)))
    else:
        se = float("nan")
    return float(coef[0]), se


DESIGN = f"""\
**Design.** Truth: y0 = 0, y0' = 1, A = 0.1, B = 3 (linear), and C = 0.2, D = 4 (nonlinear),
integrated with `torchql.simulate` at rtol {DATA_RTOL:g}, atol {DATA_ATOL:g} on t = 0, 0.01, ..., 6.5;
y is observed. Densities over 0-6.5 s: 8 points (t = 0, 1, ..., 6, 6.5, as in `thesis.py`), 14
(step 0.5, the thesis' "low density"), 27 (0.25), 66 (0.1, "high density") and 131 (0.05).
Every fit is the Kantorovich iteration of `torchql.fit(..., method="kantorovich", grid={FIT_GRID},
max_steps={FIT_MAX_STEPS})`, run for all datasets of a setting at once by `torchql.fit_many` (each dataset
on its own iteration, the single fit's estimates and statuses), with
`rtol={FIT_RTOL_NOISY:g}` (default rtol 1e-10 for 6-digit data) and the residual variance estimated
from the data (`sigma=None`, Student-t Wald intervals), started about 10 % from the truth:
(y0, y0', A, B, C, D) = {GUESS['nonlinear']}.

Noise:

* **Gaussian** sd 0.01 and 0.001, absolute (|y| <= 0.56), independent at every point; seeded.
* **Rounded to d significant digits, fixed** ("fixed" columns): the thesis' own data, the y0' = 1
  response rounded once. Rounding is deterministic, so this is one fit per density, one draw.
* **Rounded to d significant digits, replicated**: repeated datasets come from repeated
  *experiments*, as they would for a real instrument that rounds: replicate j starts with its own
  initial velocity y0' = a_j, a_j ~ U({1 - AMPLITUDE_HALF_WIDTH:g}, {1 + AMPLITUDE_HALF_WIDTH:g}), with the same
  A, B, C, D, and its response is rounded. Each rounding error is still a deterministic function of
  the signal (correlated with it), but a 10 % change of amplitude moves every value by many rounding
  steps, so the errors differ between replicates. The same a_j are used at every density and digit
  count (common random numbers), so differences between densities are not blurred by different
  draws. Errors of y0' are measured against each replicate's own a_j. We do not simulate rounding
  as independent uniform noise: whether rounding behaves like such noise is what is tested. That
  model's prediction is the "theory" column instead.

**Theory** ("theory sd"): the linearized sd of each estimate under independent noise, from the
Jacobian J of y(t_k) with respect to the unknowns at the truth (y0' = 1): sd * sqrt(diag((J^T J)^-1))
for Gaussian noise, and for rounding to d digits the sandwich G J^T diag(q_k^2 / 12) J G,
G = (J^T J)^-1, with q_k the rounding step of y(t_k) (uniform quantization noise; least squares is
unweighted). An RMS error that falls below its theory-predicted decrease, i.e. RMS / theory that
grows with density, is the signature of correlated errors and of an approaching plateau.

Statistics over the converged fits of a setting, per unknown, of the error e = estimate - truth:
bias = mean e, sd = sample sd of e, RMS = sqrt(mean e^2) with its delta-method standard error
(sd(e^2) / (2 RMS sqrt(N))), mean se = mean reported standard error, coverage = fraction of 95 %
Wald intervals containing the truth, ± its binomial standard error at the nominal 95 %
(sqrt(0.95 * 0.05 / N)). Fits whose status is not a success are counted under "failed" (with
their status) and left out of the statistics; none are dropped silently.
"""


def points_of(config: Config, noise: Noise) -> list[int]:
    """Densities run for this noise setting: the main ones, then its extension."""
    return list(config.densities) + [n for nz, n in config.extension if nz == noise]


def key_table(report: Report, cells: dict, config: Config, model: str) -> None:
    name = KEY[model]
    i = NAMES[model].index(name)
    rounds = [noise for noise in NOISES if noise.kind == "round"]
    headers = ["points"] + [f"{noise.label} RMS({name}) (theory)" for noise in NOISES]
    headers += [f"{int(noise.level)} digits fixed abs err({name})" for noise in rounds]
    rows = []
    all_points = list(config.densities) + sorted({n for _, n in config.extension})
    for n in all_points:
        row = [str(n)]
        for noise in NOISES:
            c = cells.get((model, noise, n))
            if c is None:
                row.append("—")
                continue
            s = c.stat(name)
            row.append(f"{e(s['rms'])} ± {e(s['rms_se'])} ({e(s['theory'])})")
        for noise in rounds:
            c = cells.get((model, noise, n))
            if c is None:
                row.append("—")
            else:
                row.append(e(abs(c.fixed.errors[i])) if c.fixed.success else f"failed ({c.fixed.status})")
        rows.append(row)
    row = [f"slope of log RMS vs log points, {min(config.densities)}-{max(config.densities)} (theory)"]
    for noise in NOISES:
        cs = [cells[model, noise, n] for n in config.densities]
        b, se = slope(cs, name)
        bt, _ = slope(cs, name, "theory")
        row.append(f"{g(b)} ± {g(se, 1)} ({g(bt)})")
    rows.append(row + [""] * len(rounds))
    report.table(headers, rows)


def coverage_table(report: Report, cells: dict, config: Config, model: str) -> None:
    names = NAMES[model]
    headers = ["noise", "points", "N", "failed"] + [f"cover {n}" for n in names] + ["± (binomial se)"]
    rows = []
    for noise in NOISES:
        for n in points_of(config, noise):
            c = cells[model, noise, n]
            stats = [c.stat(nm) for nm in names]
            fails = ", ".join(f"{k} {v}" for k, v in c.failures.items()) or "0"
            rows.append([noise.label, str(n), str(c.n), fails] + [g(s["coverage"], 3) for s in stats]
                        + [g(stats[0]["coverage_se"], 1)])
    report.table(headers, rows)


def full_table(report: Report, cells: dict, config: Config, model: str) -> None:
    headers = ["noise", "points", "unknown", "N ok", "bias", "sd", "RMS", "theory sd", "RMS / theory", "mean se",
               "RMS / mean se", "coverage"]
    rows = []
    for noise in NOISES:
        for n in points_of(config, noise):
            c = cells[model, noise, n]
            for nm in NAMES[model]:
                s = c.stat(nm)
                rows.append([noise.label, str(n), nm, str(s["m"]), e(s["bias"]), e(s["sd"]), e(s["rms"]),
                             e(s["theory"]), g(s["rms"] / s["theory"]), e(s["mean_se"]), g(s["rms"] / s["mean_se"]),
                             g(s["coverage"], 3)])
    report.table(headers, rows)


def pooled_coverage(cells: dict, model: str, kind: str) -> tuple[float, int, int]:
    """Coverage over every unknown, density and dataset of one model and noise kind."""
    hits = total = fails = 0
    for (m, noise, _), c in cells.items():
        if m != model or noise.kind != kind:
            continue
        fails += sum(c.failures.values())
        for o in c.ok:
            cov = o.covered[np.isfinite(o.covered)]
            hits += int(cov.sum())
            total += len(cov)
    return (hits / total if total else float("nan")), total, fails


def findings(cells: dict, config: Config) -> list[str]:
    """Numbers behind the 'optimum density' question, per model."""
    out = []
    lo, hi = min(config.densities), max(config.densities)
    for model in config.models:
        name = KEY[model]
        parts = []
        for noise in NOISES:
            cs = [cells[model, noise, n] for n in config.densities]
            s_lo, s_hi = cs[0].stat(name), cs[-1].stat(name)
            b, se = slope(cs, name)
            bt, _ = slope(cs, name, "theory")
            ratios = [c.stat(name)["rms"] / c.stat(name)["theory"] for c in cs]
            parts.append(
                f"* {noise.label}: RMS({name}) {e(s_lo['rms'])} at {lo} points -> {e(s_hi['rms'])} at {hi} "
                f"(factor {g(s_hi['rms'] / s_lo['rms'])}; independent-noise theory {e(s_lo['theory'])} -> "
                f"{e(s_hi['theory'])}, factor {g(s_hi['theory'] / s_lo['theory'])}); slope {g(b)} ± {g(se, 1)} "
                f"(theory {g(bt)}); RMS / theory by density: " + ", ".join(g(r) for r in ratios) + ".")
        out.append(f"**{model.capitalize()} model, {name}.**\n\n" + "\n".join(parts))
        i = NAMES[model].index(name)
        fixed = []
        for noise in NOISES:
            if noise.kind == "round":
                fixed.append(f"{int(noise.level)} digits: " + ", ".join(
                    f"{n}: {e(abs(cells[model, noise, n].fixed.errors[i])) if cells[model, noise, n].fixed.success else cells[model, noise, n].fixed.status}"
                    for n in config.densities))
        out.append(f"Single fits to the fixed (thesis) data, |error of {name}| by points: " + "; ".join(fixed) + ".")
        for noise, n in config.extension:
            c, prev = cells[model, noise, n], cells[model, noise, hi]
            s, sp = c.stat(name), prev.stat(name)
            out.append(
                f"Extension, {noise.label} at {n} points (step 0.01 s): RMS({name}) {e(s['rms'])} ± {e(s['rms_se'])} "
                f"against {e(sp['rms'])} at {hi} points (factor {g(s['rms'] / sp['rms'])}; independent-noise theory "
                f"factor {g(s['theory'] / sp['theory'])}); RMS / theory {g(sp['rms'] / sp['theory'])} at {hi} points, "
                f"{g(s['rms'] / s['theory'])} at {n}; fixed data |error| {e(abs(c.fixed.errors[i]))}.")
    return out


def _log_ratio_z(a: dict, b: dict) -> float:
    """(log observed ratio - log theory ratio) of RMS between two cells, in standard errors."""
    se = math.hypot(a["rms_se"] / a["rms"], b["rms_se"] / b["rms"])
    return (math.log(b["rms"] / a["rms"]) - math.log(b["theory"] / a["theory"])) / se if se > 0 else float("nan")


def interpretation(cells: dict, config: Config) -> str:
    """What the numbers say about the thesis' 'optimum density' and about the Wald intervals."""
    lines = []
    hi = max(config.densities)
    lo = 14 if 14 in config.densities else min(config.densities)
    two = next(noise for noise in NOISES if noise.kind == "round" and noise.level == 2)
    # --- does the error keep falling from the thesis' low density to the highest?
    rows = []
    for model in config.models:
        name = KEY[model]
        for noise in NOISES:
            a, b = cells[model, noise, lo].stat(name), cells[model, noise, hi].stat(name)
            rows.append((b["rms"] / a["rms"], b["theory"] / a["theory"], _log_ratio_z(a, b), model, noise))
    falling = [r for r in rows if r[0] < 1]
    finite = [r for r in rows if math.isfinite(r[2])] or rows
    fastest = min(finite, key=lambda r: r[2])
    slowest = max(finite, key=lambda r: r[2])
    ratios = [c.stat(KEY[m])["rms"] / c.stat(KEY[m])["theory"] for (m, noise, n), c in cells.items()
              if noise.kind == "round" and n in config.densities]
    text = (f"**Is there an optimum density?** From {lo} to {hi} points the RMS error of the key coefficient "
            f"(B, D) falls in {len(falling)} of the {len(rows)} model/noise settings, by factors "
            f"{g(min(r[0] for r in rows))} to {g(max(r[0] for r in rows))}; the independent-noise theory predicts "
            f"factors {g(min(r[1] for r in rows))} to {g(max(r[1] for r in rows))} (1/sqrt(n) alone: "
            f"{g(math.sqrt(lo / hi))}). Relative to theory the fastest decrease is {fastest[3]}, "
            f"{fastest[4].label} (factor {g(fastest[0])} against {g(fastest[1])}, {g(abs(fastest[2]))} se "
            f"{'faster' if fastest[2] < 0 else 'slower'}) and "
            f"the slowest {slowest[3]}, {slowest[4].label} (factor {g(slowest[0])} against {g(slowest[1])}, "
            f"{g(abs(slowest[2]))} se {'slower' if slowest[2] > 0 else 'faster'}), in units of the standard error of "
            f"the log ratio; with {len(rows)} "
            "settings, departures of about 2 se either way are expected by chance. Over all rounding settings and "
            f"densities RMS / theory lies between {g(min(ratios))} and {g(max(ratios))}. ")
    if len(falling) == len(rows):
        text += (f"So within {lo}-{hi} points there is no optimum density: every setting keeps "
                 "improving with more points of the same accuracy, at roughly the rate independent noise "
                 "predicts, rounded data included.\n")
    else:
        text += ("Not every setting improves over this range; see the ± columns for whether the departures "
                 "exceed the sampling error.\n")
    lines.append(text)
    # --- the thesis' own single comparisons
    if "linear" in config.models and 66 in config.densities and 14 in config.densities:
        iB = NAMES["linear"].index("B")
        c14, c66 = cells["linear", two, 14], cells["linear", two, 66]
        f14, f66 = abs(c14.fixed.errors[iB]), abs(c66.fixed.errors[iB])
        r14, r66 = c14.stat("B")["rms"], c66.stat("B")["rms"]
        text = ("**The thesis' evidence.** Its linear-model conclusion rests on one fit per density. With its "
                f"2-digit data the error of B is {e(f14)} at 14 points and {e(f66)} at 66 (ours; the thesis printed "
                f"{e(abs(THESIS['linear', 2, 14][3] - 3))} and {e(abs(THESIS['linear', 2, 66][3] - 3))}), while over "
                f"replicated experiments the RMS is {e(r14)} and {e(r66)}: that 14-point dataset's error is "
                f"{g(f14 / r14)} times the typical one, the 66-point dataset's {g(f66 / r66)} times. One fit's error is "
                "a single draw (for a normal error, 95 % of draws lie between 0.03 and 2.2 times the RMS), so two "
                "single fits cannot show whether density helps. "
                + (f"The ensemble shows that it does (RMS factor {g(r66 / r14)}, theory "
                   f"{g(c66.stat('B')['theory'] / c14.stat('B')['theory'])}): the thesis' \"optimum\" comes from "
                   "comparing two single datasets." if r66 < r14 else
                   f"Here the ensemble RMS does not fall either (factor {g(r66 / r14)}) at this number of "
                   "replicates."))
        if "nonlinear" in config.models:
            iD = NAMES["nonlinear"].index("D")
            n14, n66 = cells["nonlinear", two, 14], cells["nonlinear", two, 66]
            text += (f" For the nonlinear model the ensemble agrees with the thesis that 66 points beat 14 (RMS of D "
                     f"{e(n14.stat('D')['rms'])} -> {e(n66.stat('D')['rms'])}; single fixed-data fits "
                     f"{e(abs(n14.fixed.errors[iD]))} -> {e(abs(n66.fixed.errors[iD]))}).")
        lines.append(text + "\n")
    # --- extension: the densest grid
    for noise, n in config.extension:
        parts, zs = [], []
        for model in config.models:
            name = KEY[model]
            c, p = cells[model, noise, n].stat(name), cells[model, noise, hi].stat(name)
            z = _log_ratio_z(p, c)
            zs.append(z)
            parts.append(f"{name} ({model}): RMS {e(p['rms'])} -> {e(c['rms'])}, theory {e(p['theory'])} -> "
                         f"{e(c['theory'])}, RMS / theory {g(p['rms'] / p['theory'])} -> {g(c['rms'] / c['theory'])} "
                         f"({g(z)} se)")
        verdict = ("the RMS falls as the independent-noise theory predicts, within the sampling error: no plateau "
                   "yet" if all(abs(z) < 2.5 for z in zs) else
                   "the RMS falls less than the independent-noise theory predicts by more than its sampling error: "
                   "the correlated rounding errors begin to show, the slowing towards a plateau that the thesis "
                   "describes" if any(z >= 2.5 for z in zs) else
                   "the RMS departs from the independent-noise theory by more than its sampling error")
        lines.append(
            f"**Beyond the thesis' densities.** From {hi} to {n} points (step 0.01 s) with {noise.label}: "
            + "; ".join(parts) + f". Verdict: {verdict}. (Near each extremum the signal stays within one 2-digit "
            "rounding step for about 0.1 s, so at a 0.01 s step some ten neighbouring values share one rounding "
            "error: this is where correlation could first appear.)\n")
    # --- coverage
    cov_parts = []
    for model in config.models:
        for kind, label in (("gauss", "Gaussian"), ("round", "replicated rounding")):
            p, total, fails = pooled_coverage(cells, model, kind)
            se = math.sqrt(LEVEL * (1 - LEVEL) / total) if total else float("nan")
            cov_parts.append(f"{model}, {label}: {g(p, 3)} of {total} intervals (binomial se at 0.95: {g(se, 1)}; "
                             f"{fails} failed fits)")
    lines.append(
        "**Wald intervals.** Pooled over unknowns and densities, the 95 % intervals cover the truth: "
        + "; ".join(cov_parts) + ". (Pooled intervals of one dataset are correlated, so the binomial se is a lower "
        "bound on the pooled value's sampling error.) For rounded data the reported se treats the residuals as "
        "independent with one common variance (SSE / dof), whereas the rounding step is proportional to |y|; "
        "'RMS / mean se' in the full tables shows how well the reported se matches the actual spread.\n")
    return "\n".join(lines)


def plot(cells: dict, config: Config, path: Path) -> None:
    fig, axes = plt.subplots(1, len(config.models), figsize=(max(11.0, 6.6 * len(config.models)), 7.0), squeeze=False)
    colors = dict(zip(NOISES, ("tab:blue", "tab:cyan", "tab:green", "tab:orange", "tab:red")))
    for ax, model in zip(axes[0], config.models):
        name = KEY[model]
        i = NAMES[model].index(name)
        for noise in NOISES:
            pts = points_of(config, noise)
            n_arr = np.array(pts, dtype=float)
            stats = [cells[model, noise, n].stat(name) for n in pts]
            rms = np.array([s["rms"] for s in stats])
            err = np.nan_to_num(np.array([s["rms_se"] for s in stats]))
            style = "-" if noise.kind == "gauss" else "--"
            ax.errorbar(n_arr, rms, yerr=err, fmt="o" + style, color=colors[noise], capsize=3, ms=5,
                        label=f"{noise.label}{' (replicated)' if noise.kind == 'round' else ''}")
            ax.plot(n_arr, [s["theory"] for s in stats], ":", color=colors[noise], lw=1.2)
            if noise.kind == "round":
                fixed = [cells[model, noise, n].fixed for n in pts]
                vals = np.array([abs(f.errors[i]) if f.success else np.nan for f in fixed])
                ax.plot(n_arr, vals, "s", mfc="none", color=colors[noise], ms=8,
                        label=f"{noise.label}, fixed thesis data (one fit each)")
                th = [(n, abs(v[i] - TRUTH[model][i])) for (m, d, n), v in THESIS.items()
                      if m == model and d == noise.level]
                if th:
                    ax.plot([p[0] for p in th], [p[1] for p in th], "*", color=colors[noise], ms=13, mec="k",
                            mew=0.6, label=f"{noise.label}, thesis' printed value")
        ticks = sorted({n for (m, _, n) in cells if m == model})
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xticks(ticks)
        ax.set_xticklabels([str(n) for n in ticks])
        ax.minorticks_off()
        ax.set_xlabel("observation points over 0-6.5 s")
        ax.set_ylabel(f"RMS error of {name}  (markers: |error| of one fit)")
        ax.set_title(f"{model} oscillator, {name} (truth {TRUTH[model][i]:g}); N = "
                     f"{config.n_datasets[model, 'gauss']} per Gaussian, {config.n_datasets[model, 'round']} per "
                     "rounding setting", fontsize=10)
        ax.grid(alpha=0.3)
    handles, labels = axes[0][-1].get_legend_handles_labels()
    order = sorted(range(len(labels)), key=lambda k: ("fixed" in labels[k] or "thesis'" in labels[k],
                                                      "fixed" in labels[k], k))
    fig.legend([handles[k] for k in order], [labels[k] for k in order], loc="lower center", ncol=3, fontsize=7.5,
               frameon=False)
    fig.suptitle("RMS error vs observation density; error bars: ± 1 se of the RMS;\ndotted: independent-noise "
                 "theory (linearized; rounding as uniform noise q²/12)", fontsize=9.5)
    fig.tight_layout(rect=(0, 0.2, 1, 1))
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write_csv(cells: dict, path: Path) -> None:
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["model", "noise", "points", "dataset", "status", "unknown", "error", "stderr", "covered"])
        for (model, noise, n), c in cells.items():
            runs = [("fixed", c.fixed)] if c.fixed is not None else []
            runs += list(enumerate(c.outcomes))
            for k, o in runs:
                for i, nm in enumerate(NAMES[model]):
                    if o.success:
                        w.writerow([model, noise.label, n, k, o.status, nm, repr(float(o.errors[i])),
                                    repr(float(o.stderr[i])), o.covered[i]])
                    else:
                        w.writerow([model, noise.label, n, k, o.status, nm, "", "", ""])


# ----------------------------------------------------------------------------------------------
def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "output")
    parser.add_argument("--quick", action="store_true", help="tiny setting: linear model, 2 densities, 3 datasets")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    config = QUICK if args.quick else FULL
    args.out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()

    def progress(text: str) -> None:
        print(f"[{time.perf_counter() - t_start:6.1f} s] {text}", flush=True)

    cells: dict[tuple[str, Noise, int], Cell] = {}
    checks: list[str] = []
    for model in config.models:
        t0 = time.perf_counter()
        truths = Truths(model, config.n_datasets[model, "round"])
        progress(f"{model}: true responses in {time.perf_counter() - t0:.1f} s")
        if not args.quick:
            checks += numerical_check(model, truths)
            progress(f"{checks[-2]}\n{' ' * 11}{checks[-1]}")
        theory = {n: theory_sd(model, truths, n) for n in sorted(DENSITIES)
                  if n in config.densities or any(n == m for _, m in config.extension)}
        for noise in NOISES:
            for n in points_of(config, noise):
                t0 = time.perf_counter()
                cell = run_cell(model, noise, n, config.n_datasets[model, noise.kind], truths)
                cell.theory = theory[n][noise]
                cells[model, noise, n] = cell
                s = cell.stat(KEY[model])
                fails = sum(cell.failures.values())
                progress(f"{model:9s} {noise.label:19s} {n:4d} points: {cell.n} fits ({fails} failed) in "
                         f"{time.perf_counter() - t0:5.1f} s; RMS({KEY[model]}) {e(s['rms'])} (theory "
                         f"{e(s['theory'])}), coverage {g(s['coverage'], 3)}")

    report = Report()
    report.add("# Noise and observation density: a Monte Carlo study of the thesis' oscillators\n")
    report.add("Written by `experiments/noise_study.py`" + (" (`--quick`: a smoke-test setting, not results)"
                                                           if args.quick else "") + ".\n")
    report.add(DESIGN)
    if checks:
        report.add("**Numerical settings checked** (one dataset each, against the `torchql.fit` defaults grid 1000, "
                   "rtol 1e-10):\n\n" + "\n".join(f"* {c}" for c in checks) + "\n")
    for model in config.models:
        counts = {kind: config.n_datasets[model, kind] for kind in ("gauss", "round")}
        report.add(f"## {model.capitalize()} oscillator\n")
        report.add(f"### RMS error of {KEY[model]} by density\n")
        report.add(f"N = {counts['gauss']} datasets per Gaussian setting and {counts['round']} replicates per "
                   "rounding setting and density. Cells: RMS ± its se over the converged fits (in parentheses: "
                   "the independent-noise theory sd). 'fixed': |error| of the single fit to the thesis' own "
                   "rounded data. Last row: least-squares slope of log RMS against log(points), ± its standard "
                   "error (in parentheses: the theory's slope; 1/sqrt(n) is -0.5).\n")
        key_table(report, cells, config, model)
        report.add(f"### Coverage of the 95 % Wald intervals and failed fits ({model})\n")
        coverage_table(report, cells, config, model)
        report.add(f"### All statistics ({model})\n")
        full_table(report, cells, config, model)

    report.add("## Figure\n")
    report.add("![RMS error vs density](noise_study.png)\n\n*Lines with error bars: RMS error over the datasets "
               "(± 1 se); dotted: independent-noise theory; squares: the single fit to the thesis' own rounded data; "
               "stars: the thesis' printed estimates (Tables 4.1-4.5; its 6- and 4-digit values carry errors of its "
               "own computation, ~1e-4, and its 8-point 2-digit column is not a least-squares fit, see thesis.md).*\n")
    report.add("## Findings\n")
    report.add("\n\n".join(findings(cells, config)) + "\n")
    report.add(interpretation(cells, config))
    elapsed = time.perf_counter() - t_start
    n_fits = sum(c.n + (c.fixed is not None) for c in cells.values())
    report.add(f"\nTotal runtime {elapsed:.0f} s ({n_fits} fits, single thread).\n")
    report.write(args.out / "noise_study.md")
    plot(cells, config, args.out / "noise_study.png")
    write_csv(cells, args.out / "noise_study.csv")
    progress(f"wrote {args.out / 'noise_study.md'}, noise_study.png, noise_study.csv")


if __name__ == "__main__":
    main()
