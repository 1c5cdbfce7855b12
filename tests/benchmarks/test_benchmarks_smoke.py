"""`benchmarks/fit_speed.py --quick`, `benchmarks/batch.py --quick` and a small `benchmarks/batch_families.py` run
end to end and write their tables (no timing assertions); the JAX peer of batch.py recovers exact data (skipped
without jax, diffrax, optimistix)."""

import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np
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


def _has_jax() -> bool:
    return all(importlib.util.find_spec(m) is not None for m in ("jax", "diffrax", "optimistix"))


def _section(table: str, title: str) -> list[str]:
    """The table rows of one family's section of batch.md."""
    body = table.split(f"## {title}")[1].split("\n## ")[0]
    return [line for line in body.splitlines() if line.startswith("| ") and not line.startswith("| method")]


def _cells(row: str) -> list[str]:
    return [c.strip() for c in row.split("|")[1:-1]]


@pytest.mark.slow
def test_batch_quick_writes_table_and_plot(tmp_path):
    pytest.importorskip("matplotlib")
    run = subprocess.run([sys.executable, str(BATCH_SCRIPT), "--quick", "--out", str(tmp_path)], capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    table = (tmp_path / "batch.md").read_text()
    header = next(line for line in table.splitlines() if line.startswith("| method"))
    for column in ("fits / s", "/ scipy loop", "/ torchql loop", "/ JAX", "converged", "max dSSE", "max diff",
                   "peak RSS"):
        assert column in header
    jax = _has_jax()
    assert ("JAX rows skipped" in run.stdout) is not jax
    for title, sizes in (("Coasting cars", ["4", "16"]), ("Linear oscillators", ["8"])):
        rows = _section(table, title)
        labels = [_cells(row)[0] for row in rows]
        assert [_cells(row)[1] for row in rows if _cells(row)[0] == "torchql fit_many"] == sizes
        assert "torchql fit_many, tuned (grid=20)" in labels and "torchql fit_many, tuned (rtol=1e-8)" in labels
        assert "torchql fit_many, grid=1000 (the former fixed default)" in labels
        assert "torchql fit, loop" in labels and "scipy least_squares + solve_ivp DOP853, loop" in labels
        jax_rows = [row for row in rows if _cells(row)[0].startswith("JAX")]
        assert [_cells(row)[1] for row in jax_rows] == (sizes if jax else [])
        for row in rows:  # every dataset converged (JAX: reported successful), every row at the best SSE
            cells = _cells(row)
            if cells[7]:
                done, total = cells[7].split("/")
                assert done == total, row
            assert float(cells[9]) <= 1e-6, row
        loop = _cells(next(row for row in rows if _cells(row)[0] == "torchql fit, loop"))
        assert float(loop[10]) <= 1e-8  # batched estimates are the single fits'
        for row in jax_rows:  # JAX solved the same problem
            assert float(_cells(row)[10]) <= 1e-5, row
    assert table.count("statuses identical: yes") == 2
    # the defaults' standard errors are those of the fine fixed grid to its interpolation accuracy
    notes = [line for line in table.splitlines() if line.startswith("* Standard errors")]
    assert len(notes) == 2
    for line in notes:
        assert float(line.split("defaults ")[1].split(",")[0]) < 1e-5, line
    assert (tmp_path / "batch.png").stat().st_size > 0


def _load_batch():
    """benchmarks/batch.py as a module (registered, as its dataclasses need)."""
    if "batch_benchmark" not in sys.modules:
        spec = importlib.util.spec_from_file_location("batch_benchmark", BATCH_SCRIPT)
        module = importlib.util.module_from_spec(spec)
        sys.modules["batch_benchmark"] = module
        spec.loader.exec_module(module)
    return sys.modules["batch_benchmark"]


@pytest.mark.slow
@pytest.mark.parametrize("family", ["CARS", "OSCILLATORS"])
def test_jax_peer_recovers_exact_data(family):
    """The JAX peer (optimistix LM over diffrax, vmapped) recovers the truth of noise-free datasets."""
    for module in ("jax", "diffrax", "optimistix"):
        pytest.importorskip(module)
    sys.path.insert(0, str(BATCH_SCRIPT.parent))
    try:
        import jax_peer
    finally:
        sys.path.remove(str(BATCH_SCRIPT.parent))
    batch = _load_batch()
    fam = getattr(batch, family)
    data = batch.make_data(fam, 3, seed=2, noise=0.0)
    result = jax_peer.fit_batch(fam.peer(jax_peer), data.t, data.y, data.starts)
    assert result.success.all()
    assert result.estimates.shape == data.truth.shape
    assert np.max(batch.relative_difference(result.estimates, data.truth)) <= 1e-6
    assert result.seconds > 0 and result.compile_seconds > 0


FAMILIES_SCRIPT = SCRIPT.parent / "batch_families.py"


@pytest.mark.slow
def test_batch_families_writes_a_row_per_family_and_size(tmp_path):
    run = subprocess.run([sys.executable, str(FAMILIES_SCRIPT), "--sizes", "3", "--loop", "2", "--families",
                          "logistic", "michaelis_menten", "--out", str(tmp_path)], capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    table = (tmp_path / "batch_families.md").read_text()
    rows = [_cells(line) for line in table.splitlines() if line.startswith("| logistic") or line.startswith("| mich")]
    assert [(r[0], r[1]) for r in rows] == [("logistic", "3"), ("michaelis_menten", "3")]
    for r in rows:
        assert r[7] == "3/3" and r[9] == "yes"  # every batched fit converged, as its single fit
        assert float(r[8]) <= 1e-8  # batched estimates equal the single fits'


@pytest.mark.slow
def test_compare_commits_times_fit_many_of_two_revisions(tmp_path):
    """``--batches``: fit_many on batch.py's two families, the working tree against a revision (here
    HEAD, from git), one row per family with both medians and their ratio."""
    script = SCRIPT.parent / "compare_commits.py"
    run = subprocess.run([sys.executable, str(script), "--base", "HEAD", "--batches", "4", "--repeats", "1", "--out",
                          str(tmp_path)], capture_output=True, text=True, timeout=300, cwd=SCRIPT.parents[1])
    assert run.returncode == 0, run.stderr[-2000:]
    rows = [_cells(line) for line in (tmp_path / "compare_commits.md").read_text().splitlines()
            if line.startswith("| cars") or line.startswith("| oscillators")]
    assert [row[0] for row in rows] == ["cars, B = 4", "oscillators, B = 4"]
    for row in rows:
        base, work, ratio = float(row[1].split()[0]), float(row[3].split()[0]), float(row[5].strip("*"))
        assert base > 0 and work > 0 and ratio == pytest.approx(work / base, rel=0.1)  # medians shown to 1 ms
        assert float(row[6]) < 1e-6  # the same fits, up to the working tree's changes


TRADEOFF_SCRIPT = SCRIPT.parent / "grid_tradeoff.py"


@pytest.mark.slow
def test_grid_tradeoff_quick_writes_one_table_per_family(tmp_path):
    run = subprocess.run([sys.executable, str(TRADEOFF_SCRIPT), "--quick", "--out", str(tmp_path)],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    table = (tmp_path / "grid_tradeoff.md").read_text()
    assert table.count("| setting | time | fits/s | speed-up over defaults |") == 2
    for family in ("Linear oscillators", "Coasting cars"):
        section = table.split(f"## {family}")[1].split("##")[0]
        rows = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[2:-1]]
                for line in section.splitlines() if line.startswith("| ") and "---" not in line and "setting" not in line}
        assert list(rows) == ["defaults", "grid=20", "grid=50", "grid=100", "rtol=1e-8", "grid=1000 (reference)"]
        assert rows["defaults"][2] == "1.00" and rows["grid=1000 (reference)"][3:5] == ["0.0e+00", "0.0e+00"]
        assert all(cells[5] == "8/8" for cells in rows.values())
        assert float(rows["defaults"][3]) < 1e-8 and float(rows["defaults"][4]) < 1e-5  # the defaults are accurate


SENSITIVITIES_SCRIPT = SCRIPT.parent / "final_sensitivities.py"


def test_final_sensitivities_quick_prints_both_cases_and_the_methods_agree():
    run = subprocess.run([sys.executable, str(SENSITIVITIES_SCRIPT), "--quick"], capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    rows = [line for line in run.stdout.splitlines() if line.startswith("| ") and "case" not in line]
    assert len(rows) == 2
    for row in rows:
        assert float(row.split("|")[-2]) < 1e-6  # the two methods' columns, relative to their scale
