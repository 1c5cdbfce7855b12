"""Test-suite settings.

The fits in these tests work on tiny tensors, where torch's intra-op thread pool costs more
than it gives (and slows everything down badly when the machine is busy): run single-threaded,
and use the machine's cores with one pytest-xdist worker process each (``addopts`` in
pyproject.toml), at most :data:`MAX_WORKERS` (each holds torch, scipy and matplotlib).
"""

import os

import torch

torch.set_num_threads(1)

#: Most worker processes of ``-n auto``.
MAX_WORKERS = 4


def pytest_xdist_auto_num_workers(config):
    """``-n auto``: one worker per core, at most :data:`MAX_WORKERS`."""
    return max(1, min(MAX_WORKERS, os.cpu_count() or 1))
