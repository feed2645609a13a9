"""The candidates file of a run: every candidate a pipeline returned, one row per (query, rank).

``candidates_<pipeline>.csv`` has the columns::

    query_id,rank,match_id,score,inliers,x,y,z,roll,pitch,yaw,verified_score,fitness,rmse,accepted

* ``rank`` 1 is the best candidate; a query that got no candidate has one row with ``rank`` 1, ``match_id`` -1
  and empty fields after it, so every evaluated query is listed.
* ``inliers``: the supporting correspondences (`placerec.types.Candidate.inliers`), empty when not counted.
* ``x,y,z,roll,pitch,yaw``: the candidate's ``relative_pose`` ``T_match_query``: translation in metres and the
  rotation ``R = Rz(yaw) Ry(pitch) Rx(roll)`` in degrees (fixed axes x, then y, then z); empty without a pose.
  Six readable numbers rather than the twelve of the 3x4 matrix; they round-trip to ~1e-12.
* ``verified_score``, ``fitness``, ``rmse`` (m), ``accepted`` (1/0): the geometric verification's statistics
  (``Candidate.verification`` and ``Candidate.accepted``, `placerec.verify.candidates`); empty for a pipeline
  that does not verify, or a statistic that was not computed (``fitness`` of a candidate rejected before ICP).

Files of earlier runs still read: without ``rank`` (``query_id,match_id,score``, the top candidate only) as rank 1,
without the pose or verification columns as unknown.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from placerec.errors import ScanDataError, ScanFormatError
from placerec.io.atomic import atomic_write
from placerec.types import Candidate, as_pose

__all__ = [
    "CandidateTable",
    "write_candidates",
    "read_candidates",
    "pose_to_xyzrpy",
    "poses_to_xyzrpy",
    "xyzrpy_to_pose",
]

POSE_COLUMNS = ("x", "y", "z", "roll", "pitch", "yaw")
VERIFY_COLUMNS = ("verified_score", "fitness", "rmse")
COLUMNS = ("query_id", "rank", "match_id", "score", "inliers", *POSE_COLUMNS, *VERIFY_COLUMNS, "accepted")
_REQUIRED = ("query_id", "match_id", "score")


def pose_to_xyzrpy(T: np.ndarray) -> np.ndarray:
    """(x, y, z, roll, pitch, yaw) of a 4x4 pose: metres and degrees, ``R = Rz(yaw) Ry(pitch) Rx(roll)``."""
    return poses_to_xyzrpy(as_pose(T)[None])[0]


def poses_to_xyzrpy(P: np.ndarray) -> np.ndarray:
    """`pose_to_xyzrpy` of (N, 4, 4) rigid poses at once: (N, 6)."""
    from scipy.spatial.transform import Rotation

    P = np.asarray(P, dtype=np.float64).reshape(-1, 4, 4)
    if P.shape[0] == 0:
        return np.zeros((0, 6))
    return np.concatenate([P[:, :3, 3], Rotation.from_matrix(P[:, :3, :3]).as_euler("xyz", degrees=True)], 1)


def xyzrpy_to_pose(v: Sequence[float] | np.ndarray) -> np.ndarray:
    """The 4x4 pose of (x, y, z, roll, pitch, yaw) (inverse of `pose_to_xyzrpy`)."""
    from scipy.spatial.transform import Rotation

    v = np.asarray(v, dtype=np.float64)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", v[3:6], degrees=True).as_matrix()
    T[:3, 3] = v[:3]
    return T


@dataclass(frozen=True)
class _Row:
    """One candidate as the file holds it (NaN / -1 / None where unknown)."""

    match_id: int
    score: float
    inliers: int = -1
    pose: np.ndarray | None = None
    verified_score: float = math.nan
    fitness: float = math.nan
    rmse: float = math.nan
    accepted: int = -1

    @classmethod
    def of(cls, c: Candidate) -> _Row:
        v = c.verification.as_dict() if c.verification is not None else {}
        acc = c.accepted
        return cls(
            int(c.match_id),
            float(c.score),
            -1 if c.inliers is None else int(c.inliers),
            None if c.relative_pose is None else as_pose(c.relative_pose),
            verified_score=_float_or_nan(v.get("score")),
            fitness=_float_or_nan(v.get("fitness")),
            rmse=_float_or_nan(v.get("rmse")),
            accepted=-1 if acc is None else int(bool(acc)),
        )

    def cells(self, xyzrpy: np.ndarray | None) -> list[Any]:
        """The row's cells; ``xyzrpy``: `pose_to_xyzrpy` of its pose (None without one)."""
        pose = [""] * 6 if xyzrpy is None else [repr(float(x)) for x in xyzrpy]
        stats = [
            "" if math.isnan(x) else repr(float(x)) for x in (self.verified_score, self.fitness, self.rmse)
        ]
        return [
            self.match_id,
            repr(float(self.score)),
            "" if self.inliers < 0 else self.inliers,
            *pose,
            *stats,
            "" if self.accepted < 0 else self.accepted,
        ]


def _float_or_nan(x: Any) -> float:
    return math.nan if x is None else float(x)


@dataclass(frozen=True, eq=False)
class CandidateTable:
    """Candidates per query: ``query_ids`` (Q,), and per (query, rank), columns in rank order: ``match_ids``
    (Q, N) (-1 padded), ``scores`` (NaN padded), ``inliers`` (-1 where unknown or padded), ``relative_poses``
    (Q, N, 4, 4) ``T_match_query`` (NaN where none), ``verified_scores``, ``fitness``, ``rmse`` (NaN where
    unknown) and ``accepted`` (1, 0, or -1 where unknown)."""

    query_ids: np.ndarray
    match_ids: np.ndarray
    scores: np.ndarray
    inliers: np.ndarray
    relative_poses: np.ndarray
    verified_scores: np.ndarray
    fitness: np.ndarray
    rmse: np.ndarray
    accepted: np.ndarray

    @classmethod
    def from_candidates(
        cls, query_ids: Sequence[int], candidates: Sequence[list[Candidate]]
    ) -> CandidateTable:
        """The table of a run's candidate lists (best first), as `read_candidates` gives it back."""
        return _table(query_ids, [[_Row.of(c) for c in cands] for cands in candidates])

    def top1(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(query_ids, match_ids, scores) of the best candidate (-1 / NaN where none)."""
        return self.query_ids, self.match_ids[:, 0], self.scores[:, 0]

    def refused(self, refused: np.ndarray) -> CandidateTable:
        """The table with the (Q, N) ``refused`` candidates turned into rejected ones (score 0, ``accepted`` 0, the
        verification's rule for a gate, `placerec.verify.candidates`) and each query's ranks sorted again by
        score, accepted ones first on equal scores, the order kept otherwise."""
        refused = np.asarray(refused, dtype=bool) & (self.match_ids >= 0)
        scores = np.where(refused, 0.0, self.scores)
        accepted = np.where(refused, np.int8(0), self.accepted).astype(np.int8)
        order = rank_order(self.match_ids, scores, accepted)
        take = lambda a: np.take_along_axis(a, order.reshape(order.shape + (1,) * (a.ndim - 2)), 1)  # noqa: E731
        return CandidateTable(
            self.query_ids,
            take(self.match_ids),
            take(scores),
            take(self.inliers),
            take(self.relative_poses),
            take(self.verified_scores),
            take(self.fitness),
            take(self.rmse),
            take(accepted),
        )

    def topn(self, n: int) -> np.ndarray:
        """(Q, n) match ids of the first ``n`` ranks, -1 padded."""
        out = np.full((self.match_ids.shape[0], n), -1, dtype=np.int64)
        width = min(n, self.match_ids.shape[1])
        out[:, :width] = self.match_ids[:, :width]
        return out


def rank_order(match_ids: np.ndarray, scores: np.ndarray, accepted: np.ndarray) -> np.ndarray:
    """Per row (the last axis: one query's candidates), the ranks sorted by score, accepted ones first on equal
    scores, padding (``match_ids`` -1) last, the order kept otherwise."""
    primary = np.where(match_ids >= 0, -scores, np.inf)
    return np.lexsort((accepted != 1, primary), axis=-1)  # stable: equal keys keep their ranks


def _table(query_ids: Sequence[int], rows: Sequence[list[_Row]]) -> CandidateTable:
    q, n = len(rows), max((len(r) for r in rows), default=1) or 1
    match = np.full((q, n), -1, dtype=np.int64)
    inliers = np.full((q, n), -1, dtype=np.int64)
    accepted = np.full((q, n), -1, dtype=np.int8)
    score, vscore, fitness, rmse = (np.full((q, n), np.nan) for _ in range(4))
    poses = np.full((q, n, 4, 4), np.nan)
    for i, cands in enumerate(rows):
        for j, r in enumerate(cands):
            match[i, j], score[i, j], inliers[i, j], accepted[i, j] = (
                r.match_id,
                r.score,
                r.inliers,
                r.accepted,
            )
            vscore[i, j], fitness[i, j], rmse[i, j] = r.verified_score, r.fitness, r.rmse
            if r.pose is not None:
                poses[i, j] = r.pose
    ids = np.asarray(query_ids, dtype=np.int64).reshape(-1)
    return CandidateTable(ids, match, score, inliers, poses, vscore, fitness, rmse, accepted)


def write_candidates(
    path: str | Path, query_ids: Sequence[int], candidates: Sequence[list[Candidate]]
) -> None:
    """Write every query's candidates (best first), atomically."""
    if len(query_ids) != len(candidates):
        raise ScanDataError(f"{path}: {len(query_ids)} query ids for {len(candidates)} candidate lists")
    rows = [[_Row.of(c) for c in cands] for cands in candidates]
    posed = [r.pose for rs in rows for r in rs if r.pose is not None]
    angles = iter(poses_to_xyzrpy(np.asarray(posed)) if posed else ())  # all at once: 0.3 ms a pose alone
    with atomic_write(Path(path), "w") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(COLUMNS)
        for qid, rs in zip(query_ids, rows, strict=True):
            if not rs:
                w.writerow([int(qid), 1, -1] + [""] * (len(COLUMNS) - 3))
            for rank, r in enumerate(rs, start=1):
                w.writerow([int(qid), rank, *r.cells(None if r.pose is None else next(angles))])


def _int(path: Path, line: int, key: str, text: str | None) -> int:
    try:
        return int(text)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ScanFormatError(f"{path}, line {line}: {key} must be an integer, got {text!r:.40}") from None


def _float(path: Path, line: int, key: str, text: str | None) -> float:
    """A number, NaN for an empty or missing cell."""
    if not text:
        return math.nan
    try:
        return float(text)
    except ValueError:
        raise ScanFormatError(f"{path}, line {line}: {key} must be a number, got {text!r:.40}") from None


def _parse(path: Path, line: int, r: dict[str, str]) -> _Row:
    m = _int(path, line, "match_id", r["match_id"])
    pose_cells = [_float(path, line, k, r.get(k)) for k in POSE_COLUMNS]
    known = [not math.isnan(v) for v in pose_cells]
    if any(known) and not all(known):
        raise ScanFormatError(f"{path}, line {line}: give all of {','.join(POSE_COLUMNS)} or none")
    acc = r.get("accepted")
    if acc not in (None, "", "0", "1"):
        raise ScanFormatError(f"{path}, line {line}: accepted must be 1, 0 or empty, got {acc!r:.40}")
    return _Row(
        m,
        _float(path, line, "score", r["score"]),
        _int(path, line, "inliers", r["inliers"]) if r.get("inliers") else -1,
        xyzrpy_to_pose(pose_cells) if all(known) else None,
        verified_score=_float(path, line, "verified_score", r.get("verified_score")),
        fitness=_float(path, line, "fitness", r.get("fitness")),
        rmse=_float(path, line, "rmse", r.get("rmse")),
        accepted=int(acc) if acc else -1,
    )


def read_candidates(path: str | Path) -> CandidateTable:
    """Read a ``candidates_<pipeline>.csv`` (format in the module docstring); `ScanFormatError` on a malformed
    file, naming the file, the line and what was expected."""
    path = Path(path)
    if not path.is_file():
        raise ScanFormatError(f"{path}: candidates file not found")
    rows: dict[int, list[_Row]] = {}
    with path.open(encoding="utf-8", newline="") as fh:
        reader = csv.DictReader(fh)
        missing = [c for c in _REQUIRED if c not in (reader.fieldnames or [])]
        if missing:
            raise ScanFormatError(
                f"{path}: missing column(s) {missing}; expected the header {','.join(COLUMNS)}"
            )
        for line, r in enumerate(reader, start=2):
            q = _int(path, line, "query_id", r["query_id"])
            rank = _int(path, line, "rank", r["rank"]) if "rank" in r else 1
            row = _parse(path, line, r)
            ranks = rows.setdefault(q, [])
            if rank != len(ranks) + 1:
                raise ScanFormatError(
                    f"{path}, line {line}: query {q} has rank {rank} after {len(ranks)} row(s); "
                    "expected its ranks 1, 2, ... in consecutive rows"
                )
            if (row.match_id < 0) != math.isnan(row.score) or (row.match_id < 0 and rank != 1):
                raise ScanFormatError(
                    f"{path}, line {line}: expected a match id >= 0 with a score, or a single row with -1 and no score"
                )
            ranks.append(row)
    return _table(list(rows), list(rows.values()))
