"""Test-suite settings.

The fits in these tests work on tiny tensors, where torch's intra-op thread pool costs more
than it gives (and slows everything down badly when the machine is busy): run single-threaded,
and use the machine's cores with one pytest-xdist worker process each (``addopts`` in
pyproject.toml), at most :data:`MAX_WORKERS` (each holds torch, scipy and matplotlib).
Data fixtures that several test modules use are defined here.
"""

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import torchql
from torchql.models import NonlinearOscillator

torch.set_num_threads(1)

#: Most worker processes of ``-n auto``.
MAX_WORKERS = 4
#: The checkout's root: its scripts, and its package whichever one the environment has installed.
ROOT = Path(__file__).resolve().parents[1]


def pytest_xdist_auto_num_workers(config):
    """``-n auto``: one worker per core, at most :data:`MAX_WORKERS`."""
    return max(1, min(MAX_WORKERS, os.cpu_count() or 1))


@pytest.fixture(scope="module")
def table_4_5_two_digit():
    """Thesis Table 4.5: 8 points (t = 0, 1, ..., 6, 6.5) of the nonlinear oscillator, rounded to 2 decimals."""
    dt = torch.float64
    times = torch.tensor([0, 1, 2, 3, 4, 5, 6, 6.5], dtype=dt)
    x = torchql.simulate(NonlinearOscillator(), torch.tensor([0.0, 1.0], dtype=dt), times, rtol=1e-13, atol=1e-15)
    return torchql.Observations(times, torch.round(x[:, :1] * 100) / 100, observe=["y"])


@pytest.fixture
def run_script():
    """``run_script(path, *args, timeout=300)``: run a script of the checkout (``path`` relative to
    its root) with this checkout's package first on the path; the completed process, output
    captured as text."""

    def run(path: str, *args: str, timeout: float = 300) -> subprocess.CompletedProcess:
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
        return subprocess.run([sys.executable, str(ROOT / path), *args], capture_output=True, text=True,
                              timeout=timeout, env=env)

    return run
