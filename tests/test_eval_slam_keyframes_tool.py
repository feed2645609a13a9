"""tools/eval_slam_keyframes.py on a short drive: both parts' rows, the keyframe settings the sensor benchmark
captures with, the second drive of a world."""

from __future__ import annotations

import json

import pytest
from tool_modules import load_tool


def test_both_parts_on_a_short_drive(capsys: pytest.CaptureFixture[str]) -> None:
    tool = load_tool("eval_slam_keyframes")
    assert tool.keyframe_setting("mid360") == "loops.keyframes={seconds: 1.0, every_metres: 1.8}"
    assert tool.second_drive(4601, [4601]) == 4602 and tool.second_drive(0, [0]) == tool.TUNING_SECOND_DRIVE
    out = tool.main(["--scans", "40", "--sensors", "mid360", "--pipelines", "scan-context"])
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["tool"] == "eval_slam_keyframes"
    assert out["split"] == "tuning"
    single, kf = out["frames"]
    assert (single["keyframes"], kf["keyframes"]) == (False, True) and single["frames"] == kf["frames"] == 40
    assert single["ate_odometry_m"] == kf["ate_odometry_m"] and kf["threshold"] == 0.2
    (s,) = out["sessions"]
    assert s["drives"] == [0, tool.TUNING_SECOND_DRIVE]
    assert s["joined"] and s["keyframes"] == [12, 12]  # 1 s keyframes every 1.8 m of a 4 s drive
    assert s["inter_session_closures"] >= 2 and s["inter_session_false"] == 0 and s["merged_ate_m"] < 0.2
