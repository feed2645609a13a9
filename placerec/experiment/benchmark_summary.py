"""The matrix figures of a benchmark: per pipeline each figure per cell and over the matrix (`summarise`), the
tuning rule that picks operating thresholds (`suggest_thresholds`), the console / HTML table (`rows`), the one JSON
line (`bench_line`) and the files of the benchmark folder (`write_outputs`: ``benchmark.json``, ``cells.csv``,
heatmaps, ``index.html``)."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from placerec.experiment.run_folder import finite_or_null, json_default
from placerec.experiment.tables import lookup, write_html_page
from placerec.io.atomic import atomic_write

if TYPE_CHECKING:
    from placerec.experiment.benchmark import BenchmarkConfig

__all__ = [
    "BENCH_VERSION",
    "CELL_FIGURES",
    "bench_line",
    "rows",
    "suggest_thresholds",
    "rule_inputs",
    "suggest_by_sensor",
    "summarise",
    "write_outputs",
]

#: The version of ``cell.json`` and ``benchmark.json``.
BENCH_VERSION = 1


def _num(x: Any) -> float:
    return float(x) if isinstance(x, int | float) and x is not None and math.isfinite(float(x)) else math.nan


#: Figures per cell and pipeline: (name, path in metrics.json, "high" if higher is better else "low")
CELL_FIGURES: tuple[tuple[str, tuple[str, ...], str], ...] = (
    ("max_f1", ("max_f1",), "high"),
    ("pose_max_f1", ("pose_truth", "max_f1"), "high"),
    ("precision", ("pose_truth", "operating", "precision"), "high"),
    ("recall", ("pose_truth", "operating", "recall"), "high"),
    ("f1", ("pose_truth", "operating", "f1"), "high"),
    ("false_closures", ("pose_truth", "operating", "fp"), "low"),
    ("distance_precision", ("operating", "precision"), "high"),
    ("distance_recall", ("operating", "recall"), "high"),
    ("same_direction_recall", ("directions", "same", "recall_at_threshold"), "high"),
    ("reverse_recall", ("directions", "reverse", "recall_at_threshold"), "high"),
    ("pose_same_direction_recall", ("pose_truth", "directions", "same", "recall_at_threshold"), "high"),
    ("pose_reverse_recall", ("pose_truth", "directions", "reverse", "recall_at_threshold"), "high"),
    ("recall_at_100_precision", ("recall_at_100_precision",), "high"),
    ("pose_recall_at_100_precision", ("pose_truth", "recall_at_100_precision"), "high"),
    ("describe_ms", ("time_ms", "stages", "describe", "mean"), "low"),
    ("query_ms", ("time_ms", "stages", "query", "mean"), "low"),
    ("verify_ms", ("time_ms", "stages", "verify", "mean"), "low"),
    ("ms_per_scan", ("time_ms", "mean"), "low"),
)


def summarise(bench: BenchmarkConfig, cells: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """``benchmark.json``: per pipeline, each figure per cell and over the matrix (mean, worst), the accepted
    closures' pose errors pooled over the matrix, and the threshold each pipeline was judged at; whether the
    closures were judged with the odometry gate (``odometry_gate``) or on appearance alone."""
    labels = [p.display_name for p in bench.pipelines]
    pipelines: dict[str, Any] = {}
    for label in labels:
        per_cell = {name: c["metrics"].get(label, {}) for name, c in cells.items()}
        figures: dict[str, Any] = {}
        for fig, path, better in CELL_FIGURES:
            values = {name: _num(lookup(m, path)) for name, m in per_cell.items()}
            arr = np.array([v for v in values.values() if math.isfinite(v)])
            worst = (arr.min() if better == "high" else arr.max()) if arr.size else math.nan
            figures[fig] = {"cells": values, "mean": float(arr.mean()) if arr.size else math.nan,
                            "worst": float(worst)}  # fmt: skip
        t_err, r_err = [], []
        for m in per_cell.values():
            op = lookup(m, ("pose_truth", "operating")) or {}
            t_err += [v for v in op.get("accepted_translation_m", []) if v is not None]
            r_err += [v for v in op.get("accepted_rotation_deg", []) if v is not None]
        missed: dict[str, Any] = {}
        for m in per_cell.values():
            for key, value in (lookup(m, ("pose_truth", "operating", "missed")) or {}).items():
                if isinstance(value, list):
                    old = missed.get(key, [0, 0])
                    missed[key] = [old[0] + value[0], old[1] + value[1]]
                else:
                    missed[key] = missed.get(key, 0) + value
        thresholds = {lookup(m, ("operating", "threshold")) for m in per_cell.values()}
        pipelines[label] = {
            "threshold": next(iter(thresholds)) if len(thresholds) == 1 else sorted(map(str, thresholds)),
            "figures": figures,
            "accepted_translation_m": _stats(t_err),
            "accepted_rotation_deg": _stats(r_err),
            "missed": missed,
            "cells_with_false_closures": sorted(
                name for name, v in figures["false_closures"]["cells"].items() if v and v > 0
            ),
        }
    return {
        "version": BENCH_VERSION,
        "name": bench.name,
        "split": bench.split,
        "odometry_gate": bench.evaluation.odometry_gate is not None,
        "cells": list(cells),
        "n_scans": {name: c.get("n_scans") for name, c in cells.items()},
        "pipelines": pipelines,
    }


def _stats(values: list[float]) -> dict[str, Any]:
    a = np.asarray(values, dtype=np.float64)
    if a.size == 0:
        return {"n": 0, "median": math.nan, "p95": math.nan, "max": math.nan}
    return {"n": int(a.size), "median": float(np.median(a)), "p95": float(np.percentile(a, 95)),
            "max": float(a.max())}  # fmt: skip


def suggest_thresholds(
    bench: BenchmarkConfig, cells: dict[str, dict[str, Any]], step: float = 0.05
) -> dict[str, float | None]:
    """Per pipeline, the operating threshold the tuning rule picks (docs/protocol.md): above the best score of any
    false closure (pose ground truth) in any cell, rounded up to the next multiple of ``step`` (scores in [0, 1];
    1 for counts), and never below the verification's ``min_score`` (a rejected candidate is no answer)."""
    return {
        label: None if inputs is None else tuning_pick(*inputs)
        for label, inputs in rule_inputs(bench, cells, step).items()
    }


def rule_inputs(
    bench: BenchmarkConfig, cells: dict[str, dict[str, Any]], step: float = 0.05
) -> dict[str, tuple[float, float, float] | None]:
    """Per pipeline, what the tuning rule reads from the cells' metrics: (the best false closure's score or -inf,
    the verification's floor, the grid's unit: ``step`` for scores in [0, 1], 1 for counts); None when the
    pipeline scored nothing."""
    out: dict[str, tuple[float, float, float] | None] = {}
    for spec in bench.pipelines:
        label = spec.display_name
        false = [
            _num(lookup(c["metrics"].get(label, {}), ("pose_truth", "max_false_score")))
            for c in cells.values()
        ]
        top = [_num(lookup(c["metrics"].get(label, {}), ("max_score",))) for c in cells.values()]
        if not any(math.isfinite(t) for t in top):
            out[label] = None
            continue
        unit = step if max(t for t in top if math.isfinite(t)) <= 1.0 else 1.0
        worst = max((f for f in false if math.isfinite(f)), default=-math.inf)
        floors = [lookup(c["metrics"].get(label, {}), ("min_score",)) for c in cells.values()]
        floor = max((f for f in floors if isinstance(f, int | float)), default=0.0)
        out[label] = (worst, floor, unit)
    return out


def tuning_pick(worst_false: float, floor: float, step: float = 0.05) -> float:
    """The tuning rule (docs/protocol.md): above ``worst_false``, the best score of any false closure (-inf: none),
    rounded up to the next multiple of ``step``, and never below the verification's ``floor``."""
    pick = 0.0 if worst_false == -math.inf else (math.floor(worst_false / step + 1e-9) + 1) * step
    return round(max(pick, floor), 6)


def suggest_by_sensor(
    bench: BenchmarkConfig, cells: dict[str, dict[str, Any]], step: float = 0.05
) -> dict[str, dict[str, float | None]]:
    """`suggest_thresholds` over each sensor's cells alone (what `placerec.sensor_presets` holds)."""
    sensor_of = {c.name: c.sensor for c in bench.cells()}
    out: dict[str, dict[str, float | None]] = {}
    for sensor in dict.fromkeys(sensor_of[name] for name in cells):
        mine = {name: cell for name, cell in cells.items() if sensor_of[name] == sensor}
        out[sensor] = suggest_thresholds(bench, mine, step)
    return out


def bench_line(payload: dict[str, Any]) -> str:
    """The one JSON line the benchmark ends with: per pipeline the matrix means / worsts of the headline figures."""
    short = {}
    for label, p in payload["pipelines"].items():
        f = p["figures"]
        short[label] = {
            "threshold": p["threshold"],
            "max_f1_mean": f["max_f1"]["mean"],
            "precision_mean": f["precision"]["mean"],
            "precision_worst": f["precision"]["worst"],
            "recall_mean": f["recall"]["mean"],
            "recall_worst": f["recall"]["worst"],
            "false_closures": int(np.nansum(list(f["false_closures"]["cells"].values()))),
            "t_err_p95_m": p["accepted_translation_m"]["p95"],
            "ms_per_scan_mean": f["ms_per_scan"]["mean"],
        }
    line = {"tool": "bench", "name": payload["name"], "split": payload["split"], "cells": len(payload["cells"]),
            "odometry_gate": payload.get("odometry_gate", False), "seconds": payload.get("seconds"),
            "pipelines": short}  # fmt: skip
    return json.dumps(_finite(line), separators=(",", ":"))


def _finite(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    if isinstance(value, float):
        return round(value, 4) if math.isfinite(value) else None
    return value


#: the columns of the console's default benchmark table (`rows` with ``wide`` False)
_COMPACT = ("pipeline", "thr", "maxF1", "P mean", "R mean", "ms/scan")


def rows(payload: dict[str, Any], wide: bool = True) -> tuple[list[str], list[list[str]]]:
    """The console / HTML table: one row per pipeline, the matrix mean and worst of the headline figures (with
    ``wide`` False only the `_COMPACT` columns, the console's default)."""
    header = [
        "pipeline",
        "thr",
        "maxF1",
        "P mean",
        "P worst",
        "R mean",
        "R worst",
        "FP",
        "t p95 m",
        "ms/scan",
    ]
    out = []
    for label, p in payload["pipelines"].items():
        f = p["figures"]
        thr = p["threshold"]
        out.append([
            label,
            "-" if thr is None else f"{thr:g}" if isinstance(thr, float | int) else "mixed",
            _fmt(f["max_f1"]["mean"]),
            _fmt(f["precision"]["mean"]),
            _fmt(f["precision"]["worst"]),
            _fmt(f["recall"]["mean"]),
            _fmt(f["recall"]["worst"]),
            str(int(np.nansum(list(f["false_closures"]["cells"].values())))),
            _fmt(p["accepted_translation_m"]["p95"]),
            _fmt(f["ms_per_scan"]["mean"], 0),
        ])  # fmt: skip
    if not wide:
        keep = [header.index(h) for h in _COMPACT]
        return [header[i] for i in keep], [[r[i] for i in keep] for r in out]
    return header, out


def _fmt(x: Any, digits: int = 3) -> str:
    return "-" if x is None or not math.isfinite(float(x)) else f"{float(x):.{digits}f}"


def write_outputs(bench: BenchmarkConfig, root: Path, payload: dict[str, Any]) -> None:
    with atomic_write(root / "benchmark.json", "w") as fh:
        json.dump(finite_or_null(payload), fh, indent=1, allow_nan=False, default=json_default)
    with atomic_write(root / "config.yaml", "w") as fh:
        import yaml

        yaml.safe_dump(bench.model_dump(mode="json"), fh, sort_keys=False)
    with atomic_write(root / "cells.csv", "w") as fh:
        w = csv.writer(fh, lineterminator="\n")
        names = [f for f, _, _ in CELL_FIGURES]
        w.writerow(["pipeline", "cell", *names])
        for label, p in payload["pipelines"].items():
            for cell in payload["cells"]:
                w.writerow([label, cell, *(_fmt(p["figures"][n]["cells"].get(cell), 4) for n in names)])
    if bench.output.figures:
        from placerec.experiment.figures import plot_heatmap

        for fig, title in (("recall", "recall at the fixed threshold (pose truth); x: a false closure"),
                           ("max_f1", "max F1 (distance truth, threshold chosen after the fact)")):  # fmt: skip
            labels = list(payload["pipelines"])
            values = np.array([[_num(payload["pipelines"][lb]["figures"][fig]["cells"][c]) for c in payload["cells"]]
                               for lb in labels])  # fmt: skip
            marks = np.array([[(_num(payload["pipelines"][lb]["figures"]["false_closures"]["cells"][c]) or 0) > 0
                               for c in payload["cells"]] for lb in labels])  # fmt: skip
            plot_heatmap(values, labels, payload["cells"], root / f"heatmap_{fig}.png",
                         f"{bench.name} ({bench.split} split): {title}", marks if fig == "recall" else None)  # fmt: skip
        write_html_page(root, f"{bench.name} ({bench.split} split)",
                        f"{len(payload['cells'])} cells", [rows(payload)], first=("heatmap_recall.png",))  # fmt: skip
