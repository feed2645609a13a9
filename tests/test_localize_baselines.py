"""The ISHOT paper's Table III baselines: SHOT global registration (a) and Bosse & Zlot's keypoint voting on SHOT
(b): the log-normal threshold, one vote per place and query keypoint, early termination, world keypoints, and
6-DoF localisation of simulated scans."""

import math

import numpy as np
import pytest
from synthetic_places import add_synthetic_places

from placerec.pipelines.gestalt_voting import GestaltVoting, lognormal_threshold, place_votes
from placerec.pipelines.global_registration import GlobalRegistration
from placerec.recognizer import make_pipeline
from placerec.three_d.entries import EntryTable


def test_lognormal_threshold_is_exp_of_mu_plus_z_sigma_of_the_other_places_logs():
    e = math.e
    votes = np.array([e, e**2, 0.0, e**3, 100.0])  # the top (100) and the empty place are not in the model
    mu, sigma = 2.0, math.sqrt(2.0 / 3.0)  # logs 1, 2, 3: population standard deviation
    assert lognormal_threshold(votes, 3.0) == pytest.approx(math.exp(mu + 3.0 * sigma))
    assert lognormal_threshold(votes, 1.0) == pytest.approx(math.exp(mu + sigma))
    # fewer than two other places with votes: no model, no early stop
    assert lognormal_threshold(np.array([5.0, 1.0, 0.0, 0.0]), 3.0) == math.inf
    # equal counts elsewhere: sigma 0, the threshold is that count
    assert lognormal_threshold(np.array([2.0, 2.0, 2.0, 7.0]), 3.0) == pytest.approx(2.0)


def test_each_query_keypoint_votes_once_per_distinct_place():
    row_entry = np.array([0, 0, 1, 1, 2, 3])
    idx = np.array([[0, 1, 5, -1], [2, 2, 3, 4], [4, 4, 4, 4]])
    # row 0: places {0, 3}; row 1: places {1, 2}; row 2: place {2}
    assert place_votes(idx, row_entry, 5).tolist() == [1, 1, 2, 1, 0]


def _synthetic_db(rec, rng):
    return add_synthetic_places(rec, rng, n_places=200, per_place=20, dim=352)


def test_voting_stops_after_one_round_of_ten_percent_when_the_place_stands_out():
    rng = np.random.default_rng(2)
    rec = GestaltVoting(features={"descriptor": "shot"}, verify={"enabled": False})
    descs = _synthetic_db(rec, rng)
    query = np.concatenate([descs[7], descs[7]]) + 0.02 * rng.normal(size=(40, 352)).astype(np.float32)
    top = rec.query_description({"keypoints": np.zeros((40, 3)), "descriptors": query}, k=3)[0]
    assert top.match_id == 7 and top.extra["early_stop"]
    assert top.extra["keypoints_consumed"] == 4 and top.extra["n_keypoints"] == 40
    assert top.extra["votes"] == 4 and top.extra["threshold"] < 4
    # a threshold never passed: every keypoint is consumed, then the most voted place is the answer
    strict = GestaltVoting(features={"descriptor": "shot"}, verify={"enabled": False}, lognormal_z=50.0)
    _synthetic_db(strict, np.random.default_rng(2))
    top = strict.query_description({"keypoints": np.zeros((40, 3)), "descriptors": query}, k=1)[0]
    assert top.match_id == 7 and not top.extra["early_stop"] and top.extra["keypoints_consumed"] == 40
    assert top.extra["votes"] == 40
    # max_id: the place and everything after it are out of reach
    assert all(c.match_id <= 5 for c in rec.query_description({"keypoints": np.zeros((40, 3)),
                                                                "descriptors": query}, k=3, max_id=5))  # fmt: skip


def test_world_keypoints_apply_each_entrys_pose():
    T = np.eye(4)
    c, s = math.cos(0.5), math.sin(0.5)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = [10.0, -2.0, 1.0]
    a, b = np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 2.0, 0.0], [1.0, 1.0, 1.0]])
    table = EntryTable.empty(4)
    table.append(0, np.eye(4), a, np.zeros((1, 4), np.float32))
    table.append(1, T, b, np.zeros((2, 4), np.float32))
    w = table.world_keypoints()
    assert np.allclose(w[0], [1, 0, 0])
    assert np.allclose(w[1], [10 - 2 * s, -2 + 2 * c, 1])
    assert np.allclose(w[2], T[:3, :3] @ [1, 1, 1] + T[:3, 3])


@pytest.fixture(scope="module")
def town():
    from placerec.sim import SimulatedSequence

    return SimulatedSequence(world="town", sensor="vlp16", n_scans=5, seed=5, clutter=False, spacing=2.0)


@pytest.mark.parametrize("name", ["shot-global", "shot-gestalt-votes"])
def test_localises_a_simulated_scan_with_a_6dof_pose(town, name):
    from placerec.types import relative_pose

    rec = make_pipeline(name)
    assert rec.params.features.descriptor == "shot"
    assert rec.params.verify.consistency.enabled  # the shared verification: grouping, RANSAC, ICP
    for i in (0, 2, 4):
        rec.add(i, town[i], town.poses[i])
    cands = rec.query(town[1], k=1, query_id=1)
    assert cands and cands[0].accepted
    c = cands[0]
    gt = relative_pose(town.poses[c.match_id], town.poses[1])
    assert np.linalg.norm(c.relative_pose[:3, 3] - gt[:3, 3]) < 0.3
    assert np.linalg.norm(c.T_world_query[:3, 3] - town.poses[1][:3, 3]) < 0.3
    if name == "shot-global":
        # the match is the map entry nearest to the estimated position, every keypoint is paired with K = 4
        assert isinstance(rec, GlobalRegistration) and c.match_id in (0, 2)
        assert c.extra["correspondences"] == 4 * c.extra["n_query"]


def test_localize_config_verifies_every_pipeline_as_localize_verify():
    from placerec.config import read_config_file
    from placerec.recognizer import LOCALIZE_VERIFY, pipeline_class

    rows = read_config_file("configs/localize.yaml")["pipelines"]
    votes = next(r for r in rows if r["name"] == "ishot-votes")
    params = pipeline_class("ishot-votes").Params(**votes["params"])
    # ishot-votes has no early stop, so no fallback; everything else of the shared preset is given by hand
    verify = {k: v for k, v in LOCALIZE_VERIFY["verify"].items() if k != "fallback_top_k"}
    expected = pipeline_class("ishot-votes").Params(verify=verify, places=votes["params"]["places"])
    assert params.model_dump() == expected.model_dump()
