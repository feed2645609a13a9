"""tools/eval_cross_sensor.py: the quick path on a tiny configuration (JSON structure), success counted from
accepted answers only, the concatenated sequence and the common-scale fit."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from tool_modules import load_tool

from placerec.experiment.runner import PipelineRecord
from placerec.types import Candidate
from placerec.verify.ambiguity import AmbiguityParams

ROOT = Path(__file__).resolve().parents[1]


def _tool():
    return load_tool("eval_cross_sensor")


def _pose(x: float) -> np.ndarray:
    p = np.eye(4)
    p[0, 3] = x
    return p


def test_success_counts_accepted_answers_only() -> None:
    tool = _tool()
    map_poses = np.stack([_pose(0.0), _pose(10.0)])
    query_poses = np.stack([_pose(0.2), _pose(10.1), _pose(0.1)])
    rec = PipelineRecord("p", "P", "p")
    rec.query_ids = [0, 1, 2]
    rel = np.eye(4)
    rec.candidates = [
        [Candidate(0, 0, 0.9, relative_pose=rel, accepted=True)],  # right place, accepted: success
        [Candidate(1, 1, 0.9, relative_pose=rel, accepted=False)],  # right place, rejected: no answer
        [Candidate(2, 1, 0.9, relative_pose=rel, accepted=True)],  # wrong place, accepted: wrong
    ]
    f = tool.localize_figures(rec, map_poses, query_poses)
    assert f["answer_rule"] == "accepted"
    assert (f["n_success"], f["n_no_answer"], f["n_wrong"]) == (1, 1, 1)
    assert f["success"] == pytest.approx(1 / 3)
    assert f["r_at_p1"] == 0.0  # a wrong accepted answer: precision below 1.00
    rec.candidates[2] = []
    assert tool.localize_figures(rec, map_poses, query_poses)["r_at_p1"] == pytest.approx(1 / 3)
    # --ambiguity: a right answer that another accepted place, 10 m away, nearly matches (0.85 / 0.9 = 0.94)
    rec.candidates[0].append(Candidate(0, 1, 0.85, relative_pose=rel, accepted=True))
    f = tool.localize_figures(rec, map_poses, query_poses, AmbiguityParams(max_ratio=0.9))
    assert (f["n_success"], f["n_no_answer"], f["n_wrong"]) == (0, 3, 0)  # refused: no answer
    f = tool.localize_figures(rec, map_poses, query_poses, AmbiguityParams(max_ratio=0.95))
    assert (f["n_success"], f["n_no_answer"], f["n_wrong"]) == (1, 2, 0)


def test_world_splits_drive_each_splits_seeds_in_each_world() -> None:
    tool = _tool()
    runs = tool.world_splits(["test"], ["town", "campus"])
    assert set(runs) == {"test", "test-campus"}
    assert runs["test-campus"]["world"] == "campus"
    assert {k: v for k, v in runs["test-campus"].items() if k != "world"} == {
        k: v for k, v in tool.SPLITS["test"].items() if k != "world"
    }
    tuning = tool.world_splits(["tuning"], ["campus"])["tuning-campus"]
    assert tuning == {**tool.SPLITS["tuning"], "world": "campus"}
    assert not any(tool.protocol.is_test_seed(tuning[k]) for k in ("world_seed", "map_seed", "query_seed"))


def test_concat_sequence_and_monotone_fit() -> None:
    tool = _tool()

    class Seq:
        def __init__(self, n: int, t0: float, tag: str) -> None:
            self.poses = np.stack([_pose(float(i)) for i in range(n)])
            self.timestamps = t0 + np.arange(n, dtype=float)
            self.name = tag

        def __len__(self) -> int:
            return len(self.poses)

        def __getitem__(self, i: int) -> str:
            return f"{self.name}{i}"

    both = tool.ConcatSequence(Seq(3, 5.0, "a"), Seq(2, 0.0, "b"))
    assert len(both) == 5 and both[3] == "b0" and both[-1] == "b1"
    assert both.timestamps[3] - both.timestamps[2] == tool.GAP_S
    assert both.poses.shape == (5, 4, 4)
    x = np.linspace(0.05, 0.95, 500)
    xs, ys = tool.fit_monotone(x, np.sqrt(x))
    assert np.all(np.diff(ys) >= 0) and xs[0] == 0 and xs[-1] == 1
    assert np.interp(0.25, xs, ys) == pytest.approx(0.5, abs=0.03)


def test_quick_path_tiny(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    tool = _tool()
    out = tool.main([
        "--quick", "--pairs", "vlp16:avia", "--pipelines", "scan-context", "ishot-prob", "--intensity", "raw",
        "calibrated",
        "--map-spacing", "40", "--query-spacing", "80", "--cal-scans", "6", "--cache-dir", str(tmp_path),
        "--ambiguity", "0.85", "--set", "scan-context.full_shift_search=true", "--loop-ambiguity", "0.85",
        "--loop-threshold", "scan-context=0.05",
    ])  # fmt: skip
    line = capsys.readouterr().out.strip().splitlines()[-1]
    assert json.loads(line)["tool"] == "eval_cross_sensor"
    assert set(out["splits"]) == {"test"} and out["splits"]["test"]["label"] == "test"
    assert out["calibration_drives"]["label"] == "tuning"
    assert out["ambiguity"] == 0.85 and out["pipeline_params"]["scan-context"] == {"full_shift_search": True}
    assert out["loop_ambiguity"] == 0.85 and out["pipelines"]["scan-context"] == 0.05
    for bad in ("ishot-prob=0.1", "scan-context=x", "scan-context=nan"):
        with pytest.raises(SystemExit, match="--loop-threshold"):
            tool.main(["--quick", "--pipelines", "scan-context", "ishot-prob", "--loop-threshold", bad])
    with pytest.raises(SystemExit, match="orb-dbow.top_k"):
        tool.main(["--quick", "--pipelines", "scan-context", "--set", "orb-dbow.top_k=5"])
    res = out["results"]["test"]
    assert set(res) == {"raw", "calibrated"}
    assert set(res["raw"]) == {"vlp16>avia", "avia>avia", "vlp16>vlp16"}
    # every scan cropped to the band both sensors see: the VLP-16's +-15 deg inside the Avia's +-38.6
    assert out["elevation_deg"] == [-15.0, 15.0]
    for per_pair in res.values():
        for r in per_pair.values():
            # the 3D voting pipeline has no loop threshold: localised only
            assert "ishot-prob" not in r["loop"] and "ishot-prob" in r["localise"]
            loc, loop = r["localise"]["scan-context"], r["loop"]["scan-context"]
            assert (
                loc["n_success"] + loc["n_no_answer"] + loc["n_wrong"] == loc["n_queries"] == r["n_queries"]
            )
            assert 0.0 <= loop["r_at_p1"] <= loop["recall"] <= 1.0
            assert loop["threshold"] == out["pipelines"]["scan-context"]
            assert 0 <= loop["refused_ambiguous"] <= r["n_queries"] and "max_false_score" in loop
    ratio = out["summary"]["test"]["ratios"]["vlp16>avia"]["calibrated"]["loop"]
    assert ratio["best"] == "scan-context" and set(ratio["pipelines"]["scan-context"]) == {
        "cross",
        "same",
        "ratio",
    }
    loc = out["summary"]["test"]["ratios"]["vlp16>avia"]["calibrated"]["localise"]
    best = loc["pipelines"][loc["best"]]["cross"]
    same = res["calibrated"]["avia>avia"]["localise"]
    s1, s = max(v["r_at_p1"] for v in same.values()), max(v["success"] for v in same.values())
    assert loc["best_over_best_same"] == (best / s1 if s1 > 0 else None)
    assert loc["best_over_best_same_success"] == (best / s if s > 0 else None)
    assert {"avia map", "avia query", "vlp16 map", "vlp16 query"} <= set(out["calibration_check"])
