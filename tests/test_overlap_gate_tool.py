"""tools/eval_overlap_gate.py: a gated candidate is no answer, the best kept one answers; displacements are the
verified poses' translations; a test-split run is refused."""

from __future__ import annotations

import numpy as np
import pytest
from tool_modules import load_tool

from placerec.errors import ConfigError
from placerec.experiment.candidates import CandidateTable


def _tool():
    return load_tool("eval_overlap_gate")


def _table() -> CandidateTable:
    poses = np.full((2, 3, 4, 4), np.nan)
    for i, t in enumerate([(0.3, 0.4, 0.0), (3.0, 0.0, 4.0), (0.0, 0.0, 0.0)]):
        poses[0, i] = np.eye(4)
        poses[0, i, :3, 3] = t
    scores = np.array([[0.4, 0.3, 0.0], [np.nan, np.nan, np.nan]])
    return CandidateTable(
        query_ids=np.array([5, 6]),
        match_ids=np.array([[1, 2, 3], [-1, -1, -1]]),
        scores=scores,
        inliers=np.full((2, 3), 20),
        relative_poses=poses,
        verified_scores=scores,
        fitness=np.array([[0.3, 0.6, np.nan], [np.nan] * 3]),
        rmse=np.full((2, 3), 0.2),
        accepted=np.array([[1, 1, 0], [-1, -1, -1]], dtype=np.int8),
    )


def test_the_best_kept_candidate_answers_and_a_gated_one_is_no_answer():
    tool, t = _tool(), _table()
    np.testing.assert_allclose(tool.displacement(t)[0], [0.5, 5.0, 0.0])
    assert np.isnan(tool.displacement(t)[1]).all()
    m, s = tool.answers(t, np.ones((2, 3), bool))
    assert m.tolist() == [1, -1] and s[0] == 0.4 and np.isnan(s[1])
    gate = np.nan_to_num(t.fitness, nan=-1.0) >= 0.5  # the first candidate fails, the second answers
    m, s = tool.answers(t, gate)
    assert m.tolist() == [2, -1] and s[0] == 0.3
    m, _ = tool.answers(t, np.zeros((2, 3), bool))
    assert m.tolist() == [-1, -1]  # nothing kept: no answer, never the top candidate


def test_a_test_split_run_is_refused(tmp_path):
    (tmp_path / "config.yaml").write_text("split: test\npipelines: [{name: orb-dbow}]\n")
    with pytest.raises(ConfigError, match="tuning cells only"):
        _tool().load_cells(tmp_path, ["orb-dbow"])
