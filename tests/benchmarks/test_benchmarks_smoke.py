"""`benchmarks/fit_speed.py --quick` runs end to end and writes its table (no timing assertions)."""

import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("scipy")

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "fit_speed.py"


@pytest.mark.slow
def test_fit_speed_quick_writes_table(tmp_path):
    run = subprocess.run([sys.executable, str(SCRIPT), "--quick", "--out", str(tmp_path)], capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    table = (tmp_path / "fit_speed.md").read_text()
    header = next(line for line in table.splitlines() if line.startswith("| problem"))
    for column in ("median time", "/ scipy DOP853", "fit / solve", "RHS evals", "accuracy"):
        assert column in header
    rows = [line for line in table.splitlines() if line.startswith("| linear oscillator")]
    assert [row.split("|")[2].strip() for row in rows] == ["torchql kantorovich", "torchql shooting", "scipy DOP853"]
    for row in rows:  # every fit reached the common accuracy target on the exact data
        cells = [c.strip() for c in row.split("|")[1:-1]]
        assert cells[7] == "yes", row
        assert float(cells[6].split()[1]) <= 1e-6


BATCH_SCRIPT = SCRIPT.parent / "batch.py"


@pytest.mark.slow
def test_batch_quick_writes_table_and_plot(tmp_path):
    pytest.importorskip("matplotlib")
    run = subprocess.run([sys.executable, str(BATCH_SCRIPT), "--quick", "--out", str(tmp_path)], capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    table = (tmp_path / "batch.md").read_text()
    header = next(line for line in table.splitlines() if line.startswith("| method"))
    for column in ("fits / s", "/ scipy loop", "/ torchql loop", "converged", "peak RSS"):
        assert column in header
    rows = [line for line in table.splitlines() if line.startswith("| torchql fit_many |")]
    assert [row.split("|")[2].strip() for row in rows] == ["4", "16"]
    assert any(line.startswith("| torchql fit_many, rtol=1e-08 | 16 |") for line in table.splitlines())
    for row in rows:  # every dataset converged
        cells = [c.strip() for c in row.split("|")[1:-1]]
        done, total = cells[6].split("/")
        assert done == total
    assert "statuses identical: yes" in table
    difference = float(table.split("largest relative difference of the estimates ")[1].split(",")[0])
    assert difference <= 1e-8  # batched estimates are the single fits'
    assert (tmp_path / "batch.png").stat().st_size > 0
