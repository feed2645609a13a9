"""Loop-closure ground truth from poses: exclusion windows, revisits and true matches.

Conventions
-----------
* Scans are identified by their *index* in the pose array (acquisition order). The loop evaluator adds scan ``i``
  under id ``i``, so ids and indices coincide.
* **Eligibility**: `placerec.eval.exclusion.ExclusionWindow` (the rule the loop-closure detector applies too).
  A database scan ``j`` is eligible for query ``i`` when ``j <= max_eligible[i]`` (``-1`` = nothing eligible).
* A **true match** of query ``i`` is an eligible ``j`` whose position is within ``gt_distance`` of ``i``'s
  (3D Euclidean distance of the pose translations by default, xy only with ``planar=True``) and, when
  ``gt_yaw_deg`` is set, whose heading (yaw of the sensor x axis in the world frame) differs by at most that many
  degrees. A query is a **revisit** when it has at least one true match.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from placerec.errors import ScanDataError
from placerec.eval.exclusion import ExclusionWindow

log = logging.getLogger(__name__)

__all__ = [
    "positions_from_poses",
    "yaws_from_poses",
    "LoopGroundTruth",
    "loop_ground_truth",
]

_KNN_FIRST = 32  # neighbours tried per query before falling back to brute force over the eligible prefix
_CHUNK = 256  # queries per brute-force block


def _check_poses(poses: np.ndarray) -> np.ndarray:
    P = np.asarray(poses, dtype=np.float64)
    if P.ndim != 3 or P.shape[1:] != (4, 4):
        raise ScanDataError(f"poses must have shape (N, 4, 4), got {P.shape}")
    if not np.all(np.isfinite(P)):
        raise ScanDataError("poses contain NaN or inf")
    return P


def positions_from_poses(poses: np.ndarray) -> np.ndarray:
    """(N, 3) translations of (N, 4, 4) ``T_world_sensor`` poses."""
    return _check_poses(poses)[:, :3, 3].copy()


def yaws_from_poses(poses: np.ndarray) -> np.ndarray:
    """(N,) heading in radians: the angle of the sensor x axis projected on the world xy plane."""
    P = _check_poses(poses)
    return np.arctan2(P[:, 1, 0], P[:, 0, 0])


@dataclass(frozen=True, eq=False)
class LoopGroundTruth:
    """Ground truth of one sequence for loop mode (see the module docstring for the definitions).

    ``max_eligible`` (N,) int: largest eligible index per query (-1 = none). ``is_revisit`` (N,) bool.
    ``nearest_distance`` (N,) float: distance to the nearest eligible scan (inf when none; position only, the yaw
    limit does not apply), ``nearest_index`` (N,) int (-1 when none).
    """

    positions: np.ndarray
    yaws: np.ndarray
    max_eligible: np.ndarray
    is_revisit: np.ndarray
    nearest_distance: np.ndarray
    nearest_index: np.ndarray
    gt_distance: float
    gt_yaw_deg: float | None
    planar: bool

    def __len__(self) -> int:
        return int(self.positions.shape[0])

    @property
    def n_revisits(self) -> int:
        return int(self.is_revisit.sum())

    def _coords(self) -> np.ndarray:
        return self.positions[:, :2] if self.planar else self.positions

    def is_true_match(self, query: np.ndarray | int, match: np.ndarray | int) -> np.ndarray:
        """Element-wise: is ``match`` a true match of ``query``? (indices; ``match < 0`` or out of range -> False)."""
        q = np.asarray(query, dtype=np.int64)
        m = np.asarray(match, dtype=np.int64)
        q, m = np.broadcast_arrays(q, m)
        n = len(self)
        if np.any((q < 0) | (q >= n)):
            raise ScanDataError(
                f"query indices must lie in [0, {n}), got {q[(q < 0) | (q >= n)][:5].tolist()}"
            )
        valid = (m >= 0) & (m < n)
        mm = np.where(valid, m, 0)
        c = self._coords()
        ok = valid & (mm <= self.max_eligible[q])
        ok &= np.linalg.norm(c[q] - c[mm], axis=-1) <= self.gt_distance
        if self.gt_yaw_deg is not None:
            ok &= _yaw_diff_deg(self.yaws[q], self.yaws[mm]) <= self.gt_yaw_deg
        return ok

    def true_matches(self, query: int) -> np.ndarray:
        """Sorted indices of all true matches of one query."""
        q = int(query)
        if self.max_eligible[q] < 0:
            return np.zeros(0, dtype=np.int64)
        c = self._coords()
        prefix = c[: self.max_eligible[q] + 1]
        j = np.flatnonzero(np.linalg.norm(prefix - c[q], axis=1) <= self.gt_distance)
        if self.gt_yaw_deg is not None:
            j = j[_yaw_diff_deg(self.yaws[q], self.yaws[j]) <= self.gt_yaw_deg]
        return j.astype(np.int64)


def _yaw_diff_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = np.angle(np.exp(1j * (np.asarray(a) - np.asarray(b))))
    return np.degrees(np.abs(d))


def _nearest_eligible(coords: np.ndarray, max_eligible: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact nearest eligible neighbour per query: kNN on a KD-tree, brute force over the prefix if unresolved."""
    n = coords.shape[0]
    dist = np.full(n, np.inf)
    near = np.full(n, -1, dtype=np.int64)
    if n == 0:
        return dist, near
    tree = cKDTree(coords)
    k = min(_KNN_FIRST, n)
    d, j = tree.query(coords, k=k)
    d, j = d.reshape(n, k), j.reshape(n, k)
    eligible = j <= max_eligible[:, None]  # kNN sorted by distance: the first eligible one is the nearest
    first = np.argmax(eligible, axis=1)
    found = eligible[np.arange(n), first]
    dist[found] = d[found, first[found]]
    near[found] = j[found, first[found]]
    todo = np.flatnonzero(~found & (max_eligible >= 0))
    for start in range(0, todo.size, _CHUNK):
        qs = todo[start : start + _CHUNK]
        width = int(max_eligible[qs].max()) + 1
        D = np.linalg.norm(coords[qs, None, :] - coords[None, :width, :], axis=2)
        D[np.arange(width)[None, :] > max_eligible[qs, None]] = np.inf
        jj = np.argmin(D, axis=1)
        dist[qs] = D[np.arange(qs.size), jj]
        near[qs] = jj
    ok = near >= 0  # one distance formula everywhere, so is_revisit agrees with LoopGroundTruth.is_true_match
    dist[ok] = np.linalg.norm(coords[ok] - coords[near[ok]], axis=1)
    return dist, near


def loop_ground_truth(
    poses: np.ndarray,
    gt_distance: float = 5.0,
    gt_yaw_deg: float | None = None,
    planar: bool = False,
    exclusion: ExclusionWindow | None = None,
    timestamps: np.ndarray | None = None,
) -> LoopGroundTruth:
    """Revisits, true-match test and nearest eligible distance for every scan of a trajectory.

    ``poses`` (N, 4, 4) ``T_world_sensor``; ``exclusion`` the window (default `ExclusionWindow()`, 120 frames);
    ``timestamps`` (N,) are needed when it has a limit in seconds.
    Cost: one KD-tree kNN query for all scans plus brute force for the few whose 32 nearest are all too recent.
    """
    if not gt_distance > 0:
        raise ScanDataError(f"gt_distance must be > 0, got {gt_distance}")
    if gt_yaw_deg is not None and not gt_yaw_deg > 0:
        raise ScanDataError(f"gt_yaw_deg must be > 0 or None, got {gt_yaw_deg}")
    P = _check_poses(poses)
    positions = P[:, :3, 3].copy()
    yaws = np.arctan2(P[:, 1, 0], P[:, 0, 0])
    n = positions.shape[0]
    window = ExclusionWindow() if exclusion is None else exclusion
    max_eligible = window.sequence_bounds(n, timestamps, positions)
    coords = positions[:, :2] if planar else positions
    dist, near = _nearest_eligible(coords, max_eligible)
    is_revisit = dist <= gt_distance
    if gt_yaw_deg is not None and np.any(is_revisit):
        tree = cKDTree(coords)
        cand = np.flatnonzero(is_revisit)
        for i, js in zip(cand, tree.query_ball_point(coords[cand], gt_distance), strict=True):
            js = np.asarray(js, dtype=np.int64)
            js = js[js <= max_eligible[i]]
            is_revisit[i] = bool(np.any(_yaw_diff_deg(yaws[i], yaws[js]) <= gt_yaw_deg))
    log.debug("loop ground truth: %d scans, %d revisits within %.2f m", n, int(is_revisit.sum()), gt_distance)
    return LoopGroundTruth(
        positions=positions,
        yaws=yaws,
        max_eligible=max_eligible,
        is_revisit=is_revisit,
        nearest_distance=dist,
        nearest_index=near,
        gt_distance=float(gt_distance),
        gt_yaw_deg=None if gt_yaw_deg is None else float(gt_yaw_deg),
        planar=bool(planar),
    )
