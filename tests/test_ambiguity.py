"""The ambiguity rule of localisation (placerec.verify.ambiguity): an accepted answer is refused when another
accepted candidate placing the query elsewhere in the map scores nearly as well, never because of candidates that
agree with it; in the experiments' localize mode (`localize_estimates`) and in `placerec.Localizer`'s global search."""

from __future__ import annotations

import numpy as np
import pytest

from placerec.errors import ConfigError, ScanDataError
from placerec.eval import localization_metrics
from placerec.experiment.candidates import CandidateTable
from placerec.experiment.report import ambiguous_answers, localize_estimates
from placerec.types import Candidate
from placerec.verify.ambiguity import AmbiguityParams, runner_up_ratio


def _at(*xs: float) -> np.ndarray:
    return np.array([[x, 0.0, 0.0] for x in xs])


def test_the_runner_up_is_the_best_answer_elsewhere():
    # the second answer agrees (3 m off), the third is 40 m away: the ratio is the third's score over the best
    assert runner_up_ratio(np.array([0.20, 0.19, 0.15]), _at(0, 3, 40), 5.0) == pytest.approx(0.75)
    # the best answer elsewhere, not the first one elsewhere
    assert runner_up_ratio(np.array([0.20, 0.10, 0.18]), _at(0, 40, -30), 5.0) == pytest.approx(0.9)
    assert runner_up_ratio(np.array([0.2, 0.19]), _at(0, 4.9), 5.0) == 0.0  # they agree: no runner-up
    assert runner_up_ratio(np.array([0.2]), _at(0), 5.0) == 0.0
    assert runner_up_ratio(np.array([0.2, 0.19]), _at(0, 4.9), 4.0) == pytest.approx(
        0.95
    )  # separation counts
    p = AmbiguityParams(max_ratio=0.85)
    assert p.refuses(0.85) and p.refuses(0.9) and not p.refuses(0.84)
    assert not AmbiguityParams().refuses(1.0)  # off by default


def test_bad_answers_and_values_are_refused():
    with pytest.raises(ScanDataError, match="positions"):
        runner_up_ratio(np.array([0.2, 0.1]), _at(0), 5.0)
    with pytest.raises(ScanDataError, match="positions"):
        runner_up_ratio(np.array([]), np.zeros((0, 3)), 5.0)
    with pytest.raises(ScanDataError, match="positive"):
        runner_up_ratio(np.array([0.0, 0.1]), _at(0, 9), 5.0)
    for bad in (
        {"max_ratio": 0.0},
        {"max_ratio": 1.5},
        {"separation_m": -1.0},
        {"separation_m": float("inf")},
    ):
        with pytest.raises(ConfigError):
            AmbiguityParams.model_validate(bad)
    with pytest.raises(ConfigError, match="max_raito"):
        AmbiguityParams.model_validate({"max_raito": 0.8})


def _table() -> tuple[CandidateTable, np.ndarray, np.ndarray]:
    """Map scans at x = 0, 10, 50; three queries at x = 0.5: one with a look-alike 50 m away nearly as good, one
    whose runner-up is a neighbouring scan of the same place, one whose look-alike was rejected."""
    map_poses = np.stack([np.eye(4)] * 3)
    map_poses[:, 0, 3] = [0.0, 10.0, 50.0]
    truth = np.stack([np.eye(4)] * 3)
    truth[:, 0, 3] = 0.5
    near, back = np.eye(4), np.eye(4)
    near[0, 3], back[0, 3] = 0.5, -9.5  # the query seen from scan 0 and from scan 1

    def cand(q: int, m: int, pose: np.ndarray, score: float, accepted: bool = True) -> Candidate:
        return Candidate(q, m, score, pose, 20, accepted=accepted)

    rows = [
        [cand(0, 0, near, 0.20), cand(0, 2, near, 0.19)],  # x = 50.5: 50 m away, 0.95 of the best
        [cand(1, 0, near, 0.20), cand(1, 1, back, 0.19)],  # x = 0.5: the same place
        [cand(2, 0, near, 0.20), cand(2, 2, near, 0.19, accepted=False)],
    ]
    return CandidateTable.from_candidates([0, 1, 2], rows), map_poses, truth


def test_localize_mode_refuses_an_ambiguous_answer_only():
    table, map_poses, truth = _table()
    est, basis, rule = localize_estimates(table, map_poses)
    assert (basis, rule) == ("pose", "accepted") and np.isfinite(est).all()
    est, basis, rule = localize_estimates(table, map_poses, AmbiguityParams(max_ratio=0.85))
    assert (basis, rule) == ("pose", "accepted")
    assert np.isnan(est[0]).all() and np.isfinite(est[1:]).all()
    assert np.allclose(est[1:, 0, 3], 0.5)
    m = localization_metrics(est, truth, 3.0, basis=basis, answer_rule=rule)
    assert (m.n_success, m.n_no_estimate, m.n_wrong) == (2, 1, 0)
    # a ratio above the runner-up's keeps the answer
    est, _, _ = localize_estimates(table, map_poses, AmbiguityParams(max_ratio=0.96))
    assert np.isfinite(est).all()
    # the runner-up placed within separation_m agrees
    est, _, _ = localize_estimates(table, map_poses, AmbiguityParams(max_ratio=0.85, separation_m=60.0))
    assert np.isfinite(est).all()


def test_loop_mode_refuses_every_candidate_of_an_ambiguous_query():
    """Loop mode across two drives (tools/eval_cross_sensor.py): the queries `ambiguous_answers` names lose every
    candidate, so their top score is 0 and no threshold closes them; the others keep their answer."""
    table, map_poses, _ = _table()
    assert not ambiguous_answers(table, map_poses, AmbiguityParams()).any()  # off
    refused = ambiguous_answers(table, map_poses, AmbiguityParams(max_ratio=0.85))
    assert refused.tolist() == [True, False, False]
    judged = table.refused(np.repeat(refused[:, None], table.match_ids.shape[1], 1))
    _, match, scores = judged.top1()
    assert scores.tolist() == [0.0, 0.20, 0.20] and judged.accepted[0].tolist() == [0, 0]
    assert match[1:].tolist() == [0, 0]
    # a pipeline that does not verify has no accepted answers for the rule to judge
    plain = CandidateTable.from_candidates([0], [[Candidate(0, 0, 0.2), Candidate(0, 2, 0.19)]])
    assert not ambiguous_answers(plain, map_poses, AmbiguityParams(max_ratio=0.5)).any()


def test_the_experiment_config_takes_the_rule():
    from placerec.config import parse_config

    base = {
        "dataset": {"source": "simulator", "simulator": {"world": "town"}},
        "pipelines": [{"name": "orb-hbst"}],
    }
    cfg = parse_config(
        {**base, "evaluation": {"mode": "localize", "localize": {"ambiguity": {"max_ratio": 0.85}}}}
    )
    assert cfg.evaluation.localize.ambiguity == AmbiguityParams(max_ratio=0.85, separation_m=5.0)
    with pytest.raises(ConfigError, match="ambiguity"):
        parse_config({**base, "evaluation": {"localize": {"ambiguity": {"max_ratio": 2}}}})
