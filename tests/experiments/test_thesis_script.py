"""The main job, `experiments/thesis.py`, runs end to end and reproduces the thesis' key results."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("matplotlib")

SCRIPT = Path(__file__).resolve().parents[2] / "experiments" / "thesis.py"


@pytest.mark.slow
def test_thesis_script_writes_every_table_and_figure(tmp_path):
    run = subprocess.run([sys.executable, str(SCRIPT), "--out", str(tmp_path)], capture_output=True, text=True,
                         timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    for name in ("thesis.md", "figure_3_1.png", "figure_4_2.png"):
        assert (tmp_path / name).stat().st_size > 1000
    report = (tmp_path / "thesis.md").read_text()
    for table in ("Table 3.1", "Table 3.2", "Table 4.1", "Table 4.2", "Table 4.3", "Table 4.4", "Table 4.5", "Table 4.6"):
        assert f"## {table}" in report
    xi_error = float(re.search(r"xi - pi\^2 = (\S+)", run.stdout.split("## Summary")[-1]).group(1))
    assert abs(xi_error) < 1e-8
    summary = run.stdout.split("## Summary")[-1]
    for car, cd in (("Sunbeam Alpine", 0.51), ("Porsche 911", 0.27), ("XKE Jaguar", 0.37)):
        ours = float(re.search(re.escape(car) + r" C_D (\S+)", summary).group(1))
        assert abs(ours - cd) <= 0.01
