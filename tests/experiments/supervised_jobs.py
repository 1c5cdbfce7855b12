"""Job functions for the tests of `experiments/basin.py`'s `run_supervised`: top-level in an
importable module, so that its spawned worker processes can import them."""

import os
import time


def job(spec: tuple[str, float]) -> tuple[str, int]:
    """``("sleep", s)``: sleep ``s`` seconds; ``("exit", code)``: end the process at once, as a crash
    would; ``("raise", _)``: raise. Returns the job's name and the worker's process id."""
    kind, value = spec
    if kind == "sleep":
        time.sleep(value)
    elif kind == "exit":
        os._exit(int(value))
    elif kind == "raise":
        raise ValueError("a job that raises")
    return kind, os.getpid()
