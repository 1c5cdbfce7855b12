"""`benchmarks/shooting_fast_models.py --quick` runs end to end and writes its table (no timing assertions)."""

import pytest

pytest.importorskip("scipy")


@pytest.mark.slow
def test_shooting_fast_models_quick_writes_table(tmp_path, run_script):
    run = run_script("benchmarks/shooting_fast_models.py", "--quick", "--out", str(tmp_path))
    assert run.returncode == 0, run.stderr[-2000:]
    table = (tmp_path / "shooting_fast_models.md").read_text()
    rows = [line.split("|") for line in table.splitlines() if line.startswith("| 30 |")]
    assert [row[2].strip() for row in rows] == ["defaults", 'linear_solver="rodas5p"']
    for row in rows:  # both at scipy's optimum: estimates to 1e-7, the SSE within its integration error (3e-5)
        assert row[3].strip() == "CONVERGED" and float(row[6]) < 1e-7 and abs(float(row[7])) < 3e-5, row
