"""The type checker on the package (mypy with the pydantic plugin, `[tool.mypy]` in pyproject.toml), on a ratchet:
its error count may not exceed the one recorded in tools/mypy_ratchet.txt, and that record may not exceed 30."""

from __future__ import annotations

import re
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RATCHET = ROOT / "tools" / "mypy_ratchet.txt"
#: the most errors the ratchet may ever record
CEILING = 30


def recorded() -> int:
    """The error count tools/mypy_ratchet.txt allows (its first number; ``#`` starts a comment)."""
    return int(RATCHET.read_text().split("#")[0].strip())


def errors_in(output: str) -> int:
    """The error count of mypy's summary line ("Success: ..." is 0)."""
    if re.search(r"^Success: no issues found", output, re.M):
        return 0
    m = re.search(r"^Found (\d+) errors? in \d+ files?", output, re.M)
    if m is None:
        raise AssertionError(f"mypy gave no summary line:\n{output[-2000:]}")
    return int(m.group(1))


def test_summary_lines_are_read():
    assert errors_in("x.py:1: error: no\nFound 12 errors in 3 files (checked 9 source files)\n") == 12
    assert errors_in("Found 1 error in 1 file (checked 2 source files)\n") == 1
    assert errors_in("Success: no issues found in 181 source files\n") == 0
    with pytest.raises(AssertionError, match="no summary"):
        errors_in("mypy: crashed")


def test_the_ratchet_never_exceeds_its_ceiling():
    assert 0 <= recorded() <= CEILING


def test_mypy_errors_stay_within_the_ratchet():
    pytest.importorskip("mypy", reason="mypy comes with the dev extra (tools/bootstrap.sh installs it)")
    run = subprocess.run(
        [sys.executable, "-m", "mypy"], cwd=ROOT, capture_output=True, text=True, timeout=600, check=False
    )
    found = errors_in(run.stdout + run.stderr)
    allowed = recorded()
    assert found <= allowed, (
        f"mypy finds {found} errors, the ratchet allows {allowed} (tools/mypy_ratchet.txt); fix the new ones:\n"
        f"{run.stdout[-4000:]}"
    )
    if found < allowed:
        warnings.warn(
            f"mypy finds {found} errors: lower tools/mypy_ratchet.txt from {allowed} to {found}", stacklevel=1
        )
