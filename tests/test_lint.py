"""``ruff check`` and ``ruff format --check`` over the project's packages and tests (the
``[tool.ruff]`` configuration of pyproject.toml): lint runs with the test suite, so CI
fails on a new finding or an unformatted file.

Ruff is in the ``test`` extra (``pip install -e .[test]``); without it the tests fail.
"""

from __future__ import annotations

import importlib.util
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: What is linted: every package of the project, and the tests.
LINTED = ("scenefmt", "assets_procedural", "generators", "svorf", "benchmark", "tests")


def _ruff() -> list[str] | None:
    """The command that runs ruff here, or None where it is not installed."""
    if importlib.util.find_spec("ruff") is not None:
        return [sys.executable, "-m", "ruff"]
    exe = shutil.which("ruff")
    return None if exe is None else [exe]


def test_ruff_check_passes():
    ruff = _ruff()
    assert ruff is not None, (
        "ruff is not installed: pip install -e '.[test]' (it is in the test extra)"
    )
    proc = subprocess.run(
        [*ruff, "check", "--no-cache", "--output-format", "concise", *LINTED],
        cwd=ROOT,
        check=False,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, f"ruff check found problems:\n{proc.stdout}{proc.stderr}"


def test_ruff_format_is_clean():
    ruff = _ruff()
    assert ruff is not None, (
        "ruff is not installed: pip install -e '.[test]' (it is in the test extra)"
    )
    proc = subprocess.run(
        [*ruff, "format", "--check", "--no-cache", *LINTED],
        cwd=ROOT,
        check=False,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, (
        f"ruff format would change files (run `ruff format`):\n{proc.stdout}{proc.stderr}"
    )
