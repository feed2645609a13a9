"""`placerec slam` and `OnlineSlam` with keyframes (``loops.keyframes``): the graph keeps a pose a scan, closures
between keyframes enter as loop factors between their windows' last scans, candidates are recorded in scan ids;
a saved or prior map with keyframes is refused; a non-spinning sensor without keyframes is warned about."""

from __future__ import annotations

import csv
import json
import logging

import numpy as np
import pytest

from placerec.errors import ConfigError
from placerec.keyframes import KeyframeParams
from placerec.realtime import RealtimeParams
from placerec.recognizer import make_pipeline
from placerec.sim import SimulatedSequence
from placerec.slam import OnlineSlam
from placerec.slam_app.config import load_slam_config
from placerec.slam_app.run import run_slam

RATE_HZ = 10.0


@pytest.fixture(scope="module")
def stretch():
    return SimulatedSequence(world="town", sensor="vlp16", n_scans=8, rate_hz=RATE_HZ, clutter=False, seed=3)


@pytest.mark.parametrize(
    "realtime", [None, RealtimeParams(budget_ms=100.0, max_backlog=3)], ids=["seq", "rt"]
)
def test_keyframe_closures_join_the_last_scans_of_their_windows(stretch, realtime):
    slam = OnlineSlam(
        make_pipeline("scan-context"),
        threshold=0.0,
        exclusion_frames=2,
        keyframes=KeyframeParams(seconds=0.4),
        realtime=realtime,
    )
    for lap in range(2):  # the same stretch twice, 10 s apart: keyframes of scans 0-3, 4-7, 8-11, 12-15
        for i in range(len(stretch)):
            slam.process(stretch[i], stretch.poses[i], timestamp=10.0 * lap + i / RATE_HZ)
    poses = slam.finish()
    assert poses.shape == (16, 4, 4) and slam.n_scans == 16  # a pose a scan
    assert [slam.detector.keyframe_scans(k) for k in range(4)] == [
        (0, 1, 2, 3),
        (4, 5, 6, 7),
        (8, 9, 10, 11),
        (12, 13, 14, 15),
    ]
    loops = {(lp.query_id, lp.match_id): lp for lp in slam.loops}
    assert {(11, 3), (15, 7)} <= set(loops)  # keyframes 2 -> 0 and 3 -> 1, in the graph's scan ids
    # the second lap's scans are the first lap's: each keyframe pair coincides, T_match_query ~ identity
    np.testing.assert_allclose(loops[(11, 3)].T_match_query, np.eye(4), atol=0.05)
    assert len(slam.candidates) == 16
    queried = [i for i, c in enumerate(slam.candidates) if c]
    assert set(queried) <= {11, 15} and 11 in queried  # keyframes 0 and 1 have nothing eligible
    for i in queried:
        assert all(c.query_id == i and c.match_id in (3, 7) for c in slam.candidates[i])
    with pytest.raises(ConfigError, match="descriptions do not accumulate"):
        slam.process(None, stretch.poses[0], description=object())  # type: ignore[arg-type]


def test_keyframes_with_join_pipelines_are_refused(tmp_path):
    with pytest.raises(ConfigError, match="prior_map.join_pipelines: not with loops.keyframes"):
        load_slam_config(
            None,
            [
                "loops.keyframes={seconds: 0.5}",
                f"prior_map.path={tmp_path / 'map'}",
                "prior_map.join_pipelines=[scan-context]",
            ],
        )
    with pytest.raises(ConfigError, match="loops.keyframes"):
        load_slam_config(None, ["loops.keyframes={secs: 0.5}"])


def test_slam_with_keyframes_on_a_livox_style_scanner(tmp_path, caplog):
    """A MID-360-like scanner's 10 Hz frames, taken while moving: warned about without keyframes. With 0.5 s
    keyframes (5 scans) and no threshold, the keyframes 1 s apart along the road close onto each other: loops
    between the last scans of their windows (4, 9, 14, ...), right against those scans' true poses, which they would
    not be if keyframe ids were taken for scan ids."""
    sets = ["dataset.simulator.sensor=mid360", "dataset.simulator.rate_hz=10", "dataset.simulator.sweep_motion=true",
            "dataset.simulator.n_scans=40", "output.progress=false", "output.figures=false",
            "loops.pipeline.name=scan-context", "loops.exclusion={frames: 2}", "loops.threshold=0.0"]  # fmt: skip
    with caplog.at_level(logging.WARNING, logger="placerec.slam_app.run"):
        run_slam(load_slam_config(None, sets), tmp_path / "single")
    assert "set loops.keyframes" in caplog.text
    caplog.clear()
    cfg = load_slam_config(None, [*sets, "loops.keyframes={seconds: 0.5}"])
    with caplog.at_level(logging.WARNING, logger="placerec.slam_app.run"):
        run, payload = run_slam(cfg, tmp_path / "kf")
    assert "set loops.keyframes" not in caplog.text
    loops = payload["loops"]
    assert payload["n_scans"] == 40 and loops["accepted"] >= 3
    assert loops["false_accepted"] == 0 and loops["max_translation_error"] < 0.2
    rows = list(csv.DictReader((run / "loops.csv").open()))
    assert len(rows) == loops["accepted"]
    assert all(int(r["query_id"]) % 5 == 4 and int(r["match_id"]) % 5 == 4 for r in rows)
    assert all(float(r["true_distance"]) > 5.0 for r in rows)  # keyframes two or more windows apart
    stages = json.loads((run / "metrics.json").read_text())["time_ms"]["stages"]
    assert (
        stages["keyframe"]["n"] == 40 and stages["keyframe"]["mean"] > 0
    )  # the build counts in the scan's time


def test_a_slam_run_with_keyframes_saves_a_map_of_keyframes(tmp_path):
    """``output.save_map`` with ``loops.keyframes``: the map's places are the run's keyframes (its database the
    detector's), each at its window's last scan's optimised pose; the graph's odometry factors compose the scans'
    between those scans, its loops join keyframe ids; another drive's keyframes are localised right in it."""
    from placerec.io import read_poses
    from placerec.maps import MapArtifact
    from placerec.slam_app.localize import localize_sequence

    sets = ["dataset.simulator.sensor=mid360", "dataset.simulator.rate_hz=10", "dataset.simulator.sweep_motion=true",
            "dataset.simulator.n_scans=40", "output.progress=false", "output.figures=false",
            "loops.pipeline.name=scan-context", "loops.exclusion={frames: 2}", "loops.threshold=0.0",
            "loops.keyframes={seconds: 0.5}", f"output.save_map={tmp_path / 'map'}"]  # fmt: skip
    run, payload = run_slam(load_slam_config(None, sets), tmp_path / "run")
    the_map = MapArtifact.open(tmp_path / "map")
    ends = np.arange(4, 40, 5)  # keyframes of 5 scans each
    assert len(the_map) == 8 and the_map.scan_index.tolist() == ends.tolist()
    optimized, _ = read_poses(run / "poses_kitti.txt")
    np.testing.assert_allclose(the_map.poses, optimized[ends], atol=1e-9)
    graph = the_map.graph()
    assert graph is not None and [(i, j) for i, j, _, _ in graph.odometry] == [(k, k + 1) for k in range(7)]
    odometry, _ = read_poses(run / "odometry_kitti.txt")
    for (
        i,
        j,
        T,
        sigmas,
    ) in graph.odometry:  # the scans' steps composed: the odometry between the two keyframes
        np.testing.assert_allclose(T, np.linalg.inv(odometry[ends[i]]) @ odometry[ends[j]], atol=1e-6)
        assert (sigmas > 0).all()
    rows = list(csv.DictReader((run / "loops.csv").open()))
    assert {(lp.match_id, lp.query_id) for lp in graph.loops} == {
        (int(r["match_id"]) // 5, int(r["query_id"]) // 5) for r in rows
    } and len(rows) == payload["loops"]["accepted"] >= 3
    drive = SimulatedSequence(world="town", sensor="mid360", n_scans=30, rate_hz=RATE_HZ, sweep_motion=True,
                              seed=11, world_seed=0, unit_seed=0)  # fmt: skip
    found = localize_sequence(the_map, drive, None, "global", "none", None, KeyframeParams(seconds=0.5))
    correct = found.correct()
    assert correct is not None and correct.sum() >= 5, [f.reason for f in found.fixes]


def test_a_second_keyframe_session_joins_a_map_of_keyframes(tmp_path, caplog):
    """Multi-session with ``loops.keyframes``: a second MID-360 drive of the same world (other clutter and noise)
    against the first one's map of keyframes: joined where it truly is, its inter-session closures right (keyframe
    scans onto map places), and the merged map holds both sessions' keyframes with the inter-session edges."""
    from placerec.maps import MapArtifact

    common = ["dataset.simulator.sensor=mid360", "dataset.simulator.rate_hz=10", "dataset.simulator.sweep_motion=true",
              "output.progress=false", "output.figures=false", "loops.pipeline.name=scan-context",
              "loops.exclusion={frames: 2}", "loops.threshold=0.2", "loops.keyframes={seconds: 0.5}"]  # fmt: skip
    run_slam(load_slam_config(None, [*common, "dataset.simulator.n_scans=40", f"output.save_map={tmp_path / 'm1'}"]),
             tmp_path / "r1")  # fmt: skip
    second = [*common, "dataset.simulator.n_scans=30", "dataset.simulator.seed=11", "dataset.simulator.world_seed=0",
              "dataset.simulator.unit_seed=0", f"prior_map.path={tmp_path / 'm1'}", f"output.save_map={tmp_path / 'm2'}"]  # fmt: skip
    with caplog.at_level(logging.WARNING, logger="placerec.slam_app.run"):
        run, payload = run_slam(load_slam_config(None, second), tmp_path / "r2")
    assert "unlike places" not in caplog.text
    pm = payload["prior_map"]
    assert pm["joined"] and pm["inter_session_closures"] >= 2 and pm["rejected_by_graph"] == 0, pm
    truth = SimulatedSequence(
        world="town", sensor="mid360", n_scans=1, rate_hz=RATE_HZ, seed=11, world_seed=0
    )
    assert np.linalg.norm(np.array(pm["T_map_session"])[:3, 3] - truth.poses[0][:3, 3]) < 0.3
    merged = MapArtifact.open(tmp_path / "m2", check_hashes=True)
    assert [s.count for s in merged.manifest.sessions] == [8, 6] and len(merged) == 14
    graph = merged.graph()
    assert graph is not None and len(graph.odometry) == 7 + 5
    assert any(lp.match_id < 8 <= lp.query_id for lp in graph.loops)  # inter-session edges, in keyframe ids
    assert max(max(lp.match_id, lp.query_id) for lp in graph.loops) < 14
    # a session of single frames against that map of keyframes is told it compares unlike places
    single = [x for x in second if not x.startswith(("loops.keyframes", "output.save_map"))]
    with caplog.at_level(logging.WARNING, logger="placerec.slam_app.run"):
        run_slam(load_slam_config(None, [*single, "dataset.simulator.n_scans=5"]), tmp_path / "r3")
    assert "the map's places are keyframes" in caplog.text
