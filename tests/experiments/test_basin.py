"""`experiments/basin.py --quick` runs end to end and writes its table, figure and CSV; its
supervisor kills a fit past its hard wall-time limit, survives a crashed worker and leaves no process."""

import csv
import importlib
import math
import multiprocessing
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("matplotlib")
pytest.importorskip("scipy")

SCRIPT = Path(__file__).resolve().parents[2] / "experiments" / "basin.py"
#: Hard limit of the supervisor tests' jobs, and how late past it the kill may come on a busy machine.
LIMIT_S, KILL_SLACK_S = 1.0, 3.0
#: A job that would run this long, were it not killed.
LONG_S = 60.0
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


@pytest.fixture(scope="module")
def modules():
    """``basin`` and the test jobs, imported by name: the spawned workers import them the same way
    (they inherit ``sys.path``)."""
    paths = [str(SCRIPT.parent), str(Path(__file__).resolve().parent)]
    sys.path[:0] = paths
    try:
        yield importlib.import_module("basin"), importlib.import_module("supervised_jobs")
    finally:
        for path in paths:
            sys.path.remove(path)


def _run(modules, jobs, workers):
    """``run_supervised`` on the test jobs with limit ``LIMIT_S``: ``{job: result}`` and the wall time."""
    basin, test_jobs = modules
    results = {}
    start = time.perf_counter()
    basin.run_supervised(jobs, test_jobs.job, workers, lambda job: LIMIT_S,
                         lambda job, result: results.setdefault(job, result))
    return results, time.perf_counter() - start


def test_supervisor_kills_a_job_past_its_limit_and_replaces_only_that_worker(modules):
    basin, _ = modules
    jobs = [("sleep", 0.0), ("sleep", 0.01), ("sleep", LONG_S), ("sleep", 0.02)]
    results, wall = _run(modules, jobs, workers=1)
    assert wall < LONG_S / 2
    killed = results[("sleep", LONG_S)]
    assert isinstance(killed, basin.JobFailure) and killed.status == "TIME_BUDGET"
    assert LIMIT_S <= killed.wall < LIMIT_S + KILL_SLACK_S
    pids = [results[job][1] for job in jobs if job != ("sleep", LONG_S)]
    assert pids[0] == pids[1] != pids[2]  # a persistent worker, replaced after the kill
    assert not multiprocessing.active_children()


def test_supervisor_records_a_dead_worker_and_runs_the_other_jobs(modules):
    basin, _ = modules
    jobs = [("exit", 3), ("sleep", 0.0), ("sleep", 0.01), ("sleep", 0.02)]
    results, _ = _run(modules, jobs, workers=2)
    died = results[("exit", 3)]
    assert isinstance(died, basin.JobFailure) and died.status == "WORKER_DIED" and died.wall < LIMIT_S
    assert [results[job][0] for job in jobs[1:]] == ["sleep"] * 3
    assert not multiprocessing.active_children()


@pytest.mark.parametrize("jobs", [[("raise", 0), ("sleep", LONG_S)], [("sleep", 0.0), ("sleep", LONG_S)]],
                         ids=["job raises", "parent raises"])
def test_supervisor_leaves_no_worker_behind_on_an_exception(modules, jobs):
    basin, test_jobs = modules

    def on_result(job, result):
        raise KeyError("the parent fails")

    start = time.perf_counter()
    with pytest.raises((RuntimeError, KeyError), match="a job that raises|the parent fails"):
        basin.run_supervised(jobs, test_jobs.job, 2, lambda job: LONG_S, on_result)
    assert time.perf_counter() - start < LONG_S / 2
    assert not multiprocessing.active_children()


def test_basin_job_limits_and_failed_rows(modules):
    basin, _ = modules
    setting = basin.oscillator_setting()
    cfg = basin.FULL
    coefs = setting.truth_coefs * 2
    assert basin._job_limit(("oscillator", 3, coefs, "adam", True, cfg)) == cfg["adam_time"] + basin.FIT_GRACE_S
    job = ("oscillator", 3, coefs, "shooting", True, cfg)
    assert basin._job_limit(job) == cfg["budget"] + basin.FIT_GRACE_S
    row = basin.failed_row(setting, job, basin.JobFailure("TIME_BUDGET", 131.5))
    assert row["status"] == "TIME_BUDGET" and row["wall"] == 131.5 and row["iterations"] == -1
    assert row["estimates"] is None and math.isnan(row["sse"])
    assert (row["setting"], row["start"], row["method"]) == ("oscillator", 3, "shooting")
    np.testing.assert_allclose(row["factors"], [2.0, 2.0])
    row.update(reached=False)
    assert basin.failure_mode(row) == "TIME_BUDGET"
    assert basin.summarize([row])[0]["failures"] == {"TIME_BUDGET": 1}
