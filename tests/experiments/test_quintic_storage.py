"""`experiments/quintic_storage.py --quick`: both tables come out, and on every nonlinear problem
and grid the quintic storage's fixed point is closer to the fine grid's than the cubic one's."""

import re
import sys
from pathlib import Path

import pytest

pytest.importorskip("scipy")

SCRIPT_DIR = Path(__file__).resolve().parents[2] / "experiments"


def test_quick_run_reports_closer_fixed_points(capsys, tmp_path):
    sys.path.insert(0, str(SCRIPT_DIR))
    try:
        import quintic_storage
    finally:
        sys.path.remove(str(SCRIPT_DIR))
    quintic_storage.main(["--quick", "--out", str(tmp_path)])
    text = capsys.readouterr().out
    ratios = [float(r) for r in re.findall(r"\((\d+)x\)", text)]
    assert len(ratios) == 3 * 3  # logistic, Lotka-Volterra, Michaelis-Menten at three grids
    assert min(ratios) > 10
    whole = [line for line in text.splitlines() if "CONVERGED" in line]
    assert len(whole) == 5 and all(line.count("CONVERGED") == 2 for line in whole)
    assert not list(tmp_path.iterdir())  # --quick writes nothing
