"""Adapter for the peer MapClosures (PyPI ``map-closures``, PRBonn), so it runs in placerec's evaluator.

MapClosures describes a *local map* by ORB features on its bird's-eye-view density image, retrieves with HBST and
verifies with RANSAC. This adapter feeds it **single scans** (each scan, as preprocessed by placerec, is one "local
map"); it does not build local maps from poses or odometry, so results are those of MapClosures on single scans,
which is how a per-scan place recognizer is compared. Document that when quoting numbers.

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
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from pydantic import Field

from placerec.errors import DependencyError, ScanDataError
from placerec.io.artifact_schema import Member, check_counts, check_unique
from placerec.io.atomic import load_artifact, save_artifact
from placerec.params import Params
from placerec.recognizer import Recognizer, check_saved_params, params_key, require_points
from placerec.types import Candidate, Description, Scan

__all__ = ["MapClosuresPeer", "MapClosuresParams"]

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


class MapClosuresPeer(Recognizer):
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
        cfg = self.params.model_dump(exclude={"top_k"})
        self._new_peer = lambda: MapClosures(MapClosuresConfig(**cfg))
        self._reset()

    def _reset(self) -> None:
        self._peer = self._new_peer()
        self._points: dict[int, np.ndarray] = {}
        self._pending: tuple[int, np.ndarray] | None = None

    def __len__(self) -> int:
        return len(self._points)

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
        if sid in self._points:
            raise ScanDataError(f"map-closures: id {sid} was added already")
        pending, self._pending = self._pending, None
        if pending is None or pending[0] != sid or not np.array_equal(pending[1], pts):
            self._pending = pending
            self._rollback()
            self._peer.get_top_k_closures(sid, pts, 1)
        self._points[sid] = pts

    def query_description(
        self, description: Description, k: int = 1, max_id: int | None = None, query_id: int = -1
    ) -> list[Candidate]:
        pts = self._unwrap(description)
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
        """The added scans' points (insertion order) with the parameters."""
        ids = list(self._points)
        arrays = {
            "ids": np.asarray(ids, np.int64),
            "counts": np.asarray([self._points[i].shape[0] for i in ids], np.int64),
            "points": np.concatenate([self._points[i] for i in ids]) if ids else np.zeros((0, 3)),
        }
        save_artifact(path, _KIND, _VERSION, arrays, {"params": self.params.model_dump(mode="json")})

    def load(self, path: str | Path) -> None:
        arrays, header = load_artifact(path, _KIND, (_VERSION,), _SCHEMA)
        check_saved_params(path, header, self.params)
        ids, counts, points = arrays["ids"], arrays["counts"], arrays["points"]
        check_unique(ids, path, "ids")
        check_counts(counts, points.shape[0], path, "counts")
        self._reset()
        offsets = np.r_[0, np.cumsum(counts)]
        for sid, a, b in zip(ids, offsets[:-1], offsets[1:], strict=True):
            self.add_description(int(sid), {"points": points[a:b]})
