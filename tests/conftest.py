"""Shared pytest fixtures."""

from __future__ import annotations

from pathlib import Path

import pytest

REAL_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"


@pytest.fixture
def real_data() -> Path:
    """The real LiDAR samples in ``../shared/data/real`` (skips the test when that folder is absent)."""
    if not REAL_DATA.is_dir():
        pytest.skip(
            f"real sample data not found at {REAL_DATA} (it lives outside the repository, in ../shared)"
        )
    return REAL_DATA


@pytest.fixture(scope="session")
def warm_kernels() -> None:
    """Compile (or load from the disk cache) the simulator's Numba kernels once, so that tests with a loose time
    bound measure rendering rather than a cold compile (about 15 s on a fresh clone)."""
    from placerec.sim import SimulatedSequence

    for world in ("town", "campus"):
        SimulatedSequence(world, "vlp16", seed=0, n_scans=2)[0]
