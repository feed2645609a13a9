"""Recall against keyframe length on the TUNING cells of the sensors that do not spin (how protocol.CAPTURE's
keyframe length was chosen; docs/sensors.md). Not a result: tuning data.

Each (sensor, length) is one loop-mode cell of ``configs/benchmark_sensors_tuning.yaml`` (town, seed 0) with the
sensor's capture and the keyframe length replaced, run into ``--out``; reported per pipeline: recall at the
preset's fixed threshold under the pose ground truth (precision beside it), and the same-direction revisits'
recall at that threshold (``same R``; a sensor with a limited horizontal field of view cannot see a revisit
driven the other way).

    .venv/bin/python tools/sweep_keyframes.py [--sensors avia e1r mid360] [--seconds 0.5 1.0] [--every 0 0.9]

``--every`` sweeps ``keyframes.every_metres`` too (0: windows one after another). Ends with one JSON line:
{"recall": {"<sensor> <pipeline>[ every <m>]": {"<seconds>": recall}}, ...}.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from placerec.experiment.benchmark import Cell, load_benchmark_config, run_cell
from placerec.experiment.protocol import CAPTURE, TUNING_SEEDS

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sensors", nargs="+", default=[s for s, c in CAPTURE.items() if "keyframes" in c])
    ap.add_argument("--seconds", nargs="+", type=float, default=[0.5, 1.0])
    ap.add_argument("--every", nargs="+", type=float, default=[0.0], help="every_metres values (0: none)")
    ap.add_argument("--out", default=str(ROOT / "results" / "sweep_keyframes"))
    args = ap.parse_args()
    bench = load_benchmark_config(ROOT / "configs" / "benchmark_sensors_tuning.yaml")
    recall: dict[str, dict[str, float]] = {}
    rows = []
    for sensor in args.sensors:
        for seconds in args.seconds:
            for every in args.every:
                window = {"seconds": seconds, "every_metres": every or None}
                base = bench.capture[sensor]
                capture = base.model_copy(update={"keyframes": base.keyframes.model_copy(update=window)})
                cfg = bench.model_copy(update={"capture": {**bench.capture, sensor: capture}})
                cell_cfg = cfg.cell_config(Cell("town", sensor, TUNING_SEEDS[0]))
                t0 = time.perf_counter()
                folder = f"{args.out}/{sensor}_{seconds:g}s" + (f"_every{every:g}m" if every else "")
                result = run_cell(cell_cfg.model_dump(mode="json"), folder)
                took = time.perf_counter() - t0
                for label, m in result["metrics"].items():
                    op = m["pose_truth"]["operating"]
                    same = m.get("directions", {}).get("same", {})
                    key = f"{sensor} {label}" + (f" every {every:g} m" if every else "")
                    recall.setdefault(key, {})[f"{seconds:g}"] = round(op["recall"], 3)
                    rows.append((sensor, seconds, every, label, result["n_scans"], op["precision"], op["recall"],
                                 op["n_revisits"], same.get("recall_at_threshold"), took))  # fmt: skip
    print(f"{'sensor':8} {'kf s':>5} {'every':>5} {'pipeline':16} {'keyframes':>9} {'P':>5} {'R':>6} "
          f"{'revisits':>8} {'same R':>6} {'cell s':>6}")  # fmt: skip
    for s, sec, every, label, n, p, r, nr, same, took in rows:
        same_txt = "-" if same is None else f"{same:.3f}"
        print(
            f"{s:8} {sec:5g} {every:5g} {label:16} {n:9d} {p:5.2f} {r:6.3f} {nr:8d} {same_txt:>6} {took:6.0f}"
        )
    print(json.dumps({"tool": "sweep_keyframes", "split": "tuning", "recall": recall}))


if __name__ == "__main__":
    main()
