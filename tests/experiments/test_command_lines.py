"""The experiments' and benchmarks' command lines: each script parses its arguments, so that ``--help``
answers and a mistyped option is an error instead of a silent full run."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SCRIPTS = sorted([*ROOT.glob("experiments/*.py"), *ROOT.glob("benchmarks/*.py")])


def _parses_arguments(tree: ast.Module) -> bool:
    """Whether the module calls ``parse_args`` (or ``parse_known_args``) somewhere."""
    return any(isinstance(node, ast.Attribute) and node.attr in ("parse_args", "parse_known_args")
               for node in ast.walk(tree))


def _refuses_to_run(tree: ast.Module) -> bool:
    """Whether the module, run as a script, only raises ``SystemExit`` (a module of another script)."""
    for node in tree.body:
        if isinstance(node, ast.If) and "__main__" in ast.unparse(node.test):
            return all(isinstance(stmt, ast.Raise) and "SystemExit" in ast.unparse(stmt) for stmt in node.body)
    return False


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_every_script_parses_its_command_line(script):
    tree = ast.parse(script.read_text())
    assert _parses_arguments(tree) or _refuses_to_run(tree), (
        f"{script.relative_to(ROOT)} neither parses its arguments nor refuses to run as a script")


@pytest.mark.parametrize("script", ["experiments/core_figures.py", "experiments/driven_oscillator.py"])
def test_a_mistyped_option_is_an_error_and_help_answers(script):
    """(Scripts without options once ran in full, silently, on ``--plt`` for ``--plot``.)"""
    wrong = subprocess.run([sys.executable, script, "--plt"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert wrong.returncode == 2 and "unrecognized arguments: --plt" in wrong.stderr
    helped = subprocess.run([sys.executable, script, "--help"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert helped.returncode == 0 and "usage:" in helped.stdout
