"""How far the refinement of an accepted pose moves it (`placerec.verify.params.RefineParams`), on tuning cells.

Runs a `placerec bench` config of the tuning split in this process (one cell after another), watching every
refinement the verification makes: the judged pose, the refined one and the one used (the judged one when the
refinement moved farther than ``refine.max_shift``). Each accepted candidate the cells keep is matched to its
refinement and judged against the true relative pose: a *right place* is one whose judged pose is within the pose
truth's bounds (``evaluation.pose_truth``: 0.5 m / 2 deg). Per sensor it prints, for the right places, the judged
and the used pose's error and how far the refinement moved (the shift ``max_shift`` caps), and the refinements
``max_shift`` kept out; the same shift for the accepted candidates that are not right places. That distribution
is what ``max_shift`` is chosen on (docs/verification.md, 'How far a refinement may move the pose'); ``--closures``
lists each closure.

Refuses a test-split config (a tuning config refuses test seeds itself): a default is never chosen on test data
(docs/protocol.md).

    .venv/bin/python tools/eval_refine_shift.py configs/benchmark_sensors_tuning.yaml \\
        --set 'sensors=[vlp16, hdl32, avia, mid360, e1r]' --set 'pipelines=[{name: orb-dbow}]' \\
        --set 'evaluation.odometry_gate={}' --set 'seeds=[0, 1, 2]' --out runs/refine_shift

Ends with one JSON line.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from placerec.errors import ConfigError
from placerec.eval.pose_error import pose_errors
from placerec.experiment import benchmark
from placerec.experiment.benchmark import load_benchmark_config, run_benchmark
from placerec.experiment.candidates import read_candidates
from placerec.experiment.run_folder import slug
from placerec.io import read_poses

MATCH_M = 1e-3  # a table's pose and a watched refinement's used pose are the same numbers, written to a CSV


@dataclass
class Watched:
    """One refinement: the cell it ran in, the judged, refined and used poses (T_match_query)."""

    cell: str
    judged: np.ndarray
    refined: np.ndarray
    used: np.ndarray


def watch(log: list[Watched]) -> None:
    """Record every refinement into ``log``, with the cell it ran in (cells run in this process, in turn)."""
    verify_mod = importlib.import_module("placerec.verify.verify")
    refinement, refined, run_cell = verify_mod._refinement, verify_mod._refined, benchmark.run_cell
    now: dict[str, Any] = {"cell": ""}

    def watched_refinement(source: Any, target: Any, T: np.ndarray, params: Any, timings: dict) -> np.ndarray:
        now["refined"] = refinement(source, target, T, params, timings)
        return now["refined"]

    def watched_refined(source: Any, target: Any, T: np.ndarray, params: Any, timings: dict) -> np.ndarray:
        used = refined(source, target, T, params, timings)
        log.append(Watched(now["cell"], T.copy(), now["refined"].copy(), used.copy()))
        return used

    def cell(cfg_json: dict, folder: str) -> dict:
        now["cell"] = Path(folder).name
        return run_cell(cfg_json, folder)

    verify_mod._refinement, verify_mod._refined = watched_refinement, watched_refined
    benchmark.run_cell = cell


def matched(root: Path, bench: Any, log: list[Watched]) -> list[dict[str, Any]]:
    """Each accepted candidate of each cell's tables with its watched refinement and true relative pose."""
    rows = []
    for c in bench.cells():
        folder = root / "cells" / c.name
        poses = read_poses(folder / "poses.txt")[0]
        mine = [w for w in log if w.cell == c.name]
        used = np.array([w.used[:3, 3] for w in mine]).reshape(-1, 3)
        for spec in bench.cell_config(c).pipelines:
            table = read_candidates(folder / f"candidates_{slug(spec.display_name)}.csv")
            for qi, ri in zip(*np.nonzero(table.accepted == 1), strict=True):
                T = table.relative_poses[qi, ri]
                if not np.isfinite(T).all() or not len(used):
                    continue
                d = np.linalg.norm(used - T[:3, 3], axis=1)
                if d.min() > MATCH_M:
                    continue  # accepted without a refinement (refine off for this pipeline)
                w = mine[int(d.argmin())]
                q, m = int(table.query_ids[qi]), int(table.match_ids[qi, ri])
                true = np.linalg.inv(poses[m]) @ poses[q]
                rows.append(
                    {"cell": c.name, "sensor": c.sensor, "query": q, "match": m, "watched": w, "true": true}
                )
    return rows


def summary(rows: list[dict[str, Any]], max_t: float, max_r: float) -> dict[str, Any]:
    """Per sensor and over all: the right places' judged / used errors and shifts, the others' shifts."""
    out: dict[str, Any] = {}
    for sensor in sorted({r["sensor"] for r in rows}) + ["all"]:
        mine = [r for r in rows if sensor in ("all", r["sensor"])]
        true = np.array([r["true"] for r in mine]).reshape(-1, 4, 4)
        judged, refined, used = (
            np.array([getattr(r["watched"], k) for r in mine]).reshape(-1, 4, 4)
            for k in ("judged", "refined", "used")
        )
        jt, jr = pose_errors(judged, true)
        ut = pose_errors(used, true)[0]
        shift = np.linalg.norm(refined[:, :3, 3] - judged[:, :3, 3], axis=1)
        kept_out = ~np.isclose(used, refined).all(axis=(1, 2))
        right = (jt <= max_t) & (jr <= max_r)
        q = lambda a, p: round(float(np.percentile(a, p)), 4) if a.size else None  # noqa: E731
        out[sensor] = {
            "right": int(right.sum()),
            "judged_t_median": q(jt[right], 50),
            "judged_t_max": q(jt[right], 100),
            "used_t_median": q(ut[right], 50),
            "used_t_max": q(ut[right], 100),
            "worse_by_5cm": int((ut[right] - jt[right] > 0.05).sum()),
            "shift_median": q(shift[right], 50),
            "shift_p99": q(shift[right], 99),
            "shift_max": q(shift[right], 100),
            "kept_out": int(kept_out[right].sum()),
            "other": int((~right).sum()),
            "other_shift_median": q(shift[~right], 50),
        }
    return out


def write_closures(path: Path, rows: list[dict[str, Any]]) -> None:
    """One line a matched closure: its cell, query and match, the judged / refined / used pose's errors (m, deg)
    against the truth and the refinement's shift (m)."""
    lines = ["cell,query,match,judged_m,judged_deg,refined_m,refined_deg,used_m,used_deg,shift_m"]
    for r in rows:
        w = r["watched"]
        errs = [pose_errors(T, r["true"]) for T in (w.judged, w.refined, w.used)]
        shift = np.linalg.norm(w.refined[:3, 3] - w.judged[:3, 3])
        values = [f"{float(e[0][0]):.4f},{float(e[1][0]):.3f}" for e in errs]
        lines.append(f"{r['cell']},{r['query']},{r['match']},{','.join(values)},{shift:.4f}")
    path.write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("config", help="a placerec bench config of the tuning split")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override")
    ap.add_argument("--out", default="runs/refine_shift", help="the benchmark folder (run afresh)")
    ap.add_argument(
        "--closures", metavar="CSV", help="also write each matched closure's errors and shift here"
    )
    a = ap.parse_args(argv)
    bench = load_benchmark_config(a.config, a.set)
    if bench.split != "tuning":  # a tuning config refuses test seeds itself
        raise ConfigError(
            f"{a.config}: a {bench.split}-split config; max_shift is chosen on tuning cells only"
        )
    bench = bench.model_copy(update={"execution": bench.execution.model_copy(update={"workers": 1})})
    log: list[Watched] = []
    watch(log)
    root, _ = run_benchmark(bench, a.out, fresh=True)
    if not log:
        raise ConfigError(
            f"{a.config}: no accepted closure was refined; the pipelines need verify.refine.enabled"
        )
    pt = bench.evaluation.pose_truth
    rows = matched(Path(root), bench, log)
    result = summary(rows, pt.max_translation, pt.max_rotation_deg)
    if a.closures:
        write_closures(Path(a.closures), rows)
    print(
        f"{'sensor':8} {'right':>5} {'judged m med/max':>17} {'used m med/max':>15} {'worse>5cm':>9} "
        f"{'shift m med/p99/max':>20} {'kept out':>8} {'other':>5} {'other shift':>11}"
    )
    for sensor, s in result.items():
        print(
            f"{sensor:8} {s['right']:5d} {s['judged_t_median']!s:>8}/{s['judged_t_max']!s:<8} "
            f"{s['used_t_median']!s:>7}/{s['used_t_max']!s:<7} {s['worse_by_5cm']:9d} "
            f"{s['shift_median']!s:>6}/{s['shift_p99']!s}/{s['shift_max']!s:<6} {s['kept_out']:8d} "
            f"{s['other']:5d} {s['other_shift_median']!s:>11}"
        )
    payload = {"tool": "eval_refine_shift", "refinements": len(log), "sensors": result}
    print(json.dumps(payload))
    return payload


if __name__ == "__main__":
    sys.exit(0 if main() else 1)
