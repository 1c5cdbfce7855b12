"""`experiments/vs_gradient.py --quick` runs end to end and writes its table and figure."""

import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("matplotlib")
pytest.importorskip("scipy")

SCRIPT = Path(__file__).resolve().parents[2] / "experiments" / "vs_gradient.py"
METHODS = ("torchql kantorovich", "torchql shooting", "adjoint + Adam", "adjoint + L-BFGS", "scipy LM + solve_ivp")


@pytest.mark.slow
def test_vs_gradient_quick_writes_table_and_figure(tmp_path):
    run = subprocess.run([sys.executable, str(SCRIPT), "--quick", "--out", str(tmp_path)], capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    assert (tmp_path / "vs_gradient.png").stat().st_size > 10_000
    report = (tmp_path / "vs_gradient.md").read_text()
    assert "## linear oscillator, 6-digit data" in report and "## Findings" in report
    assert "Budgets of the gradient runs" in report
    rows = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[2:-1]]
            for line in report.splitlines() if line.startswith("| ") and not line.startswith("| method")}
    for method in METHODS:
        assert method in rows, report
    # columns: status, iterations, RHS evals, wall time, error, SSE
    for method in ("torchql kantorovich", "torchql shooting", "scipy LM + solve_ivp"):
        status, _, nfev, _, error, sse = rows[method]
        assert status.startswith("CONVERGED") and float(error) < 1e-5 and float(sse) < 1e-10 and int(nfev) > 0
    # the gradient runs stop on their tiny budgets and say so
    for method in ("adjoint + Adam", "adjoint + L-BFGS"):
        assert rows[method][0] in ("MAX_ITER", "CONVERGED")
        assert int(rows[method][2]) > 0
