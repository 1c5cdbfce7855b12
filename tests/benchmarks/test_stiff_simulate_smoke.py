"""`benchmarks/stiff_simulate.py --quick` runs end to end and writes its table (no timing assertions)."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("scipy")

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "benchmarks" / "stiff_simulate.py"


@pytest.mark.slow
def test_stiff_simulate_quick_writes_table(tmp_path):
    # this checkout's package, whichever one the environment has installed
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    run = subprocess.run([sys.executable, str(SCRIPT), "--quick", "--out", str(tmp_path)], capture_output=True,
                         text=True, timeout=300, env=env)
    assert run.returncode == 0, run.stderr[-2000:]
    table = (tmp_path / "stiff_simulate.md").read_text()
    rows = [line for line in table.splitlines() if line.startswith("| Robertson") or line.startswith("| HIRES")]
    assert [row.split("|")[3].strip() for row in rows] == ["torchql rodas5p", "scipy Radau", "scipy BDF"] * 2
    for row in rows[::3]:  # torchql meets its tolerance against the references
        assert float(row.split("|")[8]) < 3, row
    assert "`dopri5`" in table
