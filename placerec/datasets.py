"""Datasets named by a config: a registry of sequence sources, and slicing of any `Sequence`."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from placerec.config import DatasetConfig
from placerec.errors import ConfigError
from placerec.types import Scan, Sequence

__all__ = ["DATASET_SOURCES", "open_dataset", "SlicedSequence"]


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
    def base_indices(self) -> np.ndarray:
        """Index of each scan in the underlying sequence."""
        return self._index


def _simulator(cfg: DatasetConfig) -> Sequence:
    from placerec.sim import SimulatedSequence

    sim = cfg.simulator
    return SimulatedSequence(
        world=sim.world,
        sensor=sim.sensor,
        n_scans=sim.n_scans,
        seed=sim.seed,
        route=sim.route,
        spacing=sim.spacing,
        clutter=sim.clutter,
        occluders=sim.occluders,
        sensor_height=sim.sensor_height,
    )


def _path(cfg: DatasetConfig) -> Sequence:
    from placerec.io import open_sequence

    kwargs = {}
    if cfg.format:
        kwargs["format"] = cfg.format
    if cfg.poses:
        kwargs["poses"] = cfg.poses
    return open_sequence(cfg.path, **kwargs)


#: Dataset sources by the ``dataset.source`` config value.
DATASET_SOURCES: dict[str, Callable[[DatasetConfig], Sequence]] = {
    "simulator": _simulator,
    "path": _path,
}


def open_dataset(cfg: DatasetConfig) -> Sequence:
    """The sequence a `DatasetConfig` describes, sliced by its ``first``/``last``/``step``."""
    seq = DATASET_SOURCES[cfg.source](cfg)
    if cfg.first == 0 and cfg.last is None and cfg.step == 1:
        return seq
    return SlicedSequence(seq, cfg.first, cfg.last, cfg.step)
