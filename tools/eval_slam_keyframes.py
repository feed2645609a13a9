"""`placerec slam` on scanners that do not spin, with and without keyframes (docs/slam.md, "Scanners that do not
spin: keyframes").

Two parts, each a table and one JSON line at the end:

* ``frames``: per sensor (Avia, MID-360, E1R), pipeline (Scan Context, ORB-DBoW) and seed, the default route of a
  world driven at 10 Hz with each frame taken while moving, the demo's drifting odometry
  (`configs/slam_demo.yaml`), each pipeline at the sensor's operating threshold (`placerec.sensor_presets`) and
  the exclusion of the sensor benchmark (120 m of path), run twice: every frame a place, then places accumulated
  into the sensor benchmark's keyframes (`placerec.experiment.protocol.CAPTURE`: 0.5 s / 1 s / 0.5 s, one every
  1.8 m). Loops accepted (false: beyond `placerec slam`'s 1 m / 5 deg), odometry and optimised ATE.
* ``sessions``: two MID-360 sessions of one world (`configs/slam_livox.yaml`): the first saved as a map of
  keyframes, the second (another drive: other clutter and noise) joined to it (``--prior-map``), its merged map's
  keyframes scored against the simulator's truth: joined or not, inter-session closures and the false ones (beyond
  1 m / 5 deg of the true relative pose), their median error, the merged ATE over both sessions' keyframes (one
  rigid alignment).

Every setting was chosen before on the sensor benchmark's tuning cells; nothing is chosen here. Seeds: the tuning
world (0) by default; ``--seeds 4601 4602`` the test split's (a world seed's drives: the seed and the other test
seed for ``sessions``).

    .venv/bin/python tools/eval_slam_keyframes.py                          # both parts, tuning world: ~6 min
    .venv/bin/python tools/eval_slam_keyframes.py --part sessions --seeds 4601 4602 --worlds town campus industrial
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from placerec.eval.pose_error import pose_errors
from placerec.eval.trajectory import ate
from placerec.experiment import protocol
from placerec.maps import MapArtifact
from placerec.recognizer import PIPELINES
from placerec.sim import SimulatedSequence
from placerec.slam_app.config import load_slam_config
from placerec.slam_app.run import run_slam

ROOT = Path(__file__).resolve().parents[1]
SENSORS = ("avia", "mid360", "e1r")
FRAME_PIPELINES = ("scan-context", "orb-dbow")
#: a tuning seed's second drive for ``sessions`` (the test seeds pair with each other)
TUNING_SECOND_DRIVE = 11
CORRECT = (1.0, 5.0)


def keyframe_setting(sensor: str) -> str:
    """``loops.keyframes`` as the sensor benchmark captures the sensor (`protocol.CAPTURE`)."""
    k = protocol.CAPTURE[sensor]["keyframes"]
    return f"loops.keyframes={{seconds: {k['seconds']}, every_metres: {k['every_metres']}}}"


def frames_row(
    world: str, sensor: str, pipeline: str, seed: int, keyframes: bool, n: int | None, out: Path
) -> dict:
    """One `placerec slam` run of the ``frames`` part."""
    threshold = PIPELINES[pipeline].threshold_for(sensor)
    sets = [f"dataset.simulator.world={world}", f"dataset.simulator.sensor={sensor}", "dataset.simulator.rate_hz=10",
            "dataset.simulator.sweep_motion=true", f"dataset.simulator.seed={seed}", "output.progress=false",
            "output.figures=false", f"loops.pipeline.name={pipeline}", f"loops.threshold={threshold}",
            "loops.exclusion={frames: null, metres: 120}",
            *([f"dataset.simulator.n_scans={n}"] if n else []), *([keyframe_setting(sensor)] if keyframes else [])]  # fmt: skip
    t0 = time.perf_counter()
    _, p = run_slam(load_slam_config(ROOT / "configs" / "slam_demo.yaml", sets), out)
    tr, lp = p["trajectory"], p["loops"]
    return {"world": world, "sensor": sensor, "pipeline": pipeline, "seed": seed, "keyframes": keyframes,
            "threshold": threshold, "frames": p["n_scans"], "loops": lp["accepted"], "false": lp["false_accepted"],
            "opposite": lp["opposite_direction"], "ate_odometry_m": round(tr["odometry"]["ate_rmse"], 3),
            "ate_m": round(tr["optimized"]["ate_rmse"], 3), "seconds": round(time.perf_counter() - t0, 1)}  # fmt: skip


def merged_figures(merged: MapArtifact, truths: tuple[np.ndarray, np.ndarray]) -> dict[str, Any]:
    """A two-session map of keyframes against the sessions' true poses: the inter-session closures of its graph
    and the false ones (beyond `CORRECT` of the true relative pose), their median error, the merged ATE."""
    sess, idx = np.asarray(merged.session), np.asarray(merged.scan_index)
    truth = np.stack([truths[int(s)][int(i)] for s, i in zip(sess, idx, strict=True)])
    M = int((sess == 0).sum())
    graph = merged.graph()
    inter = [] if graph is None else [lp for lp in graph.loops if lp.match_id < M <= lp.query_id]
    errors = np.zeros((0, 2))
    if inter:
        rel = np.stack([np.linalg.inv(truth[lp.match_id]) @ truth[lp.query_id] for lp in inter])
        te, re = pose_errors(np.stack([lp.T_match_query for lp in inter]), rel)
        errors = np.stack([te, re], axis=1)
    false = int(((errors[:, 0] > CORRECT[0]) | (errors[:, 1] > CORRECT[1])).sum())
    e = ate(np.asarray(merged.poses), truth)
    return {"keyframes": [M, len(sess) - M], "inter_session_closures": len(inter), "inter_session_false": false,
            "inter_error_median_m": round(float(np.median(errors[:, 0])), 3) if inter else None,
            "merged_ate_m": round(float(np.sqrt(np.mean(e**2))), 3)}  # fmt: skip


def sessions_row(world: str, seed: int, second: int, n: int | None, out: Path) -> dict:
    """Two MID-360 sessions of world ``seed``: drive ``seed`` saved as a map, drive ``second`` joined to it."""
    common = [f"dataset.simulator.world={world}", f"dataset.simulator.world_seed={seed}",
              f"dataset.simulator.unit_seed={seed}", "output.progress=false", "output.figures=false",
              *([f"dataset.simulator.n_scans={n}"] if n else [])]  # fmt: skip
    config = ROOT / "configs" / "slam_livox.yaml"
    t0 = time.perf_counter()
    _, p1 = run_slam(load_slam_config(config, [*common, f"dataset.simulator.seed={seed}",
                                               f"output.save_map={out / 'm1'}"]), out / "r1")  # fmt: skip
    _, p2 = run_slam(load_slam_config(config, [*common, f"dataset.simulator.seed={second}",
                                               f"prior_map.path={out / 'm1'}", f"output.save_map={out / 'm2'}"]),
                     out / "r2")  # fmt: skip
    row = {"world": world, "world_seed": seed, "drives": [seed, second], "session1_loops": p1["loops"]["accepted"],
           "session1_false": p1["loops"]["false_accepted"],
           "session1_ate_m": round(p1["trajectory"]["optimized"]["ate_rmse"], 3),
           "session1_odometry_ate_m": round(p1["trajectory"]["odometry"]["ate_rmse"], 3),
           "joined": bool(p2["prior_map"]["joined"])}  # fmt: skip
    if row["joined"]:
        sims = [SimulatedSequence(world=world, sensor="mid360", rate_hz=10, sweep_motion=True, seed=s, world_seed=seed,
                                  unit_seed=seed, n_scans=n) for s in (seed, second)]  # fmt: skip
        row.update(merged_figures(MapArtifact.open(out / "m2"), (sims[0].poses, sims[1].poses)))
    row["seconds"] = round(time.perf_counter() - t0, 1)
    return row


def second_drive(seed: int, seeds: list[int]) -> int:
    """The second session's drive of world ``seed``: another of the given test seeds, else `TUNING_SECOND_DRIVE`."""
    if protocol.is_test_seed(seed):
        others = [s for s in protocol.TEST_SEEDS if s != seed]
        return others[0]
    return TUNING_SECOND_DRIVE


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", nargs="+", choices=("frames", "sessions"), default=["frames", "sessions"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0])
    ap.add_argument("--worlds", nargs="+", default=["town"], choices=protocol.TEST_WORLDS)
    ap.add_argument("--sensors", nargs="+", default=list(SENSORS), choices=SENSORS)
    ap.add_argument("--pipelines", nargs="+", default=list(FRAME_PIPELINES), choices=FRAME_PIPELINES)
    ap.add_argument("--scans", type=int, default=None, help="frames a drive (default: the whole route)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    out: dict[str, Any] = {"tool": "eval_slam_keyframes", "seeds": args.seeds, "worlds": args.worlds,
                           "split": "test" if all(protocol.is_test_seed(s) for s in args.seeds) else "tuning"}  # fmt: skip
    with tempfile.TemporaryDirectory(prefix="placerec-slam-keyframes-") as tmp:
        work = Path(tmp)
        if "frames" in args.part:
            rows = []
            for world in args.worlds:
                for sensor in args.sensors:
                    for pipeline in args.pipelines:
                        for seed in args.seeds:
                            for kf in (False, True):
                                folder = work / f"{world}-{sensor}-{pipeline}-{seed}-{kf}"
                                rows.append(frames_row(world, sensor, pipeline, seed, kf, args.scans, folder))
                                r = rows[-1]
                                print(f"  {world} {sensor:7} {pipeline:13} seed {seed:5} "
                                      f"{'keyframes' if kf else 'frames   '}: {r['loops']:3} loops ({r['false']} false), "
                                      f"ATE {r['ate_odometry_m']:.3f} -> {r['ate_m']:.3f} m", flush=True)  # fmt: skip
            out["frames"] = rows
        if "sessions" in args.part:
            rows = []
            for world in args.worlds:
                for seed in args.seeds:
                    r = sessions_row(
                        world, seed, second_drive(seed, args.seeds), args.scans, work / f"s-{world}-{seed}"
                    )
                    rows.append(r)
                    print(f"  {world} world {seed}: joined {r['joined']}, {r.get('inter_session_closures')} "
                          f"inter-session closures ({r.get('inter_session_false')} false), merged ATE "
                          f"{r.get('merged_ate_m')} m", flush=True)  # fmt: skip
            out["sessions"] = rows
    out["seconds"] = round(time.perf_counter() - t0)
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
