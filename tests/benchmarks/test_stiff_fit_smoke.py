"""`benchmarks/stiff_fit.py --quick` runs end to end: Robertson from its first start, torchql and
scipy reaching the same optimum (no timing assertions)."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("scipy")

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "benchmarks" / "stiff_fit.py"


@pytest.mark.slow
def test_stiff_fit_quick_fits_robertson_to_scipys_optimum(tmp_path):
    # this checkout's package, whichever one the environment has installed
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    run = subprocess.run([sys.executable, str(SCRIPT), "--quick", "--out", str(tmp_path)], capture_output=True,
                         text=True, timeout=600, env=env)
    assert run.returncode == 0, run.stderr[-2000:]
    # the table is printed after each problem and once more at the end: its distinct rows
    rows = list(dict.fromkeys(line for line in run.stdout.splitlines() if line.startswith("| Robertson")))
    assert len(rows) == 1, run.stdout[-2000:]
    cells = [cell.strip() for cell in rows[0].strip().strip("|").split("|")]
    assert cells[4].startswith("CONVERGED"), rows[0]
    assert cells[6] == "yes" and cells[10] == "yes", rows[0]  # both within 1e-6 of the best SSE
    assert not (tmp_path / "stiff_fit.md").exists()  # a quick run leaves the recorded table alone
