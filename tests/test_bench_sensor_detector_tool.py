"""tools/bench_sensor_detector.py: it times tuning cells only."""

from __future__ import annotations

import sys

import pytest
from tool_modules import load_tool


def test_a_test_split_seed_is_refused(monkeypatch, capsys):
    tool = load_tool("bench_sensor_detector")
    monkeypatch.setattr(sys, "argv", ["bench_sensor_detector.py", "--seed", "4601"])
    with pytest.raises(SystemExit) as exc:
        tool.main()
    assert exc.value.code == 2 and "test split" in capsys.readouterr().err
