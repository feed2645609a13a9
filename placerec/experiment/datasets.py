"""Datasets named by a config: a registry of sequence sources, and slicing of any `Sequence`."""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from pathlib import Path

import numpy as np

from placerec.config import DatasetConfig
from placerec.errors import ConfigError
from placerec.keyframes import KeyframeParams, KeyframeSequence
from placerec.preprocess import PreprocessParams, preprocess_scan
from placerec.types import Scan, Sequence

__all__ = [
    "DATASET_SOURCES",
    "open_dataset",
    "keyframed",
    "dataset_fingerprint",
    "files_fingerprint",
    "SlicedSequence",
]


class SlicedSequence:
    """Scans ``first, first + step, ...`` (up to ``last``, exclusive) of another sequence, renumbered from 0."""

    def __init__(self, base: Sequence, first: int = 0, last: int | None = None, step: int = 1) -> None:
        n = len(base)
        stop = n if last is None else min(last, n)
        if first >= stop:
            raise ConfigError(
                f"dataset slice first={first}, last={last} selects no scan of {base.name} ({n} scans)"
            )
        self._base = base
        self._index = np.arange(first, stop, step)

    def __len__(self) -> int:
        return int(self._index.size)

    def __getitem__(self, index: int) -> Scan:
        if not -len(self) <= index < len(self):
            raise IndexError(f"scan index {index} out of range for {len(self)} scans")
        return self._base[int(self._index[index])]

    @property
    def poses(self) -> np.ndarray | None:
        poses = self._base.poses
        return None if poses is None else poses[self._index]

    @property
    def timestamps(self) -> np.ndarray | None:
        ts = self._base.timestamps
        return None if ts is None else ts[self._index]

    @property
    def name(self) -> str:
        return self._base.name

    @property
    def odometry_poses(self) -> np.ndarray | None:
        """The base sequence's drifting odometry poses of the selected scans (a simulator's), else None."""
        odometry = getattr(self._base, "odometry_poses", None)
        return None if odometry is None else np.asarray(odometry)[self._index]

    @property
    def base_indices(self) -> np.ndarray:
        """Index of each scan in the underlying sequence."""
        return self._index


def _simulator(cfg: DatasetConfig) -> Sequence:
    from placerec.sim import SimulatedSequence

    return SimulatedSequence(**cfg.simulator.model_dump())  # every simulator setting is a keyword of it


def _path(cfg: DatasetConfig) -> Sequence:
    from placerec.io import open_sequence

    kwargs = {k: v for k in ("dataset", "sequence", "sensor", "topic") if (v := getattr(cfg, k)) is not None}
    if cfg.format:
        kwargs["format"] = cfg.format
    if cfg.poses:
        kwargs["poses"] = cfg.poses
    assert cfg.path is not None  # DatasetConfig requires it for source "path"
    return open_sequence(cfg.path, **kwargs)


#: Dataset sources by the ``dataset.source`` config value.
DATASET_SOURCES: dict[str, Callable[[DatasetConfig], Sequence]] = {
    "simulator": _simulator,
    "path": _path,
}


def files_fingerprint(*paths: str | Path | None) -> list:
    """(relative name, size, mtime) of every file at or under ``paths``: changes when any file is replaced."""
    out = []
    for p in paths:
        if p is None:
            continue
        root = Path(p).expanduser()
        files = sorted(f for f in root.rglob("*") if f.is_file()) if root.is_dir() else [root]
        for f in files:
            st = f.stat() if f.exists() else None
            out.append(
                [
                    str(f.relative_to(root)) if root.is_dir() else str(f),
                    st and st.st_size,
                    st and st.st_mtime_ns,
                ]
            )
    return out


def _simulator_fingerprint() -> list:
    """(file name, content hash) of the simulator's sources: any change to the simulator changes its scans."""
    from placerec.hashing import stable_hash

    sim = Path(__file__).parents[1] / "sim"
    return [[f.name, stable_hash(f.read_text())] for f in sorted(sim.glob("*.py"))]


def dataset_fingerprint(cfg: DatasetConfig) -> list:
    """What, besides the config, determines the scans of a dataset: the simulator's code, or the files' sizes and
    modification times. Part of the description cache key, so that cached descriptions never outlive their data."""
    if cfg.source == "simulator":
        return _simulator_fingerprint()
    return files_fingerprint(cfg.path, cfg.poses)


def keyframed(params: KeyframeParams | None, preprocess: PreprocessParams, seq: Sequence) -> Sequence:
    """``seq`` as pipelines with an experiment's (or a vocabulary's training config's) ``keyframes`` and
    ``preprocess`` see it: with ``params`` set, a `KeyframeSequence` over it (left as it is when it already is one),
    else ``seq``. The keyframes' odometry (``keyframes.odometry: poses``) is the sequence's drifting
    ``odometry_poses`` when it has them (the simulator with ``odometry_drift``), else its own (ground-truth) poses
    used as odometry; ``kiss-icp`` registers the scans instead. Every source scan is
    preprocessed (``preprocess``) before it is accumulated, so `preprocessed_scan` does not preprocess the
    keyframe again. `ConfigError` when ``poses`` odometry has nothing to use."""
    if params is None or isinstance(seq, KeyframeSequence):
        return seq
    odometry = getattr(seq, "odometry_poses", None)
    if odometry is None:
        odometry = seq.poses
    if odometry is None and params.odometry == "poses":
        raise ConfigError(
            f"keyframes.odometry 'poses': {seq.name} has neither odometry nor poses (use keyframes.odometry: kiss-icp)"
        )
    return KeyframeSequence(seq, params, odometry, prepare=partial(preprocess_scan, params=preprocess))


def open_dataset(cfg: DatasetConfig) -> Sequence:
    """The sequence a `DatasetConfig` describes, sliced by its ``first``/``last``/``step``."""
    seq = DATASET_SOURCES[cfg.source](cfg)
    if cfg.first == 0 and cfg.last is None and cfg.step == 1:
        return seq
    return SlicedSequence(seq, cfg.first, cfg.last, cfg.step)
