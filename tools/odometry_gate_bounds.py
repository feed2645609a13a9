"""The odometry gate's bounds, chosen on tuning benchmark runs (`placerec.odometry_gate`, docs/protocol.md).

For every cell of the given tuning runs: the odometry the evaluation's gate uses (the cell's true poses drifting
as `placerec.config.OdometryGateConfig` says, with the cell's seed) and every pair of places within
``--radius`` m of each other (true poses) and at least ``--min-path`` m of odometry path apart, i.e. every place a
correct closure could join (the benchmark's exclusion window is 120 m). A correct closure disagrees with the
odometry by that pair's drift (plus its own error, at most the pose truth's 0.5 m / 2 deg), so the rule is

    per_metre, degrees_per_metre = twice the largest disagreement / path of any pair, rounded up to 0.01
    metres, degrees = twice the pose truth's tolerances (0.5 m, 2 deg)

Prints each cell's figures, the bounds and one JSON line. A test-split run is refused.

    python tools/odometry_gate_bounds.py RUN [RUN ...]   # e.g. the tuning runs of `placerec bench ... --out RUN`
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from placerec.config import OdometryGateConfig, PoseTruthConfig  # noqa: E402
from placerec.errors import ConfigError  # noqa: E402
from placerec.experiment.benchmark import load_benchmark_config  # noqa: E402
from placerec.io import read_poses  # noqa: E402
from placerec.odometry_gate import odometry_disagreement  # noqa: E402
from placerec.sim.odometry import drift_poses  # noqa: E402
from placerec.types import path_length  # noqa: E402


def cell_ratios(poses: np.ndarray, seed: int, radius: float, min_path: float) -> dict[str, float]:
    """The largest disagreement / path (translation, rotation) of a cell's pairs (module docstring)."""
    gate = OdometryGateConfig()
    odom = drift_poses(poses, gate.drift, seed)
    path = path_length(odom[:, :3, 3])
    p = poses[:, :3, 3]
    near = np.linalg.norm(p[:, None] - p[None], axis=2) < radius
    q, m = np.nonzero(np.tril(near, -1))
    keep = path[q] - path[m] >= min_path
    q, m = q[keep], m[keep]
    if q.size == 0:
        return {"pairs": 0, "t_per_m": 0.0, "deg_per_m": 0.0, "t_max": 0.0, "deg_max": 0.0}
    t, r = odometry_disagreement(np.linalg.solve(poses[m], poses[q]), odom[m], odom[q])
    L = path[q] - path[m]
    return {
        "pairs": int(q.size),
        "t_per_m": float(np.max(t / L)),
        "deg_per_m": float(np.max(r / L)),
        "t_max": float(t.max()),
        "deg_max": float(r.max()),
    }


def bounds(worst_t: float, worst_deg: float) -> dict[str, float]:
    """The rule of the module docstring."""
    up = lambda x: math.ceil(round(2 * x * 100, 9)) / 100  # noqa: E731
    truth = PoseTruthConfig()
    return {
        "metres": 2 * truth.max_translation,
        "per_metre": up(worst_t),
        "degrees": 2 * truth.max_rotation_deg,
        "degrees_per_metre": up(worst_deg),
    }


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="tuning benchmark folders (config.yaml, cells/)")
    ap.add_argument("--radius", type=float, default=20.0, help="pairs closer than this (m, true poses)")
    ap.add_argument("--min-path", type=float, default=100.0, help="and at least this far apart by path (m)")
    a = ap.parse_args(argv)
    worst_t = worst_deg = 0.0
    cells = 0
    for run in a.runs:
        bench = load_benchmark_config(run / "config.yaml")
        if bench.split != "tuning":
            raise ConfigError(
                f"{run}: a {bench.split}-split benchmark; the gate's bounds are chosen on tuning runs"
            )
        for cell in bench.cells():
            folder = run / "cells" / cell.name
            if not (folder / "poses.txt").is_file():
                print(f"{folder}: no poses.txt, left out")
                continue
            poses = read_poses(folder / "poses.txt")[0]
            r = cell_ratios(poses, bench.cell_config(cell).dataset.simulator.seed, a.radius, a.min_path)
            cells += 1
            worst_t, worst_deg = max(worst_t, r["t_per_m"]), max(worst_deg, r["deg_per_m"])
            print(
                f"{run.name:>16s} {cell.name:<22s} pairs {r['pairs']:6d}  translation max {r['t_max']:5.2f} m, "
                f"{r['t_per_m']:.4f} m/m   rotation max {r['deg_max']:5.2f} deg, {r['deg_per_m']:.4f} deg/m"
            )
    out = {"tool": "odometry_gate_bounds", "cells": cells, "worst_per_metre": round(worst_t, 5)}
    out |= {"worst_degrees_per_metre": round(worst_deg, 5), "bounds": bounds(worst_t, worst_deg)}
    print(f"bounds: {out['bounds']}")
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
