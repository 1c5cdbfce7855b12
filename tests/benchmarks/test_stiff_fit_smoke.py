"""`benchmarks/stiff_fit.py --quick` runs end to end: Robertson from its first start, torchql and
scipy reaching the same optimum (no timing assertions)."""

import pytest

pytest.importorskip("scipy")


@pytest.mark.slow
def test_stiff_fit_quick_fits_robertson_to_scipys_optimum(tmp_path, run_script):
    run = run_script("benchmarks/stiff_fit.py", "--quick", "--out", str(tmp_path), timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    # the table is printed after each problem and once more at the end: its distinct rows
    rows = list(dict.fromkeys(line for line in run.stdout.splitlines() if line.startswith("| Robertson")))
    assert len(rows) == 1, run.stdout[-2000:]
    cells = [cell.strip() for cell in rows[0].strip().strip("|").split("|")]
    assert cells[4].startswith("CONVERGED"), rows[0]
    assert cells[6] == "yes" and cells[10] == "yes", rows[0]  # both within 1e-6 of the best SSE
    assert not (tmp_path / "stiff_fit.md").exists()  # a quick run leaves the recorded table alone
