"""The loop-closure detector's real-time mode (placerec.realtime, LoopClosureDetector(realtime=...)) with real
recognizers on a small simulated revisit: the same closures as the sequential mode (ids, scores, poses), late but
all by flush(); the backlog's wait; a failed query raised at the next call naming its scan; no thread left after
close(); OnlineSlam and `placerec slam` with the real-time mode: the same loop factors, the same final poses
(MultiSessionSlam's: tests/test_multisession.py, on that module's sessions)."""

from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest

from placerec.errors import ConfigError, ScanDataError
from placerec.keyframes import KeyframeParams
from placerec.loop_closure import LoopClosureDetector
from placerec.realtime import LateScanError, RealtimeParams
from placerec.recognizer import make_pipeline
from placerec.sim import SimulatedSequence
from placerec.sim.odometry import OdometryDrift, drift_poses
from placerec.types import ListSequence

N = 30  # scans per pass: the street, then the same street again (other clutter)
EXCLUSION = 20
THRESHOLD = {"orb-hbst": 0.25, "scan-context": 0.3}


@pytest.fixture(scope="module")
def revisit():
    """Scans 0..29 of the town's route (clutter seed 1), then the same 30 places again (clutter seed 2): scans
    30..59 revisit scans 0..29 beyond the exclusion window; their true poses and 10 Hz time stamps."""
    a = SimulatedSequence(world="town", sensor="vlp16", n_scans=N, seed=1, world_seed=0)
    b = SimulatedSequence(world="town", sensor="vlp16", n_scans=N, seed=2, world_seed=0)
    scans = [a[i] for i in range(N)] + [b[i] for i in range(N)]
    return scans, np.concatenate([a.poses, b.poses])


def _run(scans, poses, name, realtime=None, keyframes=None, recognizer=None, exclusion=EXCLUSION):
    """Feed every scan; returns [(call index, closure)] (call len(scans): flush) and the detector (closed)."""
    rec = recognizer if recognizer is not None else make_pipeline(name)
    out = []
    with LoopClosureDetector(
        rec, THRESHOLD[name], exclusion_frames=exclusion, keyframes=keyframes, realtime=realtime
    ) as det:
        for i, (scan, pose) in enumerate(zip(scans, poses, strict=True)):
            out += [(i, c) for c in det.process(scan, pose, timestamp=0.1 * i)]
        out += [(len(scans), c) for c in det.flush()]
    return out, det


def _same(a, b):
    """The two runs accepted the same closures in the same order: ids and scores equal, poses to 1e-9."""
    assert [(c.query_id, c.match_id, c.score) for _, c in a] == [
        (c.query_id, c.match_id, c.score) for _, c in b
    ]
    for (_, x), (_, y) in zip(a, b, strict=True):
        assert (x.relative_pose is None) == (y.relative_pose is None)
        if x.relative_pose is not None:
            np.testing.assert_allclose(x.relative_pose, y.relative_pose, atol=1e-9, rtol=0)


def _worker_threads():
    return [t for t in threading.enumerate() if t.name == "placerec-loop-closure"]


@pytest.mark.parametrize("name", ["orb-hbst", "scan-context"])
def test_the_same_closures_as_sequential_late_but_all_by_flush(revisit, name):
    scans, poses = revisit
    seq, _ = _run(scans, poses, name)
    rt, det = _run(scans, poses, name, RealtimeParams(budget_ms=100, max_backlog=3))
    assert len(seq) >= 20  # the revisit closes
    _same(seq, rt)
    assert all(c.query_id <= call for call, c in rt)  # never ahead of the scan fed
    st = det.realtime_stats
    assert st.scans == len(scans) and len(st.process_ms) == len(scans) and len(st.worker_ms) == len(scans)
    assert st.closures == len(rt) and st.worker_errors == 0 and st.max_backlog <= 4
    deferred = [(call, c) for call, c in rt if call > c.query_id]
    assert st.deferred_closures == len(deferred)
    assert st.max_delay == max((min(call, len(scans) - 1) - c.query_id for call, c in deferred), default=0)
    assert det.closures == [c for _, c in rt] and not _worker_threads()


def test_keyframes_in_real_time(revisit):
    scans, poses = revisit
    kf = KeyframeParams(seconds=0.25, deskew=False)  # 3 scans a keyframe
    seq, det_seq = _run(scans, poses, "orb-hbst", keyframes=kf, exclusion=6)
    rt, det = _run(scans, poses, "orb-hbst", RealtimeParams(max_backlog=1), keyframes=kf, exclusion=6)
    assert len(seq) >= 3
    _same(seq, rt)
    assert det.n_processed == det_seq.n_processed
    assert [det.keyframe_scans(i) for i in range(det.n_processed)] == [
        det_seq.keyframe_scans(i) for i in range(det.n_processed)
    ]


class Slowed:
    """A real recognizer whose queries take ``delay`` s longer, and whose query of ``fail_at`` raises."""

    def __init__(self, rec, delay=0.0, fail_at=None):
        self.rec, self.delay, self.fail_at = rec, delay, fail_at

    def __getattr__(self, name):
        return getattr(self.rec, name)

    def query_description(self, description, k=1, max_id=None, query_id=None):
        time.sleep(self.delay)
        if query_id == self.fail_at:
            raise ScanDataError("descriptor shape (0,), expected (20, 60)")
        return self.rec.query_description(description, k=k, max_id=max_id, query_id=query_id)


def test_backlog_defers_then_waits(revisit):
    """A worker slower than the feed: closures come late (at most max_backlog places late before the flush),
    process() waits when the backlog is over max_backlog; max_backlog 0 returns every closure in its own call."""
    scans, poses = revisit
    seq, _ = _run(scans, poses, "orb-hbst")
    slow = Slowed(make_pipeline("orb-hbst"), delay=0.03)
    rt, det = _run(scans, poses, "orb-hbst", RealtimeParams(budget_ms=1, max_backlog=2), recognizer=slow)
    _same(seq, rt)
    st = det.realtime_stats
    assert st.waited > 0 and st.max_backlog == 3 and st.over_budget == st.scans  # 1 ms: every call over
    assert st.deferred_closures == len(rt) and 1 <= st.max_delay <= 3
    now, det0 = _run(scans, poses, "orb-hbst", RealtimeParams(max_backlog=0))
    _same(seq, now)
    assert all(call == c.query_id for call, c in now) and det0.realtime_stats.deferred_closures == 0


def test_a_failed_query_is_raised_at_the_next_call_with_its_scan(revisit):
    scans, poses = revisit
    rec = Slowed(make_pipeline("scan-context"), fail_at=35)
    det = LoopClosureDetector(rec, 0.3, exclusion_frames=EXCLUSION, realtime=RealtimeParams(max_backlog=0))
    got = []
    for i in range(36):
        got += det.process(scans[i], poses[i])
    assert det.next_id == 36 and det.realtime_stats.worker_errors == 1
    with pytest.raises(LateScanError, match="scan 35: .*descriptor shape") as info:
        det.process(scans[36], poses[36])
    assert info.value.scan_id == 35 and isinstance(info.value, ScanDataError)
    assert det.next_id == 36  # the call's own scan was left untouched: feed it again
    for i in range(36, len(scans)):
        got += det.process(scans[i], poses[i])
    got += det.close()
    assert 35 not in {c.query_id for c in got} and 35 not in {c.match_id for c in got}
    assert {c.query_id for c in got} >= {31, 32, 33, 34, 36, 37}
    assert not _worker_threads()
    with pytest.raises(ConfigError, match="closed"):
        det.process(scans[0], poses[0])


def test_the_thread_ends_with_close_and_with_an_error(revisit):
    scans, poses = revisit
    det = LoopClosureDetector(make_pipeline("scan-context"), 0.3, realtime=RealtimeParams())
    assert not _worker_threads()  # started on the first scan
    det.process(scans[0], poses[0])
    assert len(_worker_threads()) == 1
    det.close()
    det.close()  # idempotent
    assert not _worker_threads()
    with pytest.raises(RuntimeError, match="boom"):
        with LoopClosureDetector(make_pipeline("scan-context"), 0.3, realtime=RealtimeParams()) as det2:
            det2.process(scans[0], poses[0])
            raise RuntimeError("boom")
    assert not _worker_threads()
    with pytest.raises(ConfigError, match="budget_ms"):
        RealtimeParams(budget_ms=0)


def _slam(revisit, realtime):
    pytest.importorskip("gtsam")
    from placerec.slam import OnlineSlam

    scans, poses = revisit
    drift = OdometryDrift(translation=0.01, rotation_deg=0.03, yaw_bias_deg_per_100m=20.0, scale_bias=0.0)
    odo = drift_poses(poses, drift, seed=3)
    slam = OnlineSlam(make_pipeline("orb-hbst"), 0.25, exclusion_frames=EXCLUSION, realtime=realtime)
    for scan, T in zip(scans, odo, strict=True):
        slam.process(scan, T)
    return slam, slam.finish()


def test_online_slam_in_real_time_gives_the_same_loops_and_poses(revisit):
    seq, poses_seq = _slam(revisit, None)
    rt, poses_rt = _slam(revisit, RealtimeParams(max_backlog=3))
    key = lambda lp: (lp.match_id, lp.query_id, lp.score)  # noqa: E731
    assert len(seq.loops) >= 20
    assert sorted(map(key, seq.loops)) == sorted(map(key, rt.loops))
    by_key = {key(lp): lp.T_match_query for lp in seq.loops}
    for lp in rt.loops:
        np.testing.assert_allclose(lp.T_match_query, by_key[key(lp)], atol=1e-9, rtol=0)
    np.testing.assert_allclose(poses_rt, poses_seq, atol=1e-6, rtol=0)
    assert [len(c) for c in rt.candidates] == [len(c) for c in seq.candidates]
    assert not _worker_threads()


def test_placerec_slam_with_loops_realtime(revisit, tmp_path):
    pytest.importorskip("gtsam")
    from placerec.slam_app.config import load_slam_config
    from placerec.slam_app.run import run_slam

    scans, poses = revisit
    seq = ListSequence(scans, poses, np.arange(len(scans)) * 0.1, name="revisit")
    over = ["output.progress=false", "output.figures=false", f"loops.exclusion.frames={EXCLUSION}"]
    _, sequential = run_slam(load_slam_config(None, over), tmp_path / "seq", seq)
    cfg = load_slam_config(None, [*over, "loops.realtime={budget_ms: 100, max_backlog: 3}"])
    assert cfg.loops.realtime == RealtimeParams(budget_ms=100, max_backlog=3)
    run, payload = run_slam(cfg, tmp_path / "rt", seq)
    assert "realtime" not in sequential and payload["loops"] == sequential["loops"]
    rt = json.loads((run / "metrics.json").read_text())["realtime"]
    assert rt["scans"] == len(scans) and rt["closures"] >= payload["loops"]["accepted"]
    assert set(rt) >= {"over_budget", "deferred_closures", "max_delay", "process_ms", "worker_ms"}
    assert "wait" in payload["time_ms"]["stages"]
    seq_loops = (tmp_path / "seq").glob("*/loops.csv")
    # the same closures, with the same scores and transforms; the batch optimisation's columns (residual,
    # weight) may move in the last printed digit: its closures reached the graph at other scans
    before, after = (_loop_rows(path) for path in (next(seq_loops), run / "loops.csv"))
    assert [r[0] for r in before] == [r[0] for r in after]
    np.testing.assert_allclose([r[1] for r in before], [r[1] for r in after], rtol=1e-4, atol=1e-6)
    assert not _worker_threads()


def _loop_rows(path) -> list[tuple[tuple[str, ...], list[float]]]:
    """``loops.csv``'s rows, sorted: (every column but the batch optimisation's, those as floats)."""
    from placerec.slam_app.report import BATCH_COLUMNS

    header, *lines = path.read_text().splitlines()
    names = header.split(",")
    batch = [names.index(c) for c in BATCH_COLUMNS]
    rows = []
    for line in lines:
        cells = line.split(",")
        rows.append(
            (tuple(c for i, c in enumerate(cells) if i not in batch), [float(cells[i]) for i in batch])
        )
    return sorted(rows)


def test_a_query_that_refuses_a_place_leaves_one_trace() -> None:
    """A recognizer whose query refuses a description (ScanDataError) after the detector recorded the place's
    motion: the back end skips the scan, and the detector's ids and path stay one per scan, as the graph's poses."""
    pytest.importorskip("gtsam")
    from placerec.baselines.scan_context import ScanContext
    from placerec.errors import ScanDataError
    from placerec.slam.online import OnlineSlam

    class RefusesScan5(ScanContext):
        def query_description(self, description, k=1, max_id=None, query_id=-1):
            if query_id == 5:
                raise ScanDataError("query 5: refused")
            return super().query_description(description, k, max_id, query_id)

    seq = SimulatedSequence(world="town", sensor="vlp16", n_scans=8, seed=2)
    slam = OnlineSlam(RefusesScan5(), 0.3, exclusion_frames=2)
    for i in range(8):
        slam.process(seq[i], seq.poses[i], float(i))
    det = slam.detector
    assert det.n_processed == slam.graph.n_poses == 8
    assert len(det._times) == len(det._path) == 8
    np.testing.assert_allclose(
        det._path[-1], np.linalg.norm(np.diff(seq.poses[:, :3, 3], axis=0), axis=1).sum()
    )
