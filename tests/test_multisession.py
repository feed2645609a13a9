"""Multi-session SLAM (placerec.slam.multisession) on simulated sessions with a real recognizer (ORB-HBST) and
GTSAM: a second session over the same world joins the prior map and lands in its frame; a session over another
world, or one false inter-session closure, never joins; the prior map fixed or anchored; the detector's
``prior_entries`` arithmetic; bad input; the same closures in the detector's real-time mode."""

import threading

import numpy as np
import pytest

from placerec.errors import ConfigError, ScanDataError
from placerec.eval import ExclusionWindow
from placerec.eval.pose_error import pose_errors
from placerec.loop_closure import LoopClosureDetector
from placerec.realtime import RealtimeParams
from placerec.recognizer import make_pipeline
from placerec.sim import SimulatedSequence
from placerec.sim.geometry import euler_rotation
from placerec.sim.odometry import OdometryDrift, drift_poses
from placerec.slam.graph import GraphParams, LoopFactor, PoseGraph
from placerec.slam.multisession import MultiSessionSlam
from placerec.types import Scan, relative_pose

pytest.importorskip("gtsam")

N_MAP, START, N_SESSION = 50, 5, 45


@pytest.fixture(scope="module")
def sessions():
    """The prior map (town, world 0, clutter seed 1: 50 scans at their true poses), a second session over the same
    world (clutter seed 2, from scan 5 on, drifting odometry in its own frame: its first pose is the identity) and
    a session over another world (world 5); ORB-HBST descriptions of every scan."""
    rec = make_pipeline("orb-hbst")
    a = SimulatedSequence(world="town", sensor="vlp16", n_scans=N_MAP, seed=1, world_seed=0)
    b = SimulatedSequence(world="town", sensor="vlp16", n_scans=START + N_SESSION, seed=2, world_seed=0)
    c = SimulatedSequence(world="town", sensor="vlp16", n_scans=N_SESSION, seed=2, world_seed=5)
    drift = OdometryDrift(translation=0.01, rotation_deg=0.03, yaw_bias_deg_per_100m=2.0, scale_bias=0.0)
    truth_b = b.poses[START:]
    odo_b = drift_poses(truth_b, drift, seed=3)
    odo_c = drift_poses(c.poses, drift, seed=4)
    return {
        "map_poses": a.poses.copy(),
        "map": [rec.describe(a[i]) for i in range(N_MAP)],
        "b": [rec.describe(b[i]) for i in range(START, START + N_SESSION)],
        "truth_b": truth_b,
        "odo_b": np.linalg.inv(odo_b[0]) @ odo_b,
        "c": [rec.describe(c[i]) for i in range(N_SESSION)],
        "odo_c": np.linalg.inv(odo_c[0]) @ odo_c,
    }


def _recognizer(sessions):
    """A fresh ORB-HBST holding the prior map's places under ids 0..N_MAP-1 (what a loaded map gives)."""
    rec = make_pipeline("orb-hbst")
    for i, (d, T) in enumerate(zip(sessions["map"], sessions["map_poses"], strict=True)):
        rec.add_description(i, d, T)
    return rec


def _run(sessions, which="b", extra=None, **options):
    """Feed session ``which`` (descriptions + its own odometry) against the prior map; ``extra``: {scan: loops}."""
    slam = MultiSessionSlam(
        _recognizer(sessions), 0.25, sessions["map_poses"], exclusion_frames=30, **options
    )
    for s, (d, T) in enumerate(zip(sessions[which], sessions[f"odo_{which}"], strict=True)):
        slam.process(None, T, description=d, extra_loops=(extra or {}).get(s))
    return slam, slam.finish()


def _chain(poses, sigmas=(0.1, 0.02)):
    """Odometry factors along a map's poses (its own graph), ``sigmas``: (deg, m) per step."""
    sig = np.array([np.radians(sigmas[0])] * 3 + [sigmas[1]] * 3)
    return [(i, i + 1, relative_pose(poses[i], poses[i + 1]), sig) for i in range(len(poses) - 1)]


@pytest.fixture(scope="module")
def joined_fixed(sessions):
    return _run(sessions)


def test_prior_entries_exclusion_arithmetic():
    """The map's places are always eligible; the window counts only the session's own places; ids follow the
    map's; default 0 is the plain detector."""
    rng = np.random.default_rng(0)
    scans = [Scan(rng.normal(size=(150, 3)) * [20, 20, 2], np.ones(150)) for _ in range(9)]
    poses = np.tile(np.eye(4), (9, 1, 1))
    poses[:, 0, 3] = np.cumsum(rng.choice([0.0, 1.0, 2.5], size=9))
    M = 4
    for frames, metres in ((3, None), (None, 2.0), (2, 3.0), (0, None)):
        rec = make_pipeline("scan-context")
        for i in range(M):
            rec.add(i, scans[i])
        det = LoopClosureDetector(rec, 0.0, frames, None, metres, k=50, prior_entries=M)
        plain = LoopClosureDetector(make_pipeline("scan-context"), 0.0, frames, None, metres, k=50)
        own = ExclusionWindow(frames, None, metres).sequence_bounds(5, positions=poses[M:, :3, 3])
        for s in range(5):
            det.process(scans[M + s], pose=poses[M + s])
            plain.process(scans[M + s], pose=poses[M + s])
            assert det.last_max_id == M + own[s] == M + plain.last_max_id
            ids = {c.match_id for c in det.last_candidates}
            assert ids and ids <= set(range(det.last_max_id + 1))  # the map is queried from the first scan
            assert {c.query_id for c in det.last_candidates} == {M + s}
        assert det.n_processed == 5 and det.next_id == M + 5
        assert det.skip(poses[-1]) == M + 5
    with pytest.raises(ConfigError, match="prior_entries"):
        LoopClosureDetector(make_pipeline("scan-context"), 0.0, prior_entries=-1)


def test_a_session_over_the_same_world_joins_in_the_map_frame(sessions, joined_fixed):
    slam, res = joined_fixed
    assert res.joined and res.frame == "map" and res.summary().startswith("joined to the prior map (fixed)")
    assert res.joined_at is not None and res.joined_at <= 3  # two agreeing closures from the first scans
    assert len(res.inter_loops) > 30 and not res.rejected_at_join and res.rejected_by_graph == 0
    assert all(lp.match_id < N_MAP <= lp.query_id for lp in res.inter_loops)
    truth = sessions["truth_b"]
    t_err, r_err = pose_errors(res.session_poses, truth)  # no alignment: the map's frame is the truth's
    assert np.median(t_err) < 0.05 and t_err.max() < 0.3 and r_err.max() < 1.0
    # the session's odometry frame (first pose = identity) lies at its true first pose in the map
    t, r = pose_errors(res.T_map_session, truth[0])
    assert t[0] < 0.1 and r[0] < 0.5
    # fixed: the prior map does not move; the iSAM2 estimate is in the map frame too
    assert np.abs(res.map_poses - sessions["map_poses"]).max() < 1e-5
    assert pose_errors(slam.poses(), truth)[0].max() < 0.3
    # the graph's keys are the detector's ids: map 0..M-1, session scan s at M+s
    assert res.graph.n_poses == N_MAP + N_SESSION


def test_a_session_over_another_world_stays_separate(sessions):
    slam, res = _run(sessions, "c")
    assert not res.joined and res.frame == "session" and res.T_map_session is None
    assert res.summary() == "sessions never overlapped: kept separate (no inter-session closure)"
    assert not res.inter_loops and not res.pending
    assert res.graph is slam.session and res.graph.n_poses == N_SESSION
    assert all(lp.match_id >= N_MAP for lp in res.intra_loops)
    # in its own frame: its first pose stays its first odometry pose
    assert np.abs(res.session_poses[0] - np.eye(4)).max() < 1e-5
    assert np.array_equal(res.map_poses, sessions["map_poses"])


def _false_closure(query_scan: int, match: int, yaw_deg: float = 40.0) -> LoopFactor:
    T = np.eye(4)
    T[:3, :3] = euler_rotation(np.radians(yaw_deg), 0.0, 0.0)
    T[:3, 3] = [3.0, -2.0, 0.0]
    return LoopFactor(match, N_MAP + query_scan, T, 0.9, injected=True)


def test_one_false_inter_session_closure_never_joins(sessions):
    _, alone = _run(sessions, "c", extra={10: [_false_closure(10, 20)]})
    assert not alone.joined and len(alone.pending) == 1
    assert "kept separate (1 inter-session closures" in alone.summary()
    # two false closures that disagree with each other do not join either
    _, two = _run(sessions, "c", extra={10: [_false_closure(10, 20)], 20: [_false_closure(20, 5, -60.0)]})
    assert not two.joined and len(two.pending) == 2


def test_a_false_closure_beside_true_ones_is_rejected_at_the_join(sessions):
    false = _false_closure(0, 30)
    _, res = _run(sessions, extra={0: [false]})
    assert res.joined and res.rejected_at_join == [false]
    assert false not in res.inter_loops
    assert pose_errors(res.session_poses, sessions["truth_b"])[0].max() < 0.3


def _offset_closure(sessions, query_scan: int, dx: float) -> LoopFactor:
    """A closure of session scan ``query_scan`` onto its nearest map place, its true relative pose moved ``dx``
    metres along the match's x axis."""
    truth = sessions["truth_b"][query_scan]
    m = int(np.argmin(np.linalg.norm(sessions["map_poses"][:, :3, 3] - truth[:3, 3], axis=1)))
    T = relative_pose(sessions["map_poses"][m], truth)
    T[0, 3] += dx
    return LoopFactor(m, N_MAP + query_scan, T, 0.9, injected=True)


def test_the_odometry_gate_checks_inter_session_closures_against_the_joined_estimate(sessions, joined_fixed):
    """After the join an inter-session closure must agree with the joined estimate: a look-alike place 40 deg and
    3.6 m off, and a closure 1.5 m off next to tied scans (bound 1 m + 0.04 m/m over a step or two), are refused;
    0.5 m off is admitted; bases of 2 m admit the 1.5 m one. The detector's own closures all agree."""
    from placerec.odometry_gate import OdometryGateParams

    _, plain = joined_fixed
    gate = OdometryGateParams()
    slam, res = _run(sessions, odometry_gate=gate)
    assert res.joined and not res.refused_by_gate and "odometry gate" not in res.summary()
    key = lambda lp: (lp.match_id, lp.query_id)  # noqa: E731
    assert list(map(key, res.inter_loops)) == list(map(key, plain.inter_loops))
    far, off, near = (
        _false_closure(30, 12),
        _offset_closure(sessions, 32, 1.5),
        _offset_closure(sessions, 34, 0.5),
    )
    extra = {30: [far], 32: [off], 34: [near]}
    _, gated = _run(sessions, extra=extra, odometry_gate=gate)
    ids = lambda loops: [id(lp) for lp in loops]  # noqa: E731 (LoopFactor holds arrays: compare by identity)
    assert ids(gated.refused_by_gate) == ids([far, off])
    assert id(near) in ids(gated.inter_loops) and not {id(far), id(off)} & set(ids(gated.inter_loops))
    assert gated.summary().endswith(", 2 refused by the odometry gate")
    assert pose_errors(gated.session_poses, sessions["truth_b"])[0].max() < 0.3
    _, wide = _run(sessions, extra=extra, odometry_gate=gate.model_copy(update={"metres": 2.0}))
    assert ids(wide.refused_by_gate) == ids([far])
    _, off_gate = _run(sessions, extra=extra)  # without the gate all three reach the graph
    assert set(ids([far, off, near])) <= set(ids(off_gate.inter_loops))


def test_anchored_map_moves_within_its_own_factors(sessions, joined_fixed):
    map_poses = sessions["map_poses"]
    _, res = _run(sessions, anchor="anchored", prior_odometry=_chain(map_poses))
    assert res.joined and res.summary().startswith("joined to the prior map (anchored)")
    moved = pose_errors(res.map_poses, map_poses)[0]
    assert moved[0] < 1e-5  # map pose 0 holds the map
    # the rest may move, within the map's odometry covariance (0.14 m at pose 49)
    assert 1e-5 < moved.max() < 0.5
    assert pose_errors(res.session_poses, sessions["truth_b"])[0].max() < 0.3
    # a map whose own factors are 10x tighter moves far less
    _, tight = _run(sessions, anchor="anchored", prior_odometry=_chain(map_poses, (0.01, 0.002)))
    assert pose_errors(tight.map_poses, map_poses)[0].max() < moved.max() / 5
    # without the map's factors, an anchored map would be held by nothing
    with pytest.raises(ConfigError, match="pose 1 .* not connected"):
        MultiSessionSlam(_recognizer(sessions), 0.25, map_poses, anchor="anchored")
    with pytest.raises(ConfigError, match="pose 30 "):
        chain = _chain(map_poses)
        MultiSessionSlam(_recognizer(sessions), 0.25, map_poses, anchor="anchored", prior_odometry=chain[:29])


def test_bad_prior_maps_and_loops_are_placerec_errors(sessions):
    rec, poses = make_pipeline("scan-context"), sessions["map_poses"].copy()
    bad = poses.copy()
    bad[7, :3, :3] *= 2.0
    with pytest.raises(ScanDataError, match="prior map pose 7 is no rigid motion"):
        MultiSessionSlam(rec, 0.25, bad)
    bad[7] = poses[7]
    bad[3, 0, 3] = np.nan
    with pytest.raises(ScanDataError, match="prior map pose 3"):
        MultiSessionSlam(rec, 0.25, bad)
    with pytest.raises(ScanDataError, match=r"\(M, 4, 4\)"):
        MultiSessionSlam(rec, 0.25, poses[:0])
    with pytest.raises(ConfigError, match="anchor must be"):
        MultiSessionSlam(rec, 0.25, poses, anchor="loose")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="min_join_loops"):
        MultiSessionSlam(rec, 0.25, poses, min_join_loops=1)
    with pytest.raises(ConfigError, match="join_rotation_deg"):
        MultiSessionSlam(rec, 0.25, poses, join_rotation_deg=float("nan"))
    chain = _chain(poses)
    with pytest.raises(ScanDataError, match="prior map odometry factor 2: .*sigmas"):
        MultiSessionSlam(
            rec, 0.25, poses, anchor="anchored", prior_odometry=[*chain[:2], (2, 3, chain[2][2], -1)]
        )
    with pytest.raises(ScanDataError, match=r"odometry factor 2 -> 99"):
        MultiSessionSlam(
            rec, 0.25, poses, anchor="anchored", prior_odometry=[*chain, (2, 99, chain[2][2], chain[0][3])]
        )
    with pytest.raises(ScanDataError, match="prior map loop 3 -> 60"):
        MultiSessionSlam(
            rec,
            0.25,
            poses,
            anchor="anchored",
            prior_odometry=chain,
            prior_loops=[LoopFactor(3, 60, np.eye(4))],
        )
    slam = MultiSessionSlam(rec, 0.25, poses)
    with pytest.raises(ScanDataError, match="query must be one of this session's scans"):
        slam.process(None, np.eye(4), extra_loops=[LoopFactor(3, N_MAP + 5, np.eye(4))])


def test_add_graph_appends_a_graph_under_the_next_keys():
    """A session appended with add_graph (moved, without its prior) under an anchor pose: the same relative
    trajectory, the chain continues with add_pose; PoseGraph's own behaviour is unchanged otherwise."""
    steps = [np.eye(4) for _ in range(5)]
    for k, T in enumerate(steps):
        T[:3, :3] = euler_rotation(np.radians(3.0 * k), 0.0, 0.0)
        T[0, 3] = 1.0
    session = PoseGraph(GraphParams())
    odo = [np.eye(4)]
    for T in steps[:4]:
        odo.append(odo[-1] @ T)
    for T in odo:
        session.add_pose(T)
    session.update()
    A = np.eye(4)
    A[:3, 3] = [10.0, 5.0, 0.0]
    joined = PoseGraph(GraphParams())
    joined.add_free_pose(A, prior=True)
    assert joined.add_graph(session, transform=A, priors=False) == 1
    assert joined.n_poses == 6 and len(joined.odometry) == 4 and len(joined.priors) == 1
    joined.add_odometry(0, 1, np.eye(4))  # the anchor holds the session's first pose
    joined.add_pose(odo[-1] @ steps[4])  # continues the session's chain: pose 6 after pose 5
    assert joined.odometry[-1][:2] == (5, 6)
    poses, _ = joined.optimize()
    expected = np.stack([A @ T for T in [*odo, odo[-1] @ steps[4]]])
    assert np.abs(poses[1:] - expected).max() < 1e-6
    with pytest.raises(ScanDataError, match="odometry factor 2 -> 9"):
        joined.add_odometry(2, 9, np.eye(4))


def test_multi_session_in_real_time_joins_with_the_same_closures(sessions):
    """MultiSessionSlam with the detector's real-time mode and the odometry gate: the same closures, joined (maybe a
    few scans later), the same look-alike refused, poses close; no worker thread left."""
    from placerec.odometry_gate import OdometryGateParams

    results = []
    for realtime in (None, RealtimeParams(max_backlog=3)):
        slam = MultiSessionSlam(
            _recognizer(sessions), 0.25, sessions["map_poses"], exclusion_frames=30, realtime=realtime,
            odometry_gate=OdometryGateParams(),
        )  # fmt: skip
        for s, (d, T) in enumerate(zip(sessions["b"], sessions["odo_b"], strict=True)):
            # a look-alike injected after the join, routed with the late closures of the real-time mode
            slam.process(None, T, description=d, extra_loops=[_false_closure(30, 12)] if s == 30 else None)
        results.append(slam.finish())
    seq, rt = results
    assert [(lp.match_id, lp.query_id) for lp in rt.refused_by_gate] == [(12, N_MAP + 30)]
    assert len(seq.refused_by_gate) == 1
    key = lambda lp: (lp.match_id, lp.query_id, lp.score)  # noqa: E731
    every = lambda r: sorted(map(key, r.intra_loops + r.inter_loops + r.rejected_at_join + r.pending))  # noqa: E731
    assert seq.joined and rt.joined and every(seq) == every(rt)
    assert rt.joined_at >= seq.joined_at
    np.testing.assert_allclose(rt.session_poses[:, :3, 3], seq.session_poses[:, :3, 3], atol=0.05)
    assert not [t for t in threading.enumerate() if t.name == "placerec-loop-closure"]


def test_the_sessions_figure_draws_the_closures_the_gate_refused(sessions, tmp_path, monkeypatch):
    """sessions.png (placerec slam --prior-map) shows a refused closure, dashed and labelled with their count."""
    from placerec.experiment import figures
    from placerec.odometry_gate import OdometryGateParams
    from placerec.slam_app import report

    far = _false_closure(30, 12)
    _, res = _run(sessions, extra={30: [far]}, odometry_gate=OdometryGateParams())
    seen = {}

    def keep(fig, ax, path, **legend):
        seen["labels"] = ax.get_legend_handles_labels()[1]
        seen["dashed"] = [line for line in ax.get_lines() if line.get_linestyle() == "--"]
        return path

    monkeypatch.setattr(figures, "_finish", keep)
    report._sessions_figure(tmp_path / "sessions.png", sessions["map_poses"], res, res.session_poses, "title")
    assert "refused by the odometry gate (1)" in seen["labels"]
    (line,) = seen["dashed"]
    np.testing.assert_allclose(line.get_xdata(), [res.map_poses[12, 0, 3], res.session_poses[30, 0, 3]])
