"""Adapter for the peer MapClosures (PyPI ``map-closures``, PRBonn), so it runs in placerec's evaluator.

MapClosures describes a *local map* by ORB features on its bird's-eye-view density image, retrieves with HBST and
verifies with RANSAC. This adapter feeds it **single scans** (each scan, as preprocessed by placerec, is one "local
map"); it does not build local maps from poses or odometry, so results are those of MapClosures on single scans,
which is how a per-scan place recognizer is compared. Document that when quoting numbers.

Protocol notes (the peer's API inserts while it queries):

* ``query(scan, query_id=i)`` calls the peer's ``get_top_k_closures(i, scan)``, which also inserts the scan under
  id ``i``; a following ``add(i, ...)`` with the same id is then a no-op. ``add`` of a new id inserts it. This
  is the one deviation from "query never modifies the database"; the evaluator's order (query, then add the same
  id) makes it harmless.
* Candidates whose match id is above ``max_id`` (inside the exclusion window) are dropped after the peer answers.
* ``score`` = number of RANSAC inliers; ``relative_pose`` = ``T_match_query``: the peer's ``pose`` maps the match's
  (``source_id``) points into the query's (``target_id``) frame, so it is inverted here (checked in the tests).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from placerec.errors import DependencyError, PlacerecError
from placerec.recognizer import coerce_params
from placerec.types import Candidate, Scan

__all__ = ["MapClosuresPeer", "MapClosuresParams"]


@dataclass(frozen=True)
class MapClosuresParams:
    """The peer's own settings (its defaults) plus how many candidates to ask for."""

    density_map_resolution: float = 0.5
    density_threshold: float = 0.05
    hamming_distance_threshold: int = 50
    inliers_threshold: int = 5
    top_k: int = 5


class MapClosuresPeer:
    """`placerec.types.PlaceRecognizer` over ``map_closures.MapClosures`` (optional extra ``peers``)."""

    name: ClassVar[str] = "map-closures"
    Params: ClassVar[type] = MapClosuresParams

    def __init__(self, params: MapClosuresParams | None = None, **overrides: Any) -> None:
        self.params = coerce_params(type(self), params, overrides)
        try:
            from map_closures.config import MapClosuresConfig
            from map_closures.map_closures import MapClosures
        except ImportError as exc:
            raise DependencyError(
                f"the map-closures peer needs the 'map-closures' package (pip install 'placerec[peers]'): {exc}"
            ) from exc
        cfg = {k: v for k, v in asdict(self.params).items() if k != "top_k"}
        self._peer = MapClosures(MapClosuresConfig(**cfg))
        self._inserted: set[int] = set()

    @classmethod
    def from_params(cls, params: dict[str, Any] | None = None) -> MapClosuresPeer:
        return cls(None, **(params or {}))

    @staticmethod
    def _points(scan: Scan) -> np.ndarray:
        xyz = scan.xyz[np.isfinite(scan.xyz).all(axis=1) & np.any(scan.xyz != 0, axis=1)]
        return np.ascontiguousarray(xyz, dtype=np.float64)

    def _insert(self, scan_id: int, scan: Scan) -> list[Any]:
        if scan_id in self._inserted:
            raise PlacerecError(f"map-closures: id {scan_id} was already inserted")
        self._inserted.add(scan_id)
        k = max(1, self.params.top_k)
        return list(self._peer.get_top_k_closures(int(scan_id), self._points(scan), k))

    def add(self, scan_id: int, scan: Scan, pose: np.ndarray | None = None) -> None:
        if scan_id not in self._inserted:
            self._insert(scan_id, scan)

    def query(self, scan: Scan, k: int = 1, max_id: int | None = None, query_id: int = -1) -> list[Candidate]:
        if query_id < 0:
            raise PlacerecError("map-closures: query needs the query_id the scan will be stored under")
        closures = self._insert(query_id, scan)
        out = []
        for c in closures:
            match = int(c.source_id) if int(c.target_id) == query_id else int(c.target_id)
            if match == query_id or (max_id is not None and match > max_id):
                continue
            T_query_match = np.asarray(c.pose, dtype=np.float64)
            out.append(
                Candidate(
                    query_id=query_id,
                    match_id=match,
                    score=float(c.number_of_inliers),
                    relative_pose=np.linalg.inv(T_query_match),
                    inliers=int(c.number_of_inliers),
                )
            )
        out.sort(key=lambda c: -c.score)
        return out[:k]

    def save(self, path: str | Path) -> None:
        raise PlacerecError("map-closures: the peer's database cannot be saved through placerec")

    def load(self, path: str | Path) -> None:
        raise PlacerecError("map-closures: the peer's database cannot be loaded through placerec")
