"""Shared pytest fixtures."""

from __future__ import annotations

from pathlib import Path

import pytest

REAL_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"


@pytest.fixture
def real_data() -> Path:
    """The real LiDAR samples in ``../shared/data/real`` (skips the test when that folder is absent)."""
    if not REAL_DATA.is_dir():
        pytest.skip(f"real sample data not found at {REAL_DATA} (it lives outside the repository, in ../shared)")
    return REAL_DATA
