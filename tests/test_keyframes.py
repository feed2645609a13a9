"""Keyframes (placerec.keyframes): de-skew against a known moving sensor, windows by seconds and metres, the
keyframe frame, KeyframeSequence, bad input, and the wiring into configs, the runner and the loop-closure detector."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from placerec.errors import ConfigError, ScanDataError
from placerec.keyframes import (
    DESKEW_BIN_S,
    Keyframe,
    KeyframeBuilder,
    KeyframeParams,
    KeyframeSequence,
    deskewed_points,
)
from placerec.types import ListSequence, Scan

ROOT = Path(__file__).resolve().parents[1]
RATE_HZ = 10.0
SPEED = np.array([8.0, 3.0, 0.2])  # m/s, world frame
YAW_RATE = 0.6  # rad/s


def _true_pose(tau: np.ndarray | float) -> np.ndarray:
    """T_world_sensor at time ``tau``: constant world velocity and yaw rate (what linear + slerp reproduce)."""
    tau = np.atleast_1d(np.asarray(tau, dtype=np.float64))
    T = np.tile(np.eye(4), (tau.size, 1, 1))
    c, s = np.cos(YAW_RATE * tau), np.sin(YAW_RATE * tau)
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -s, s, c
    T[:, :3, 3] = tau[:, None] * SPEED + [5.0, -2.0, 1.5]
    return T


def _scene(n: int, seed: int = 0) -> np.ndarray:
    """Static world points 3-40 m around the route."""
    rng = np.random.default_rng(seed)
    r = rng.uniform(3.0, 40.0, n)
    a = rng.uniform(-np.pi, np.pi, n)
    return np.c_[r * np.cos(a) + 5.0, r * np.sin(a) - 2.0, rng.uniform(-1.0, 5.0, n)]


def _moving_scans(n_scans: int = 5, n_points: int = 4000) -> tuple[list[Scan], np.ndarray, list[np.ndarray]]:
    """Scans of static scenes measured by the moving sensor: each point at its own time in [0, 1/RATE_HZ);
    returns (scans, odometry poses at the scan timestamps, each scan's world points)."""
    scans, worlds = [], []
    for i in range(n_scans):
        stamp = i / RATE_HZ
        t = np.sort(np.random.default_rng(10 + i).uniform(0.0, 1.0 / RATE_HZ, n_points))
        world = _scene(n_points, seed=i)
        T = _true_pose(stamp + t)
        local = np.einsum("nji,nj->ni", T[:, :3, :3], world - T[:, :3, 3])  # R^T (p_w - p)
        scans.append(Scan(local, np.ones(n_points), time=t, timestamp=stamp, source=f"moving[{i}]"))
        worlds.append(world)
    return scans, _true_pose(np.arange(n_scans) / RATE_HZ), worlds


def _error_in_keyframe_frame(keyframe: Keyframe, worlds: list[np.ndarray]) -> float:
    T = _true_pose(keyframe.timestamp)[0]
    expected = (np.concatenate(worlds) - T[:3, 3]) @ T[:3, :3]
    return float(np.linalg.norm(keyframe.scan.xyz - expected, axis=1).max())


def _one_keyframe(scans: list[Scan], poses: np.ndarray, **params: object) -> Keyframe:
    builder = KeyframeBuilder(KeyframeParams(seconds=len(scans) / RATE_HZ, **params))  # type: ignore[arg-type]
    out = [builder.add(s, poses[i]) for i, s in enumerate(scans)]
    assert all(k is None for k in out[:-1]) and out[-1] is not None
    return out[-1]


# -- de-skew ---------------------------------------------------------------------------------------------------


def test_deskewed_keyframe_matches_the_static_scene_in_the_last_scans_frame():
    scans, poses, worlds = _moving_scans()
    keyframe = _one_keyframe(scans, poses)
    assert keyframe.scan_indices == (0, 1, 2, 3, 4)
    assert keyframe.timestamp == pytest.approx(0.4)
    np.testing.assert_allclose(keyframe.pose, poses[-1])  # the frame of the last scan at its timestamp
    assert _error_in_keyframe_frame(keyframe, worlds) < 0.01


def test_the_deskew_test_fails_for_a_wrong_sign_or_no_deskew():
    """The scene check above is sensitive: time running backwards, or no de-skew, is off by decimetres."""
    scans, poses, worlds = _moving_scans()
    flipped = [Scan(s.xyz, s.intensity, time=-s.time, timestamp=s.timestamp) for s in scans]
    assert _error_in_keyframe_frame(_one_keyframe(flipped, poses), worlds) > 0.1
    assert _error_in_keyframe_frame(_one_keyframe(scans, poses, deskew=False), worlds) > 0.1
    # interpolating towards the previous scan instead of the next one
    shifted = np.concatenate([poses[:1], poses[:-1]])
    assert _error_in_keyframe_frame(_one_keyframe(scans, shifted), worlds) > 0.1


def test_time_bins_agree_with_exact_per_point_interpolation():
    scans, poses, _ = _moving_scans(n_scans=2)
    s = scans[0]
    stamps = np.array([0.0, 0.1])
    binned = deskewed_points(s.xyz, s.time, 0.0, stamps, poses, np.eye(4))
    exact = deskewed_points(s.xyz, s.time, 0.0, stamps, poses, np.eye(4), bin_s=None)
    # a point takes the pose of its bin's centre: off by at most half a bin of motion (speed + yaw rate x range)
    bound = DESKEW_BIN_S / 2 * (np.linalg.norm(SPEED) + YAW_RATE * np.linalg.norm(s.xyz, axis=1).max())
    assert 0 < np.linalg.norm(binned - exact, axis=1).max() <= bound


def test_keyframe_scan_fields():
    scans, poses, _ = _moving_scans(n_scans=3, n_points=100)
    keyframe = _one_keyframe(scans, poses)
    cloud = keyframe.scan
    assert len(cloud) == 300 and cloud.ring is None  # the sources have no rings
    assert cloud.source == "keyframe[0:3]"
    # per-point time relative to the keyframe timestamp (0.2 s): the first scan's points are ~0.2 s earlier
    np.testing.assert_allclose(cloud.time[:100], scans[0].time - 0.2, atol=1e-6)
    voxelised = _one_keyframe(scans, poses, voxel_m=5.0).scan
    assert 0 < len(voxelised) < len(cloud)


def test_deskew_undoes_the_simulators_sweep_motion():
    """Scans the simulator renders while moving (each ray from the pose at its own time), de-skewed, lie on the
    surfaces of the same scans rendered at rest; not de-skewed, or with time running backwards, they do not
    (tools/bench_keyframes.py's measure)."""
    spec = importlib.util.spec_from_file_location("bench_keyframes", ROOT / "tools" / "bench_keyframes.py")
    assert spec is not None and spec.loader is not None
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    p90 = bench.sweep_motion_p90(n_scans=10, seconds=0.5, seed=2, keyframes=[1])
    assert p90["deskewed"] < 0.08
    assert p90["not_deskewed"] > 3 * p90["deskewed"] and p90["time_reversed"] > 3 * p90["deskewed"]


# -- windows ---------------------------------------------------------------------------------------------------


def _straight(n: int, step_m: float = 1.0) -> tuple[list[Scan], np.ndarray]:
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = np.arange(n) * step_m
    pts = np.random.default_rng(0).uniform(-10, 10, (50, 3))
    scans = [Scan(pts, np.ones(50), time=np.zeros(50), timestamp=i / RATE_HZ) for i in range(n)]
    return scans, poses


def _windows(params: KeyframeParams, scans: list[Scan], poses: np.ndarray) -> list[tuple[int, ...]]:
    builder = KeyframeBuilder(params)
    out = [k.scan_indices for i, s in enumerate(scans) if (k := builder.add(s, poses[i])) is not None]
    last = builder.flush()
    return out + ([last.scan_indices] if last is not None else [])


@pytest.mark.parametrize(
    ("params", "expected"),
    [
        (KeyframeParams(seconds=0.5), [tuple(range(0, 5)), tuple(range(5, 10)), (10, 11)]),
        (KeyframeParams(seconds=0.25), [(0, 1, 2), (3, 4, 5), (6, 7, 8), (9, 10, 11)]),  # at least 0.25 s
        (KeyframeParams(metres=3.0), [(0, 1, 2), (3, 4, 5), (6, 7, 8), (9, 10, 11)]),
        (KeyframeParams(seconds=5.0, max_scans=4), [(0, 1, 2, 3), (4, 5, 6, 7), (8, 9, 10, 11)]),
        # overlapping windows: the trailing window, every so many metres; then flush's trailing scans
        (KeyframeParams(seconds=0.5, every_metres=1.0), [tuple(range(j - 4, j + 1)) for j in range(4, 12)]),
        (
            KeyframeParams(seconds=0.5, every_metres=2.0),
            [tuple(range(j - 4, j + 1)) for j in (4, 6, 8, 10, 11)],
        ),
        (
            KeyframeParams(metres=3.0, every_metres=2.0),
            [(0, 1, 2), (2, 3, 4), (4, 5, 6), (6, 7, 8), (8, 9, 10), (9, 10, 11)],
        ),
        (
            KeyframeParams(seconds=5.0, max_scans=4, every_metres=3.0),
            [(0, 1, 2, 3), (3, 4, 5, 6), (6, 7, 8, 9), (8, 9, 10, 11)],
        ),
    ],
)
def test_window_boundaries_online_and_offline(params, expected):
    scans, poses = _straight(12)
    assert _windows(params, scans, poses) == expected
    seq = KeyframeSequence(ListSequence(scans, poses, np.arange(12) / RATE_HZ), params, poses)
    assert [seq.scan_indices(k) for k in range(len(seq))] == expected


def test_overlapping_windows_at_9_metres_per_second():
    """10 Hz at 9 m/s, 0.5 s windows: one after another they end 4.5 m apart; every_metres 1.0 ends one on every
    second scan (the first scan at least 1 m on: 1.8 m), each of the 5 scans of the trailing 0.5 s."""
    scans, poses = _straight(30, step_m=0.9)
    plain = _windows(KeyframeParams(seconds=0.5), scans, poses)
    windows = _windows(KeyframeParams(seconds=0.5, every_metres=1.0), scans, poses)
    assert len(plain) == 6 and len(windows) == 14  # 13 complete + the trailing scans at the end (flush)
    ends = [w[-1] for w in windows]
    assert ends[0] == 4 and ends[:-1] == list(range(4, 29, 2)) and ends[-1] == 29
    assert all(w == tuple(range(w[-1] - 4, w[-1] + 1)) for w in windows)  # each the 5 scans ending there
    spacing = np.diff(poses[ends[:-1], 0, 3])
    np.testing.assert_allclose(spacing, 1.8)
    # every scan is described in about window / every = 4.5 / 1.8 keyframes
    assert sum(len(w) for w in windows) / 30 == pytest.approx(2.5, abs=0.2)


@pytest.mark.parametrize(
    ("params", "expected"),
    [
        # no metres travelled: after the first keyframe (its window complete) no other one; flush: the last window
        (KeyframeParams(seconds=0.5, every_metres=1.0), [(0, 1, 2, 3, 4), (15, 16, 17, 18, 19)]),
        # a metres window at rest completes by max_scans only
        (KeyframeParams(metres=3.0, max_scans=5, every_metres=1.0), [(0, 1, 2, 3, 4), (15, 16, 17, 18, 19)]),
        # not even one complete window: flush gives every scan
        (KeyframeParams(metres=3.0, every_metres=1.0), [tuple(range(20))]),
    ],
)
def test_overlapping_windows_at_rest(params, expected):
    scans, poses = _straight(20, step_m=0.0)
    assert _windows(params, scans, poses) == expected
    seq = KeyframeSequence(ListSequence(scans, poses, np.arange(20) / RATE_HZ), params, poses)
    assert [seq.scan_indices(k) for k in range(len(seq))] == expected


def test_overlapping_flush_and_pending():
    scans, poses = _straight(10)
    builder = KeyframeBuilder(KeyframeParams(seconds=0.3, every_metres=2.0))
    made = [builder.add(scans[i], poses[i]) for i in range(8)]
    assert [k.scan_indices for k in made if k is not None] == [(0, 1, 2), (2, 3, 4), (4, 5, 6)]
    assert builder.pending == (7,)  # added since the last keyframe
    last = builder.flush()
    assert last is not None and last.scan_indices == (5, 6, 7)  # the trailing scans the builder holds
    assert builder.pending == () and builder.flush() is None  # nothing added since
    # the stream may go on: the flushed keyframe counts as the last one (scan 7, 7 m)
    assert builder.add(scans[8], poses[8]) is None
    k = builder.add(scans[9], poses[9])
    assert k is not None and k.scan_indices == (7, 8, 9)


def test_keyframe_sequence_poses_timestamps_and_scans():
    scans, odometry, _ = _moving_scans(n_scans=10, n_points=200)
    truth = odometry.copy()
    truth[:, 1, 3] += 0.5  # ground truth differs from the odometry
    stamps = np.arange(10) / RATE_HZ
    params = KeyframeParams(seconds=0.5)
    seq = KeyframeSequence(ListSequence(scans, truth, stamps, name="moving"), params, odometry)
    assert len(seq) == 2 and seq.name == "moving-keyframes"
    np.testing.assert_array_equal(seq.reference_indices, [4, 9])
    np.testing.assert_allclose(seq.poses, truth[[4, 9]])
    np.testing.assert_allclose(seq.keyframe_poses, odometry[[4, 9]])
    np.testing.assert_allclose(seq.timestamps, stamps[[4, 9]])
    builder = KeyframeBuilder(params, label="moving")
    online = [k for i, s in enumerate(scans) if (k := builder.add(s, odometry[i])) is not None]
    for k in range(2):  # offline and online give the same keyframes
        np.testing.assert_array_equal(seq[k].xyz, online[k].scan.xyz)
        assert seq[k].source == online[k].scan.source == f"moving[{5 * k}:{5 * k + 5}]"


@pytest.mark.parametrize(
    "params",
    [
        KeyframeParams(seconds=0.5),
        KeyframeParams(seconds=0.3),
        KeyframeParams(seconds=0.5, every_metres=1.5),
        KeyframeParams(seconds=0.3, every_metres=0.5, voxel_m=1.0),
        KeyframeParams(metres=2.0, every_metres=1.0),
        KeyframeParams(metres=2.0, every_metres=1.0, deskew=False),
    ],
)
def test_builder_and_sequence_give_identical_keyframes(params):
    """Every keyframe, the flushed last one included: the same scans, points, pose and timestamp online and
    offline (windows one after another and overlapping ones, whose de-skew takes the scan before the window)."""
    scans, odometry, worlds = _moving_scans(n_scans=13, n_points=200)
    seq = KeyframeSequence(
        ListSequence(scans, odometry, np.arange(13) / RATE_HZ, name="moving"), params, odometry
    )
    builder = KeyframeBuilder(params, label="moving")
    online = [k for i, s in enumerate(scans) if (k := builder.add(s, odometry[i])) is not None]
    last = builder.flush()
    online += [last] if last is not None else []
    assert len(online) == len(seq) >= 3
    for k, keyframe in enumerate(online):
        offline = seq.keyframe(k)
        assert keyframe.scan_indices == offline.scan_indices == seq.scan_indices(k)
        assert keyframe.scan.source == offline.scan.source
        np.testing.assert_array_equal(keyframe.scan.xyz, offline.scan.xyz)
        np.testing.assert_array_equal(keyframe.pose, offline.pose)
        assert keyframe.timestamp == offline.timestamp
        if (
            params.deskew and params.voxel_m is None
        ):  # de-skewed onto the static scene, windows mid-stream too
            window = list(keyframe.scan_indices)
            assert _error_in_keyframe_frame(keyframe, [worlds[i] for i in window]) < 0.01
    if params.every_metres is not None:
        assert any(
            a.scan_indices[-1] >= b.scan_indices[0] for a, b in zip(online, online[1:], strict=False)
        )  # overlap


# -- bad input ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("data", "key"),
    [
        ({}, "exactly one"),
        ({"seconds": 1.0, "metres": 2.0}, "exactly one"),
        ({"seconds": float("inf")}, "seconds"),
        ({"metres": -1.0}, "metres"),
        ({"seconds": 1.0, "voxel_m": 0.0}, "voxel_m"),
        ({"seconds": 1.0, "odometry": "gps"}, "odometry"),
        ({"seconds": 1.0, "windows": 3}, "windows"),
        ({"seconds": 1.0, "every_metres": 0.0}, "every_metres"),
        ({"seconds": 1.0, "every_metres": -1.0}, "every_metres"),
        ({"seconds": 1.0, "every_metres": float("nan")}, "every_metres"),
        ({"seconds": 1.0, "every_metres": float("inf")}, "every_metres"),
        ({"seconds": 1.0, "every_metres": 20_000.0}, "every_metres"),
    ],
)
def test_bad_params_are_config_errors(data, key):
    with pytest.raises(ConfigError, match=key):
        KeyframeParams.model_validate(data)


def test_bad_scans_and_poses_are_refused_naming_the_field_and_leave_nothing():
    scans, poses, _ = _moving_scans(n_scans=3, n_points=20)
    builder = KeyframeBuilder(KeyframeParams(seconds=10.0))
    builder.add(scans[0], poses[0], index=0)
    untimed = Scan(scans[1].xyz, scans[1].intensity, timestamp=0.1, source="untimed")
    bad = [
        ((untimed, poses[1]), "untimed: time"),
        ((scans[1], None), r"moving\[1\]: odometry_pose"),
        ((scans[1], np.full((4, 4), np.nan)), r"moving\[1\]: odometry_pose contains NaN"),
        ((scans[1], np.diag([2.0, 1.0, 1.0, 1.0])), r"odometry_pose is no rigid motion"),
        ((Scan(scans[1].xyz, scans[1].intensity, time=scans[1].time, timestamp=0.0), poses[1]), "timestamp"),
        ((Scan(scans[1].xyz, scans[1].intensity, time=scans[1].time * 1e9, timestamp=0.1), poses[1]), "time"),
    ]
    for args, message in bad:
        with pytest.raises(ScanDataError, match=message):
            builder.add(*args)
        assert builder.pending == (0,)
    builder.add(scans[1], poses[1], index=1)
    assert builder.pending == (0, 1)


def test_bad_sequences_are_refused_naming_the_field():
    scans, poses, _ = _moving_scans(n_scans=3, n_points=20)
    params = KeyframeParams(seconds=0.2)
    seq = ListSequence(scans, poses, np.arange(3) / RATE_HZ, name="seq")
    with pytest.raises(ScanDataError, match="seq: odometry_poses"):
        KeyframeSequence(seq, params)
    with pytest.raises(ScanDataError, match="seq: odometry_poses: 2 poses for 3 scans"):
        KeyframeSequence(seq, params, poses[:2])
    with pytest.raises(ScanDataError, match="seq: odometry_poses: pose 1 is no rigid motion"):
        KeyframeSequence(seq, params, np.concatenate([poses[:1], np.zeros((2, 4, 4))]))
    with pytest.raises(ScanDataError, match="seq: timestamps must increase"):
        KeyframeSequence(ListSequence(scans, poses, [0.0, 0.1, 0.1], name="seq"), params, poses)
    with pytest.raises(ScanDataError, match="seq: timestamps: windows of keyframes.seconds"):
        KeyframeSequence(ListSequence(scans, poses, name="seq"), params, poses)
    untimed = [Scan(s.xyz, s.intensity, timestamp=s.timestamp, source=f"u{i}") for i, s in enumerate(scans)]
    kf = KeyframeSequence(ListSequence(untimed, poses, np.arange(3) / RATE_HZ), params, poses)
    with pytest.raises(ScanDataError, match="u0: time"):
        kf[0]


# -- wiring: config, runner, cache key, detector -----------------------------------------------------------------


@pytest.fixture(scope="module")
def sim16():
    from placerec.sim import SimulatedSequence

    return SimulatedSequence(world="town", sensor="vlp16", n_scans=16, rate_hz=10, clutter=False, seed=3)


def _config(tmp_path, **extra):
    from placerec.config import parse_config

    data = {
        "name": "kf",
        "dataset": {
            "simulator": {
                "world": "town",
                "sensor": "vlp16",
                "n_scans": 16,
                "rate_hz": 10,
                "clutter": False,
                "seed": 3,
                "odometry_drift": 0.02,
                "sweep_motion": True,
            }
        },
        "keyframes": {"seconds": 0.4},
        "pipelines": [{"name": "scan-context"}],
        "evaluation": {"exclusion": {"frames": 1}},
        "output": {"cache_dir": None, "progress": False, "figures": False, "dir": str(tmp_path)},
    }
    return parse_config({**data, **extra})


def test_config_with_keyframes_runs_a_pipeline_on_keyframes(tmp_path, sim16):
    from placerec.experiment import run_experiment
    from placerec.io import read_poses

    run, payload = run_experiment(_config(tmp_path), tmp_path / "out")
    metrics = payload["pipelines"]["scan-context"]
    assert metrics["n_queries"] == 4  # 16 scans at 10 Hz in windows of 0.4 s
    # the evaluation runs on the keyframes: the true poses of each window's last scan
    np.testing.assert_allclose(read_poses(run / "poses.txt")[0], sim16.poses[[3, 7, 11, 15]], atol=1e-6)


def test_keyframe_runs_have_their_own_description_cache_key(tmp_path):
    from placerec.experiment.runner import _data_key

    keyed = _config(tmp_path)
    plain = keyed.model_copy(update={"keyframes": None})
    other = _config(tmp_path, keyframes={"seconds": 0.5})
    overlapping = _config(tmp_path, keyframes={"seconds": 0.4, "every_metres": 1.0})
    keys = {_data_key(c, c.dataset) for c in (keyed, plain, other, overlapping)}
    assert len(keys) == 4
    # windows one after another dump (and key) as they did before every_metres existed
    assert "every_metres" not in KeyframeParams(seconds=0.4).model_dump(mode="json")
    assert KeyframeParams(seconds=0.4, every_metres=1.0).model_dump()["every_metres"] == 1.0


def test_the_runner_uses_the_simulators_drifting_odometry(tmp_path):
    from placerec.experiment.runner import loop_sequence

    seq = loop_sequence(_config(tmp_path))
    assert isinstance(seq, KeyframeSequence) and seq.prepare is not None
    base = seq.base
    np.testing.assert_allclose(seq.keyframe_poses, base.odometry_poses[[3, 7, 11, 15]])
    assert not np.allclose(seq.keyframe_poses, seq.poses)  # drifting odometry, true poses


def test_loop_closure_detector_on_keyframes_finds_a_revisit(sim16):
    from placerec.loop_closure import LoopClosureDetector
    from placerec.recognizer import make_pipeline

    scans = [sim16[i] for i in range(8)]
    detector = LoopClosureDetector(
        make_pipeline("scan-context"),
        threshold=0.0,
        exclusion_frames=2,
        keyframes=KeyframeParams(seconds=0.4),
    )
    found = []
    for lap in range(2):  # the same stretch twice, 10 s apart
        for i, scan in enumerate(scans):
            closures = detector.process(scan, sim16.poses[i], timestamp=10.0 * lap + i / RATE_HZ)
            if i % 4 != 3:
                assert (
                    closures == []
                    and detector.last_candidates == []
                    and "keyframe" in detector.last_timing_ms
                )
            found += closures
    assert detector.n_processed == 4  # keyframe ids
    assert [detector.keyframe_scans(k) for k in range(4)] == [
        (0, 1, 2, 3),
        (4, 5, 6, 7),
        (8, 9, 10, 11),
        (12, 13, 14, 15),
    ]
    assert {(c.query_id, c.match_id) for c in found} >= {(2, 0), (3, 1)}
    best = next(c for c in found if (c.query_id, c.match_id) == (2, 0))
    # the same scans, so the keyframes coincide: the relative pose (query keyframe -> matched keyframe) is ~identity
    assert best.relative_pose is not None
    np.testing.assert_allclose(best.relative_pose, np.eye(4), atol=0.05)
    assert detector.flush() == [] and detector.n_processed == 4  # nothing left over


def test_loop_closure_detector_with_keyframes_needs_scans():
    from placerec.loop_closure import LoopClosureDetector
    from placerec.recognizer import make_pipeline

    detector = LoopClosureDetector(make_pipeline("scan-context"), 0.0, keyframes=KeyframeParams(seconds=0.4))
    with pytest.raises(ScanDataError, match="scan itself"):
        detector.process(None, description={})
    with pytest.raises(ConfigError, match="no keyframes"):
        LoopClosureDetector(make_pipeline("scan-context"), 0.0).keyframe_scans(0)


def test_kiss_icp_odometry_offline_and_online(sim16):
    pytest.importorskip("kiss_icp")
    params = KeyframeParams(metres=3.0, odometry="kiss-icp")
    seq = KeyframeSequence(sim16, params)  # KISS-ICP from the sequence's first pose
    assert len(seq) >= 2
    np.testing.assert_allclose(seq.keyframe_poses[:, :3, 3], seq.poses[:, :3, 3], atol=0.5)
    builder = KeyframeBuilder(params, label=sim16.name)
    online = [
        k for i in range(len(sim16)) if (k := builder.add(sim16[i], sim16.poses[0] if i == 0 else None))
    ]
    assert [k.scan_indices for k in online] == [seq.scan_indices(k) for k in range(len(online))]
    np.testing.assert_allclose(online[0].pose, seq.keyframe_poses[0], atol=1e-6)


def test_placerec_detect_with_keyframes(sim16, tmp_path):
    from typer.testing import CliRunner

    from placerec.cli import app
    from placerec.sim import write_kitti_sequence

    scans = [sim16[i] for i in range(4)] * 2  # the same stretch twice
    poses = np.concatenate([sim16.poses[:4]] * 2)
    seq = ListSequence(scans, poses, np.arange(8) / RATE_HZ, name="twice")
    folder = write_kitti_sequence(seq, tmp_path / "twice", progress=False)  # KITTI scans have no point times
    out = tmp_path / "out"
    args = [
        "detect",
        str(folder),
        "--pipeline",
        "scan-context",
        "--threshold",
        "0.0",
        "--exclusion-frames",
        "2",
    ]
    result = CliRunner().invoke(app, [*args, "--keyframes-seconds", "0.2", "--out", str(out)])
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "closures.json").read_text())
    assert summary["n_scans"] == 4 and summary["keyframes"]["seconds"] == 0.2
    assert summary["keyframes"]["deskew"] is False  # no per-point times: accumulated without de-skew
    closures = {(c["query_id"], c["match_id"]): c for c in summary["closures"]}
    assert (2, 0) in closures and closures[(2, 0)]["query_file"].endswith("[4:6]")
    both = CliRunner().invoke(app, [*args, "--keyframes-seconds", "1", "--keyframes-metres", "2"])
    assert both.exit_code != 0 and "exactly one" in both.output
