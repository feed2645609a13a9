"""tools/odometry_gate_bounds.py: the bounds twice the tuning pairs' worst drift per metre, rounded up; a
test-split run refused."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from tool_modules import load_tool

from placerec.errors import ConfigError
from placerec.io import write_kitti_poses


def _square_twice(side: float = 60.0) -> np.ndarray:
    """A square block driven twice, 1 m between poses, heading along the street."""
    out = []
    for _ in range(2):
        for k, (dx, dy) in enumerate([(1, 0), (0, 1), (-1, 0), (0, -1)]):
            start = np.array([[0, 0], [side, 0], [side, side], [0, side]][k], float)
            yaw = np.arctan2(dy, dx)
            for s in range(int(side)):
                T = np.eye(4)
                T[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
                T[:2, 3] = start + s * np.array([dx, dy], float)
                out.append(T)
    return np.stack(out)


def _run(tmp_path, split):
    run = tmp_path / split
    cfg = {"split": split, "worlds": ["town"], "sensors": ["vlp16"], "seeds": [0 if split == "tuning" else 7]}
    (run / "cells" / cfg_name(cfg)).mkdir(parents=True)
    (run / "config.yaml").write_text(yaml.safe_dump(cfg | {"pipelines": [{"name": "scan-context"}]}))
    write_kitti_poses(run / "cells" / cfg_name(cfg) / "poses.txt", _square_twice())
    return run


def cfg_name(cfg):
    return f"{cfg['worlds'][0]}_{cfg['sensors'][0]}_{cfg['seeds'][0]}"


def test_bounds_are_twice_the_worst_drift_per_metre_rounded_up(tmp_path, capsys):
    tool = load_tool("odometry_gate_bounds")
    out = tool.main([str(_run(tmp_path, "tuning"))])
    assert out["cells"] == 1 and 0 < out["worst_per_metre"] < 0.05
    b = out["bounds"]
    for key, worst in (
        ("per_metre", out["worst_per_metre"]),
        ("degrees_per_metre", out["worst_degrees_per_metre"]),
    ):
        assert 2 * worst <= b[key] < 2 * worst + 0.01 + 1e-9 and round(b[key] * 100, 9) % 1 == 0
    assert (b["metres"], b["degrees"]) == (1.0, 4.0)
    poses = _square_twice()
    r = tool.cell_ratios(poses, 0, 20.0, 100.0)
    assert r["pairs"] > 0 and r["t_per_m"] == pytest.approx(out["worst_per_metre"], abs=1e-5)
    assert tool.cell_ratios(poses, 0, 20.0, 10_000.0)["pairs"] == 0
    assert '"tool": "odometry_gate_bounds"' in capsys.readouterr().out


def test_a_test_split_run_is_refused(tmp_path):
    with pytest.raises(ConfigError, match="tuning"):
        load_tool("odometry_gate_bounds").main([str(_run(tmp_path, "test"))])
