"""`benchmarks/stiff_simulate.py --quick` runs end to end and writes its table (no timing assertions)."""

import pytest

pytest.importorskip("scipy")


@pytest.mark.slow
def test_stiff_simulate_quick_writes_table(tmp_path, run_script):
    run = run_script("benchmarks/stiff_simulate.py", "--quick", "--out", str(tmp_path))
    assert run.returncode == 0, run.stderr[-2000:]
    table = (tmp_path / "stiff_simulate.md").read_text()
    rows = [line for line in table.splitlines() if line.startswith("| Robertson") or line.startswith("| HIRES")]
    assert [row.split("|")[3].strip() for row in rows] == ["torchql rodas5p", "scipy Radau", "scipy BDF"] * 2
    for row in rows[::3]:  # torchql meets its tolerance against the references
        assert float(row.split("|")[8]) < 3, row
    assert "`dopri5`" in table
    defaults = [line for line in table.splitlines() if line.startswith("| default |")]
    assert [row.split("|")[2].split(",")[0].strip() for row in defaults] == ["Robertson", "HIRES"]
    for row in defaults:  # simulate's default ("auto") meets its tolerance too
        assert float(row.split("|")[5]) < 3, row
