"""Verifying a candidate entry as a local map: its descriptors and those of its neighbours, in its frame.

With ``verify.radius_m > 0`` a candidate entry ``e`` is verified together with the (eligible) entries within
that distance of it: the query's descriptors are matched against all of theirs, their keypoints moved into
``e``'s frame by the entries' poses, and ICP runs against their clouds merged in that frame and voxelised
again (the last ``local_map_cache`` merged clouds are kept). At 0 the entry is verified alone.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from functools import partial
from typing import Any

import numpy as np

from placerec.retrieval.descriptor_store import knn2
from placerec.retrieval.nearest import nn_ratio
from placerec.three_d.entries import EntryTable
from placerec.verify.candidates import CloudStore, Retrieved
from placerec.verify.icp import IcpCloud
from placerec.verify.params import VerifyParams
from placerec.verify.verify import as_target
from placerec.verify.voxel_grid import voxel_points

__all__ = ["LocalMaps"]


class LocalMaps:
    """The local maps of an `EntryTable`'s entries and their merged ICP clouds (see the module docstring)."""

    def __init__(
        self,
        entries: EntryTable,
        clouds: CloudStore,
        radius_m: float,
        cache: int,
        verify: VerifyParams,
    ) -> None:
        self.entries = entries
        self.clouds = clouds
        self.radius_m = radius_m
        self.cache = cache
        self.verify = verify
        self._targets: OrderedDict[tuple[int, ...], IcpCloud] = OrderedDict()

    def members(self, e: int, eligible: np.ndarray | None = None) -> list[int]:
        """Entry ``e`` first, then the entries (``eligible`` ones only, when given) within ``radius_m`` of it,
        nearest first."""
        if self.radius_m <= 0:
            return [e]
        centres = self.entries.xyz()
        d = np.linalg.norm(centres - centres[e], axis=1)
        near = d <= self.radius_m
        if eligible is not None:
            near &= eligible
        near[e] = False
        others = np.flatnonzero(near)
        return [e, *(int(j) for j in others[np.argsort(d[others], kind="stable")])]

    def matches(
        self,
        e: int,
        q: np.ndarray,
        qkp: np.ndarray,
        score: float,
        extra: dict[str, Any],
        tau_max: float,
        backend: str,
        threads: int | None,
        eligible: np.ndarray | None = None,
    ) -> Retrieved:
        """Entry ``e``'s correspondences with the query: 2-NN among the descriptors of its local map, ratio
        ``< tau_max`` (the time counts in the candidate's ``verify_ms``)."""
        t0 = time.perf_counter()
        local = self.members(e, eligible)
        entry_id = self.entries.ids[e]
        rows = self.entries.rows_of(local)
        if rows.shape[0] < 2:
            return Retrieved(entry_id, score, np.zeros((0, 3)), np.zeros((0, 3)), extra=extra)
        dist, idx = knn2(q, rows, backend, threads)
        tau = nn_ratio(dist)
        ok = tau < tau_max
        dst = self.keypoints(e, local)[idx[ok, 0]]
        ms = (time.perf_counter() - t0) * 1e3
        extra = {**extra, "matches": int(ok.sum()), "local_entries": len(local)}
        target = self.target_of(local)
        return Retrieved(entry_id, score, qkp[ok], dst, tau[ok], extra=extra, target=target, verify_ms=ms)

    def keypoints(self, e: int, local: list[int]) -> np.ndarray:
        """The keypoints of the entries ``local``, stacked in entry ``e``'s frame."""
        return self.entries.in_frame(e, local, lambda j: self.entries.keypoints[j], np.float32)

    def target_of(self, local: list[int]) -> Any:
        """The ICP target to verify against for the local map ``local``: None (the entry's own cloud) for an entry
        alone, else a callable preparing the merged cloud."""
        return partial(self.target, local) if len(local) > 1 else None

    def target(self, local: list[int]) -> IcpCloud:
        """The ICP target of the local map ``local`` (its first entry's frame): the entries' clouds merged and
        voxelised again at ``icp.voxel_size`` (`as_target`); the last ``cache`` are kept."""
        key = tuple(int(j) for j in local)
        if key in self._targets:
            self._targets.move_to_end(key)
            return self._targets[key]
        ids = self.entries.ids
        merged = self.entries.in_frame(key[0], list(key), lambda j: self.clouds.cloud(ids[j]))
        target = as_target(voxel_points(merged, self.verify.icp.voxel_size), self.verify)
        self._targets[key] = target
        while len(self._targets) > self.cache:
            self._targets.popitem(last=False)
        return target
