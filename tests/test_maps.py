"""The map artifact (placerec.maps.artifact, placerec.artifacts.map, ``placerec map build``, ``placerec info MAP``):
what it stores comes back, a query against it gives poses in the map frame, and every kind of damage to the folder
is an ArtifactError naming the file."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from placerec.artifacts import build
from placerec.artifacts.map import MapBuild, select_keyframes, write_map
from placerec.cli import app
from placerec.errors import ArtifactError, ConfigError
from placerec.maps import MapArtifact, MapGraph, MapMismatchError, MapWriter, is_map_folder
from placerec.preprocess import preprocess_scan
from placerec.recognizer import make_pipeline
from placerec.sim import SimulatedSequence
from placerec.slam.graph import LoopFactor
from placerec.types import SensorInfo

N_SCANS = 30


@pytest.fixture(scope="module")
def seq() -> SimulatedSequence:
    return SimulatedSequence(world="town", sensor="vlp16", n_scans=N_SCANS, seed=3)


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory, seq: SimulatedSequence) -> Path:
    out = tmp_path_factory.mktemp("maps") / "town"
    cfg = MapBuild.model_validate(
        {
            "source": {"sim": {"world": "town", "scans": N_SCANS, "seed": 3}},
            "out": str(out),
            "pipelines": [{"name": "orb-hbst"}, {"name": "scan-context"}],
            "keyframe_metres": 0,
        }
    )
    return write_map(seq, cfg)


@pytest.fixture
def copy(built: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "copy"
    shutil.copytree(built, dst)
    return dst


def test_stored_keyframes_come_back(built: Path, seq: SimulatedSequence) -> None:
    m = MapArtifact.open(built)
    assert len(m) == N_SCANS and is_map_folder(built)
    np.testing.assert_array_equal(m.scan_index, np.arange(N_SCANS))
    np.testing.assert_allclose(m.poses, seq.poses)
    assert [p.name for p in m.manifest.pipelines] == ["orb-hbst", "scan-context"]
    # each pipeline's operating threshold on the map's sensor, chosen on VLP-16 tuning cells with the VLP-16's
    # settings, which its databases were built with (placerec.sensor_presets)
    assert [p.threshold for p in m.manifest.pipelines] == [0.2, 0.1]
    assert all(p.params["verify"]["score"]["min_fitness_ratio"] == 0.75 for p in m.manifest.pipelines)
    assert m.manifest.pipelines[0].params["feature_params"]["nfeatures"] == 1000
    assert m.manifest.sensor is not None and m.manifest.sensor["name"] == "vlp16"
    # the stored cloud is the scan voxelised at 0.4 m, in the keyframe's frame, to within the int16 step
    cloud = m.cloud(7)
    scan = preprocess_scan(seq[7], None, keep_organized=True)
    from scipy.spatial import cKDTree

    d, _ = cKDTree(scan.xyz).query(cloud)
    assert 1000 < len(cloud) < len(scan.xyz) and np.percentile(d, 99) < 0.4
    ids, dist = m.nearest(seq.poses[12, :3, 3] + [0.2, 0.0, 0.0], k=3)
    assert ids[0] == 12 and dist[0] == pytest.approx(0.2) and (np.diff(dist) >= 0).all()
    ids, _ = m.nearest(seq.poses[12, :3, 3], k=5, radius=1.5)
    assert set(ids) == {11, 12, 13}
    with pytest.raises(IndexError):
        m.cloud(N_SCANS)


def test_a_query_against_the_map_gives_its_pose_in_the_map_frame(built: Path) -> None:
    m = MapArtifact.open(built)
    other = SimulatedSequence(
        world="town", sensor="vlp16", n_scans=N_SCANS, seed=9, world_seed=3, unit_seed=3
    )
    rec = m.recognizer("orb-hbst")
    assert m.recognizer("orb-hbst") is rec  # loaded once
    found = 0
    for i in (4, 15, 25):
        cands = rec.query(preprocess_scan(other[i], None, keep_organized=True), k=3)
        good = [c for c in cands if c.accepted and c.score >= 0.25]
        if good:
            T = m.poses[good[0].match_id] @ good[0].relative_pose
            assert np.linalg.norm(T[:3, 3] - other.poses[i][:3, 3]) < 1.0
            found += 1
    assert found >= 2


def test_summary_and_cli_info(built: Path) -> None:
    s = MapArtifact.open(built).summary()
    assert s["keyframes"] == N_SCANS and set(s["pipelines"]) == {"orb-hbst", "scan-context"}
    assert s["figure"] and Path(s["figure"]).is_file()
    assert s["bytes"] == sum(f.stat().st_size for f in built.rglob("*") if f.is_file())
    res = CliRunner().invoke(app, ["info", str(built), "--check", "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.output)["keyframes"] == N_SCANS


def test_cli_build_refuses_to_overwrite_unless_asked(tmp_path: Path) -> None:
    out = tmp_path / "m"
    args = [
        "map",
        "build",
        "--sim-world",
        "town",
        "--sim-scans",
        "8",
        "-p",
        "scan-context",
        "--out",
        str(out),
    ]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    assert MapArtifact.open(out).manifest.poses_source == "ground-truth"
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 2 and "already exists" in res.output
    res = CliRunner().invoke(app, [*args, "--overwrite", "--set", "keyframe_metres=3"])
    assert res.exit_code == 0, res.output
    assert len(MapArtifact.open(out)) == 3  # 8 scans 1 m apart: 0, 3, 6
    assert [p.name for p in tmp_path.iterdir()] == ["m"]  # no temporary or old folder left


def test_a_failed_build_leaves_nothing(tmp_path: Path) -> None:
    out = tmp_path / "m"
    rec = make_pipeline("scan-context")
    with pytest.raises(RuntimeError), MapWriter(out, {"scan-context": (rec, 0.3)}, name="x") as w:
        w.add_keyframe(np.eye(4), np.random.default_rng(0).normal(size=(500, 3)))
        raise RuntimeError("interrupted")
    assert list(tmp_path.iterdir()) == []
    # a database that cannot be saved (its recognizer holds fewer entries than keyframes is the caller's
    # business; an error while saving is not): nothing at out either
    with pytest.raises(ConfigError):
        build("map", {"source": {"sim": {"world": "town", "scans": 3}}, "out": str(out), "pipelines": []})
    assert list(tmp_path.iterdir()) == []


def test_graph_round_trip_and_g2o(tmp_path: Path) -> None:
    gtsam = pytest.importorskip("gtsam")
    rec = make_pipeline("scan-context")
    poses = np.stack([np.eye(4)] * 3)
    poses[:, 0, 3] = [0.0, 1.0, 2.0]
    step = np.eye(4)
    step[0, 3] = 1.0
    sig = np.array([0.01, 0.01, 0.01, 0.05, 0.05, 0.05])
    graph = MapGraph([(0, 1, step, sig), (1, 2, step, sig)], [LoopFactor(0, 2, 2 * step - np.eye(4), 0.7)])
    graph.loops[0].T_match_query[3, 3] = 1.0
    with MapWriter(tmp_path / "g", {"scan-context": (rec, 0.3)}, name="g", poses_source="slam") as w:
        pts = np.random.default_rng(1).normal(size=(800, 3)) * 5
        for T in poses:
            rec.add(len(w), _scan(pts), T)
            w.add_keyframe(T, pts)
        w.finish(graph=graph)
    m = MapArtifact.open(tmp_path / "g")
    back = m.graph()
    assert back is not None and len(back.odometry) == 2 and len(back.loops) == 1
    np.testing.assert_allclose(back.odometry[1][2], step)
    np.testing.assert_allclose(back.odometry[0][3], sig)
    assert back.loops[0].score == pytest.approx(0.7)
    g, values = gtsam.readG2o(str(tmp_path / "g" / "graph.g2o"), True)
    assert g.size() == 3 and values.size() == 3


def _scan(pts: np.ndarray):
    from placerec.types import Scan

    return Scan(pts.astype(np.float32), np.linspace(0, 1, len(pts)).astype(np.float32))


def test_pipeline_and_query_checks(built: Path) -> None:
    m = MapArtifact.open(built)
    assert m.pipeline().name == "orb-hbst"
    m.check_pipeline("orb-hbst")
    with pytest.raises(MapMismatchError, match="nfeatures"):
        m.check_pipeline("orb-hbst", {"feature_params": {"nfeatures": 123}})
    with pytest.raises(MapMismatchError, match="no database for pipeline 'orb-dbow'.*orb-hbst"):
        m.pipeline("orb-dbow")
    m.check_query(SensorInfo(name="vlp16"), "normalised:auto")
    with pytest.raises(MapMismatchError, match="sensor 'vlp16'.*'os1-64'"):
        m.check_query(SensorInfo(name="os1-64"))
    m.check_query(SensorInfo(name="os1-64"), allow_other_sensor=True)
    with pytest.raises(MapMismatchError, match="intensity"):
        m.check_query(intensity="calibrated:table.npz")


def _manifest(path: Path) -> dict:
    return json.loads((path / "manifest.json").read_text())


def _write_manifest(path: Path, data: dict) -> None:
    (path / "manifest.json").write_text(json.dumps(data))


def test_truncated_file_names_it(copy: Path) -> None:
    f = copy / "keyframes.npz"
    f.write_bytes(f.read_bytes()[:-10])
    with pytest.raises(ArtifactError, match=r"keyframes\.npz: .* bytes, the manifest says"):
        MapArtifact.open(copy)


def test_edited_small_file_fails_its_hash(copy: Path) -> None:
    f = copy / "keyframes.npz"
    data = bytearray(f.read_bytes())
    data[len(data) // 2] ^= 0xFF
    f.write_bytes(bytes(data))
    with pytest.raises(ArtifactError, match=r"keyframes\.npz: its SHA-256 differs"):
        MapArtifact.open(copy)


def test_edited_big_file_is_found_by_check_hashes(copy: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import placerec.maps.artifact as artifact

    monkeypatch.setattr(artifact, "HASH_ON_OPEN_BYTES", 1000)  # every database counts as big here
    f = copy / "pipelines" / "scan-context.npz"
    data = bytearray(f.read_bytes())
    data[-100] ^= 0x01
    f.write_bytes(bytes(data))
    MapArtifact.open(copy)  # sizes agree: opens
    with pytest.raises(ArtifactError, match=r"scan-context\.npz: its SHA-256 differs"):
        MapArtifact.open(copy, check_hashes=True)
    res = CliRunner().invoke(app, ["info", str(copy), "--check"])
    assert res.exit_code == 2 and "SHA-256" in res.output and "Traceback" not in res.output


def test_missing_and_unlisted_files(copy: Path) -> None:
    (copy / "notes.txt").write_text("mine")
    with pytest.raises(ArtifactError, match="does not list.*notes.txt"):
        MapArtifact.open(copy)
    (copy / "notes.txt").unlink()
    (copy / "clouds.npz").unlink()
    with pytest.raises(ArtifactError, match=r"clouds\.npz: missing"):
        MapArtifact.open(copy)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda d: d.update(format_version=2), "format version 2 is not supported"),
        (lambda d: d.update(kind="places-db"), "expected 'placerec-map'"),
        (lambda d: d.update(colour="red"), "colour"),
        (lambda d: d.update(n_keyframes=N_SCANS + 1), "keyframes, the manifest says"),
        (lambda d: d["files"].update({"../evil.npz": d["files"]["graph.npz"]}) if "graph.npz" in d["files"]
         else d["files"].update({"../evil.npz": d["files"]["clouds.npz"]}), "not a path inside the map"),
        (lambda d: d["pipelines"][0].update(file="pipelines/other.npz"), "is not in 'files'"),
        (lambda d: d["sessions"][0].update(count=3), "'sessions' do not cover"),
        (lambda d: d["pipelines"][0].update(threshold="high"), "threshold"),
    ],
)  # fmt: skip
def test_bad_manifest_names_what_is_wrong(copy: Path, edit, message: str) -> None:
    data = _manifest(copy)
    edit(data)
    _write_manifest(copy, data)
    with pytest.raises(ArtifactError, match=message) as info:
        MapArtifact.open(copy)
    assert "manifest.json" in str(info.value) or ".npz" in str(info.value)


def test_manifest_not_json(copy: Path) -> None:
    (copy / "manifest.json").write_bytes(b"\xff{")
    with pytest.raises(ArtifactError, match="manifest.json is not valid JSON"):
        MapArtifact.open(copy)
    with pytest.raises(ArtifactError, match="no such map folder"):
        MapArtifact.open(copy / "nothing")


def test_select_keyframes() -> None:
    poses = np.stack([np.eye(4)] * 6)
    poses[:, 0, 3] = [0.0, 0.4, 0.8, 1.2, 3.0, 3.1]
    np.testing.assert_array_equal(select_keyframes(poses, 0), np.arange(6))
    np.testing.assert_array_equal(select_keyframes(poses, 1.0), [0, 3, 4])
    np.testing.assert_array_equal(select_keyframes(poses[:0], 1.0), [])


def test_slam_saves_its_map(tmp_path: Path) -> None:
    pytest.importorskip("gtsam")
    from placerec.slam_app.config import load_slam_config
    from placerec.slam_app.run import run_slam

    sets = ["dataset.simulator.n_scans=20", "dataset.simulator.sensor=vlp16", "output.progress=false",
            "output.figures=false", f"output.save_map={tmp_path / 'map'}"]  # fmt: skip
    cfg = load_slam_config("configs/slam_demo.yaml", sets)
    run, _ = run_slam(cfg, tmp_path / "res")
    m = MapArtifact.open(tmp_path / "map", check_hashes=True)
    assert len(m) == 20 and m.manifest.poses_source == "slam" and m.manifest.config["name"] == "slam_demo"
    from placerec.io import read_poses

    optimised, _ = read_poses(run / "poses_kitti.txt", "kitti")
    np.testing.assert_allclose(m.poses, optimised, atol=1e-6)
    graph = m.graph()
    assert graph is not None and len(graph.odometry) == 19
    assert m.manifest.pipelines[0].name == "orb-hbst" and m.manifest.pipelines[0].threshold == 0.25
    # a second run must not replace it unless asked, and fails before it starts
    (tmp_path / "res2").mkdir()
    with pytest.raises(ConfigError, match="already exists"):
        run_slam(cfg, tmp_path / "res2")
    assert list((tmp_path / "res2").iterdir()) == []


def _slam_cfg(tmp_path: Path, *sets: str):
    from placerec.slam_app.config import load_slam_config

    base = ["dataset.simulator.sensor=vlp16", "output.progress=false", "output.figures=false"]
    return load_slam_config("configs/slam_demo.yaml", [*base, *sets])


def test_a_second_session_joins_the_map_and_the_merged_map_is_saved(tmp_path: Path) -> None:
    pytest.importorskip("gtsam")
    from placerec.slam_app.run import run_slam

    first = _slam_cfg(tmp_path, "dataset.simulator.n_scans=30", f"output.save_map={tmp_path / 'm1'}")
    run_slam(first, tmp_path / "res")
    second = _slam_cfg(
        tmp_path, "dataset.simulator.n_scans=20", "dataset.simulator.seed=5", "dataset.simulator.world_seed=0",
        "dataset.simulator.unit_seed=0", f"prior_map.path={tmp_path / 'm1'}", f"output.save_map={tmp_path / 'm2'}",
        "output.figures=true",
    )  # fmt: skip
    run, payload = run_slam(second, tmp_path / "res")
    pm = payload["prior_map"]
    assert pm["joined"] and pm["inter_session_closures"] >= 10 and pm["rejected_by_graph"] == 0
    assert pm["refused_by_odometry_gate"] == 0  # no gate in this run
    # the session's odometry started at the identity; the join put it where it truly is in the map's frame
    T = np.array(pm["T_map_session"])
    truth = SimulatedSequence(world="town", sensor="vlp16", n_scans=1, seed=5, world_seed=0).poses[0]
    assert np.linalg.norm(T[:3, 3] - truth[:3, 3]) < 0.3
    assert (run / "sessions.png").is_file()
    merged = MapArtifact.open(tmp_path / "m2", check_hashes=True)
    assert len(merged) == 50 and [s.count for s in merged.manifest.sessions] == [30, 20]
    assert merged.manifest.poses_source == "merged"
    np.testing.assert_array_equal(merged.session, np.r_[np.zeros(30), np.ones(20)])
    graph = merged.graph()
    assert graph is not None and len(graph.odometry) == 29 + 19
    assert any(lp.match_id < 30 <= lp.query_id for lp in graph.loops)  # inter-session edges kept
    assert len(merged.recognizer("orb-hbst").tree.image_ids) == 50


def test_a_session_elsewhere_is_kept_separate_and_no_merged_map_is_written(tmp_path: Path) -> None:
    pytest.importorskip("gtsam")
    from placerec.slam_app.run import run_slam

    run_slam(
        _slam_cfg(tmp_path, "dataset.simulator.n_scans=15", f"output.save_map={tmp_path / 'm1'}"), tmp_path
    )
    other = _slam_cfg(
        tmp_path, "dataset.simulator.n_scans=15", "dataset.simulator.world=industrial",
        f"prior_map.path={tmp_path / 'm1'}", f"output.save_map={tmp_path / 'm2'}",
    )  # fmt: skip
    _, payload = run_slam(other, tmp_path / "res")
    assert not payload["prior_map"]["joined"] and "kept separate" in payload["prior_map"]["summary"]
    assert not (tmp_path / "m2").exists() and not list(tmp_path.glob(".m2*"))


def test_a_prior_map_that_cannot_serve_the_run_is_refused_before_it(tmp_path: Path) -> None:
    pytest.importorskip("gtsam")
    from placerec.slam_app.run import run_slam

    build("map", {"source": {"sim": {"world": "town", "scans": 5, "sensor": "os1-64"}}, "out": str(tmp_path / "m"),
                  "pipelines": [{"name": "scan-context"}]})  # fmt: skip
    for sets, message in (
        ([], "no database for pipeline 'orb-hbst'"),
        (["loops.pipeline.name=scan-context", "dataset.simulator.sensor=vlp16"], "from sensor 'os1-64'"),
        (["loops.pipeline.name=scan-context", "preprocess.intensity.mode=raw"], "intensity"),
        (["loops.pipeline.name=scan-context", "loops.pipeline.params.num_sectors=30"], "front end"),
        (["loops.pipeline.name=scan-context", "prior_map.anchor=anchored"], "has none"),
    ):
        cfg = _slam_cfg(tmp_path, "dataset.simulator.n_scans=5", f"prior_map.path={tmp_path / 'm'}",
                        "dataset.simulator.sensor=os1-64", *sets)  # fmt: skip
        with pytest.raises(ConfigError, match=message):
            run_slam(cfg, tmp_path / "res")
    assert not (tmp_path / "res").exists()


def test_a_maps_elevation_band_is_recorded_and_applied_to_its_queries(tmp_path: Path) -> None:
    out = build("map", {"source": {"sim": {"world": "town", "scans": 4}}, "out": str(tmp_path / "m"),
                        "pipelines": [{"name": "scan-context"}],
                        "preprocess": {"elevation_deg": [-15.0, 2.0]}})  # fmt: skip
    m = MapArtifact.open(out, check_hashes=True)
    assert m.preprocess().elevation_deg == [-15.0, 2.0]
    from placerec.maps import Localizer

    loc = Localizer(m)
    assert loc.preprocess.elevation_deg == [-15.0, 2.0]
    fix = loc.localize(SimulatedSequence(world="town", sensor="vlp16", n_scans=3, seed=0)[2])
    assert fix.accepted, fix.reason


def test_a_calibrated_map_carries_its_table(tmp_path: Path) -> None:
    from placerec.artifacts import build as build_artifact

    table = build_artifact(
        "calibration", {"source": {"sim": {"world": "town", "scans": 20}}, "out": str(tmp_path / "t.npz")}
    )
    out = build("map", {"source": {"sim": {"world": "town", "scans": 4}}, "out": str(tmp_path / "m"),
                        "pipelines": [{"name": "scan-context"}],
                        "preprocess": {"intensity": {"calibration": str(table)}}})  # fmt: skip
    table.unlink()  # the map needs its own copy, not the user's file
    m = MapArtifact.open(out, check_hashes=True)
    assert m.manifest.intensity == "calibrated:t.npz" and (out / "calibration.npz").is_file()
    assert m.preprocess().intensity.calibration == str(out / "calibration.npz")
    from placerec.maps import Localizer

    fix = Localizer(m).localize(SimulatedSequence(world="town", sensor="vlp16", n_scans=3, seed=0)[2])
    assert fix.accepted, fix.reason
    (out / "calibration.npz").unlink()
    data = _manifest(out)
    data["files"].pop("calibration.npz")
    _write_manifest(out, data)
    with pytest.raises(ArtifactError, match="disagree on calibration.npz"):
        MapArtifact.open(out)


def test_top_level_names_are_imported_on_first_use() -> None:
    import subprocess
    import sys

    code = (
        "import sys, placerec; assert 'placerec.maps' not in sys.modules; "
        "from placerec.maps import Localizer, MapArtifact; "
        "assert placerec.Localizer is Localizer and placerec.MapArtifact is MapArtifact"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_poses_in_another_convention_are_refused(tmp_path: Path, seq: SimulatedSequence) -> None:
    """Inverted poses (T_sensor_world) or poses of a camera frame do not fit the scans: no map is built from them,
    and a map holding them is refused as a prior map before the run."""
    from placerec.maps.artifact import MapMismatchError as Mismatch

    cam = np.array([[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1.0]])
    for name, poses in (("inverted", np.linalg.inv(seq.poses)), ("camera", seq.poses @ cam)):
        cfg = MapBuild.model_validate({"source": {"sim": {"world": "town"}}, "out": str(tmp_path / name),
                                       "pipelines": [{"name": "scan-context"}], "keyframe_metres": 0})  # fmt: skip
        with pytest.raises(Mismatch, match="the poses do not fit the scans"):
            write_map(seq, cfg, poses=poses)
        assert not (tmp_path / name).exists() and not list(tmp_path.glob(f".{name}*"))
    # the same scans at their true poses fit (write_map above in the fixture); a map written with inverted poses
    # by hand is refused when a session would join it
    rec = make_pipeline("orb-hbst")
    inverted = np.linalg.inv(seq.poses)
    with MapWriter(tmp_path / "bad", {"orb-hbst": (rec, 0.25)}, name="bad") as w:
        for i in range(12):
            scan = preprocess_scan(seq[i], None, keep_organized=True)
            rec.add(i, scan, inverted[i])
            w.add_keyframe(inverted[i], scan.xyz)
        w.finish()
    with pytest.raises(Mismatch, match="do not fit"):
        MapArtifact.open(tmp_path / "bad").check_pose_fit()


def test_the_built_map_fits_its_poses(built: Path) -> None:
    MapArtifact.open(built).check_pose_fit()


def test_the_merged_graph_holds_each_factor_once() -> None:
    """An anchored join's graph already holds the map's own factors: the merged map keeps them once."""
    from types import SimpleNamespace

    from placerec.slam_app.run import _merged_graph

    eye, sig = np.eye(4), np.ones(6)
    prior = MapGraph([(0, 1, eye, sig), (1, 2, eye, sig)], [LoopFactor(0, 2, eye, 0.5)], sig)
    joined = SimpleNamespace(
        params=SimpleNamespace(loop_sigma_rotation_deg=1.0, loop_sigma_translation=0.1),
        odometry=[(0, 1, eye, sig), (1, 2, eye, sig), (3, 4, eye, sig)],
        loops=[LoopFactor(0, 2, eye, 0.5), LoopFactor(1, 3, eye, 0.4), LoopFactor(3, 4, eye, 0.3)],
    )
    merged = _merged_graph(prior, joined, 3)  # type: ignore[arg-type]
    assert [(i, j) for i, j, _, _ in merged.odometry] == [(0, 1), (1, 2), (3, 4)]
    assert [(lp.match_id, lp.query_id) for lp in merged.loops] == [(0, 2), (1, 3), (3, 4)]


def test_the_maps_other_pipelines_add_inter_session_closures(tmp_path: Path, built: Path) -> None:
    pytest.importorskip("gtsam")
    from placerec.slam_app.run import run_slam

    # another drive (seed 5) through the map's world and with its unit (the map: seed 3)
    common = ("dataset.simulator.n_scans=12", "dataset.simulator.seed=5", "dataset.simulator.world_seed=3",
              "dataset.simulator.unit_seed=3", f"prior_map.path={built}")  # fmt: skip
    closures, stages = {}, {}
    for join in ([], ["scan-context"]):
        cfg = _slam_cfg(tmp_path, *common, f"prior_map.join_pipelines={join}")
        _, payload = run_slam(cfg, tmp_path / "res")
        closures[len(join)] = payload["prior_map"]["inter_session_closures"]
        stages[len(join)] = set(payload["time_ms"]["stages"])
        assert payload["prior_map"]["joined"]
    # Scan Context's global search of the map found closures ORB-HBST's detector did not
    assert closures[1] > closures[0] > 0
    assert "map_search" in stages[1] and "map_search" not in stages[0]
    for join, message in ((["orb-hbst"], "loops.pipeline already"), (["fpfh-votes"], "no database for")):
        with pytest.raises(ConfigError, match=message):
            run_slam(_slam_cfg(tmp_path, *common, f"prior_map.join_pipelines={join}"), tmp_path / "res2")


def test_slam_saves_more_pipelines_and_the_merged_map_extends_them(tmp_path: Path) -> None:
    pytest.importorskip("gtsam")
    from placerec.slam_app.run import run_slam

    first = _slam_cfg(tmp_path, "dataset.simulator.n_scans=20", f"output.save_map={tmp_path / 'm1'}",
                      "output.map_pipelines=[scan-context]")  # fmt: skip
    run_slam(first, tmp_path / "res")
    m1 = MapArtifact.open(tmp_path / "m1", check_hashes=True)
    assert [p.name for p in m1.manifest.pipelines] == ["orb-hbst", "scan-context"]
    sc = m1.pipeline(
        "scan-context"
    )  # its threshold on the VLP-16, with the VLP-16's settings it was chosen with
    assert sc.threshold == 0.1 and sc.params["verify"]["score"]["min_fitness_ratio"] == 0.75
    assert len(m1.recognizer("scan-context")) == 20
    second = _slam_cfg(
        tmp_path, "dataset.simulator.n_scans=12", "dataset.simulator.seed=5", "dataset.simulator.world_seed=0",
        "dataset.simulator.unit_seed=0", f"prior_map.path={tmp_path / 'm1'}", "prior_map.join_pipelines=[scan-context]",
        f"output.save_map={tmp_path / 'm2'}", "output.map_pipelines=[scan-context]",
    )  # fmt: skip
    _, payload = run_slam(second, tmp_path / "res")
    assert payload["prior_map"]["joined"]
    merged = MapArtifact.open(tmp_path / "m2", check_hashes=True)
    sc = merged.recognizer("scan-context")
    assert len(merged) == len(sc) == 32  # the map's 20 keyframes and the session's 12, one entry each
    assert len(m1.recognizer("scan-context", fresh=True)) == 20  # the prior map's file is untouched
    with pytest.raises(ConfigError, match="loops.pipeline already"):
        _slam_cfg(tmp_path, "dataset.simulator.n_scans=5", f"output.save_map={tmp_path / 'm3'}",
                  "output.map_pipelines=[orb-hbst]")  # fmt: skip


def test_slam_saves_map_pipelines_with_their_parameters_and_joins_with_its_settings(tmp_path: Path) -> None:
    """``output.map_pipeline_params`` reaches the saved map's database (merged over the sensor's settings);
    ``prior_map.join_threshold`` / ``join_ambiguity`` reach the join's global searches; a parameter for a pipeline
    the map does not hold is refused."""
    pytest.importorskip("gtsam")
    from placerec.slam_app.run import _map_searches, run_slam

    sc = "{scan-context: {num_candidates: 1000, verify: {score: {min_fitness_ratio: null}}}}"
    first = _slam_cfg(tmp_path, "dataset.simulator.n_scans=12", f"output.save_map={tmp_path / 'm1'}",
                      "output.map_pipelines=[scan-context]", f"output.map_pipeline_params={sc}")  # fmt: skip
    run_slam(first, tmp_path / "res")
    held = MapArtifact.open(tmp_path / "m1").pipeline("scan-context")
    assert (
        held.params["num_candidates"] == 1000 and held.params["verify"]["score"]["min_fitness_ratio"] is None
    )
    assert held.params["verify"]["score"]["min_score"] == 0.1  # the VLP-16's own setting kept under them
    second = _slam_cfg(tmp_path, "dataset.simulator.n_scans=5", f"prior_map.path={tmp_path / 'm1'}",
                       "prior_map.join_pipelines=[scan-context]", "prior_map.join_threshold=0.05",
                       "prior_map.join_ambiguity.max_ratio=0.85")  # fmt: skip
    (search,) = _map_searches(second, MapArtifact.open(tmp_path / "m1"))
    assert search.params.threshold == 0.05 and search.params.ambiguity.max_ratio == 0.85
    assert search.searches[0][2] == 0.05
    with pytest.raises(ConfigError, match="not in output.map_pipelines"):
        _slam_cfg(tmp_path, "dataset.simulator.n_scans=5", f"output.map_pipeline_params={sc}")
    with pytest.raises(ConfigError, match="prior map's own"):
        _slam_cfg(tmp_path, "dataset.simulator.n_scans=5", f"prior_map.path={tmp_path / 'm1'}",
                  "output.map_pipelines=[scan-context]", f"output.map_pipeline_params={sc}")  # fmt: skip
