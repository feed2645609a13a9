"""Relocalisation against a map (placerec.maps.localizer, placerec.slam_app.localize, ``placerec localize``): a
second session over the mapped world is localised within 1 m / 5 deg by global search and by tracking, a scan of
another world gets no fix, a kidnapped robot is found again within 3 scans, queries never change the map, and the
command writes its outputs or ends with one error line."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from placerec.artifacts import build
from placerec.cli import app
from placerec.errors import ConfigError, ScanDataError
from placerec.eval.pose_error import pose_errors
from placerec.maps import MapArtifact
from placerec.maps.localizer import Fix, Localizer, LocalizerParams, correction
from placerec.sim import SimulatedSequence
from placerec.sim.export import write_kitti_sequence
from placerec.slam_app.localize import localize_sequence, report_localize
from placerec.types import ListSequence

N_MAP = 50
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def map_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("loc") / "town"
    return build(
        "map",
        {
            "source": {"sim": {"world": "town", "scans": N_MAP, "seed": 0}},
            "out": str(out),
            "pipelines": [{"name": "orb-hbst"}, {"name": "scan-context"}],
        },
    )


@pytest.fixture(scope="module")
def day2() -> SimulatedSequence:
    """Session 2: the same world and sensor unit, other clutter, noise and parked cars."""
    return SimulatedSequence(world="town", sensor="vlp16", n_scans=N_MAP, seed=11, world_seed=0, unit_seed=0)


@pytest.fixture(scope="module")
def loc(map_dir: Path) -> Localizer:
    return Localizer(map_dir)


def _correct(fix: Fix, truth: np.ndarray) -> bool:
    assert fix.accepted and fix.T_world_query is not None
    te, re = pose_errors(fix.T_world_query, truth)
    return bool(te[0] <= 1.0 and re[0] <= 5.0)


def test_global_fixes_are_within_1m_5deg(loc: Localizer, day2: SimulatedSequence) -> None:
    fixes = [loc.localize(day2[i]) for i in (3, 17, 31, 44)]
    assert all(f.mode == "global" for f in fixes)
    accepted = [(i, f) for i, f in zip((3, 17, 31, 44), fixes, strict=True) if f.accepted]
    assert len(accepted) >= 3, [f.reason for f in fixes]
    assert all(_correct(f, day2.poses[i]) for i, f in accepted)  # no accepted wrong fix
    f = accepted[0][1]
    assert f.reason == "ok" and f.keyframe_id >= 0 and f.candidates_tried >= 1 and f.score > 0
    assert {"preprocess", "describe", "query"} <= set(f.timing_ms) and f.time_ms > 0


def test_tracking_is_correct_and_faster_than_global(map_dir: Path, day2: SimulatedSequence) -> None:
    loc = Localizer(map_dir)
    idx = range(5, 25)
    fixes = [loc.track(day2[i]) for i in idx]
    assert fixes[0].mode == "global"  # no prior yet
    tracked = [f for f in fixes if f.mode == "tracking" and f.accepted]
    assert len(tracked) >= 17, [f.reason for f in fixes]
    assert all(_correct(f, day2.poses[i]) for i, f in zip(idx, fixes, strict=True) if f.accepted)
    global_ms = np.median([loc.localize(day2[i]).time_ms for i in (8, 12, 16)])
    assert np.median([f.time_ms for f in tracked]) < global_ms
    assert all(f.candidates_tried <= loc.params.tracking.max_keyframes for f in tracked)


def test_tracking_with_odometry_follows_the_caller_motion(map_dir: Path, day2: SimulatedSequence) -> None:
    loc = Localizer(map_dir)
    odom_origin = np.eye(4)
    odom_origin[:3, 3] = (100.0, -50.0, 3.0)  # odometry in its own frame
    for i in range(30, 36):
        T_odom = odom_origin @ day2.poses[i]
        f = loc.track(day2[i], T_odom)
        assert _correct(f, day2.poses[i])
        if i > 30:
            assert f.mode == "tracking"
            assert correction(loc.prior(T_odom), f.T_world_query)[0] < 0.3  # type: ignore[arg-type]


def test_another_world_gets_no_fix(loc: Localizer, day2: SimulatedSequence) -> None:
    campus = SimulatedSequence(world="campus", sensor="vlp16", n_scans=12, seed=5)
    for i in (2, 8):
        f = loc.localize(campus[i])
        assert not f.accepted and f.T_world_query is None, f
        # a prior at a mapped place: tracking refuses it, then global search finds nothing
        f = loc.localize(campus[i], prior=day2.poses[10])
        assert not f.accepted and f.reason.startswith("tracking: rejected"), f.reason


def test_kidnapped_robot_is_found_within_3_scans(map_dir: Path, day2: SimulatedSequence) -> None:
    loc = Localizer(map_dir)
    for i in (2, 3, 4):
        assert loc.track(day2[i]).accepted
    # teleported 35 m on without reset: tracking fails at the old place, global search finds the new one
    after = [loc.track(day2[i]) for i in (40, 41, 42)]
    first = next(k for k, f in enumerate(after) if f.accepted)
    assert first < 3 and _correct(after[first], day2.poses[40 + first])
    assert after[first].mode == "global" and after[-1].accepted
    loc.reset()
    f = loc.track(day2[20])
    assert f.mode == "global" and _correct(f, day2.poses[20])


def test_refused_jump_and_no_keyframe_near_the_prior(map_dir: Path, day2: SimulatedSequence) -> None:
    params = LocalizerParams.model_validate({"tracking": {"max_correction_m": 0.01, "fail_after": 3}})
    loc = Localizer(map_dir, params)
    assert loc.track(day2[10]).mode == "global"
    f = loc.track(day2[11])  # the prior (scan 10's fix) is 1 m behind: a 1 m correction is refused
    assert not f.accepted and f.mode == "tracking" and f.reason.startswith("jump"), f.reason
    far = day2.poses[12].copy()
    far[:3, 3] += (500.0, 0.0, 0.0)
    f = Localizer(map_dir).localize(day2[12], prior=far)
    assert f.mode == "global" and _correct(f, day2.poses[12])  # fell back to global search
    with pytest.raises(ScanDataError, match="prior"):
        loc.localize(day2[12], prior=np.eye(3))


def test_queries_never_change_the_map(map_dir: Path, day2: SimulatedSequence, tmp_path: Path) -> None:
    m = MapArtifact.open(map_dir)
    loc = Localizer(m)
    rec = m.recognizer()
    rec.save(tmp_path / "before.npz")
    loc.localize(day2[7])
    for i in (20, 21, 22):
        loc.track(day2[i])
    rec.save(tmp_path / "after.npz")
    assert (tmp_path / "before.npz").read_bytes() == (tmp_path / "after.npz").read_bytes()
    assert (map_dir / "pipelines" / "orb-hbst.npz").read_bytes() == (tmp_path / "after.npz").read_bytes()


def test_localize_sequence_writes_its_report(map_dir: Path, tmp_path: Path) -> None:
    seq = SimulatedSequence(world="town", sensor="vlp16", n_scans=8, seed=12, world_seed=0, unit_seed=0)
    run = localize_sequence(map_dir, seq, mode="tracking")
    m = report_localize(run, tmp_path / "r")
    assert m["scans"] == 8 and m["false_fixes"] == 0 and m["correct"] == m["accepted"] >= 7
    assert m["success_rate"] == m["correct"] / 8
    fixed = [int(v) for v in (tmp_path / "r" / "fixed_scans.txt").read_text().split()]
    assert len(fixed) == m["accepted"] == len((tmp_path / "r" / "poses_kitti.txt").read_text().splitlines())
    tum = np.loadtxt(tmp_path / "r" / "poses_tum.txt", ndmin=2)
    np.testing.assert_allclose(tum[:, 0], np.asarray(seq.timestamps)[fixed])
    rows = (tmp_path / "r" / "fixes.csv").read_text().splitlines()
    assert len(rows) == 9 and rows[0].endswith("translation_error,rotation_error_deg,correct")
    assert (tmp_path / "r" / "fixes.png").stat().st_size > 1000
    # fixes.mcap: a pose per fix, an edge per scan answered against a keyframe, the fix's pose on the edge
    from mcap.reader import make_reader

    with (tmp_path / "r" / "fixes.mcap").open("rb") as fh:
        msgs = [(ch.topic, json.loads(msg.data)) for _, ch, msg in make_reader(fh).iter_messages()]
    poses = [d for t, d in msgs if t == "/placerec/pose"]
    assert len(poses) == len(fixed)
    for i, d in zip(fixed, poses, strict=True):
        p = d["pose"]["position"]
        np.testing.assert_allclose([p["x"], p["y"], p["z"]], run.fixes[i].T_world_query[:3, 3], atol=1e-9)
    edges = [d for t, d in msgs if t == "/placerec/loop_closures"]
    assert [e["query_index"] for e in edges] == [i for i, f in enumerate(run.fixes) if f.keyframe_id >= 0]
    for e in edges:
        f = run.fixes[e["query_index"]]
        assert e["match_index"] == f.keyframe_id and e["accepted"] == f.accepted
        if f.accepted:
            T = np.asarray(e["relative_pose"]).reshape(4, 4)
            np.testing.assert_allclose(map_dir_poses(map_dir)[f.keyframe_id] @ T, f.T_world_query, atol=1e-9)
        else:
            assert e["rejection"] == f.reason

    run = localize_sequence(map_dir, seq, mode="tracking", odometry="kiss-icp")
    assert all(_correct(f, seq.poses[i]) for i, f in enumerate(run.fixes) if f.accepted)
    assert sum(f.mode == "tracking" and f.accepted for f in run.fixes) >= 6
    assert all("odometry" in f.timing_ms for f in run.fixes)
    with pytest.raises(ConfigError, match="odometry"):
        localize_sequence(map_dir, seq, mode="global", odometry="kiss-icp")


def test_a_sequence_without_poses_is_reported_without_scores(
    map_dir: Path, day2: SimulatedSequence, tmp_path: Path
) -> None:
    seq = ListSequence([day2[i] for i in (4, 5, 6)], name="no-poses")
    m = report_localize(localize_sequence(map_dir, seq, mode="global"), tmp_path)
    assert m["accepted"] == 3 and "correct" not in m and "false_fixes" not in m
    assert (tmp_path / "fixes.csv").read_text().splitlines()[0].endswith("candidates,time_ms")
    np.testing.assert_array_equal(np.loadtxt(tmp_path / "poses_tum.txt")[:, 0], [0, 1, 2])  # scan indices


def map_dir_poses(map_dir: Path) -> np.ndarray:
    return MapArtifact.open(map_dir).poses


def _cli_error(res: object) -> list[str]:
    return [line for line in res.output.splitlines() if line.startswith("error:")]  # type: ignore[attr-defined]


def test_cli_localize(map_dir: Path, tmp_path: Path) -> None:
    seq = SimulatedSequence(world="town", sensor="vlp16", n_scans=5, seed=13, world_seed=0, unit_seed=0)
    folder = write_kitti_sequence(seq, tmp_path / "day2", progress=False)
    out = tmp_path / "out"
    res = CliRunner().invoke(app, ["localize", str(map_dir), str(folder), "--out", str(out), "--set", "k=3"])
    assert res.exit_code == 0, res.output
    names = {"poses_tum.txt", "poses_kitti.txt", "fixed_scans.txt", "fixes.csv", "metrics.json", "fixes.png",
             "fixes.mcap"}  # fmt: skip
    assert names <= {p.name for p in out.iterdir()}
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["scans"] == 5 and metrics["false_fixes"] == 0 and metrics["params"]["k"] == 3
    assert metrics["pipelines"] == [p.name for p in MapArtifact.open(map_dir).manifest.pipelines]
    assert "within 1 m / 5 deg" in res.output

    res = CliRunner().invoke(app, ["localize", str(tmp_path / "nope"), str(folder)])
    assert res.exit_code == 2 and len(_cli_error(res)) == 1 and "no such map" in res.output

    other = write_kitti_sequence(
        SimulatedSequence(world="town", sensor="hdl64", n_scans=2, seed=13), tmp_path / "hdl", progress=False
    )
    res = CliRunner().invoke(app, ["localize", str(map_dir), str(other), "--out", str(tmp_path / "o2")])
    assert res.exit_code == 2 and len(_cli_error(res)) == 1 and "--allow-other-sensor" in res.output
    assert not (tmp_path / "o2").exists()  # refused before any work
    res = CliRunner().invoke(app, ["localize", str(map_dir), str(folder), "--pipeline", "nope"])
    assert (
        res.exit_code == 2 and len(_cli_error(res)) == 1 and "no database for pipeline 'nope'" in res.output
    )
    res = CliRunner().invoke(app, ["localize", str(map_dir), str(folder), "--mode", "sideways"])
    assert res.exit_code == 2 and "mode" in _cli_error(res)[0]


def test_global_search_refuses_an_ambiguous_fix(map_dir: Path, day2: SimulatedSequence) -> None:
    """`LocalizerParams.ambiguity` reaches global search: with every other accepted keyframe counted as another
    place (a 1 mm separation) and any share of the score enough, a fix with more than one accepted keyframe is
    refused with its reason; the rule itself is tested in tests/test_ambiguity.py."""
    one = {"pipeline": "orb-hbst"}
    strict = Localizer(
        map_dir,
        LocalizerParams.model_validate({**one, "ambiguity": {"max_ratio": 0.01, "separation_m": 0.001}}),
    )
    plain = Localizer(map_dir, LocalizerParams.model_validate(one))
    refused = 0
    for i in (3, 17, 31, 44):
        f, g = strict.localize(day2[i]), plain.localize(day2[i])
        if f.reason.startswith("ambiguous"):
            refused += 1
            assert (
                g.accepted and not f.accepted and f.T_world_query is None and f.keyframe_id == g.keyframe_id
            )
        else:
            assert (f.accepted, f.keyframe_id) == (g.accepted, g.keyframe_id)
    assert refused >= 1


@pytest.mark.parametrize(("map_sensor", "query_sensor"), [("hdl64", "vlp16"), ("vlp16", "os1-64")])
def test_the_cross_sensor_map_config_localises_another_sensors_scans(
    tmp_path: Path, map_sensor: str, query_sensor: str
) -> None:
    """configs/map_cross_sensor.yaml (docs/sensors.md): a map with Scan Context over the whole map and the band
    both sensors see; scans of another sensor and drive, localised with the settings the docs give (another sensor
    allowed, threshold 0.05, the ambiguity rule), are placed within 1 m / 5 deg: sparser queries of a dense map, and
    dense ones of a VLP-16 map (whose own overlap gate the config turns off)."""
    from placerec.config import read_config_file

    cfg = read_config_file(ROOT / "configs" / "map_cross_sensor.yaml")
    sim = {"world": "town", "sensor": map_sensor, "scans": 20, "seed": 0}
    out = build("map", {**cfg, "source": {"sim": sim}, "out": str(tmp_path / "map")})
    assert [p.name for p in MapArtifact.open(out).manifest.pipelines] == ["scan-context"]
    queries = SimulatedSequence(
        world="town", sensor=query_sensor, n_scans=20, seed=11, world_seed=0, unit_seed=0
    )
    params = {"allow_other_sensor": True, "threshold": 0.05, "ambiguity": {"max_ratio": 0.85}}
    loc = Localizer(out, LocalizerParams.model_validate(params))
    fixes = {i: loc.localize(queries[i]) for i in (4, 10, 15)}
    assert all(_correct(f, queries.poses[i]) for i, f in fixes.items()), {
        i: f.reason for i, f in fixes.items()
    }
    if map_sensor != "vlp16":
        return
    # tracking from the true pose: a dense OS1-64 scan's voxels overlap a VLP-16 keyframe's cloud less than the
    # keyframe's voxels overlap the scan; registering the keyframe onto the scan judges the latter
    by_keyframe = {**params, "tracking": {"icp_moves": "keyframe"}}
    fits = {}
    for moved, p in (("scan", params), ("keyframe", by_keyframe)):
        loc = Localizer(out, LocalizerParams.model_validate(p))
        fits[moved] = [loc._localize(queries[i], queries.poses[i], allow_global=False) for i in (4, 10, 15)]
    for by_scan, by_kf, i in zip(fits["scan"], fits["keyframe"], (4, 10, 15), strict=True):
        assert by_scan.mode == by_kf.mode == "tracking"
        assert _correct(by_kf, queries.poses[i]) and by_kf.fitness > by_scan.fitness + 0.1, (by_scan, by_kf)


def test_cli_localizes_another_sensors_scans_with_the_documented_settings(tmp_path: Path) -> None:
    """The commands configs/map_cross_sensor.yaml's header gives: a VLP-16 map built with it, then an OS1-64
    drive localised with `placerec localize --allow-other-sensor --set ...` (nested keys included)."""
    built = CliRunner().invoke(app, ["map", "build", "--sim-world", "town", "--sim-sensor", "vlp16", "--sim-scans", "20",
                                     "--config", str(ROOT / "configs" / "map_cross_sensor.yaml"),
                                     "--out", str(tmp_path / "map")])  # fmt: skip
    assert built.exit_code == 0, built.output
    seq = SimulatedSequence(world="town", sensor="os1-64", n_scans=6, seed=11, world_seed=0, unit_seed=0)
    folder = write_kitti_sequence(seq, tmp_path / "os1", progress=False)
    sets = ["threshold=0.05", "ambiguity.max_ratio=0.85", "tracking.icp_moves=keyframe",
            "tracking.verify.score.min_constraint=0.05"]  # fmt: skip
    args = [
        "localize",
        str(tmp_path / "map"),
        str(folder),
        "--allow-other-sensor",
        "--out",
        str(tmp_path / "out"),
    ]
    res = CliRunner().invoke(app, [*args, *(x for s in sets for x in ("--set", s))])
    assert res.exit_code == 0, res.output
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    params = metrics["params"]
    assert params["tracking"]["icp_moves"] == "keyframe" and params["ambiguity"]["max_ratio"] == 0.85
    assert params["tracking"]["verify"]["score"]["min_constraint"] == 0.05 and params["threshold"] == 0.05
    assert metrics["scans"] == 6 and metrics["false_fixes"] == 0 and metrics["correct"] == 6, metrics


@pytest.fixture(scope="module")
def hdl64_map_for_avia(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An HDL-64 map built with configs/map_cross_sensor.yaml and the band an Avia sees of it (the header's)."""
    from placerec.config import read_config_file

    cfg = read_config_file(ROOT / "configs" / "map_cross_sensor.yaml")
    cfg["preprocess"]["elevation_deg"] = [-24.9, 2.0]
    sim = {"world": "town", "sensor": "hdl64", "scans": 30, "seed": 0}
    return build("map", {**cfg, "source": {"sim": sim}, "out": str(tmp_path_factory.mktemp("hdl64") / "map")})


AVIA_SETTINGS = {"allow_other_sensor": True, "threshold": 0.05, "ambiguity": {"max_ratio": 0.85}}


def test_keyframes_of_a_livox_style_drive_are_localised(hdl64_map_for_avia: Path, tmp_path: Path) -> None:
    """A forward-looking Avia's 10 Hz frames, taken while moving, against an HDL-64 map: localised as 0.5 s
    keyframes (each fixed at its window's last scan, scored against that scan's true pose), in both modes."""
    from placerec.keyframes import KeyframeParams

    drive = SimulatedSequence(world="town", sensor="avia", n_scans=25, rate_hz=10, sweep_motion=True, seed=11,
                              world_seed=0, unit_seed=0)  # fmt: skip
    params = LocalizerParams.model_validate(AVIA_SETTINGS)
    for mode in ("tracking", "global"):
        run = localize_sequence(
            hdl64_map_for_avia, drive, params, mode, "none", None, KeyframeParams(seconds=0.5)
        )
        assert len(run.fixes) == 5 and run.keyframes == KeyframeParams(seconds=0.5)
        np.testing.assert_array_equal(run.ground_truth, drive.poses[[4, 9, 14, 19, 24]])
        correct = run.correct()
        assert correct is not None and correct.all(), [f.reason for f in run.fixes]
    metrics = report_localize(run, tmp_path / "out")
    assert metrics["scans"] == 5 and metrics["correct"] == 5 and metrics["keyframes"]["seconds"] == 0.5


def test_cli_localizes_keyframes(hdl64_map_for_avia: Path, tmp_path: Path) -> None:
    """`placerec localize --keyframes-seconds`: keyframes accumulated along the sequence's poses; a sequence
    without poses needs --poses or --odometry kiss-icp; a window needs its length."""
    drive = SimulatedSequence(
        world="town", sensor="avia", n_scans=20, rate_hz=10, seed=11, world_seed=0, unit_seed=0
    )
    folder = write_kitti_sequence(drive, tmp_path / "avia", progress=False)
    args = [
        "localize",
        str(hdl64_map_for_avia),
        str(folder),
        "--allow-other-sensor",
        "--set",
        "threshold=0.05",
    ]
    res = CliRunner().invoke(app, [*args, "--keyframes-seconds", "0.5", "--out", str(tmp_path / "out")])
    assert res.exit_code == 0, res.output
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert metrics["scans"] == 4 and metrics["keyframes"]["seconds"] == 0.5 and metrics["false_fixes"] == 0
    assert metrics["correct"] >= 3, metrics
    (folder / "poses.txt").unlink()
    res = CliRunner().invoke(app, [*args, "--keyframes-seconds", "0.5", "--out", str(tmp_path / "o2")])
    assert res.exit_code == 2 and "--poses FILE or --odometry kiss-icp" in res.output
    res = CliRunner().invoke(app, [*args, "--keyframes-every-metres", "2", "--out", str(tmp_path / "o3")])
    assert res.exit_code == 2 and "seconds" in res.output and not (tmp_path / "o3").exists()


def test_a_map_of_keyframes_localises_keyframes(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """`MapBuild.keyframes`: a map of a Livox-style drive's 0.5 s keyframes (each at its window's last scan, built
    along the poses), then another drive of the same world localised as keyframes in it, every fix right."""
    from placerec.keyframes import KeyframeParams

    sim = {"world": "town", "sensor": "avia", "scans": 40, "seed": 0, "rate_hz": 10, "sweep_motion": True}
    out = build("map", {"source": {"sim": sim}, "out": str(tmp_path / "map"), "keyframes": {"seconds": 0.5},
                        "keyframe_metres": 0, "pipelines": [{"name": "scan-context"}]})  # fmt: skip
    the_map = MapArtifact.open(out)
    assert len(the_map) == 8 and the_map.places is not None and the_map.places["seconds"] == 0.5
    assert the_map.summary()["places"].startswith("keyframes")
    route = SimulatedSequence(world="town", sensor="avia", n_scans=40, rate_hz=10, sweep_motion=True, seed=0)
    np.testing.assert_allclose(the_map.poses, route.poses[4::5])  # the windows' last scans
    drive = SimulatedSequence(world="town", sensor="avia", n_scans=30, rate_hz=10, sweep_motion=True, seed=11,
                              world_seed=0, unit_seed=0)  # fmt: skip
    with caplog.at_level(logging.WARNING, logger="placerec.slam_app.localize"):
        run = localize_sequence(out, drive, None, "global", "none", None, KeyframeParams(seconds=0.5))
    correct = run.correct()
    assert len(run.fixes) == 6 and correct is not None and correct.all(), [f.reason for f in run.fixes]
    assert "places are" not in caplog.text
    # single frames against a map of keyframes: told so
    with caplog.at_level(logging.WARNING, logger="placerec.slam_app.localize"):
        localize_sequence(out, ListSequence([drive[0]], name="one-frame"), None, "global")
    assert "the map's places are keyframes" in caplog.text
