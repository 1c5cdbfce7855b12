"""`benchmarks/vs_adam.py --quick` runs end to end and writes its table and figure (no timing assertions)."""

import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("matplotlib")

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "vs_adam.py"


@pytest.mark.slow
def test_vs_adam_quick_writes_table_and_figure(tmp_path):
    run = subprocess.run([sys.executable, str(SCRIPT), "--quick", "--out", str(tmp_path)], capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    assert (tmp_path / "vs_adam.png").stat().st_size > 5_000
    table = (tmp_path / "vs_adam.md").read_text()
    row = next(line for line in table.splitlines() if line.startswith("| linear oscillator"))
    cells = [c.strip() for c in row.split("|")[1:-1]]
    assert cells[1].endswith("(CONVERGED)")
    assert float(cells[3]) <= 1e-6  # torchql reaches the target on the exact data
    assert cells[4].startswith("20 ")  # Adam ran its 20 quick steps (its stopping rule is off)
    assert cells[6] == "not reached" and cells[9].startswith(">")  # 20 Adam steps are far from 1e-6
