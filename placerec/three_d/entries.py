"""The entry table of the 3D retrieval pipelines: described entries (scans or places) with their poses.

An entry has an id (a scan id, or a place's centre scan), a pose ``T_world_entry``, keypoints in its own frame
and one descriptor per keypoint. The descriptors of every entry sit in one `DescriptorStore` in insertion
order, so entry ``e`` owns rows ``starts[e]:starts[e + 1]`` and ``row_entry`` maps a row back to its entry.
The same table serves the entries a pipeline adds scan by scan and a places database built offline
(`placerec.three_d.places.PlacesDatabase.entry_table`).

``eligible(max_id)`` restricts a query to the entries with ``id <= max_id`` (loop closure's exclusion window):
when ids were added in increasing order (the usual case) the eligible rows are a prefix and nothing is copied.
``version`` grows with every change, so what a pipeline derives from the entries (an approximate index,
posterior vectors, world keypoints) knows when to rebuild.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from placerec.errors import ArtifactError
from placerec.retrieval.descriptor_store import DescriptorStore, StoreView
from placerec.types import as_pose, rigid_problem

__all__ = ["EntryTable", "far_from_all"]


def far_from_all(centres: np.ndarray, xyz: np.ndarray, spacing: float) -> bool:
    """Whether ``xyz`` lies at least ``spacing`` from every row of ``centres`` (True when there are none): the
    greedy rule that makes a scan a new place, online and offline."""
    if len(centres) == 0:
        return True
    return bool(np.min(np.sum((np.asarray(centres) - xyz) ** 2, axis=1)) >= spacing**2)


class EntryTable:
    """Entries (ids, poses, keypoints) and their descriptors in one store (see the module docstring)."""

    def __init__(self, store: DescriptorStore) -> None:
        self.store = store
        self.row_entry = np.zeros(0, np.int32)
        self.ids: list[int] = []
        self.poses: list[np.ndarray] = []
        self.counts: list[int] = []
        self.keypoints: list[np.ndarray] = []
        self.version = 0
        self._idset: set[int] = set()
        self._sorted = True
        self._xyz: np.ndarray | None = None
        self._starts: np.ndarray | None = None

    @classmethod
    def empty(cls, dim: int, dtype: str = "float32") -> EntryTable:
        return cls(DescriptorStore(dim, dtype))

    @classmethod
    def of(
        cls,
        store: DescriptorStore,
        ids: Any,
        poses: Any,
        counts: Any,
        keypoints: list[np.ndarray],
    ) -> EntryTable:
        """A table over existing rows: ``store`` holds the descriptors of the entries in order, ``counts[e]``
        rows each (the store is used as it is, not copied)."""
        t = cls(store)
        t.ids = [int(i) for i in ids]
        t._idset = set(t.ids)
        t._sorted = bool(np.all(np.diff(np.asarray(ids)) > 0))
        t.poses = [np.asarray(T) for T in poses]
        t.counts = [int(c) for c in counts]
        t.keypoints = list(keypoints)
        t.row_entry = np.repeat(np.arange(len(t.ids), dtype=np.int32), t.counts)
        return t

    def __len__(self) -> int:
        return len(self.ids)

    def __contains__(self, entry_id: int) -> bool:
        return entry_id in self._idset

    def append(self, entry_id: int, pose: np.ndarray | None, keypoints: np.ndarray, desc: np.ndarray) -> None:
        """Add an entry (``pose`` None: the identity); ``desc`` (K, D) float32, ``keypoints`` (K, 3)."""
        if self.ids and entry_id <= self.ids[-1]:
            self._sorted = False
        self.store.append(desc)
        self.row_entry = np.concatenate([self.row_entry, np.full(desc.shape[0], len(self.ids), np.int32)])
        self.ids.append(entry_id)
        self._idset.add(entry_id)
        self.poses.append(np.eye(4) if pose is None else as_pose(pose))
        self.counts.append(desc.shape[0])
        self.keypoints.append(np.asarray(keypoints, np.float32).reshape(-1, 3))
        self.version += 1

    def eligible(self, max_id: int | None) -> tuple[StoreView, np.ndarray, int]:
        """(descriptor rows, their entry index, number of entries the indices range over) for ``id <= max_id``;
        the rows are a view of the store (searched in place, never decoded as a whole)."""
        entry = self.row_entry
        if max_id is None or (self.ids and max_id >= max(self.ids)):
            return self.store.view(), entry, len(self.ids)
        if self._sorted:
            n_ent = int(np.searchsorted(np.asarray(self.ids), max_id, side="right"))
            n = int(np.sum(self.counts[:n_ent]))
            return self.store.view(n), entry[:n], n_ent
        ok = np.asarray(self.ids)[entry] <= max_id
        return self.store.view(mask=ok), entry[ok], len(self.ids)

    def eligible_mask(self, max_id: int | None) -> np.ndarray:
        """Mask over the entries (insertion order) of those with ``id <= max_id``."""
        ids = np.asarray(self.ids)
        return np.ones(len(ids), bool) if max_id is None else ids <= max_id

    def xyz(self) -> np.ndarray:
        """(entries, 3) positions of the entries (their poses' translations)."""
        if self._xyz is None or len(self._xyz) != len(self.poses):
            self._xyz = np.asarray([T[:3, 3] for T in self.poses], np.float64).reshape(-1, 3)
        return self._xyz

    def starts(self) -> np.ndarray:
        """First descriptor row of every entry, and the row count last (kept until the entries change)."""
        if self._starts is None or len(self._starts) != len(self.counts) + 1:
            self._starts = np.concatenate([[0], np.cumsum(self.counts)])
        return self._starts

    def rows_of(self, entries: list[int]) -> np.ndarray:
        """The descriptors of ``entries`` (decoded), stacked in that order."""
        starts = self.starts()
        return np.concatenate([self.store.rows(starts[j], starts[j + 1]) for j in entries])

    def in_frame(self, e: int, entries: list[int], points: Any, dtype: type = np.float64) -> np.ndarray:
        """``points(j)`` (in entry ``j``'s frame) of every entry ``j`` of ``entries``, moved into entry ``e``'s
        frame by the entries' poses (computed in ``dtype``) and stacked."""
        T_e_world = np.linalg.inv(self.poses[e])
        parts = []
        for j in entries:
            T = (T_e_world @ self.poses[j]).astype(dtype)
            parts.append(points(j) @ T[:3, :3].T + T[:3, 3])
        return np.concatenate(parts)

    def world_keypoints(self) -> np.ndarray:
        """Every entry's keypoints in the world frame, stacked in row order."""
        if not self.keypoints:
            return np.zeros((0, 3), np.float64)
        return np.concatenate(
            [
                np.asarray(k, np.float64) @ P[:3, :3].T + P[:3, 3]
                for k, P in zip(self.keypoints, self.poses, strict=True)
            ]
        )

    def arrays(self) -> dict[str, np.ndarray]:
        """ids, poses, counts, keypoints and the store's arrays (what `from_arrays` reads back)."""
        kp = self.keypoints
        return {
            "ids": np.asarray(self.ids, np.int64),
            "poses": np.asarray(self.poses, np.float64).reshape(-1, 4, 4),
            "counts": np.asarray(self.counts, np.int64),
            "keypoints": np.concatenate(kp).astype(np.float32) if kp else np.zeros((0, 3), np.float32),
            **self.store.arrays(),
        }

    @classmethod
    def from_arrays(
        cls, arrays: Mapping[str, np.ndarray], store: DescriptorStore, path: Any = ""
    ) -> EntryTable:
        """The table `arrays` wrote (checked by the caller's schema; the poses here: `ArtifactError` for one that
        is no rigid motion)."""
        problem = rigid_problem(arrays["poses"])
        if problem is not None:
            raise ArtifactError(f"{path}: 'poses' row {problem[0]} is no rigid motion: {problem[1]}")
        n = len(arrays["ids"])
        kp = np.split(arrays["keypoints"], np.cumsum(arrays["counts"])[:-1]) if n else []
        return cls.of(store, arrays["ids"], list(arrays["poses"]), arrays["counts"], list(kp))
