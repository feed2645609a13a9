"""tools/bench_realtime.py: the profile of a tiny simulated sequence (every stage present, finite, queries verified)
and slam_sequence keeping the recognizer it is given even when that one is empty (falsy)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from tool_modules import load_tool

ROOT = Path(__file__).resolve().parents[1]


def _tool():
    return load_tool("bench_realtime")


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    pytest.importorskip("gtsam", reason="placerec slam needs gtsam")
    pytest.importorskip("kiss_icp", reason="the profile's odometry is KISS-ICP")
    pytest.importorskip("small_gicp", reason="verification needs small_gicp")
    tool = _tool()
    cache = tmp_path_factory.mktemp("bench_realtime")
    return tool, tool.bench(["sim-hdl64"], ["orb-hbst"], 6, cache, None, sim_exclusion=2)


def test_every_stage_is_reported_and_finite(report):
    tool, rep = report
    assert rep["cpus"] >= 1 and len(rep["load_before"]) == 3
    seq = rep["sequences"]["sim-hdl64"]
    assert seq["scans"] == 6 and seq["points"] > 50_000 and "kiss_slam" not in seq
    p = seq["pipelines"]["orb-hbst"]
    for run in ("slam", "detector"):
        stages = p[run]["stages"]
        assert list(stages) == [s.strip() for s in tool.STAGES]
        for name, s in stages.items():
            for kind in ("wall", "cpu"):
                assert len(s[kind]) == 4 and all(math.isfinite(x) for x in s[kind]), (run, name, kind)
                med, p95, mx, _ = s[kind]
                assert med <= p95 + 1e-9 <= mx + 2e-9, (run, name, kind)
    slam = p["slam"]["stages"]
    for name in (
        "read",
        "odometry",
        "preprocess",
        "describe",
        "projection",
        "features",
        "icp cloud",
        "query",
    ):
        assert slam[name]["wall"][2] > 0, name  # the queries of scans 2..5 ran (exclusion 2 frames)
    assert p["detector"]["stages"]["odometry"]["wall"][2] == 0  # the detector alone runs no odometry
    assert slam["total"]["wall"][3] >= slam["loop closure"]["wall"][3] > 0
    assert p["lc_cpu_over_odometry"] > 0 and math.isfinite(p["slam"]["ate_m"])


def test_tables_and_json_line(report, capsys):
    tool, rep = report
    tool.print_report(rep)
    line = json.dumps(tool.summary(rep))
    out = capsys.readouterr().out
    assert "placerec slam per scan, sim-hdl64" in out and "icp prepare" in out
    back = json.loads(line)
    assert back["bench"] == "realtime" and "slam" in back["sequences"]["sim-hdl64"]["pipelines"]["orb-hbst"]


def test_slam_sequence_keeps_an_empty_recognizer():
    """A recognizer with ``__len__`` is falsy while empty; slam_sequence must still use it (the map writer and the
    caller hold it), not make another."""
    pytest.importorskip("gtsam", reason="placerec slam needs gtsam")
    from placerec.recognizer import make_pipeline
    from placerec.sim import SimulatedSequence
    from placerec.slam_app.config import load_slam_config
    from placerec.slam_app.run import slam_sequence

    cfg = load_slam_config(ROOT / "configs" / "slam_demo.yaml", ["output.progress=false"])
    rec = make_pipeline("scan-context")
    assert not rec  # empty
    slam_sequence(cfg, SimulatedSequence("town", "os1-64", n_scans=3, seed=0), rec)
    assert len(rec) == 3


def test_the_accepted_closures_pose_errors_are_reported(report):
    _, rep = report
    slam = rep["sequences"]["sim-hdl64"]["pipelines"]["orb-hbst"]["slam"]
    assert slam["loops"] > 0  # scans 2 frames apart close (exclusion 2)
    med, mx = slam["loop_error_cm"]
    assert 0 <= med <= mx < 5.0  # refined poses of true closures (configs/slam_kitti.yaml)
    assert 0 <= slam["loop_error_deg"][0] <= slam["loop_error_deg"][1] < 0.5
