"""SLAM over the matrix: `placerec.slam_app.run.slam_sequence` per odometry source x world x seed, KISS-SLAM beside it.

Cells: the odometry sources of `SOURCES` (the simulator's default drift, ``OdometryDrift()``; the drift of
configs/slam_demo.yaml; KISS-ICP on the scans) x the split's worlds and seeds (``--split test``:
`placerec.experiment.protocol.TEST_WORLDS` x ``TEST_SEEDS``; ``--split tuning``: ``TUNING_WORLDS`` x
``TUNING_SEEDS``, i.e. the demo's town, seed 0; ``--worlds`` names others), sensor OS1-64, route ``default``. Everything else is configs/slam_demo.yaml as committed: ORB-HBST loop closures at the
fixed threshold ``loops.threshold`` (chosen on the tuning split, docs/slam.md "The default threshold"), exclusion
120 frames, Cauchy loop factors, GNC batch. Per cell: ATE / RPE of the odometry (before) and of the batch-optimised
graph (after) by `placerec.eval.trajectory`, loops accepted, false (pose off by > 1 m / 5 deg), rejected by the
back end, and the highest score of a wrong candidate among those the threshold decides on (each query's best
``loops.k``): the threshold's margin.

KISS-SLAM (PyPI ``kiss-slam``, PRBonn) runs on the same sequences, exported as KITTI-style folders
(`placerec.sim.write_kitti_sequence`), through its own command ``kiss_slam_pipeline <folder>/velodyne`` with its
defaults, in its own virtual environment (its dependencies pin numpy < 2.3, pydantic and typer below placerec's):
``--install-kiss-slam`` creates it (`KISS_SLAM_INSTALL`). Its poses are scored by the same ATE / RPE code.

Each cell's result is cached as JSON in ``--cache`` with the key of what made it (the resolved config; for KISS-SLAM
its version and the dataset settings, which also name the exported folder): a rerun skips finished cells and
recomputes cells whose config changed.

    .venv/bin/python tools/bench_slam_matrix.py                       # test split, all sources, KISS-SLAM
    .venv/bin/python tools/bench_slam_matrix.py --split tuning        # the tuning cells (threshold check)
    .venv/bin/python tools/bench_slam_matrix.py --install-kiss-slam   # first: KISS-SLAM's environment
    .venv/bin/python tools/bench_slam_matrix.py --split tuning --noise-grid --sources kiss-icp --no-kiss-slam

``--noise-grid`` (tuning seeds only): each cell's odometry and loops replayed (`bench_slam.replay`) into graphs with
the odometry and loop noise of `NOISE_GRID`, to see whether another noise model would suit an odometry source (a
setting may be chosen on the tuning worlds only).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from placerec.config import config_to_yaml
from placerec.eval.pose_error import full_pose_mask, pose_errors
from placerec.eval.trajectory import trajectory_errors
from placerec.experiment.protocol import TEST_SEEDS, TEST_WORLDS, TUNING_SEEDS, TUNING_WORLDS
from placerec.experiment.tables import print_rows
from placerec.io import read_poses
from placerec.io.atomic import atomic_write
from placerec.sim.odometry import OdometryDrift
from placerec.slam.result import SlamResult
from placerec.slam_app.config import SlamConfig, load_slam_config
from placerec.types import relative_pose

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "slam_demo.yaml"
SENSOR = "os1-64"
#: Bump when what a cached cell holds changes.
CACHE_VERSION = 1
KISS_SLAM_VENV = ROOT / ".venv-kiss-slam"
#: The authors' install (``pip install kiss-slam``) plus two modules its pipeline imports but does not declare
#: (PIL in ``occupancy_mapper``, matplotlib for its trajectory figure).
KISS_SLAM_INSTALL = ("kiss-slam==0.0.2", "pillow", "matplotlib")


#: ``--noise-grid``: (odometry sigma per metre, deg per metre) x (loop sigma m, deg), the GraphParams fields.
NOISE_GRID = {
    "odometry": [(t, r) for t in (0.02, 0.005, 0.002) for r in (0.1, 0.02)],
    "loop": [(t, r) for t in (0.1, 0.05, 0.02) for r in (1.0, 0.3, 0.1)],
}


def _drift_overrides(drift: OdometryDrift) -> list[str]:
    return [f"odometry.drift.{name}={value}" for name, value in drift.model_dump().items()]


#: Odometry source -> config overrides on top of configs/slam_demo.yaml.
SOURCES: dict[str, list[str]] = {
    "sim-default": ["odometry.source=dataset", *_drift_overrides(OdometryDrift())],
    "demo-drift": ["odometry.source=dataset"],
    "kiss-icp": ["odometry.source=kiss-icp"],
}


def cell_config(world: str, seed: int, source: str, extra: list[str]) -> SlamConfig:
    """configs/slam_demo.yaml on ``world`` / ``seed`` (OS1-64, route default) with ``source``'s odometry."""
    sim = [f"dataset.simulator.{k}={v}" for k, v in (("world", world), ("seed", seed), ("sensor", SENSOR))]
    return load_slam_config(
        CONFIG, [*sim, "dataset.simulator.route=default", *SOURCES[source], "output.progress=false", *extra]
    )


def _key(*parts: str) -> str:
    return hashlib.sha256("\n".join((str(CACHE_VERSION), *parts)).encode()).hexdigest()[:16]


def _cached(path: Path, key: str) -> dict[str, Any] | None:
    if not path.is_file():
        return None
    data = json.loads(path.read_text())
    return data if data.get("key") == key else None


def _save(path: Path, data: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path, "w") as fh:
        json.dump(data, fh, indent=1)


def candidate_scores(cfg: SlamConfig, result: SlamResult) -> dict[str, Any]:
    """The candidates the threshold decided on (each query's best ``loops.k``) that carry a 6-DoF pose, judged like
    loop edges (> 1 m or 5 deg off: wrong): how many are right / wrong, the highest wrong score, and how many
    right ones reach the threshold."""
    gt = result.ground_truth
    cands = [c for per_scan in result.candidates for c in per_scan]
    cands = [c for c in cands if c.relative_pose is not None and full_pose_mask(c.relative_pose)[0]]
    if gt is None or not cands:
        return {"right": 0, "wrong": 0, "max_wrong_score": None, "right_at_threshold": 0}
    est = np.stack([np.asarray(c.relative_pose, dtype=np.float64) for c in cands])
    true = np.stack([relative_pose(gt[c.match_id], gt[c.query_id]) for c in cands])
    te, re_deg = pose_errors(est, true)
    ev = cfg.evaluation
    wrong = (te > ev.false_loop_translation) | (re_deg > ev.false_loop_rotation_deg)
    score = np.array([c.score for c in cands])
    return {
        "right": int((~wrong).sum()),
        "wrong": int(wrong.sum()),
        "max_wrong_score": float(score[wrong].max()) if wrong.any() else None,
        "right_at_threshold": int(((~wrong) & (score >= cfg.loops.threshold)).sum()),
    }


def run_placerec_cell(cfg: SlamConfig) -> dict[str, Any]:
    """One `placerec slam` run (no results folder): trajectory errors, loop counts, candidate scores."""
    from placerec.experiment.datasets import open_dataset
    from placerec.slam_app.report import loop_table, slam_metrics
    from placerec.slam_app.run import slam_sequence

    seq = open_dataset(cfg.dataset)
    t0 = time.perf_counter()
    result = slam_sequence(cfg, seq)
    m = slam_metrics(cfg, result, loop_table(cfg, result))
    tr, lp = m["trajectory"], m["loops"]
    return {
        "scans": len(seq),
        "before": tr["odometry"],
        "after": tr["optimized"],
        "loops": lp["accepted"],
        "false_loops": lp["false_accepted"],
        "opposite_loops": lp["opposite_direction"],
        "rejected_by_back_end": lp["rejected_by_back_end"],
        "loop_translation_error_max": lp.get("max_translation_error"),
        "candidates": candidate_scores(cfg, result),
        "seconds": time.perf_counter() - t0,
    }


def noise_grid(cfg: SlamConfig) -> dict[str, float]:
    """ATE of ``cfg``'s run replayed with every noise model of `NOISE_GRID` (key "odo t/r, loop t/r")."""
    from bench_slam import replay  # tools/ is on sys.path when this file runs as a script

    from placerec.experiment.datasets import open_dataset
    from placerec.slam_app.run import slam_sequence

    result = slam_sequence(cfg, open_dataset(cfg.dataset))
    loops = [lp for lp in result.loops if not lp.injected]
    out = {"odometry": trajectory_errors(result.odometry, result.ground_truth).ate_rmse}
    for (ot, orot), (lt, lr) in ((o, lp) for o in NOISE_GRID["odometry"] for lp in NOISE_GRID["loop"]):
        p = cfg.graph.model_copy(
            update={
                "odometry_sigma_translation": ot,
                "odometry_sigma_rotation_deg": orot,
                "loop_sigma_translation": lt,
                "loop_sigma_rotation_deg": lr,
            }
        )
        out[f"{ot:g}/{orot:g}, {lt:g}/{lr:g}"] = trajectory_errors(
            replay(result.odometry, loops, p), result.ground_truth
        ).ate_rmse
    return out


def print_noise_grid(args: argparse.Namespace, seeds: tuple[int, ...]) -> None:
    """`noise_grid` for every cell of the split (tuning only: the grid is there to choose on)."""
    if args.split != "tuning":
        sys.exit("--noise-grid chooses settings: tuning split only (--split tuning)")
    cols: dict[str, dict[str, float]] = {}
    for world in args.worlds:
        for seed in seeds:
            for source in args.sources:
                print(f"noise grid {world} {seed} {source} ...", flush=True)
                cols[f"{world} {seed} {source}"] = noise_grid(cell_config(world, seed, source, args.set))
    keys = list(next(iter(cols.values())))
    rows = [[k, *(f"{c[k]:.4f}" for c in cols.values())] for k in keys]
    header = ["odometry m/m / deg/m, loop m / deg", *(f"{name}: ATE [m]" for name in cols)]
    print_rows(header, rows, "graph noise models replayed (the config's: 0.02/0.1, 0.1/1)")
    print(json.dumps({"bench": "slam_noise_grid", "split": args.split, "ate_m": cols}))


# --- KISS-SLAM -----------------------------------------------------------------------------------------------


def install_kiss_slam(venv: Path) -> None:
    """Create ``venv`` with KISS-SLAM (`KISS_SLAM_INSTALL`), beside and apart from placerec's."""
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    pip = [str(venv / "bin" / "python"), "-m", "pip", "install"]
    subprocess.run([*pip, "--upgrade", "pip"], check=True)
    subprocess.run([*pip, *KISS_SLAM_INSTALL], check=True)


def kiss_slam_version(venv: Path) -> str | None:
    """KISS-SLAM's version in ``venv`` (None: not installed there)."""
    py = venv / "bin" / "python"
    if not (venv / "bin" / "kiss_slam_pipeline").is_file() or not py.is_file():
        return None
    code = "import importlib.metadata as m; print(m.version('kiss-slam'))"
    out = subprocess.run([str(py), "-c", code], capture_output=True, text=True)
    return out.stdout.strip() if out.returncode == 0 else None


def export_sequence(cfg: SlamConfig, folder: Path) -> Path:
    """The cell's dataset (the sequence placerec runs on) as a KITTI-style folder, written once (sensor.yaml is
    written last)."""
    if not (folder / "sensor.yaml").is_file():
        from placerec.experiment.datasets import open_dataset
        from placerec.sim import write_kitti_sequence

        write_kitti_sequence(open_dataset(cfg.dataset), folder, progress=False)
    return folder


def run_kiss_slam(venv: Path, folder: Path, out: Path, rpe_delta: int) -> dict[str, Any]:
    """``kiss_slam_pipeline folder/velodyne`` with KISS-SLAM's defaults (results in ``out``), its trajectory scored
    against ``folder/poses.txt`` by `placerec.eval.trajectory` (ATE after rigid alignment: KISS-SLAM starts at the
    identity)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.yaml").write_text(f"out_dir: {out}\n")
    cmd = [
        str(venv / "bin" / "kiss_slam_pipeline"),
        str(folder / "velodyne"),
        "--config",
        str(out / "config.yaml"),
    ]
    t0 = time.perf_counter()
    with tempfile.TemporaryFile("w+") as log:
        done = subprocess.run(
            cmd, stdout=log, stderr=subprocess.STDOUT, cwd=out, env={**os.environ, "MPLBACKEND": "Agg"}
        )
        log.seek(0)
        text = log.read()
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({done.returncode}):\n{text[-2000:]}")
    seconds = time.perf_counter() - t0
    est = np.load(out / "latest" / "velodyne_poses.npy")
    gt, _ = read_poses(folder / "poses.txt")
    closures = re.search(r"Number of closures found\s+(\d+)", text)
    return {
        "scans": len(gt),
        "after": trajectory_errors(est, gt, rpe_delta).as_dict(),
        "closures": int(closures.group(1)) if closures else None,
        "seconds": seconds,
    }


# --- the matrix ----------------------------------------------------------------------------------------------


def meets_target(cell: dict[str, Any]) -> bool | None:
    """ATE after <= 0.3 m and <= 1/3 of before (None: a cell without loops, where the target does not apply)."""
    if not cell["loops"]:
        return None
    a, b = cell["after"]["ate_rmse"], cell["before"]["ate_rmse"]
    return a <= 0.3 and a <= b / 3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--split", choices=("test", "tuning"), default="test")
    ap.add_argument("--worlds", nargs="+", help="default: the split's worlds")
    ap.add_argument("--sources", nargs="+", choices=list(SOURCES), default=list(SOURCES))
    ap.add_argument("--set", action="append", default=[], help="config override key.path=value (every cell)")
    ap.add_argument("--cache", type=Path, default=ROOT / "results" / "slam_matrix")
    ap.add_argument("--kiss-slam-venv", type=Path, default=KISS_SLAM_VENV)
    ap.add_argument("--no-kiss-slam", action="store_true", help="placerec's cells only")
    ap.add_argument("--install-kiss-slam", action="store_true", help="create --kiss-slam-venv and exit")
    ap.add_argument(
        "--noise-grid", action="store_true", help="graph noise models replayed (tuning split only)"
    )
    args = ap.parse_args()
    if args.install_kiss_slam:
        install_kiss_slam(args.kiss_slam_venv)
        return
    seeds = TEST_SEEDS if args.split == "test" else TUNING_SEEDS
    args.worlds = args.worlds or list(TEST_WORLDS if args.split == "test" else TUNING_WORLDS)
    if args.noise_grid:
        print_noise_grid(args, seeds)
        return
    kiss_version = None if args.no_kiss_slam else kiss_slam_version(args.kiss_slam_venv)
    if not args.no_kiss_slam and kiss_version is None:
        print(
            f"KISS-SLAM not found in {args.kiss_slam_venv}: run with --install-kiss-slam (or --no-kiss-slam)"
        )
        sys.exit(2)
    cells, kiss = run_matrix(args, seeds, kiss_version)
    threshold = cell_config(args.worlds[0], seeds[0], args.sources[0], args.set).loops.threshold
    title = f"{args.split} split ({SENSOR}, route default), loops.threshold {threshold}"
    print_matrix(cells, kiss, title)
    print(json.dumps(summary(cells, kiss, args.split, threshold, kiss_version)))


def run_matrix(
    args: argparse.Namespace, seeds: tuple[int, ...], kiss_version: str | None
) -> tuple[list[dict[str, Any]], dict[str, dict[str, Any]]]:
    """Every placerec cell (world x seed x source) and every KISS-SLAM cell (world x seed), from the cache when
    it holds them with the same key, else run and cached."""
    cells: list[dict[str, Any]] = []
    kiss: dict[str, dict[str, Any]] = {}
    for world in args.worlds:
        for seed in seeds:
            name = f"{world}_{SENSOR}_{seed}"
            for source in args.sources:
                cfg = cell_config(world, seed, source, args.set)
                key = _key(config_to_yaml(cfg))
                path = args.cache / "cells" / f"{name}_{source}.json"
                cell = _cached(path, key)
                if cell is None:
                    print(f"running {name} {source} ...", flush=True)
                    head = {"key": key, "world": world, "seed": seed, "source": source}
                    cell = {**head, **run_placerec_cell(cfg)}
                    _save(path, cell)
                cells.append(cell)
            if kiss_version is None:
                continue
            cfg = cell_config(world, seed, args.sources[0], args.set)
            data_key = _key(config_to_yaml(cfg.dataset))
            key = _key(f"kiss-slam {kiss_version}", data_key)
            path = args.cache / "cells" / f"{name}_kiss-slam.json"
            cell = _cached(path, key)
            if cell is None:
                print(f"running {name} KISS-SLAM {kiss_version} ...", flush=True)
                folder = export_sequence(cfg, args.cache / "sequences" / f"{name}_{data_key}")
                out = args.cache / "kiss_slam" / name
                delta = cfg.evaluation.rpe_delta
                head = {"key": key, "world": world, "seed": seed, "source": f"kiss-slam {kiss_version}"}
                cell = {**head, **run_kiss_slam(args.kiss_slam_venv, folder, out, delta)}
                _save(path, cell)
            kiss[f"{world} {seed}"] = cell
    return cells, kiss


def print_matrix(cells: list[dict[str, Any]], kiss: dict[str, dict[str, Any]], title: str) -> None:
    """Two tables: every placerec cell; then ATE before -> after side by side per sequence, KISS-SLAM beside."""
    f = "{:.3f}".format
    rows = []
    for c in cells:
        met = meets_target(c)
        b, a = c["before"], c["after"]
        rows.append([
            f"{c['world']} {c['seed']}", c["source"], f(b["ate_rmse"]), f(a["ate_rmse"]),
            f"{b['ate_rmse'] / a['ate_rmse']:.1f}x", f(b["rpe_translation_rmse"]), f(a["rpe_translation_rmse"]),
            str(c["loops"]), str(c["false_loops"]), str(c["rejected_by_back_end"]),
            f(c["candidates"]["max_wrong_score"] or 0.0), "-" if met is None else ("met" if met else "MISSED"),
        ])  # fmt: skip
    header = [
        "cell", "odometry", "ATE before [m]", "ATE after [m]", "reduction", "RPE before [m]", "RPE after [m]",
        "loops", "false", "rejected by graph", "max wrong score", "target",
    ]  # fmt: skip
    print_rows(header, rows, f"placerec slam per cell, {title}")
    sources = list(dict.fromkeys(c["source"] for c in cells))
    by = {(f"{c['world']} {c['seed']}", c["source"]): c for c in cells}
    rows = []
    for seq in dict.fromkeys(f"{c['world']} {c['seed']}" for c in cells):
        row = [seq]
        for s in sources:
            c = by[seq, s]
            row.append(f"{f(c['before']['ate_rmse'])} -> {f(c['after']['ate_rmse'])} ({c['loops']})")
        if seq in kiss:
            k = kiss[seq]
            row.append(f"{f(k['after']['ate_rmse'])} ({k['closures']})")
        rows.append(row)
    header = ["sequence", *(f"{s}: ATE [m] (loops)" for s in sources)]
    if kiss:
        header.append("KISS-SLAM: ATE [m] (closures)")
    print_rows(header, rows, f"ATE side by side, {title}")


def summary(
    cells: list[dict[str, Any]],
    kiss: dict[str, dict[str, Any]],
    split: str,
    threshold: float,
    kiss_version: str | None,
) -> dict[str, Any]:
    """The one JSON line."""
    judged = [m for m in map(meets_target, cells) if m is not None]
    return {
        "bench": "slam_matrix",
        "split": split,
        "threshold": threshold,
        "cells": len(cells),
        "cells_with_loops": len(judged),
        "targets_met": int(sum(judged)),
        "false_loops": sum(c["false_loops"] for c in cells),
        "max_wrong_candidate_score": max((c["candidates"]["max_wrong_score"] or 0.0) for c in cells),
        "ate_before_after_m": {
            f"{c['world']}_{c['seed']}_{c['source']}": [
                round(c["before"]["ate_rmse"], 4),
                round(c["after"]["ate_rmse"], 4),
            ]
            for c in cells
        },
        "loops": {f"{c['world']}_{c['seed']}_{c['source']}": c["loops"] for c in cells},
        "kiss_slam": kiss_version,
        "kiss_slam_ate_m": {k.replace(" ", "_"): round(v["after"]["ate_rmse"], 4) for k, v in kiss.items()},
        "kiss_slam_closures": {k.replace(" ", "_"): v["closures"] for k, v in kiss.items()},
    }


if __name__ == "__main__":
    main()
