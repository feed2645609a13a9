"""tools/eval_refine_shift.py: it sees the verification's every refinement (judged, refined and used pose), judges
right places by the judged pose, counts what max_shift kept out, and refuses test data."""

from __future__ import annotations

import importlib

import numpy as np
import pytest
from tool_modules import load_tool

from placerec.errors import ConfigError
from placerec.experiment import benchmark
from placerec.types import relative_pose
from placerec.verify import VerifyParams, verify_icp


def _tool():
    return load_tool("eval_refine_shift")


@pytest.fixture
def restored(monkeypatch):
    """The functions `watch` replaces, put back after the test."""
    verify_module = importlib.import_module("placerec.verify.verify")
    for module, name in (
        (verify_module, "_refinement"),
        (verify_module, "_refined"),
        (benchmark, "run_cell"),
    ):
        monkeypatch.setattr(module, name, getattr(module, name))


def _moved(t) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = t
    return T


def test_every_refinement_is_seen_with_its_judged_refined_and_used_pose(restored):
    from placerec.sim import SimulatedSequence

    seq = SimulatedSequence("town", "os1-64", seed=0, n_scans=14)
    T_gt = relative_pose(seq.poses[10], seq.poses[13])
    init = _moved([0.3, -0.2, 0.1]) @ T_gt
    log: list = []
    _tool().watch(log)
    v = verify_icp(seq[13].xyz, seq[10].xyz, init=init, params=VerifyParams(refine={"enabled": True}))
    capped = VerifyParams(refine={"enabled": True, "max_shift": 1e-9})
    c = verify_icp(seq[13].xyz, seq[10].xyz, init=init, params=capped)
    assert v.accepted and len(log) == 2
    np.testing.assert_array_equal(log[0].used, v.T_match_query)
    np.testing.assert_array_equal(log[0].refined, v.T_match_query)
    assert not np.array_equal(log[0].judged, log[0].refined)
    # max_shift kept the refinement out: the judged pose is used, the refined one still seen
    np.testing.assert_array_equal(log[1].used, c.T_match_query)
    np.testing.assert_array_equal(log[1].used, log[1].judged)
    assert not np.array_equal(log[1].refined, log[1].judged)
    verify_icp(seq[13].xyz, seq[10].xyz, init=init)  # refinement off: nothing seen
    assert len(log) == 2


def test_right_places_are_judged_by_the_judged_pose_and_kept_out_refinements_counted(tmp_path):
    tool = _tool()
    true = np.eye(4)
    rows = [
        # right: judged 0.10 m off, refined to 0.01 m and used
        tool.Watched("c", _moved([0.1, 0, 0]), _moved([0.01, 0, 0]), _moved([0.01, 0, 0])),
        # right: judged 0.2 m off, the refinement moved 0.6 m and was kept out
        tool.Watched("c", _moved([0, 0.2, 0]), _moved([0, 0.8, 0]), _moved([0, 0.2, 0])),
        # right, made worse: 0.02 -> 0.09 m
        tool.Watched("c", _moved([0, 0, 0.02]), _moved([0, 0, 0.09]), _moved([0, 0, 0.09])),
        # not a right place: judged 10 m off
        tool.Watched("c", _moved([10, 0, 0]), _moved([10.3, 0, 0]), _moved([10.3, 0, 0])),
    ]
    rows = [
        {"cell": "c", "sensor": "avia", "query": 20 + i, "match": i, "watched": w, "true": true}
        for i, w in enumerate(rows)
    ]
    out = tool.summary(rows, 0.5, 2.0)
    s = out["avia"]
    assert s["right"] == 3 and s["other"] == 1 and s["kept_out"] == 1 and s["worse_by_5cm"] == 1
    assert s["shift_max"] == pytest.approx(0.6) and s["judged_t_max"] == pytest.approx(0.2)
    assert s["used_t_max"] == pytest.approx(0.2) and s["other_shift_median"] == pytest.approx(0.3)
    assert out["all"] == s
    tool.write_closures(tmp_path / "closures.csv", rows)
    lines = (tmp_path / "closures.csv").read_text().splitlines()
    assert len(lines) == 5 and lines[0].startswith("cell,query,match,judged_m")
    assert lines[2] == "c,21,1,0.2000,0.000,0.8000,0.000,0.2000,0.000,0.6000"


def test_test_data_is_refused():
    tool = _tool()
    with pytest.raises(ConfigError, match="tuning cells only"):
        tool.main(["configs/benchmark_sensors.yaml"])
    with pytest.raises(ConfigError, match="test-split seed"):
        tool.main(["configs/benchmark_sensors_tuning.yaml", "--set", "seeds=[4601]"])


def test_a_run_that_refined_nothing_is_an_error(restored, monkeypatch, tmp_path):
    tool = _tool()
    monkeypatch.setattr(
        tool, "run_benchmark", lambda *args, **kwargs: (tmp_path, {})
    )  # a run with no refinement
    with pytest.raises(ConfigError, match="no accepted closure was refined"):
        tool.main(["configs/benchmark_sensors_tuning.yaml", "--out", str(tmp_path)])
