"""Ground truth that judges a 6-DoF loop closure by its pose, not by the distance between the two scans.

What a pose graph needs from a loop closure is a correct relative pose. The distance-only ground truth
(`placerec.eval.ground_truth`) calls a verified closure between scans 6 m apart false even when its pose is right to
centimetres, and calls a closure within 5 m true whatever its pose. Here:

* **revisit**: a query is a revisit when an eligible scan (`placerec.eval.exclusion.ExclusionWindow`) overlaps it
  by at least ``min_overlap`` (50 %). The overlap of two scans is that of their occupied voxels in the world frame
  (ground-truth poses), ``|V_q & V_m| / min(|V_q|, |V_m|)``, over the points within ``max_range`` (50 m) of each
  sensor, at ``voxel`` metres (1 m; `scan_voxels`). On the tuning sequences (town, seed 0) two scans overlap by
  50 % up to about 7.5-10 m apart with a VLP-16 and 15-20 m with an OS1-128 (docs/protocol.md). A query for which
  the pipeline returned a correct pose (below) is a revisit too, whatever the overlap: a correct registration shows
  that the two scans share enough, and a correct closure must never count against recall or precision (the report
  takes the union over every pipeline of a run, so that they share one revisit set);
* **true closure**: a candidate (query, match) with a 6-DoF relative pose ``T_match_query`` within
  ``max_translation`` (0.5 m) and ``max_rotation_deg`` (2 deg) of the true one, the match eligible, whatever the
  distance. A candidate without a pose is never a true closure here.

`PoseGroundTruth` has the interface `placerec.eval.metrics.loop_metrics` reads (``max_eligible``, ``is_revisit``,
``is_true_match``, ``len``), so precision, recall, max F1 and the rest follow the one definition of
`placerec.eval.metrics` with this truth in place of the distance one.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from placerec.errors import ScanDataError
from placerec.eval.exclusion import ExclusionWindow
from placerec.eval.pose_error import full_pose_mask, pose_errors

__all__ = [
    "overlap_directions",
    "PoseTruthSettings",
    "scan_voxels",
    "overlap_revisits",
    "PoseGroundTruth",
    "overlap_truth",
    "correct_candidates",
    "with_candidates",
    "relative_truth",
]

_KEY_BITS = 21  # bits per voxel coordinate in a key: +-1M voxels (+-1000 km at 1 m)
_KEY_OFFSET = 1 << (_KEY_BITS - 1)


@dataclass(frozen=True)
class PoseTruthSettings:
    """The tolerances of the pose ground truth (module docstring)."""

    max_translation: float = 0.5
    max_rotation_deg: float = 2.0
    min_overlap: float = 0.5
    voxel: float = 1.0
    max_range: float = 50.0
    search_radius: float = 40.0

    def __post_init__(self) -> None:
        for name in ("max_translation", "max_rotation_deg", "voxel", "max_range", "search_radius"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ScanDataError(f"pose ground truth: {name} must be finite and > 0, got {value}")
        if not 0 < self.min_overlap <= 1:
            raise ScanDataError(f"pose ground truth: min_overlap must lie in (0, 1], got {self.min_overlap}")


def scan_voxels(points: np.ndarray, pose: np.ndarray, settings: PoseTruthSettings) -> np.ndarray:
    """Sorted unique int64 keys of the world-frame voxels occupied by a scan's points (sensor frame, (N, 3)) within
    ``settings.max_range`` of the sensor, placed by ``pose`` (``T_world_sensor``); non-finite points are ignored."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    with np.errstate(invalid="ignore"):
        r = np.linalg.norm(p, axis=1)
        p = p[np.isfinite(r) & (r > 1e-6) & (r <= settings.max_range)]
    T = np.asarray(pose, dtype=np.float64)
    world = p @ T[:3, :3].T + T[:3, 3]
    cells = np.floor(world / settings.voxel).astype(np.int64) + _KEY_OFFSET
    if cells.size and (cells.min() < 0 or cells.max() >= (1 << _KEY_BITS)):
        raise ScanDataError("pose ground truth: points lie too far from the origin for the voxel keys")
    keys = (cells[:, 0] << (2 * _KEY_BITS)) | (cells[:, 1] << _KEY_BITS) | cells[:, 2]
    return np.unique(keys)


def _overlap(a: np.ndarray, b: np.ndarray) -> float:
    if a.size == 0 or b.size == 0:
        return 0.0
    return float(np.intersect1d(a, b, assume_unique=True).size / min(a.size, b.size))


def overlap_revisits(
    voxels: Sequence[np.ndarray],
    positions: np.ndarray,
    max_eligible: np.ndarray,
    settings: PoseTruthSettings,
) -> tuple[np.ndarray, np.ndarray]:
    """(is_revisit (N,) bool, best_overlap (N,) float): whether each scan overlaps an eligible one by at least
    ``settings.min_overlap``, and the largest overlap found (0 with nothing eligible within the search radius).

    Only eligible scans within ``settings.search_radius`` of the query are compared, nearest first; the search
    for a query stops at the first one that overlaps enough."""
    n = len(voxels)
    pos = np.asarray(positions, dtype=np.float64).reshape(n, 3)
    best = np.zeros(n)
    revisit = np.zeros(n, dtype=bool)
    if n == 0:
        return revisit, best
    tree = cKDTree(pos)
    for q in np.flatnonzero(np.asarray(max_eligible) >= 0).tolist():
        near = np.asarray(tree.query_ball_point(pos[q], settings.search_radius), dtype=np.int64)
        near = near[near <= max_eligible[q]]
        near = near[np.argsort(np.linalg.norm(pos[near] - pos[q], axis=1), kind="stable")]
        for m in near.tolist():
            o = _overlap(voxels[q], voxels[m])
            best[q] = max(best[q], o)
            if o >= settings.min_overlap:
                revisit[q] = True
                break
    return revisit, best


def overlap_directions(
    voxels: Sequence[np.ndarray],
    poses: np.ndarray,
    truth: PoseGroundTruth,
    reverse_yaw_deg: float = 90.0,
    closed_by: dict[int, int] | None = None,
) -> np.ndarray:
    """(N,) per scan: 0 not a revisit of ``truth``, 1 driven the same way, 2 the other way. A revisit is driven the
    same way when an eligible scan whose heading is within ``reverse_yaw_deg`` of the query's overlaps it by at
    least ``min_overlap`` (searched as `overlap_revisits` does: within ``search_radius``, nearest first), the other
    way when only scans heading further off do. A revisit that no scan overlaps enough (one a correct closure
    made, `with_candidates`) takes the direction of that closure's match in ``closed_by`` (query -> match)."""
    s = truth.settings
    P = np.asarray(poses, dtype=np.float64)
    n = P.shape[0]
    out = np.zeros(n, dtype=np.int8)
    if n == 0:
        return out
    pos = P[:, :3, 3]
    yaw = np.arctan2(P[:, 1, 0], P[:, 0, 0])
    tree = cKDTree(pos)
    for q in np.flatnonzero(truth.is_revisit).tolist():
        near = np.asarray(tree.query_ball_point(pos[q], s.search_radius), dtype=np.int64)
        near = near[near <= truth.max_eligible[q]]
        near = near[np.argsort(np.linalg.norm(pos[near] - pos[q], axis=1), kind="stable")]
        turned = np.degrees(np.abs(np.angle(np.exp(1j * (yaw[near] - yaw[q])))))
        if any(
            _overlap(voxels[q], voxels[m]) >= s.min_overlap for m in near[turned <= reverse_yaw_deg].tolist()
        ):
            out[q] = 1
        elif truth.best_overlap[q] >= s.min_overlap or not closed_by or q not in closed_by:
            out[q] = 2
        else:
            m = closed_by[q]
            out[q] = 1 if np.degrees(abs(np.angle(np.exp(1j * (yaw[m] - yaw[q]))))) <= reverse_yaw_deg else 2
    return out


def relative_truth(poses: np.ndarray, query: np.ndarray, match: np.ndarray) -> np.ndarray:
    """(K, 4, 4) true ``T_match_query`` = ``inv(T_world_match) @ T_world_query`` for index arrays of one length."""
    P = np.asarray(poses, dtype=np.float64)
    Tm, Tq = P[np.asarray(match)], P[np.asarray(query)]
    inv = np.zeros_like(Tm)
    Rt = np.transpose(Tm[:, :3, :3], (0, 2, 1))
    inv[:, :3, :3] = Rt
    inv[:, :3, 3] = -np.einsum("kij,kj->ki", Rt, Tm[:, :3, 3])
    inv[:, 3, 3] = 1.0
    return inv @ Tq


@dataclass(frozen=True, eq=False)
class PoseGroundTruth:
    """The pose ground truth of one sequence and one pipeline's candidates (module docstring).

    ``is_revisit`` (N,) and ``best_overlap`` (N,) come from the scans' overlap; ``max_eligible`` (N,) from the
    exclusion window; ``correct_keys`` are the sorted ``query * N + match`` of the candidates whose pose is right.
    """

    max_eligible: np.ndarray
    is_revisit: np.ndarray
    best_overlap: np.ndarray
    correct_keys: np.ndarray
    settings: PoseTruthSettings
    #: (N,) per scan 0 not a revisit, 1 driven the same way, 2 the other way (`overlap_directions`); None: not made
    direction: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.max_eligible.shape[0])

    @property
    def n_revisits(self) -> int:
        return int(self.is_revisit.sum())

    def is_true_match(self, query: Any, match: Any) -> np.ndarray:
        """Element-wise: is (query, match) a candidate whose relative pose was right (and the match eligible)?"""
        q, m = np.broadcast_arrays(np.asarray(query, dtype=np.int64), np.asarray(match, dtype=np.int64))
        n = len(self)
        if np.any((q < 0) | (q >= n)):
            raise ScanDataError(f"query indices must lie in [0, {n})")
        valid = (m >= 0) & (m < n)
        ok = valid & (np.where(valid, m, 0) <= self.max_eligible[q])
        return ok & np.isin(q * n + np.where(valid, m, 0), self.correct_keys)


def overlap_truth(
    voxels: Sequence[np.ndarray],
    poses: np.ndarray,
    exclusion: ExclusionWindow | None = None,
    timestamps: np.ndarray | None = None,
    settings: PoseTruthSettings | None = None,
    known: tuple[np.ndarray, np.ndarray] | None = None,
) -> PoseGroundTruth:
    """The revisits of a sequence by overlap (``voxels`` per scan from `scan_voxels`, ``poses`` (N, 4, 4)), with no
    candidate judged yet (`with_candidates` adds a pipeline's). ``known`` (is_revisit, best_overlap) from an earlier
    call on the same scans skips the overlap search, the costly part."""
    s = settings or PoseTruthSettings()
    P = np.asarray(poses, dtype=np.float64)
    n = P.shape[0]
    if len(voxels) != n:
        raise ScanDataError(f"pose ground truth: {len(voxels)} voxel sets for {n} poses")
    if not np.isfinite(P).all():
        raise ScanDataError("pose ground truth: poses contain NaN or inf")
    window = ExclusionWindow() if exclusion is None else exclusion
    max_eligible = window.sequence_bounds(n, timestamps, P[:, :3, 3])
    if known is not None and len(known[0]) == n:
        revisit, best = (np.asarray(a) for a in known)
    else:
        revisit, best = overlap_revisits(voxels, P[:, :3, 3], max_eligible, s)
    return PoseGroundTruth(max_eligible, revisit.astype(bool), best, np.zeros(0, dtype=np.int64), s)


def correct_candidates(
    truth: PoseGroundTruth,
    poses: np.ndarray,
    query_ids: np.ndarray,
    match_ids: np.ndarray,
    relative_poses: np.ndarray,
) -> np.ndarray:
    """Sorted keys ``query * N + match`` of the candidates whose ``T_match_query`` is within the tolerances of
    the true one and whose match is eligible: ``query_ids`` (Q,), ``match_ids`` (Q, K) (-1: none),
    ``relative_poses`` (Q, K, 4, 4) (NaN: no pose)."""
    s, n = truth.settings, len(truth)
    P = np.asarray(poses, dtype=np.float64)
    q = np.asarray(query_ids, dtype=np.int64).reshape(-1)
    m = np.asarray(match_ids, dtype=np.int64).reshape(q.size, -1)
    R = np.asarray(relative_poses, dtype=np.float64).reshape(q.size, m.shape[1], 4, 4)
    qq, mm, RR = np.repeat(q, m.shape[1]), m.reshape(-1), R.reshape(-1, 4, 4)
    has = (mm >= 0) & (mm < n) & full_pose_mask(RR)
    has[has] &= mm[has] <= truth.max_eligible[qq[has]]
    if not has.any():
        return np.zeros(0, dtype=np.int64)
    t_err, r_err = pose_errors(RR[has], relative_truth(P, qq[has], mm[has]))
    good = (t_err <= s.max_translation) & (r_err <= s.max_rotation_deg)
    return np.unique(qq[has][good] * n + mm[has][good])


def with_candidates(
    truth: PoseGroundTruth, keys: np.ndarray, closed: np.ndarray | None = None
) -> PoseGroundTruth:
    """``truth`` judging the candidates of ``keys`` (`correct_candidates`) as true; the queries ``closed`` (N,)
    bool, default those of ``keys``, become revisits too (a correct registration shows the scans overlap enough;
    pass the union over every pipeline of a run so that all share one revisit set)."""
    n = len(truth)
    if closed is None:
        closed = np.zeros(n, dtype=bool)
        closed[np.asarray(keys, dtype=np.int64) // max(n, 1)] = True
    return replace(truth, is_revisit=truth.is_revisit | closed, correct_keys=np.asarray(keys, dtype=np.int64))
