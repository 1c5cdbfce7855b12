"""`experiments/noise_study.py --quick` runs end to end and writes its report, figure and CSV."""

import csv
import re
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("matplotlib")

SCRIPT = Path(__file__).resolve().parents[2] / "experiments" / "noise_study.py"
NOISES = ("Gaussian sd 0.01", "Gaussian sd 0.001", "rounded 6 digits", "rounded 4 digits", "rounded 2 digits")


@pytest.mark.slow
def test_noise_study_quick_writes_tables_figure_and_csv(tmp_path):
    run = subprocess.run([sys.executable, str(SCRIPT), "--quick", "--out", str(tmp_path)], capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    for name in ("noise_study.md", "noise_study.png", "noise_study.csv"):
        assert (tmp_path / name).stat().st_size > 1000
    report = (tmp_path / "noise_study.md").read_text()
    assert "## Linear oscillator" in report and "## Findings" in report
    assert "Nonlinear oscillator" not in report  # --quick: linear model only

    # key table: one row per density (quick: 14 and 66 points) plus the slope row; every cell a number
    key = report.split("### RMS error of B by density")[1].split("###")[0]
    rows = [line for line in key.splitlines() if line.startswith("| ") and not line.startswith("| points")]
    labels = [row.split("|")[1].strip() for row in rows]
    assert labels[:2] == ["14", "66"] and len(labels) == 3 and labels[2].startswith("slope of log RMS")
    for row in rows[:2]:
        cells = [c.strip() for c in row.split("|")[2:-1]]
        assert len(cells) == 8
        # "RMS ± se (theory)" for the five noise settings, then the three fixed-data errors
        parsed = [re.fullmatch(r"(\S+) ± (\S+) \((\S+)\)", c) for c in cells[:5]]
        assert all(parsed), cells
        rms = [float(m.group(1)) for m in parsed]
        theory = [float(m.group(3)) for m in parsed]
        assert all(0 < v < 0.1 for v in rms + theory)
        assert rms[4] > rms[3] > rms[2]  # 2-digit data worse than 4-digit worse than 6-digit
        assert theory[0] > theory[1] and theory[4] > theory[3] > theory[2]
        assert all(0 <= float(c) < 0.1 for c in cells[5:])

    # coverage table: every noise setting at both densities, 3 datasets each, failures counted
    cover = report.split("### Coverage of the 95 % Wald intervals")[1].split("###")[0]
    rows = [[c.strip() for c in line.split("|")[1:-1]] for line in cover.splitlines()
            if line.startswith("| ") and not line.startswith("| noise")]
    assert [(r[0], r[1]) for r in rows] == [(noise, n) for noise in NOISES for n in ("14", "66")]
    assert all(r[2] == "3" for r in rows)
    assert all(re.fullmatch(r"0|(\w+ \d+(, )?)+", r[3]) for r in rows)

    # CSV: 5 noises x 2 densities x 3 datasets (+ one fixed dataset per rounding) x 4 unknowns
    with (tmp_path / "noise_study.csv").open() as f:
        records = list(csv.DictReader(f))
    assert len(records) == (5 * 2 * 3 + 3 * 2) * 4
    assert {r["unknown"] for r in records} == {"y0", "y0'", "A", "B"}
