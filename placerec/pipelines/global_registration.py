"""Global geometric registration with SHOT: the ISHOT paper's baseline (a) of Table III (Sec. V-C).

`GlobalRegistration` (registered as ``shot-global``) localises a scan in the whole map at once, "similar to
Rusu et al.": the map is not split into places for retrieval. Its keypoints (ISS-BR, the front end every 3D
pipeline shares) are described with SHOT and kept in the map frame; each query descriptor is paired with its
``knn`` = 4 nearest map descriptors (the paper's K = 4), and the query-to-map correspondences go through the
verification stage every localisation pipeline shares (`placerec.verify`: geometric consistency grouping with
consensus resolution 7 m and minimum cluster 8, RANSAC), which gives ``T_world_query``. ICP then refines it
against the map cloud nearest to that pose and accepts it by eps_ICP = 7 m^2, as for every other pipeline.

How a pose in the map becomes a candidate: the match is the map entry (a map scan, ``places.spacing_m`` apart
like the ISHOT places) whose position is nearest to the RANSAC estimate of the query's position; the
correspondences are expressed in that entry's frame (a rigid change of frame: grouping and RANSAC give the
same pose) and verified against its cloud with `placerec.verify.candidates.verify_candidates`, so
``relative_pose`` is ``T_match_query`` and ``map_poses[match_id] @ relative_pose`` the query's pose in the
map. At most one candidate is returned: the largest consistent cluster gives one pose; when it is rejected the
query has no candidate with a pose.

The query runs in the loop every voting pipeline shares (`placerec.pipelines.voting_engine`),
`RegistrationVotes` its strategy: one batch of every keypoint, whose registration shortlists the one entry.
``extra``: the engine's diagnostics (``match_ms``: the K-NN search, ...), ``correspondences`` (query keypoints
x K), ``T_world_ransac`` (the query's pose in the map before ICP) and ``votes`` (RANSAC inliers).
"""

from __future__ import annotations

import time
from typing import Any, ClassVar

import numpy as np
from pydantic import Field

from placerec.errors import ScanDataError
from placerec.params import Params
from placerec.pipelines.keypoint_voting import ARTIFACT_KIND, KeypointVoting, VotingParams
from placerec.pipelines.voting_engine import Query, Shortlist, VoteStrategy
from placerec.verify.candidates import Retrieved
from placerec.verify.verify import hypothesise

__all__ = ["ARTIFACT_KIND", "GlobalParams", "GlobalRegistration", "RegistrationVotes"]


class GlobalParams(VotingParams):
    """`VotingParams` (front end, map entries, verification) plus the K of the global matching."""

    knn: int = Field(
        4, ge=1, description="map descriptors paired with each query descriptor (ISHOT paper: K = 4)"
    )


class RegistrationVotes(VoteStrategy["GlobalRegistration"]):
    """Every query descriptor paired with its K nearest map descriptors (keypoints in the world frame); grouping
    and RANSAC over all pairs give the query's pose, and the entry nearest to it is the one candidate."""

    def __init__(self, rec: GlobalRegistration, query: Query) -> None:
        if not rec.params.verify.enabled:
            raise ScanDataError(
                f"{rec.name}: global registration needs verify.enabled (it is the registration)"
            )
        super().__init__(rec, query)
        self.p = rec.params
        self.pairs: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def possible(self) -> bool:
        return self.n > 0 and self.query.rows.shape[0] > 0

    def vote(self, batch: np.ndarray) -> None:
        qr, k = self.query, self.p.knn
        wkp = self.rec.derived("world_keypoints", self.rec.entries.world_keypoints)
        if qr.rows.shape[0] < len(self.rec.entries.store):
            wkp = wkp[qr.eligible[self.rec.entries.row_entry]]
        dist, idx = qr.rows.knn(qr.q[batch], k, self.p.search.nn_threads)
        found = idx.ravel() >= 0
        src = np.repeat(np.asarray(qr.qkp, np.float64)[batch], k, axis=0)[found]
        self.pairs = (src, wkp[idx.ravel()[found]], dist.ravel()[found])
        self.matched += batch.size

    def ready(self) -> Shortlist | None:
        assert self.pairs is not None
        src, dst, quality = self.pairs
        t0 = time.perf_counter()
        hyp = hypothesise(src, dst, None, self.p.verify, quality)
        locate_ms = (time.perf_counter() - t0) * 1e3
        if hyp.rejected_at is not None:
            return None
        entries, eligible = self.rec.entries, self.query.eligible
        T_world_query = hyp.T_match_query
        d = np.linalg.norm(entries.xyz() - T_world_query[:3, 3], axis=1)
        d[~eligible] = np.inf
        e = int(np.argmin(d))
        T_entry_world = np.linalg.inv(entries.poses[e])
        extra: dict[str, Any] = {
            "correspondences": int(src.shape[0]),
            "votes": int(hyp.inliers or 0),
            "n_query": self.n,
            "T_world_ransac": T_world_query,
        }
        score = float(hyp.inliers or 0) / self.n
        local = self.rec.local_maps.members(e, eligible)
        retrieved = Retrieved(
            entries.ids[e],
            score,
            src,
            dst @ T_entry_world[:3, :3].T + T_entry_world[:3, 3],
            quality,
            extra=extra,
            target=self.rec.local_maps.target_of(local),
            verify_ms=locate_ms,
        )
        return Shortlist([e], score=lambda _: score, extra=lambda _: extra, retrieve=lambda _: retrieved)


class GlobalRegistration(KeypointVoting):
    """`PlaceRecognizer`: SHOT global registration against every map keypoint (module docstring)."""

    name: ClassVar[str] = "global-registration"
    Params: ClassVar[type[Params]] = GlobalParams
    params: GlobalParams
    Strategy: ClassVar[type[VoteStrategy[Any]]] = RegistrationVotes
