"""Matching guided by a motion prior (`placerec.verify.guided`), the prior a gated detector gives
(`placerec.odometry_gate.ChainPrior`), and the candidates verified from it (`placerec.verify.candidates`)."""

from __future__ import annotations

import numpy as np
import pytest
from test_loop_filter import _Echo
from test_pose_truth import _pose

from placerec.config import parse_config
from placerec.errors import ConfigError
from placerec.experiment.benchmark import _cell_key
from placerec.experiment.runner import _guides
from placerec.keyframes import KeyframeParams
from placerec.loop_closure import LoopClosureDetector
from placerec.odometry_gate import ChainPrior, LoopChain, OdometryGateParams
from placerec.types import Candidate, Prediction
from placerec.verify.candidates import CloudStore, Retrieved, VerifiedParams, scan_cloud, verify_candidates
from placerec.verify.guided import GuidedParams, guided_nearest, usable


def _reference(dq, xq, dm, xm, p: Prediction):
    """Mutual nearest descriptors over every allowed pair, the first of equal distances each way (brute force)."""
    T = p.T_match_query
    moved = xq @ T[:3, :3].T + T[:3, 3]
    reach = p.metres + p.radians * np.linalg.norm(xq, axis=1)
    allowed = np.linalg.norm(moved[:, None] - xm[None], axis=2) <= reach[:, None]
    allowed &= np.isfinite(xq).all(1)[:, None] & np.isfinite(xm).all(1)[None]
    if dq.dtype == np.uint8:
        d = np.unpackbits(dq[:, None] ^ dm[None], axis=2).sum(2).astype(float)
    else:
        d = np.linalg.norm(dq[:, None].astype(float) - dm[None].astype(float), axis=2)
    d[~allowed] = np.inf
    out = []
    for i in range(len(xq)):
        if not np.isfinite(d[i]).any():
            continue
        j = int(np.argmin(d[i]))
        if int(np.argmin(d[:, j])) == i:
            out.append((i, j, d[i, j]))
    return out


@pytest.mark.parametrize("binary", [True, False])
def test_guided_matches_are_the_mutual_nearest_among_the_pairs_a_pose_within_the_bounds_can_bring_together(
    binary,
):
    rng = np.random.default_rng(4)
    xm = rng.uniform(-20, 20, (120, 3))
    T = _pose(3.0, -1.0, 20.0)
    xq = (xm[:80] - T[:3, 3]) @ T[:3, :3] + rng.normal(0, 0.3, (80, 3))  # the same points seen from the query
    xq[::9] = np.nan  # keypoints without a 3D point are never paired
    if binary:  # 4-byte descriptors: many equal distances, so the ties are decided as in mutual_nearest
        dq, dm = rng.integers(0, 256, (80, 4), dtype=np.uint8), rng.integers(0, 256, (120, 4), dtype=np.uint8)
    else:
        dq, dm = rng.normal(size=(80, 8)).astype(np.float32), rng.normal(size=(120, 8)).astype(np.float32)
    for p in (Prediction(T, 1.0, np.radians(2.0)), Prediction(_pose(4.0, 0.0, 25.0), 3.0, np.radians(8.0))):
        qi, mi, dist = guided_nearest(dq, xq, dm, xm, p)
        assert list(zip(qi.tolist(), mi.tolist(), dist.tolist(), strict=True)) == [
            (i, j, pytest.approx(v)) for i, j, v in _reference(dq, xq, dm, xm, p)
        ]
        assert len(qi) > 10
    # nothing in reach: no pairs at all
    far = Prediction(_pose(500.0), 1.0, 0.01)
    assert all(a.size == 0 for a in guided_nearest(dq, xq, dm, xm, far))


def test_the_reach_grows_with_the_keypoints_range_by_the_rotation_bound():
    xq = np.array([[10.0, 0.0, 0.0], [40.0, 0.0, 0.0]])
    xm = xq + [0.0, 1.5, 0.0]  # both 1.5 m to the side of where the prediction puts them
    dq = dm = np.zeros((2, 32), np.uint8)
    # 1 m + 0.02 rad: 1.2 m of reach at 10 m, 1.8 m at 40 m; only the far keypoint can pair
    qi, mi, _ = guided_nearest(dq, xq, dm, xm, Prediction(np.eye(4), 1.0, 0.02))
    assert qi.tolist() == [1] and mi.tolist() == [1]


def test_a_prediction_looser_than_max_metres_is_not_matched_within():
    p = Prediction(np.eye(4), 3.5, 0.1)
    assert usable(p, GuidedParams(max_metres=None)) is p and usable(None, GuidedParams()) is None
    assert usable(p, GuidedParams()) is None  # the default reach: 2 m
    assert usable(p, GuidedParams(max_metres=4.0)) is p and usable(p, GuidedParams(max_metres=3.0)) is None


def test_the_chain_prior_is_the_gates_prediction_with_its_bounds_over_the_path_it_rests_on():
    odom = [_pose(float(i)) for i in range(200)]
    path = np.arange(200.0)
    bounds = OdometryGateParams()
    prior = ChainPrior(LoopChain(), 150, odom, path, bounds, offset=5)
    p = prior.predict(105)  # place 100: 50 m of odometry back
    assert p is not None
    np.testing.assert_allclose(p.T_match_query, np.linalg.inv(odom[100]) @ odom[150])
    assert p.metres == pytest.approx(1.0 + 0.04 * 50) and p.radians == pytest.approx(
        np.radians(4.0 + 0.05 * 50)
    )
    assert (
        prior.predict(4) is None and prior.predict(155) is None
    )  # a prior map's entry; not before the query
    chain = LoopChain()
    chain.add(100, 148, _pose(48.0))  # a closure 2 m of odometry before the query
    p = ChainPrior(chain, 150, odom, path, bounds).predict(100)
    assert p is not None and p.metres == pytest.approx(1.0 + 0.04 * 2)
    np.testing.assert_allclose(p.T_match_query[:3, 3], [50.0, 0, 0], atol=1e-9)


class _Priors(_Echo):
    """Records the prior each query is given and answers nothing."""

    name = "priors"

    def __init__(self):
        super().__init__({})
        self.seen = {}

    def query_description(self, description, k=1, max_id=None, query_id=-1, prior=None):
        self.seen[query_id] = prior
        return []


def test_a_gated_detector_gives_its_recognizer_the_chain_prior_and_an_explicit_prior_wins():
    odom = [_pose(float(i)) for i in range(60)]
    rec = _Priors()
    det = LoopClosureDetector(rec, threshold=0.5, exclusion_frames=20, odometry_gate=OdometryGateParams())
    for i in range(60):
        det.process(None, pose=odom[i], description={"x": np.zeros(1)})
    p = rec.seen[59].predict(10)
    assert p is not None and p.metres == pytest.approx(1.0 + 0.04 * 49)
    mine = ChainPrior(LoopChain(), 60, odom + [_pose(60.0)], np.arange(61.0), OdometryGateParams(metres=7.0))
    det.process(None, pose=_pose(60.0), description={"x": np.zeros(1)}, prior=mine)
    assert rec.seen[60] is mine
    ungated = LoopClosureDetector(_Priors(), threshold=0.5, exclusion_frames=20)
    for _ in range(30):
        ungated.process(None, description={"x": np.zeros(1)})
    assert ungated.recognizer.seen[29] is None
    # a prior is over places: a detector still building keyframes refuses one, before taking the scan
    building = LoopClosureDetector(_Priors(), threshold=0.5, keyframes=KeyframeParams(seconds=0.4))
    with pytest.raises(ConfigError, match="keyframes"):
        building.process(None, pose=odom[0], prior=mine)
    assert building.n_processed == 0
    # a recognizer written without the prior parameter is called without it (test_loop_filter's _Echo)
    old = LoopClosureDetector(
        _Echo({4: [0]}), threshold=0.5, exclusion_frames=2, odometry_gate=OdometryGateParams()
    )
    got = [old.process(None, pose=odom[i], description={"x": np.zeros(1)}) for i in range(5)]
    assert [c.match_id for c in got[4]] == [0]


def _room(rng):
    """Points on the floor and three walls of a 20 x 14 m room, 3 m high (a scene ICP pins down)."""
    n = 4000
    u, v = rng.uniform(0, 1, n), rng.uniform(0, 1, n)
    floor = np.c_[u * 20 - 10, v * 14 - 7, np.zeros(n)]
    wall_x = np.c_[np.full(n, 10.0), u * 14 - 7, v * 3]
    wall_y = np.c_[u * 20 - 10, np.full(n, 7.0), v * 3]
    wall_y2 = np.c_[u * 20 - 10, np.full(n, -7.0), v * 3]
    box = np.c_[u * 2 + 2, np.full(n, 1.0), v * 1.5]
    return np.vstack([floor, wall_x, wall_y, wall_y2, box])


def test_a_candidate_ransac_rejects_is_verified_from_the_matches_its_prior_allows():
    rng = np.random.default_rng(0)
    match_pts = _room(rng)
    T = _pose(1.5, 0.5, 10.0)  # T_match_query
    query_pts = (match_pts - T[:3, 3]) @ T[:3, :3]
    params = VerifiedParams.model_validate(
        {"top_k": 1, "guided": {"enabled": True, "min_score": 0.1}, "score": {"min_score": 0.05}}
    )
    store = CloudStore.for_pipeline(params)
    store.add(7, scan_cloud(match_pts, params))
    idx = rng.choice(len(match_pts), 40, replace=False)
    src, dst = query_pts[idx], match_pts[idx]
    wrong = Retrieved(7, 0.5, src, dst[rng.permutation(40)])  # look-alike matches: no consistent pose

    def again():
        return Retrieved(7, 0.5, src, dst, extra={"guided": 1})

    cloud = scan_cloud(query_pts, params)
    plain = verify_candidates(cloud, [wrong], store, params, query_id=9)[0]
    assert not plain.accepted and plain.verification.rejection == "ransac"
    wrong.guided = again
    got = verify_candidates(cloud, [wrong], store, params, query_id=9)[0]
    assert got.accepted and got.extra["guided"] == 1 and got.inliers == 40
    np.testing.assert_allclose(got.relative_pose[:3, 3], T[:3, 3], atol=0.15)  # ICP on voxelised clouds
    # posed from guided matches, it is accepted only from verify.guided.min_score: scored 0 below it
    strict = params.model_copy(update={"guided": params.guided.model_copy(update={"min_score": 0.99})})
    low = verify_candidates(cloud, [wrong], store, strict, query_id=9)[0]
    assert not low.accepted and low.score == 0.0 and low.verification.rejection == "guided_score"
    off = params.model_copy(update={"guided": params.guided.model_copy(update={"enabled": False})})
    assert verify_candidates(cloud, [wrong], store, off, query_id=9)[0].verification.rejection == "ransac"
    # ICP goes to the candidates posed from their own matches first: with one ICP, a candidate with 12 right
    # matches is refined before the guided one with 40
    store.add(8, scan_cloud(match_pts, params))
    own = Retrieved(8, 0.4, src[:12], dst[:12])
    two = params.model_copy(update={"top_k": 2, "icp_top_k": 1})
    got = {c.match_id: c for c in verify_candidates(cloud, [wrong, own], store, two, query_id=9, k=2)}
    assert got[8].accepted and got[7].verification.rejection == "rank"


def _look_alike(match_id, src, dst, rng, asked):
    """A candidate whose own matches are shuffled (no consistent pose) and whose second chance, the matching
    within the prior, gives the right ones; each such matching is logged in ``asked`` (its match id)."""

    def again():
        asked.append(match_id)
        return Retrieved(match_id, 0.5, src, dst, extra={"guided": 1})

    return Retrieved(match_id, 0.5, src, dst[rng.permutation(len(dst))], guided=again)


def test_between_their_own_matches_and_second_chances_each_icp_is_made_once(monkeypatch):
    """``between`` sees the candidates verified on their own matches; when it gives no answer the second chances
    follow with those verifications reused: the same candidates as one call without it, one ICP a candidate."""
    import placerec.verify.candidates as vc

    rng = np.random.default_rng(0)
    match_pts = _room(rng)
    T = _pose(1.5, 0.5, 10.0)
    query_pts = (match_pts - T[:3, 3]) @ T[:3, :3]
    params = VerifiedParams.model_validate(
        {
            "top_k": 2,
            "icp_top_k": 2,
            "guided": {"enabled": True, "min_score": 0.1},
            "score": {"min_score": 0.05},
        }
    )
    store = CloudStore.for_pipeline(params)
    store.add(7, scan_cloud(match_pts, params))
    store.add(8, scan_cloud(match_pts, params))
    idx = rng.choice(len(match_pts), 40, replace=False)
    src, dst = query_pts[idx], match_pts[idx]
    asked = []

    def retrieved():
        return [_look_alike(7, src, dst, rng, asked), Retrieved(8, 0.4, src[:12], dst[:12])]

    cloud = scan_cloud(query_pts, params)
    icps = []
    complete = vc.complete
    monkeypatch.setattr(vc, "complete", lambda *a: icps.append(a[2]) or complete(*a))
    alone = verify_candidates(cloud, retrieved(), store, params, query_id=9)
    assert len(icps) == 2 and len(asked) == 1
    seen = []
    icps.clear()
    got = verify_candidates(
        cloud, retrieved(), store, params, query_id=9, between=lambda own, source: seen.append(own) or None
    )
    (own,) = seen
    assert [c.match_id for c in own] == [8, 7] and own[1].verification.rejection == "ransac"
    assert len(icps) == 2 and len(asked) == 2  # the one on its own matches was not refined again
    assert [(c.match_id, c.score, c.accepted, c.inliers) for c in got] == [
        (c.match_id, c.score, c.accepted, c.inliers) for c in alone
    ]
    for a, b in zip(got, alone, strict=True):
        np.testing.assert_array_equal(a.relative_pose, b.relative_pose)
    # an answer from ``between`` ends the verification: no second chance is matched
    icps.clear()
    (first,) = verify_candidates(
        cloud, retrieved(), store, params, 9, between=lambda own, source: seen.append(own) or own[:1]
    )
    assert first is seen[-1][0]
    assert len(icps) == 1 and len(asked) == 2


def _loop_cfg(params, gate=True, threshold=None):
    spec = {"name": "orb-dbow", "params": params} | ({} if threshold is None else {"threshold": threshold})
    ev = {"mode": "loop"} | ({"odometry_gate": {}} if gate else {})
    return parse_config(
        {"dataset": {"source": "simulator", "simulator": {"seed": 3}}, "pipelines": [spec], "evaluation": ev}
    )


def test_a_guided_pipelines_cell_is_stamped_with_the_gate_and_its_threshold_and_gets_a_guide():
    guided = {"verify": {"guided": {"enabled": True}}}
    assert _cell_key(_loop_cfg({})) == _cell_key(_loop_cfg({}, threshold=0.4))
    assert _cell_key(_loop_cfg(guided)) != _cell_key(_loop_cfg(guided, threshold=0.4))
    assert _cell_key(_loop_cfg(guided, gate=False)) == _cell_key(_loop_cfg(guided, gate=False, threshold=0.4))

    class Record:
        threshold = 0.25

    class Rec:
        def __init__(self, on):
            self.params = VerifiedParams.model_validate({"guided": {"enabled": on}})
            self.params = type("P", (), {"verify": self.params})()

    poses = np.stack([_pose(float(i)) for i in range(30)])
    pipes = [(Record(), Rec(True)), (Record(), Rec(False))]
    guide, none = _guides(_loop_cfg(guided), pipes, poses)
    assert none is None and guide is not None and guide.threshold == 0.25
    assert _guides(_loop_cfg(guided, gate=False), pipes, poses) == [None, None]
    # the guide's chain takes the best admitted answer at its threshold, as the evaluation judges it
    truth = np.linalg.inv(poses[2]) @ poses[25]
    guide.judge(25, [Candidate(25, 2, 0.3, relative_pose=truth, accepted=True)])
    guide.judge(26, [Candidate(26, 3, 0.2, relative_pose=np.linalg.inv(poses[3]) @ poses[26], accepted=True)])
    assert len(guide.chain) == 1  # 0.2 is under the threshold
    p = guide.prior(27).predict(2)
    assert p is not None and p.metres == pytest.approx(1.0 + 0.04 * 2, abs=0.01)


def _circuit(n=240, radius=30.0):
    """Odometry round a circle twice (places 120 apart are the same spot), and its path."""
    poses = []
    for i in range(n):
        a = 2 * np.pi * i / (n // 2)
        T = _pose(radius * np.cos(a), radius * np.sin(a), np.degrees(a) + 90.0)
        poses.append(T)
    path = np.concatenate(
        [[0.0], np.cumsum(np.linalg.norm(np.diff([p[:3, 3] for p in poses], axis=0), axis=1))]
    )
    return poses, path


def test_the_places_predicted_near_are_those_a_brute_force_over_every_place_finds():
    odom, path = _circuit()
    bounds = OdometryGateParams()
    chain = LoopChain()
    for m, q in ((10, 131), (40, 160), (41, 161), (90, 205)):
        chain.add(m, q, np.linalg.inv(odom[m]) @ odom[q])
    for query in (135, 170, 209, 230):
        prior = ChainPrior(chain, query, odom, path, bounds, offset=3)
        for metres, reach in ((6.0, 2.0), (15.0, 1.5), (40.0, 3.0)):
            expect = []
            for place in range(query):
                p = prior.predict(place + 3)
                d = float(np.linalg.norm(p.T_match_query[:3, 3]))
                if p.metres <= reach and d <= metres:
                    expect.append((d, place + 3))
            got = prior.near(metres, reach)
            assert [i for i, _ in got] == [i for _, i in sorted(expect)]
            for i, p in got:
                np.testing.assert_array_equal(p.T_match_query, prior.predict(i).T_match_query)
    # a reach below the gate's bound at L = 0 predicts nothing near; without closures only the query's own stretch
    assert ChainPrior(chain, 209, odom, path, bounds).near(50.0, 0.5) == []
    alone = ChainPrior(LoopChain(), 150, odom, path, bounds).near(10.0, 2.0)
    assert [i for i, _ in alone] == [149, 148, 147, 146, 145, 144]


class _Near:
    """A motion prior that predicts the given places near the query, in the order given."""

    def __init__(self, near):
        self._near = near

    def predict(self, match_id):
        return dict(self._near).get(match_id)

    def near(self, metres, reach):
        return [(i, p) for i, p in self._near if np.linalg.norm(p.T_match_query[:3, 3]) <= metres]


def test_a_query_without_an_answer_registers_the_places_its_prior_predicts_near_by_icp():
    from placerec.verify.candidates import verify_near
    from placerec.verify.guided import answers

    rng = np.random.default_rng(1)
    room = _room(rng)
    T = _pose(4.0, 1.0, 12.0)  # T_match_query of place 7
    query = (room - T[:3, 3]) @ T[:3, :3]
    params = VerifiedParams.model_validate(
        {"guided": {"enabled": True, "min_score": 0.1, "near_metres": 10.0, "near_candidates": 2}}
    )
    store = CloudStore.for_pipeline(params)
    store.add(7, scan_cloud(room, params))
    store.add(8, scan_cloud(room[: len(room) // 5] + [0.0, 0.0, 40.0], params))  # nothing of the room's walls
    store.add(9, scan_cloud(room, params))
    cloud = scan_cloud(query, params)
    guess = _pose(4.8, 0.4, 9.0)  # the prediction: 0.9 m and 3 deg off
    good = Prediction(guess, 1.5, np.radians(6.0))
    prior = _Near([(8, Prediction(_pose(1.0), 1.5, np.radians(6.0))), (7, good)])
    got = verify_near(cloud, prior, store, params, lambda i: True, query_id=3)
    assert got is not None and got.match_id == 7 and got.extra["near"] == 1 and got.accepted
    np.testing.assert_allclose(got.relative_pose[:3, 3], T[:3, 3], atol=0.15)
    assert answers([got], prior, params.guided)
    # entries the caller may not use are not tried; at most near_candidates are tried
    assert verify_near(cloud, prior, store, params, lambda i: i != 7, query_id=3) is None
    one = params.model_copy(update={"guided": params.guided.model_copy(update={"near_candidates": 1})})
    assert verify_near(cloud, prior, store, one, lambda i: True, query_id=3) is None
    # a registration outside the prediction's bounds is no answer, nor is one below min_score
    tight = _Near([(7, Prediction(guess, 0.3, np.radians(6.0)))])
    assert verify_near(cloud, tight, store, params, lambda i: True, query_id=3) is None
    assert not answers([got], tight, params.guided)
    strict = params.model_copy(update={"guided": params.guided.model_copy(update={"min_score": 0.99})})
    assert verify_near(cloud, prior, store, strict, lambda i: True, query_id=3) is None
    off = params.model_copy(update={"guided": params.guided.model_copy(update={"near_metres": None})})
    assert verify_near(cloud, prior, store, off, lambda i: True, query_id=3) is None
    # too far away: only places predicted within near_metres
    far = _Near([(9, Prediction(_pose(4.8, 0.4, 9.0) @ _pose(12.0), 1.5, np.radians(6.0)))])
    assert verify_near(cloud, far, store, params, lambda i: True, query_id=3) is None


def _orb_description(rng, cloud, n=200):
    xyz = cloud[rng.choice(len(cloud), n, replace=False)].astype(np.float32)
    return {
        "keypoints": rng.uniform(0, 500, (n, 2)).astype(np.float32),
        "descriptors": rng.integers(0, 256, (n, 32), dtype=np.uint8),
        "width": np.array(512, np.int64),
        "keypoint_xyz": xyz,
        "cloud": scan_cloud(cloud),
    }


#: the true T_match_query of the room's query in the pipeline tests, and the guided settings they use
_ROOM_T = _pose(3.0, -1.0, 8.0)
_NEAR_GUIDED = {"enabled": True, "min_score": 0.1, "near_metres": 10.0}


def _room_pipeline(seed):
    """(rng, the room, its query seen from `_ROOM_T`, an ORB-DBoW pipeline with `_NEAR_GUIDED`)."""
    from placerec.recognizer import make_pipeline

    rng = np.random.default_rng(seed)
    room = _room(rng)
    query = (room - _ROOM_T[:3, 3]) @ _ROOM_T[:3, :3]
    pipe = make_pipeline("orb-dbow", {"verify": {"guided": _NEAR_GUIDED, "score": {"min_score": 0.05}}})
    return rng, room, query, pipe


def test_a_pipeline_with_a_prior_registers_a_place_predicted_near_when_its_candidates_give_no_answer():
    from placerec.recognizer import make_pipeline

    rng, room, query, pipe = _room_pipeline(2)
    T, guided = _ROOM_T, _NEAR_GUIDED
    plain = make_pipeline("orb-dbow", {"verify": {"guided": guided | {"near_metres": None}}})
    for i in range(3):  # unrelated descriptors: retrieval proposes them, RANSAC finds nothing
        d = _orb_description(rng, room if i == 1 else room + [0.0, 0.0, 30.0 * (i + 1)])
        pipe.add_description(i, d)
        plain.add_description(i, d)
    q = _orb_description(rng, query)
    prior = _Near([(1, Prediction(_pose(3.6, -0.5, 6.0), 1.5, np.radians(6.0)))])
    got = pipe.query_description(q, k=3, max_id=2, query_id=9, prior=prior)
    assert got[0].match_id == 1 and got[0].extra.get("near") == 1 and got[0].accepted
    np.testing.assert_allclose(got[0].relative_pose[:3, 3], T[:3, 3], atol=0.15)
    # without the prior, or with the place beyond max_id, or near_metres unset: the candidates alone, no answer
    for cands in (
        pipe.query_description(q, k=3, max_id=2, query_id=9),
        pipe.query_description(q, k=3, max_id=0, query_id=9, prior=prior),
    ):
        assert not any(c.extra.get("near") for c in cands) and not any(
            c.accepted and c.score >= 0.1 for c in cands
        )
    assert not any(c.extra.get("near") for c in plain.query_description(q, k=3, max_id=2, prior=prior))


def test_a_place_predicted_near_comes_before_matching_within_the_prior_onto_a_candidate():
    """ICP from a prediction onto a place predicted near registers it better than features matched within the
    prior onto a candidate that may lie tens of metres away: that second chance is taken only if the first fails."""
    rng, room, query, pipe = _room_pipeline(3)
    for i in range(3):
        pipe.add_description(i, _orb_description(rng, room))
    q = _orb_description(rng, query)
    idx = rng.choice(len(room), 40, replace=False)
    src, dst = query[idx], room[idx]
    calls = []
    wrong = _look_alike(2, src, dst, rng, calls)
    near = _Near([(1, Prediction(_pose(3.6, -0.5, 6.0), 1.5, np.radians(6.0)))])
    got = pipe._verified(q, [wrong], 9, 2, near, 2)
    assert got[0].match_id == 1 and got[0].extra["near"] == 1 and calls == []
    got = pipe._verified(q, [wrong], 9, 2, _Near([]), 2)  # nothing predicted near: the guided matching
    assert got[0].match_id == 2 and got[0].extra["guided"] == 1 and got[0].accepted and calls == [2]
