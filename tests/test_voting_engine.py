"""The shared query loop of the 3D voting pipelines (placerec.pipelines.voting_engine) and its plug-in interface:
a strategy written here, outside the package, runs through the same loop as the registered ones."""

from __future__ import annotations

import numpy as np
import pytest

from placerec.pipelines.keypoint_voting import KeypointVoting
from placerec.pipelines.voting_engine import Shortlist, VoteStrategy
from placerec.recognizer import make_pipeline
from placerec.three_d.descriptors import DESCRIPTOR_DIMS
from placerec.three_d.entries import EntryTable, far_from_all

DIM = DESCRIPTOR_DIMS["fpfh"]


class EvenEntries(VoteStrategy):
    """Consumes two keypoints a batch; once four are matched, shortlists the even entries, best the lowest."""

    stops_early = True

    def batch_size(self) -> int:
        return 2

    def vote(self, batch: np.ndarray) -> None:
        self.matched += batch.size

    def ready(self) -> Shortlist | None:
        if self.matched < 4:
            return None
        even = [e for e in range(len(self.rec.entries)) if e % 2 == 0 and self.query.eligible[e]]
        return Shortlist(even, score=lambda e: 1.0 / (1 + e), extra=lambda e: {"entry": e})


class EvenVoting(KeypointVoting):
    Strategy = EvenEntries


def _fill(rec: KeypointVoting, n: int = 6) -> None:
    rng = np.random.default_rng(0)
    for i in range(n):
        pose = np.eye(4)
        pose[0, 3] = 3.0 * i
        desc = {"keypoints": rng.normal(size=(8, 3)), "descriptors": rng.random((8, DIM), dtype=np.float32)}
        rec.add_description(10 + i, desc, pose)


def _query(n_keypoints: int = 6) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(1)
    return {
        "keypoints": rng.normal(size=(n_keypoints, 3)).astype(np.float32),
        "descriptors": rng.random((n_keypoints, DIM), dtype=np.float32),
    }


def test_a_strategy_from_outside_the_package_runs_through_the_shared_loop():
    rec = make_pipeline(
        "tests.test_voting_engine:EvenVoting",
        {"features": {"descriptor": "fpfh"}, "verify": {"enabled": False}},
    )
    _fill(rec)
    got = rec.query_description(_query(), k=2, query_id=99)
    # without verification the first shortlist answers: its best k, retrieval scores, no decision
    assert [c.match_id for c in got] == [10, 12] and [c.score for c in got] == [1.0, pytest.approx(1 / 3)]
    assert all(c.accepted is None and c.retrieval_score == c.score and c.query_id == 99 for c in got)
    assert got[0].extra == {
        "entry": 0,
        "keypoints_consumed": 4,
        "n_keypoints": 6,
        "match_ms": pytest.approx(got[0].extra["match_ms"]),
        "n_verified": 3,
        "early_stop": True,
    }
    # the exclusion bound: entries with id <= max_id only
    assert [c.match_id for c in rec.query_description(_query(), k=5, max_id=12)] == [10, 12]
    # no stop before the keypoints run out: nothing shortlisted, no fallback, no answer
    assert rec.query_description(_query(n_keypoints=3), k=2) == []


def test_ratio_votes_rank_by_votes_and_score_the_fraction():
    rec = KeypointVoting(features={"descriptor": "fpfh"}, verify={"enabled": False})
    _fill(rec)
    desc = rec.entries.store.rows(8, 16)  # entry 1's own descriptors: every one votes for it
    got = rec.query_description({"keypoints": np.zeros((8, 3), np.float32), "descriptors": desc}, k=3)
    assert got[0].match_id == 11 and got[0].score == 1.0 and got[0].extra["votes"] == 8
    assert got[0].extra["keypoints_consumed"] == 8 and "early_stop" not in got[0].extra


def test_the_entry_table_views_and_the_place_rule():
    table = EntryTable.empty(DIM)
    for i, x in ((5, 0.0), (7, 1.0), (6, 2.0)):
        pose = np.eye(4)
        pose[0, 3] = x
        table.append(i, pose, np.zeros((2, 3)), np.full((2, DIM), i, np.float32))
    rows, row_entry, n = table.eligible(6)  # ids out of order: a mask, not a prefix
    assert rows.shape[0] == 4 and row_entry.tolist() == [0, 0, 2, 2] and n == 3
    assert table.eligible_mask(6).tolist() == [True, False, True] and table.version == 3
    assert table.starts().tolist() == [0, 2, 4, 6] and table.xyz()[:, 0].tolist() == [0.0, 1.0, 2.0]
    assert far_from_all(table.xyz(), np.array([4.0, 0, 0]), 2.0)
    assert not far_from_all(table.xyz(), np.array([3.5, 0, 0]), 2.0) and far_from_all(np.zeros((0, 3)), 0, 1)
