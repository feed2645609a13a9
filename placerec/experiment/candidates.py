"""The candidates file of a run: every candidate a pipeline returned, one row per (query, rank).

``candidates_<pipeline>.csv`` has the columns ``query_id,rank,match_id,score,inliers``: ``rank`` 1 is the best
candidate; ``inliers`` is empty when the pipeline does not count them. A query that got no candidate has one row
with ``rank`` 1, ``match_id`` -1 and an empty score, so every evaluated query is listed. Files written before
ranks were added (``query_id,match_id,score``, the top candidate only) are read as rank 1.
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from placerec.errors import ScanDataError, ScanFormatError
from placerec.io.atomic import atomic_write
from placerec.types import Candidate

__all__ = ["CandidateTable", "write_candidates", "read_candidates"]

COLUMNS = ("query_id", "rank", "match_id", "score", "inliers")
_REQUIRED = ("query_id", "match_id", "score")


@dataclass(frozen=True, eq=False)
class CandidateTable:
    """Candidates per query read back from a file: ``query_ids`` (Q,), and (Q, N) ``match_ids`` (-1 padded),
    ``scores`` (NaN padded), ``inliers`` (-1 where unknown or padded), columns in rank order."""

    query_ids: np.ndarray
    match_ids: np.ndarray
    scores: np.ndarray
    inliers: np.ndarray

    @classmethod
    def from_candidates(
        cls, query_ids: Sequence[int], candidates: Sequence[list[Candidate]]
    ) -> CandidateTable:
        """The table of a run's candidate lists (best first), as `read_candidates` gives it back."""
        n = max((len(c) for c in candidates), default=1) or 1
        match = np.full((len(candidates), n), -1, dtype=np.int64)
        score = np.full((len(candidates), n), np.nan)
        inliers = np.full((len(candidates), n), -1, dtype=np.int64)
        for row, cands in enumerate(candidates):
            for rank, c in enumerate(cands):
                match[row, rank], score[row, rank] = c.match_id, c.score
                inliers[row, rank] = -1 if c.inliers is None else c.inliers
        return cls(np.asarray(query_ids, dtype=np.int64), match, score, inliers)

    def top1(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(query_ids, match_ids, scores) of the best candidate (-1 / NaN where none)."""
        return self.query_ids, self.match_ids[:, 0], self.scores[:, 0]

    def topn(self, n: int) -> np.ndarray:
        """(Q, n) match ids of the first ``n`` ranks, -1 padded."""
        out = np.full((self.match_ids.shape[0], n), -1, dtype=np.int64)
        width = min(n, self.match_ids.shape[1])
        out[:, :width] = self.match_ids[:, :width]
        return out


def write_candidates(
    path: str | Path, query_ids: Sequence[int], candidates: Sequence[list[Candidate]]
) -> None:
    """Write every query's candidates (best first), atomically."""
    if len(query_ids) != len(candidates):
        raise ScanDataError(f"{path}: {len(query_ids)} query ids for {len(candidates)} candidate lists")
    with atomic_write(Path(path), "w") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(COLUMNS)
        for qid, cands in zip(query_ids, candidates, strict=True):
            if not cands:
                w.writerow([int(qid), 1, -1, "", ""])
            for rank, c in enumerate(cands, start=1):
                inliers = "" if c.inliers is None else int(c.inliers)
                w.writerow([int(qid), rank, int(c.match_id), repr(float(c.score)), inliers])


def _int(path: Path, line: int, key: str, text: str | None) -> int:
    try:
        return int(text)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ScanFormatError(f"{path}, line {line}: {key} must be an integer, got {text!r:.40}") from None


def read_candidates(path: str | Path) -> CandidateTable:
    """Read a ``candidates_<pipeline>.csv`` (format in the module docstring); `ScanFormatError` on a malformed
    file, naming the file, the line and what was expected."""
    path = Path(path)
    if not path.is_file():
        raise ScanFormatError(f"{path}: candidates file not found")
    rows: dict[int, list[tuple[int, int, float, int]]] = {}
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
            m = _int(path, line, "match_id", r["match_id"])
            inl = _int(path, line, "inliers", r["inliers"]) if r.get("inliers") else -1
            try:
                s = float(r["score"]) if r["score"] else np.nan
            except ValueError:
                raise ScanFormatError(
                    f"{path}, line {line}: score must be a number, got {r['score']!r:.40}"
                ) from None
            ranks = rows.setdefault(q, [])
            if rank != len(ranks) + 1:
                raise ScanFormatError(
                    f"{path}, line {line}: query {q} has rank {rank} after {len(ranks)} row(s); "
                    "expected its ranks 1, 2, ... in consecutive rows"
                )
            if (m < 0) != np.isnan(s) or (m < 0 and rank != 1):
                raise ScanFormatError(
                    f"{path}, line {line}: expected a match id >= 0 with a score, or a single row with -1 and no score"
                )
            ranks.append((rank, m, s, inl))
    n = max((len(v) for v in rows.values()), default=1)
    q_ids = np.fromiter(rows, dtype=np.int64, count=len(rows))
    match = np.full((q_ids.size, n), -1, dtype=np.int64)
    score = np.full((q_ids.size, n), np.nan)
    inliers = np.full((q_ids.size, n), -1, dtype=np.int64)
    for row, cands in enumerate(rows.values()):
        for rank, m, s, inl in cands:
            match[row, rank - 1], score[row, rank - 1], inliers[row, rank - 1] = m, s, inl
    return CandidateTable(q_ids, match, score, inliers)
