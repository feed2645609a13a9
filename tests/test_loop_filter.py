"""DLoopDetector's islands and temporal consistency as the loop detector's filter (placerec.loop_filter)."""

from __future__ import annotations

import numpy as np
import pytest

from placerec.config import parse_config
from placerec.errors import ConfigError
from placerec.loop_closure import LoopClosureDetector
from placerec.loop_filter import LoopFilter, LoopFilterParams, compute_islands
from placerec.recognizer import Recognizer
from placerec.types import Candidate


def test_islands_group_close_ids():
    islands = compute_islands(
        np.array([10, 12, 13, 41, 40, 90]), np.array([0.5, 0.3, 0.3, 0.1, 0.05, 0.9]), 3, 1
    )
    assert [(i.first, i.last, i.best_id) for i in islands] == [(10, 13, 10), (40, 41, 41), (90, 90, 90)]
    assert islands[0].score == pytest.approx(1.1)
    assert len(compute_islands(np.array([10, 11, 40]), np.array([1.0, 1.0, 1.0]), 3, 2)) == 1


def _cands(query, ids, scores):
    return [
        Candidate(query, int(i), float(s), extra={"tag": (query, int(i))})
        for i, s in zip(ids, scores, strict=True)
    ]


def test_filter_keeps_each_islands_best_candidate_and_needs_temporal_consistency():
    lf = LoopFilter(LoopFilterParams(temporal_k=2))
    ids, scores = np.array([50, 51, 200]), np.array([0.2, 0.5, 0.6])
    got, status = lf.apply(300, _cands(300, ids, scores))
    assert status == "no_temporal_consistency" and got == [] and lf.islands[0].best_id == 51
    assert lf.apply(301, _cands(301, ids + 1, scores))[1] == "no_temporal_consistency"
    got, status = lf.apply(302, _cands(302, ids + 2, scores))
    # island 52-53 (0.7) beats island 202 (0.6); its representative is the candidate itself, pose and all
    assert status == "ok" and [c.match_id for c in got] == [53, 202] and got[0].extra["tag"] == (302, 53)
    # a jump to an unrelated island restarts the window
    assert lf.apply(303, _cands(303, [120], [0.3]))[1] == "no_temporal_consistency"
    # a gap of more than max_distance_between_queries queries restarts it too
    lf2 = LoopFilter(LoopFilterParams(temporal_k=1))
    lf2.apply(10, _cands(10, [5], [1.0]))
    assert lf2.apply(11, _cands(11, [6], [1.0]))[1] == "ok"
    lf2.apply(20, _cands(20, [7], [1.0]))
    assert lf2.apply(30, _cands(30, [8], [1.0]))[1] == "no_temporal_consistency"
    assert LoopFilter().apply(5, [])[1] == "no_candidates"
    assert LoopFilter(LoopFilterParams(min_matches_per_group=3)).apply(5, _cands(5, [1, 9], [1, 1]))[1] == (
        "no_groups"
    )


class _Echo(Recognizer):
    """Answers every query with the ids given to it, scores decreasing: the filter's input, fixed."""

    name = "echo"

    def __init__(self, answers):
        super().__init__()
        self.answers = answers
        self.asked_k = []

    def describe(self, scan):
        return {"x": np.zeros(1)}

    def add_description(self, scan_id, description, pose=None):
        pass

    def save(self, path):
        raise NotImplementedError

    def load(self, path):
        raise NotImplementedError

    def query_description(self, description, k=1, max_id=None, query_id=-1):
        self.asked_k.append(k)
        ids = [i for i in self.answers.get(query_id, []) if i <= max_id]
        return [Candidate(query_id, i, 1.0 - 0.01 * r) for r, i in enumerate(ids)][:k]


def test_detector_applies_the_filter_between_queries():
    rec = _Echo({3: [0, 1], 4: [1, 0], 5: [1, 2]})
    det = LoopClosureDetector(
        rec, threshold=0.5, exclusion_frames=2, loop_filter=LoopFilterParams(temporal_k=1, max_candidates=7)
    )
    out = [det.process(None, description={"x": np.zeros(1)}) for _ in range(6)]
    assert det.last_status == "ok" and max(rec.asked_k) == 7  # asks the filter's candidates
    assert out[3] == [] and [c.match_id for c in out[4]] == [1] and [c.match_id for c in out[5]] == [1]
    plain = LoopClosureDetector(_Echo({3: [0, 1]}), threshold=0.5, exclusion_frames=2)
    got = [plain.process(None, description={"x": np.zeros(1)}) for _ in range(4)]
    assert [c.match_id for c in got[3]] == [0]


def test_config_takes_a_loop_filter_per_pipeline():
    base = {"dataset": {"source": "simulator"}, "evaluation": {"mode": "loop"}}
    cfg = parse_config({**base, "pipelines": [{"name": "scan-context", "loop_filter": {"temporal_k": 3}}]})
    assert cfg.pipelines[0].loop_filter.temporal_k == 3
    with pytest.raises(ConfigError, match="loop_filter"):
        parse_config({**base, "pipelines": [{"name": "scan-context", "loop_filter": {"islands": True}}]})
