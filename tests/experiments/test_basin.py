"""`experiments/basin.py --quick` runs end to end and writes its table, figure and CSV."""

import csv
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("matplotlib")
pytest.importorskip("scipy")

SCRIPT = Path(__file__).resolve().parents[2] / "experiments" / "basin.py"
METHODS = ("torchql kantorovich (data)", "torchql kantorovich (integrate)", "torchql shooting",
           "scipy least_squares + solve_ivp", "adjoint + Adam")


@pytest.mark.slow
def test_basin_quick_writes_table_figure_and_csv(tmp_path):
    run = subprocess.run([sys.executable, str(SCRIPT), "--quick", "--out", str(tmp_path)], capture_output=True,
                         text=True, timeout=900)
    assert run.returncode == 0, run.stderr[-2000:]
    assert (tmp_path / "basin.png").stat().st_size > 10_000
    report = (tmp_path / "basin.md").read_text()
    assert "Reaching the global optimum" in report and "Bounds:" in report
    for title in ("## FitzHugh-Nagumo", "## Linear oscillator, 2-digit data"):
        section = report.split(title)[1].split("\n## ")[0]
        rows = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[2:-1]]
                for line in section.splitlines() if line.startswith("| ") and not line.startswith("| method")}
        assert set(rows) == set(METHODS), section
        for method, (starts, reached, fraction, *_rest) in rows.items():
            assert int(starts) == 1 and 0 <= int(reached) <= 1
            assert float(fraction) == int(reached) / int(starts)
        # quick mode checks the outputs only:
        # (whether the one quick start reaches the optimum depends on its 4 s wall budget on a busy machine)

    with (tmp_path / "basin.csv").open() as f:
        records = list(csv.DictReader(f))
    assert len(records) == 2 * 5  # two settings x five methods x one start
    assert {r["setting"] for r in records} == {"fhn", "oscillator"}
    for r in records:
        assert r["reached"] in ("0", "1") and float(r["wall_s"]) >= 0
        assert 0.1 <= float(r["factor_0"]) <= 10
        if r["reached"] == "1":
            assert float(r["sse"]) > 0 and float(r["se_deviation"]) <= 0.1
