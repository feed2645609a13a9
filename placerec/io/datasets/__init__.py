"""Dataset layouts users bring, one module each, behind `placerec.io.open_sequence(path, dataset=...)`.

`DATASET_LOADERS` maps a dataset name to its `DatasetLoader`: the layout it expects, a ``detect(path)`` test used
when no ``dataset`` is given (tried in the table's order) and the loader. Every loader gives LiDAR-frame poses
``T_world_lidar`` (placerec's z-up convention) and timestamps in seconds; a malformed layout (missing folder or
calibration, a pose count that differs from the scan count, a bad CSV row) is a `ScanFormatError` naming the file.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from placerec.errors import ConfigError
from placerec.io.datasets.helipr import HELIPR_LAYOUT, HeliprSequence, detect_helipr
from placerec.io.datasets.kitti import KITTI_LAYOUT, KittiSequence, detect_kitti, open_kitti_odometry
from placerec.io.datasets.mcap import McapSequence, detect_mcap
from placerec.io.datasets.mulran import MULRAN_LAYOUT, MulranSequence, detect_mulran
from placerec.io.datasets.nclt import NCLT_LAYOUT, NcltSequence, detect_nclt
from placerec.io.datasets.newer_college import (
    NEWER_COLLEGE_LAYOUT,
    NewerCollegeSequence,
    detect_newer_college,
)
from placerec.types import Sequence

__all__ = [
    "DatasetLoader",
    "DATASET_LOADERS",
    "register_dataset",
    "detect_dataset",
    "dataset_loader",
    "KittiSequence",
    "MulranSequence",
    "NewerCollegeSequence",
    "HeliprSequence",
    "NcltSequence",
    "McapSequence",
]


@dataclass(frozen=True)
class DatasetLoader:
    """One dataset layout: ``open(path, **options)`` gives its `Sequence`; ``detect(path)`` says whether
    ``path`` looks like it; ``layout`` describes the expected files (for messages and docs)."""

    name: str
    layout: str
    detect: Callable[[Path], bool]
    open: Callable[..., Sequence]


#: Dataset name -> loader, in the order auto-detection tries them.
DATASET_LOADERS: dict[str, DatasetLoader] = {}


def register_dataset(loader: DatasetLoader) -> DatasetLoader:
    """Add (or replace) a dataset layout; returns it."""
    DATASET_LOADERS[loader.name] = loader
    return loader


for _loader in (
    DatasetLoader("mcap", "<file>.mcap (ROS 2, no metadata.yaml beside it)", detect_mcap, McapSequence),
    DatasetLoader("mulran", MULRAN_LAYOUT, detect_mulran, MulranSequence),
    DatasetLoader("newer-college", NEWER_COLLEGE_LAYOUT, detect_newer_college, NewerCollegeSequence),
    DatasetLoader("helipr", HELIPR_LAYOUT, detect_helipr, HeliprSequence),
    DatasetLoader("nclt", NCLT_LAYOUT, detect_nclt, NcltSequence),
    DatasetLoader("kitti", KITTI_LAYOUT, detect_kitti, open_kitti_odometry),
):
    register_dataset(_loader)


def dataset_loader(name: str) -> DatasetLoader:
    """The loader registered as ``name``; `ConfigError` listing the known names otherwise."""
    try:
        return DATASET_LOADERS[name]
    except KeyError:
        raise ConfigError(f"unknown dataset {name!r}; known datasets: {list(DATASET_LOADERS)}") from None


def detect_dataset(path: str | Path) -> str | None:
    """The name of the first registered layout ``path`` matches, or None."""
    p = Path(path)
    return next((name for name, loader in DATASET_LOADERS.items() if loader.detect(p)), None)
