"""tools/compare_runs.py: two results folders compared, timings aside."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("compare_runs", ROOT / "tools" / "compare_runs.py")
compare_runs = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(compare_runs)


def _run(root: Path, stamp: str, max_f1: float, ms: float, pose_x: float) -> None:
    run = root / f"demo_{stamp}"
    run.mkdir(parents=True)
    (run / "metrics.json").write_text(
        json.dumps({"pipelines": {"a": {"max_f1": max_f1, "time_ms": {"mean": ms}, "verify_ms": ms}}})
    )
    (run / "candidates_a.csv").write_text(f"query_id,match_id,x\n3,1,{pose_x}\n")
    np.savez(run / "places.npz", ids=np.arange(3), __header__=np.frombuffer(stamp.encode(), np.uint8))


def test_equal_answers_at_other_times_and_dates_are_the_same(tmp_path):
    _run(tmp_path / "a", "20261127-002059", 0.8, 10.0, 0.5)
    _run(tmp_path / "b", "20261127-013514", 0.8, 99.0, 0.5)
    assert compare_runs.compare(tmp_path / "a", tmp_path / "b") == (3, [])


def test_another_answer_is_a_difference(tmp_path):
    _run(tmp_path / "a", "20261127-002059", 0.8, 10.0, 0.5)
    _run(tmp_path / "b", "20261127-013514", 0.7, 10.0, 0.6)
    n, diffs = compare_runs.compare(tmp_path / "a", tmp_path / "b")
    assert n == 3 and sorted(diffs) == [
        "demo/candidates_a.csv: differs",
        "demo/metrics.json/pipelines/a/max_f1: 0.8 != 0.7",
    ]
    assert compare_runs.main([str(tmp_path / "a"), str(tmp_path / "b")]) == 1
