"""Wall and CPU time per keyframe of the online loop-closure detector on a sensor that does not spin.

The keyframes of one tuning cell of ``configs/benchmark_sensors_tuning.yaml`` (``--world``, ``--sensor``,
``--seed``: driven as `placerec.experiment.protocol.CAPTURE` says, keyframes built and preprocessed before timing),
then `LoopClosureDetector.for_pipeline(pipeline, sensor=..., odometry_gate=...)` over them, fed the keyframes'
true poses as the odometry: the sensor's settings and threshold chosen with the odometry gate (`placerec.sensor_presets`),
the cell's exclusion window. Per keyframe the wall and CPU (the process's, all threads) milliseconds of
``process`` (describe + query + verify + insert), reported as median / p95 / mean, and the closures accepted
(their count does not depend on the machine: a change that keeps results keeps it). Tuning data, a timing only.

    .venv/bin/python tools/bench_sensor_detector.py [--sensor avia] [--world town] [--seed 0] [--pipeline orb-dbow]

Ends with one JSON line.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from placerec.experiment.benchmark import Cell, load_benchmark_config
from placerec.experiment.preprocessing import preprocessed_scan
from placerec.experiment.protocol import is_test_seed
from placerec.experiment.runner import loop_sequence
from placerec.loop_closure import LoopClosureDetector
from placerec.odometry_gate import OdometryGateParams

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sensor", default="avia")
    ap.add_argument("--world", default="town")
    ap.add_argument("--seed", type=int, default=0, help="a tuning seed (test seeds are refused)")
    ap.add_argument("--pipeline", default="orb-dbow")
    args = ap.parse_args()
    if is_test_seed(args.seed):
        ap.error(f"seed {args.seed} belongs to the test split: timings are taken on tuning cells only")
    bench = load_benchmark_config(ROOT / "configs" / "benchmark_sensors_tuning.yaml")
    cfg = bench.cell_config(Cell(args.world, args.sensor, args.seed))
    seq = loop_sequence(cfg)
    scans = [preprocessed_scan(seq, i, cfg.preprocess)[0] for i in range(len(seq))]
    poses = seq.poses
    ex = cfg.evaluation.exclusion
    det = LoopClosureDetector.for_pipeline(
        args.pipeline,
        sensor=args.sensor,
        odometry_gate=OdometryGateParams(),
        exclusion_frames=ex.frames,
        exclusion_seconds=ex.seconds,
        exclusion_metres=ex.metres,
    )
    stamps = seq.timestamps
    wall, cpu, closures = [], [], 0
    for i, scan in enumerate(scans):
        w0, c0 = time.perf_counter(), time.process_time()
        found = det.process(scan, pose=poses[i], timestamp=None if stamps is None else float(stamps[i]))
        wall.append((time.perf_counter() - w0) * 1e3)
        cpu.append((time.process_time() - c0) * 1e3)
        closures += len(found)

    def stats(v: list[float]) -> list[float]:
        return [round(float(x), 2) for x in (np.median(v), np.percentile(v, 95), np.mean(v))]

    out = {
        "tool": "bench_sensor_detector",
        "cell": f"{args.world}_{args.sensor}_{args.seed}",
        "pipeline": args.pipeline,
        "keyframes": len(scans),
        "wall_ms": stats(wall),
        "cpu_ms": stats(cpu),
        "closures": closures,
        "load_after": [round(x, 2) for x in os.getloadavg()],
    }
    print(f"{out['cell']} {args.pipeline}: {len(scans)} keyframes, {closures} closures accepted")
    print(f"  ms a keyframe, median / p95 / mean: wall {out['wall_ms']}, CPU {out['cpu_ms']}")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
