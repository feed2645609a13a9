"""Global geometric registration with SHOT: the ISHOT paper's baseline (a) of Table III (Sec. V-C).

`GlobalRegistration` (registered as ``shot-global``) localises a scan in the whole map at once, "similar to Rusu
et al.": the map is not split into places for retrieval. Its keypoints (ISS-BR, the front end every 3D pipeline
shares) are described with SHOT and kept in the map frame; each query descriptor is paired with its ``knn`` = 4
nearest map descriptors (the paper's K = 4), and the query-to-map correspondences go through the verification
stage every localisation pipeline shares (`placerec.verify`: geometric consistency grouping with consensus
resolution 7 m and minimum cluster 8, RANSAC), which gives ``T_world_query``. ICP then refines it against the map
cloud nearest to that pose and accepts it by eps_ICP = 7 m^2, as for every other pipeline.

How a pose in the map becomes a candidate: the match is the map entry (a map scan, ``place_spacing_m`` apart like
the ISHOT places) whose position is nearest to the RANSAC estimate of the query's position; the correspondences
are expressed in that entry's frame (a rigid change of frame: grouping and RANSAC give the same pose) and verified
against its cloud with `placerec.verify.candidates.verify_candidates`, so ``relative_pose`` is ``T_match_query``
and ``map_poses[match_id] @ relative_pose`` the query's pose in the map. At most one candidate is returned: the
largest consistent cluster gives one pose; when it is rejected the query has no candidate with a pose.

``extra``: ``correspondences`` (query keypoints x K), ``match_ms`` (K-NN search), ``T_world_query`` (before ICP:
``T_world_ransac``), ``keypoints_consumed`` (every query keypoint) and ``votes`` (RANSAC inliers).
"""

from __future__ import annotations

import time
from functools import partial
from typing import Any, ClassVar

import numpy as np
from pydantic import Field

from placerec.errors import ScanDataError
from placerec.params import Params
from placerec.pipelines.keypoint_voting import ARTIFACT_KIND, KeypointVoting, VotingParams
from placerec.types import Candidate, Description
from placerec.verify.candidates import Retrieved, verify_candidates
from placerec.verify.verify import hypothesise

__all__ = ["ARTIFACT_KIND", "GlobalParams", "GlobalRegistration", "world_keypoints"]


class GlobalParams(VotingParams):
    """`VotingParams` (front end, map entries, verification) plus the K of the global matching."""

    knn: int = Field(
        4, ge=1, description="map descriptors paired with each query descriptor (ISHOT paper: K = 4)"
    )


def world_keypoints(keypoints: list[np.ndarray], poses: list[np.ndarray]) -> np.ndarray:
    """The entries' keypoints (each in its entry's frame) mapped into the world frame, stacked in row order."""
    if not keypoints:
        return np.zeros((0, 3), np.float64)
    return np.concatenate(
        [np.asarray(k, np.float64) @ P[:3, :3].T + P[:3, 3] for k, P in zip(keypoints, poses, strict=True)]
    )


class GlobalRegistration(KeypointVoting):
    """`PlaceRecognizer`: SHOT global registration against every map keypoint (module docstring)."""

    name: ClassVar[str] = "global-registration"
    Params: ClassVar[type[Params]] = GlobalParams

    def _reset(self) -> None:
        super()._reset()
        self._wkp: np.ndarray | None = None

    def _append_rows(self, desc: np.ndarray, entry: np.ndarray) -> None:
        super()._append_rows(desc, entry)
        self._wkp = None  # the entries changed: their world keypoints are stacked again on the next query

    def query_description(
        self, description: Description, k: int = 1, max_id: int | None = None, query_id: int = -1
    ) -> list[Candidate]:
        p = self.params
        if not p.verify.enabled:
            raise ScanDataError(
                f"{self.name}: global registration needs verify.enabled (it is the registration)"
            )
        q = np.asarray(description["descriptors"], np.float32).reshape(-1, self._dim)
        qkp = np.asarray(description["keypoints"], np.float64).reshape(-1, 3)
        if q.shape[0] == 0 or len(self._store) == 0:
            return []
        if "cloud" not in description:
            raise ScanDataError(f"{self.name}: verification needs the query description's 'cloud'")
        if self._wkp is None:
            self._wkp = world_keypoints(self._keypoints, self._poses)
        ids = np.asarray(self._ids)
        rows, wkp, eligible = self._store.view(), self._wkp, np.ones(len(ids), bool)
        if max_id is not None:
            eligible = ids <= max_id
            keep = eligible[self._row_entry]
            rows, wkp = self._store.view(mask=keep), wkp[keep]
            if not rows.shape[0]:
                return []
        t0 = time.perf_counter()
        dist, idx = rows.knn(q, p.knn, p.nn_threads)
        found = idx.ravel() >= 0
        src = np.repeat(qkp, p.knn, axis=0)[found]
        dst = wkp[idx.ravel()[found]]
        quality = dist.ravel()[found]
        match_ms = (time.perf_counter() - t0) * 1e3
        t1 = time.perf_counter()
        hyp = hypothesise(src, dst, None, p.verify.verify, quality)
        locate_ms = (time.perf_counter() - t1) * 1e3
        if hyp.rejected_at is not None:
            return []
        T_world_query = hyp.T_match_query
        d = np.linalg.norm(self._entry_xyz() - T_world_query[:3, 3], axis=1)
        d[~eligible] = np.inf
        e = int(np.argmin(d))
        T_entry_world = np.linalg.inv(self._poses[e])
        extra: dict[str, Any] = {
            "correspondences": int(src.shape[0]),
            "votes": int(hyp.inliers or 0),
            "n_query": int(q.shape[0]),
            "keypoints_consumed": int(q.shape[0]),
            "match_ms": match_ms,
            "verify_ms": locate_ms,
            "T_world_ransac": T_world_query,
        }
        local = self._local_entries(e, eligible)
        retrieved = Retrieved(
            self._ids[e],
            float(hyp.inliers or 0) / q.shape[0],
            src,
            dst @ T_entry_world[:3, :3].T + T_entry_world[:3, 3],
            quality,
            extra=extra,
            target=partial(self._local_target, local) if len(local) > 1 else None,
        )
        cands = verify_candidates(description["cloud"], [retrieved], self._clouds, p.verify, query_id, k)
        for c in cands:
            if c.relative_pose is not None:
                c.extra["T_world_query"] = np.asarray(self._poses[e]) @ c.relative_pose
        return cands
