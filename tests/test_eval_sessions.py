"""tools/eval_sessions.py on a tiny cut: a cell's fields, a revisit relocalised and joined, a disjoint one not."""

from __future__ import annotations

from pathlib import Path

import pytest
from tool_modules import load_tool

pytest.importorskip("gtsam")


def _tool():
    return load_tool("eval_sessions")


def test_a_revisit_cell_is_relocalised_and_joined_and_a_disjoint_one_is_not(tmp_path: Path) -> None:
    tool = _tool()
    cell = tool.run_cell("town", 0, "revisit", scans=25, kidnaps=2, work=tmp_path)
    assert {"relocalisation", "kidnap", "multisession", "slam_session1", "n_map", "n_query"} <= set(cell)
    r = cell["relocalisation"]
    assert r["scans"] == 25 and r["overlap_scans"] == 25
    assert r["success"] >= 0.9 and r["wrong"] == 0 and r["tracking_ms"]["n"] > 0
    assert cell["kidnap"]["trials"] == 0 and "skipped" in cell["kidnap"]  # 25 m leave no 50 m teleport
    m = cell["multisession"]
    assert m["joined"] and m["false_inter_loops"] == 0 and m["merged_ate_rmse"] < 0.15
    assert m["join_error_m"]["median"] < 0.15 and cell["slam_session1"]["scans"] == 25
    truth = cell["multisession_truth_map"]  # the same session 2 against the true-pose map
    assert truth["joined"] and truth["false_inter_loops"] == 0 and truth["merged_ate_rmse"] < 0.15
    assert "|" in tool.cell_line(cell) and "refused" not in tool.cell_line(cell)
    gated = {**cell, "multisession": {**m, "refused_by_gate": 2, "false_refused_by_gate": 1}}
    assert "(0 false, 2 refused by the gate (1 false))" in tool.cell_line(gated)
    (slam_info,) = tmp_path.glob("*-slam.json")
    made = slam_info.stat().st_mtime_ns

    other = tool.run_cell(
        "town", 0, "disjoint", scans=25, kidnaps=2, work=tmp_path
    )  # session 1's maps reused
    assert other["relocalisation"]["overlap_scans"] == 0 and other["relocalisation"]["wrong"] == 0
    assert not other["multisession"]["joined"] and other["multisession"]["merged_ate_rmse"] is None
    assert not other["multisession_truth_map"]["joined"]
    assert len(list(tmp_path.glob("*-truth"))) == 1
    assert slam_info.stat().st_mtime_ns == made  # session 1's SLAM map too: the same config and parameters


def test_a_cells_key_holds_the_map_pipelines_parameters_on_its_sensor() -> None:
    """The VLP-16's own pipeline settings (placerec.sensor_presets) are part of a cell's key: a cell or map made
    with other parameters at the same thresholds is not reused."""
    tool = _tool()
    vlp16, hdl64 = tool.settings("vlp16", None, 5, 0), tool.settings("hdl64", None, 5, 0)
    assert vlp16["params"] == tool.map_params(None, "vlp16") != hdl64["params"]


def test_slam_odometry_reaches_both_sessions_configs_and_the_cache_key() -> None:
    from placerec.sim.sessions import make_session_pair
    from placerec.slam_app.config import load_slam_config

    tool = _tool()
    pair = make_session_pair("town", "vlp16", 0, "revisit", n_scans=5)
    for role in ("map", "query"):
        cfg = load_slam_config(tool.SLAM_CONFIG, tool.slam_overrides(pair, role, "kiss-icp"))
        assert cfg.odometry.source == "kiss-icp"
        assert (
            load_slam_config(tool.SLAM_CONFIG, tool.slam_overrides(pair, role)).odometry.source == "dataset"
        )
    kiss = tool.settings("vlp16", None, 5, 0, slam_odometry="kiss-icp")
    drift = tool.settings("vlp16", None, 5, 0)
    assert (
        kiss["slam_odometry"] == "kiss-icp" and "slam_odometry" not in drift
    )  # cached cells of before still match


def test_the_odometry_gate_reaches_both_sessions_configs_and_the_cache_key() -> None:
    from placerec.sim.sessions import make_session_pair
    from placerec.slam_app.config import load_slam_config

    tool = _tool()
    pair = make_session_pair("town", "vlp16", 0, "revisit", n_scans=5)
    for role in ("map", "query"):
        gated = load_slam_config(tool.SLAM_CONFIG, tool.slam_overrides(pair, role, gate=True))
        assert gated.loops.odometry_gate is not None and gated.loops.odometry_gate.per_metre == 0.04
        assert load_slam_config(tool.SLAM_CONFIG, tool.slam_overrides(pair, role)).loops.odometry_gate is None
    gate = tool.settings("vlp16", None, 5, 0, odometry_gate=True)
    plain = tool.settings("vlp16", None, 5, 0)
    # cached cells of before (no gate) still match their settings
    assert gate["odometry_gate"] is True and "odometry_gate" not in plain
    summary = tool._summary([])
    assert summary["refused_by_gate"] == 0 and summary["false_refused_by_gate"] == 0
    assert summary["success_by_world"] == {}


def test_a_map_config_and_localizer_settings_reach_the_map_the_localizer_and_the_key(tmp_path: Path) -> None:
    """``--map-config``: the true-pose map built with that MapBuild YAML's pipelines and preprocessing (its own
    folder, its own cell key); ``--localize-set``: LocalizerParams for relocalisation and kidnaps."""
    from placerec.maps import MapArtifact

    tool = _tool()
    config = Path(__file__).resolve().parents[1] / "configs" / "map_cross_sensor.yaml"
    build = tool.map_build(tmp_path / "m", None, config)
    assert [p.name for p in build.pipelines] == ["scan-context"] and build.preprocess.elevation_deg == [
        -15.0,
        2.0,
    ]
    assert tool.pipeline_label(None, config) == "scan-context-map_cross_sensor"
    plain, cross = tool.settings("vlp16", None, 5, 0), tool.settings("vlp16", None, 5, 0, map_config=config)
    assert plain["params"] != cross["params"] and cross["map_config"]["path"] == str(config)
    assert "map_config" not in plain  # cached cells of before still match
    params = tool.localizer_params(None, "sensor", ["threshold=0.05", "tracking.icp_moves=keyframe"])
    assert params.allow_other_sensor and params.threshold == 0.05 and params.tracking.icp_moves == "keyframe"
    with pytest.raises(Exception, match="tracking.icp_move"):
        tool.localizer_params(None, "sensor", ["tracking.icp_move=keyframe"])
    from placerec.sim.sessions import make_session_pair

    pair = make_session_pair("town", "vlp16", 0, "sensor", n_scans=6)
    folder = tool.true_map(pair, None, tmp_path / "truth", config)
    m = MapArtifact.open(folder)
    assert [p.name for p in m.manifest.pipelines] == ["scan-context"]
    assert m.preprocess().elevation_deg == [-15.0, 2.0]
    made = (folder / "manifest.json").stat().st_mtime_ns
    assert tool.true_map(pair, None, tmp_path / "truth", config) == folder
    assert (folder / "manifest.json").stat().st_mtime_ns == made  # reused, not built again
    # a cell on that map: relocalised with the given settings; the join diagnostic needs the SLAM's own pipelines
    params = tool.localizer_params(None, "sensor", ["threshold=0.05", "tracking.icp_moves=keyframe"])
    cell = tool.run_cell(
        "town", 0, "sensor", scans=8, kidnaps=0, work=tmp_path / "cells", params=params, map_config=config
    )
    assert cell["relocalisation"]["wrong"] == 0 and cell["relocalisation"]["success"] >= 0.75
    assert cell["multisession_truth_map"] is None and tool.cell_line(cell).endswith("| - |")
    assert tool._summary([cell])["max_merged_ate_truth_map"] is None
    # per world: the overlap of all its cells together (two halves of one world: 3 of 4 and 4 of 4 -> 7 / 8)
    half = {"world": "w", "seed": 0, "kind": "revisit", "multisession": cell["multisession"], "multisession_truth_map": None,
            "kidnap": {"trials": 0}}  # fmt: skip
    cells = [{**half, "relocalisation": {**cell["relocalisation"], "correct_in_overlap": n, "overlap_scans": 4,
                                         "success": n / 4}} for n in (3, 4)]  # fmt: skip
    got = tool._summary(cells)
    assert got["success_by_world"] == {"w": 7 / 8} and got["min_success"] == 0.75


def test_a_keyframe_cell_localises_keyframes_and_joins_keyframe_sessions(tmp_path: Path) -> None:
    """``--keyframes``: a MID-360's sessions driven as the sensor benchmark captures it; the true-pose map's places,
    relocalisation and kidnaps are keyframes (at their last frames), both SLAM sessions run the keyframe config."""
    from placerec.errors import ConfigError
    from placerec.maps import MapArtifact
    from placerec.sim.sessions import make_session_pair
    from placerec.slam_app.config import load_slam_config

    tool = _tool()
    kf = tool.capture("mid360")
    assert (kf.seconds, kf.every_metres) == (1.0, 1.8)
    with pytest.raises(ConfigError, match="vlp16"):
        tool.capture("vlp16")
    pair = make_session_pair("town", "mid360", 0, "revisit", n_scans=80, rate_hz=10, sweep_motion=True)
    q = tool.queries(pair, kf)
    assert len(q.seq) < 80 and q.places[-1] == 79 and len(q.odometry) == len(q.seq)
    cfg = load_slam_config(tool.SLAM_CONFIG_KEYFRAMES, tool.slam_overrides(pair, "map", keyframes=kf))
    assert cfg.loops.keyframes is not None and cfg.loops.keyframes.every_metres == 1.8
    assert cfg.loops.threshold == 0.1  # ORB-DBoW's operating threshold on the MID-360
    keyed = tool.settings("mid360", "scan-context", 80, 2, keyframes=kf)
    assert keyed["slam_config"] == tool.SLAM_CONFIG_KEYFRAMES and keyed["keyframes"]["every_metres"] == 1.8
    assert "keyframes" not in tool.settings(
        "mid360", "scan-context", 80, 2
    )  # cached cells of before still match

    cell = tool.run_cell("town", 0, "revisit", "mid360", "scan-context", scans=80, kidnaps=2, work=tmp_path,
                         keyframes=kf)  # fmt: skip
    r = cell["relocalisation"]
    assert r["scans"] == len(q.seq) and r["overlap_scans"] == len(q.seq)
    assert r["success"] >= 0.9 and r["wrong"] == 0
    # every accepted global fix's score, for choosing a threshold on tuning cells: the first fix at least
    assert r["global_scores"]["right"] and not r["global_scores"]["wrong"]
    assert r["by_mode"]["global"] == len(r["global_scores"]["right"])
    k = cell["kidnap"]
    assert k["trials"] == 2 and k["false_first_fixes"] == 0
    assert len(k["global_scores"]["right"]) + len(k["global_scores"]["wrong"]) <= 2
    m = cell["multisession"]
    assert m["joined"] and m["false_inter_loops"] == 0 and m["merged_ate_rmse"] < 0.15
    (truth,) = tmp_path.glob("*-kf-scan-context-truth")
    assert MapArtifact.open(truth).places == kf.model_dump(mode="json")  # a map of keyframes
    assert cell["multisession_truth_map"] is None  # that map has no ORB-DBoW database for the join
