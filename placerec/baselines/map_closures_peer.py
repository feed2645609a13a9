"""Adapter for the peer MapClosures (PyPI ``map-closures``, PRBonn), so it runs in placerec's evaluator.

MapClosures describes a *local map* by ORB features on its bird's-eye-view density image, retrieves with HBST and
verifies with RANSAC. Two modes:

* **single scans** (``local_map: false``, the default): each scan, as preprocessed by placerec, is one "local map";
  this is how a per-scan place recognizer is compared, not how the peer's authors run it.
* **local maps** (``local_map: true``), as the authors' ``map_closures.pipeline`` runs it: scans are accumulated in
  a ``VoxelMap`` at ``density_map_resolution`` in the frame of the local map's first scan, and a local map is
  closed (handed to the peer, which matches it against the earlier ones) as soon as a scan lies more than
  ``local_map_distance`` (their KISS-ICP ``max_range``, 100 m) from that first scan; the points within that distance
  of the closing scan are carried into the next local map, whose frame is the closing scan's. The poses come from
  ``odometry``: ``given`` uses the poses passed to ``add`` (in ``placerec run`` the dataset's: ground truth for the
  simulator; pass odometry poses to use odometry), ``kiss-icp`` runs KISS-ICP on the scans inside the adapter as
  the authors' pipeline does (voxel 1 m, max range 100 m; poses given to ``add`` are then ignored). See
  `LocalMapParams` and "Local maps" below.

Protocol notes:

* ``describe`` keeps the scan's valid points (float64); the peer computes its density map itself. Descriptions
  are as large as the scans, so they are not cached on disk (``cache_descriptions = False``).
* The peer (map-closures 2.x) only matches while inserting: each of its query calls also stores the map. So a query
  inserts the scan *tentatively*; when the next call adds the same points under the same id (the loop-closure
  order: query, then add), the insertion is kept. Any other next call first rebuilds the peer from the added
  scans, which removes the tentative one: queries never change what is stored, at the cost of re-inserting every
  scan (O(database size)) after a query that is not followed by adding that scan (e.g. localisation queries).
* A query without a ``query_id`` (or with one already stored) is given an id past the newest stored one by more
  than the 3 maps the peer never matches against (its consecutive local maps), so every stored scan is eligible.
* Candidates whose match id is above ``max_id`` (inside the exclusion window) are dropped after the peer answers.
* ``score`` = number of RANSAC inliers; ``relative_pose`` = ``T_match_query``: the peer's ``pose`` maps the match's
  (``source_id``) points into the query's (``target_id``) frame, so it is inverted here (checked in the tests).
* ``save`` stores the added scans' points; ``load`` re-inserts them in the same order.

Local maps (loop-closure order: query scan ``i``, then add scan ``i``):

* A query answers only when its scan closes the current local map (the authors query the peer only then); its
  pose is KISS-ICP's (``kiss-icp``, registered at the query) or, with ``given`` poses, predicted at constant
  velocity from the last two added poses (``add`` then brings the real pose). The local map with the query scan
  is handed to the peer tentatively, kept when ``add`` brings the same scan id and closes the map, rebuilt
  otherwise (as for single scans). Scans that do not close a map get no candidates.
* **A closure back to scans**: the peer gives ``T_b_a`` between the query local map ``a`` and an older one ``b``
  (each in its first scan's frame, ``M_a``, ``M_b``). The query scan's pose in ``b`` is
  ``X = T_b_a @ inv(M_a) @ P_query``; the match is the scan ``j`` of ``b`` (with ``j <= max_id``) whose position
  ``inv(M_b) @ P_j`` is nearest to ``X``'s, and ``relative_pose = T_match_query = inv(inv(M_b) @ P_j) @ X``
  (`closure_to_scan`), using the same poses the maps were built with. ``extra`` holds ``local_map`` (``b``),
  ``query_map`` (``a``) and ``T_b_a``. Local maps whose last scan is past ``max_id`` are not matched.
* The last local map of a sequence is never closed (the adapter cannot know a scan is the last); ``save`` /
  ``load`` refuse local-map mode (KISS-ICP's state is not serialisable): a `ConfigError`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field

from placerec.errors import ConfigError, DependencyError, ScanDataError
from placerec.io.artifact_schema import Member, check_counts, check_unique
from placerec.io.atomic import load_artifact, save_artifact
from placerec.params import Params
from placerec.recognizer import Recognizer, check_saved_params, params_key, require_points
from placerec.types import Candidate, Description, MotionPrior, Scan

__all__ = ["MapClosuresPeer", "MapClosuresParams", "closure_to_scan"]

_KIND = "map-closures-db"
_VERSION = 1
_SCHEMA = {
    "ids": Member("iu", ("n_scans",)),
    "counts": Member("iu", ("n_scans",), min_value=0),
    "points": Member("f", ("n_points", 3), finite=True),
}
#: The peer never matches a map against the 3 maps stored just before it (its consecutive local maps).
_PEER_SKIP = 3


class MapClosuresParams(Params):
    """The peer's own settings (its defaults) plus how many candidates to ask for."""

    density_map_resolution: float = Field(
        0.5, gt=0, description="m per density-map pixel (MapClosures default)"
    )
    density_threshold: float = Field(
        0.05, ge=0, le=1, description="density-map cut-off (MapClosures default)"
    )
    hamming_distance_threshold: int = Field(50, ge=0, description="ORB match distance (MapClosures default)")
    inliers_threshold: int = Field(5, ge=0, description="RANSAC inliers of a closure (MapClosures default)")
    top_k: int = Field(5, ge=1, description="closures asked of the peer per query (at least the query's k)")
    local_map: bool = Field(
        False, description="accumulate scans into local maps as the authors' pipeline does"
    )
    local_map_distance: float = Field(
        100.0,
        gt=0,
        description="m from a local map's first scan that closes it (authors: KISS-ICP max_range)",
    )
    odometry: Literal["given", "kiss-icp"] = Field(
        "given",
        description="local-map poses: those given to add, or KISS-ICP run on the scans (the authors')",
    )


def closure_to_scan(
    T_b_a: np.ndarray, M_a: np.ndarray, P_query: np.ndarray, M_b: np.ndarray, poses_b: np.ndarray
) -> tuple[int, np.ndarray]:
    """A local-map closure as a scan match (module docstring, "Local maps"): the index ``j`` into ``poses_b`` (world
    poses of local map ``b``'s scans) nearest to where ``T_b_a`` puts the query scan, and ``T_match_query``."""
    X = T_b_a @ np.linalg.inv(M_a) @ P_query
    R = np.linalg.inv(M_b)[None] @ np.asarray(poses_b, np.float64).reshape(-1, 4, 4)
    j = int(np.argmin(np.linalg.norm(R[:, :3, 3] - X[:3, 3], axis=1)))
    return j, np.linalg.inv(R[j]) @ X


@dataclass
class _LocalMap:
    """A local map's scans: ids and world poses; ``origin`` is its first scan's pose (the map frame)."""

    origin: np.ndarray
    ids: list[int] = field(default_factory=list)
    poses: list[np.ndarray] = field(default_factory=list)


class MapClosuresPeer(Recognizer[MapClosuresParams]):
    """`placerec.types.PlaceRecognizer` over ``map_closures.MapClosures`` (optional extra ``peers``)."""

    name: ClassVar[str] = "map-closures"
    Params: ClassVar[type[Params]] = MapClosuresParams
    cache_descriptions: ClassVar[bool] = False

    def __init__(self, params: MapClosuresParams | Mapping[str, Any] | None = None, **overrides: Any) -> None:
        super().__init__(params, **overrides)
        try:
            from map_closures.config import MapClosuresConfig
            from map_closures.map_closures import MapClosures
        except ImportError as exc:
            raise DependencyError(
                f"the map-closures peer needs the 'map-closures' package (pip install 'placerec[peers]'): {exc}"
            ) from exc
        cfg = self.params.model_dump(exclude={"top_k", "local_map", "local_map_distance", "odometry"})
        self._new_peer = lambda: MapClosures(MapClosuresConfig(**cfg))
        self._reset()

    def _reset(self) -> None:
        self._peer = self._new_peer()
        # what the peer stores, by its id (scan ids; local-map indices in local-map mode), in insertion order
        self._points: dict[int, np.ndarray] = {}
        self._pending: tuple[int, np.ndarray] | None = None
        # local-map mode
        self._maps: list[_LocalMap] = []
        self._current: _LocalMap | None = None
        self._voxel: Any = None
        self._added: set[int] = set()
        self._history: list[np.ndarray] = []
        self._pending_scan: int | None = None
        self._odometry: Any = None
        self._odometry_pending: tuple[int, np.ndarray] | None = None
        if self.params.local_map:
            from map_closures.voxel_map import VoxelMap

            p = self.params
            self._voxel = VoxelMap(p.density_map_resolution, p.local_map_distance)
            self._new_voxel = lambda: VoxelMap(p.density_map_resolution, p.local_map_distance)
            if p.odometry == "kiss-icp":
                from placerec.slam.odometry import KissIcpOdometry

                self._odometry = KissIcpOdometry()  # the authors' settings: max range 100 m, voxel 1 m

    def __len__(self) -> int:
        return len(self._added) if self.params.local_map else len(self._points)

    @property
    def frontend_key(self) -> str:
        return params_key(self.name, {"points": "valid"})

    def describe(self, scan: Scan) -> Description:
        """The scan's valid points, (N, 3) float64; `ScanDataError` when too few are valid."""
        ok = require_points(scan, self.name)
        return {"points": np.ascontiguousarray(scan.xyz[ok], dtype=np.float64)}

    @staticmethod
    def _unwrap(description: Description) -> np.ndarray:
        pts = np.asarray(description["points"], dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ScanDataError(f"map-closures: points must have shape (N, 3), got {pts.shape}")
        return np.ascontiguousarray(pts)

    def _rollback(self) -> None:
        """Drop a tentative insertion by rebuilding the peer from the added scans (in insertion order)."""
        if self._pending is None:
            return
        self._pending = None
        self._peer = self._new_peer()
        for sid, pts in self._points.items():
            self._peer.get_top_k_closures(sid, pts, 1)

    def add_description(self, scan_id: int, description: Description, pose: np.ndarray | None = None) -> None:
        sid, pts = int(scan_id), self._unwrap(description)
        if self.params.local_map:
            self._add_local(sid, pts, pose)
            return
        if sid in self._points:
            raise ScanDataError(f"map-closures: id {sid} was added already")
        pending, self._pending = self._pending, None
        if pending is None or pending[0] != sid or not np.array_equal(pending[1], pts):
            self._pending = pending
            self._rollback()
            self._peer.get_top_k_closures(sid, pts, 1)
        self._points[sid] = pts

    def query_description(
        self,
        description: Description,
        k: int = 1,
        max_id: int | None = None,
        query_id: int = -1,
        prior: MotionPrior | None = None,
    ) -> list[Candidate]:
        pts = self._unwrap(description)
        if self.params.local_map:
            return self._query_local(pts, k, max_id, int(query_id))
        self._rollback()
        if not self._points:
            return []
        qid = int(query_id)
        if qid < 0 or qid in self._points:  # an id the peer has not stored, past its skipped recent maps
            qid = max(self._points) + 1 + _PEER_SKIP
        closures = list(self._peer.get_top_k_closures(qid, pts, max(k, self.params.top_k)))
        self._pending = (qid, pts)
        out = []
        for c in closures:
            match = int(c.source_id) if int(c.target_id) == qid else int(c.target_id)
            if match == qid or match not in self._points or (max_id is not None and match > max_id):
                continue
            T_query_match = np.asarray(c.pose, dtype=np.float64)
            out.append(
                Candidate(
                    query_id=int(query_id),
                    match_id=match,
                    score=float(c.number_of_inliers),
                    relative_pose=np.linalg.inv(T_query_match),
                    inliers=int(c.number_of_inliers),
                )
            )
        out.sort(key=lambda c: (-c.score, c.match_id))
        return out[:k]

    def save(self, path: str | Path) -> None:
        """The added scans' points (insertion order) with the parameters; a `ConfigError` in local-map mode."""
        self._no_local_map_artifacts()
        ids = list(self._points)
        arrays = {
            "ids": np.asarray(ids, np.int64),
            "counts": np.asarray([self._points[i].shape[0] for i in ids], np.int64),
            "points": np.concatenate([self._points[i] for i in ids]) if ids else np.zeros((0, 3)),
        }
        save_artifact(path, _KIND, _VERSION, arrays, {"params": self.params.saved_dump()})

    def load(self, path: str | Path) -> None:
        self._no_local_map_artifacts()
        arrays, header = load_artifact(path, _KIND, (_VERSION,), _SCHEMA)
        check_saved_params(path, header, self.params)
        ids, counts, points = arrays["ids"], arrays["counts"], arrays["points"]
        check_unique(ids, path, "ids")
        check_counts(counts, points.shape[0], path, "counts")
        self._reset()
        offsets = np.r_[0, np.cumsum(counts)]
        for sid, a, b in zip(ids, offsets[:-1], offsets[1:], strict=True):
            self.add_description(int(sid), {"points": points[a:b]})

    # -- local-map mode ---------------------------------------------------------------------------------------
    def _no_local_map_artifacts(self) -> None:
        if self.params.local_map:
            raise ConfigError(
                "map-closures: local_map mode cannot be saved or loaded (its local map under construction and "
                "odometry state are not stored); use local_map: false"
            )

    def _scan_pose(self, sid: int, pts: np.ndarray, pose: np.ndarray | None) -> np.ndarray:
        """The pose of an added scan: KISS-ICP's (registered at its query, or now) or the one given."""
        if self._odometry is not None:
            pending, self._odometry_pending = self._odometry_pending, None
            if pending is not None:
                if pending[0] != sid:
                    raise ScanDataError(
                        f"map-closures: local-map mode with KISS-ICP registered query {pending[0]} but scan {sid} "
                        "was added: it needs the loop-closure order (query scan i, then add scan i)"
                    )
                return pending[1]
            return self._odometry.register(Scan(pts.astype(np.float32), np.zeros(len(pts), np.float32)))
        if pose is None:
            raise ScanDataError(
                f"map-closures: local_map with odometry 'given' needs the pose of every added scan (scan {sid})"
            )
        return np.asarray(pose, np.float64)

    def _add_local(self, sid: int, pts: np.ndarray, pose: np.ndarray | None) -> None:
        if sid in self._added:
            raise ScanDataError(f"map-closures: id {sid} was added already")
        P = self._scan_pose(sid, pts, pose)
        self._added.add(sid)
        self._history = [*self._history[-1:], P]
        pending_scan, self._pending_scan = self._pending_scan, None
        if self._current is None:
            self._current = _LocalMap(P, [sid], [P])
            self._voxel.integrate_frame(pts, np.eye(4))
            self._rollback()
            return
        M = self._current.origin
        rel = np.linalg.inv(M) @ P
        self._voxel.integrate_frame(pts, rel)
        self._current.ids.append(sid)
        self._current.poses.append(P)
        if np.linalg.norm(rel[:3, 3]) <= self.params.local_map_distance:
            self._rollback()  # a query predicted that this scan closes the map; it does not
            return
        a = len(self._maps)
        if self._pending is not None and pending_scan == sid and self._pending[0] == a:
            local = self._pending[1]  # the map the query handed to the peer is kept
            self._pending = None
        else:
            self._rollback()
            local = self._voxel.point_cloud()
            self._peer.get_top_k_closures(a, local, 1)
        self._points[a] = local
        self._maps.append(self._current)
        # as the authors' pipeline: keep the points near the closing scan, in its frame, for the next local map
        self._voxel.remove_far_away_points(rel[:3, 3])
        kept = self._voxel.point_cloud()
        self._voxel.clear()
        self._voxel.integrate_frame(kept, np.linalg.inv(P) @ M)
        self._current = _LocalMap(P, [sid], [P])

    def _query_pose(self, qid: int, pts: np.ndarray) -> np.ndarray | None:
        if self._odometry is not None:
            if self._odometry_pending is not None:
                raise ScanDataError(
                    f"map-closures: local-map mode with KISS-ICP got query {qid} before scan "
                    f"{self._odometry_pending[0]} was added (it needs: query scan i, then add scan i)"
                )
            P = self._odometry.register(Scan(pts.astype(np.float32), np.zeros(len(pts), np.float32)))
            self._odometry_pending = (qid, P)
            return P
        if not self._history:
            return None
        if len(self._history) == 1:
            return self._history[-1]
        prev, last = self._history
        return last @ np.linalg.inv(prev) @ last  # constant velocity

    def _query_local(self, pts: np.ndarray, k: int, max_id: int | None, qid: int) -> list[Candidate]:
        if qid < 0 or qid in self._added:
            raise ScanDataError(
                f"map-closures: local-map mode answers the loop-closure order (query scan i with query_id i, then "
                f"add it); query_id {qid} is {'missing' if qid < 0 else 'already added'}"
            )
        self._rollback()
        P = self._query_pose(qid, pts)
        if P is None or self._current is None:
            return []
        M_a = self._current.origin
        rel = np.linalg.inv(M_a) @ P
        if np.linalg.norm(rel[:3, 3]) <= self.params.local_map_distance:
            return []  # this scan does not close a local map: the peer is not asked
        tmp = self._new_voxel()
        tmp.add_points(self._voxel.point_cloud())
        tmp.integrate_frame(pts, rel)
        local = tmp.point_cloud()
        a = len(self._maps)
        closures = list(self._peer.get_top_k_closures(a, local, max(k, self.params.top_k)))
        self._pending, self._pending_scan = (a, local), qid
        out = []
        for c in closures:
            src, tgt = int(c.source_id), int(c.target_id)
            b = src if tgt == a else tgt
            if b == a or not 0 <= b < a or (max_id is not None and self._maps[b].ids[-1] > max_id):
                continue
            T = np.asarray(c.pose, dtype=np.float64)
            T_b_a = np.linalg.inv(T) if tgt == a else T
            mb = self._maps[b]
            j, T_match_query = closure_to_scan(T_b_a, M_a, P, mb.origin, np.stack(mb.poses))
            extra = {"local_map": b, "query_map": a, "T_b_a": T_b_a}
            n = int(c.number_of_inliers)
            out.append(Candidate(qid, int(mb.ids[j]), float(n), T_match_query, n, extra))
        out.sort(key=lambda c: (-c.score, c.match_id))
        return out[:k]
