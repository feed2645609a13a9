"""ORB on 16-row (VLP-16) intensity images: feature counts and loop-closure retrieval per extraction option.

A simulated VLP-16 sequence (town, default route with same- and opposite-direction revisits) goes through
ORB-HBST with each option of `OPTIONS` (overrides of the ORB parameters): the Table I settings on the 16 rows as
they are, smaller detector patches that fit 16 rows, and the rows upsampled by 2, 4, 8 (the default, to 128
rows) and 16. Loop closure as in configs/demo.yaml: scan ``i`` queries the scans up to ``i - 120``; it is a revisit when
one of those lies within 5 m. Reported per option: mean features per image, recall@1 of the revisits (top
candidate within 5 m), max F1 over the score threshold, and milliseconds per scan (describe + query + add).

    .venv/bin/python tools/eval_low_rows.py [--scans N]    # table, then one JSON line of headline figures
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from placerec.recognizer import make_pipeline
from placerec.sim import SimulatedSequence

EXCLUSION_FRAMES = 120
GT_DISTANCE_M = 5.0

#: option name -> ORB parameter overrides
OPTIONS: dict[str, dict] = {
    "Table I, 16 rows": {"row_upsample": 1},
    "patch 7, edge 3, 1 level": {"row_upsample": 1, "patch_size": 7, "edge_threshold": 3, "n_levels": 1},
    "patch 11, edge 5, 1 level": {"row_upsample": 1, "patch_size": 11, "edge_threshold": 5, "n_levels": 1},
    "rows x2 (32)": {"row_upsample": 2},
    "rows x4 (64)": {"row_upsample": 4},
    "rows x8 (128, default)": {},
    "rows x16 (256)": {"row_upsample": 16},
}


def max_f1(scores: np.ndarray, correct: np.ndarray, n_revisits: int) -> float:
    """Best F1 over thresholds: accepted = score >= t; a true positive is an accepted correct candidate."""
    if n_revisits == 0 or scores.size == 0:
        return 0.0
    order = np.argsort(-scores, kind="stable")
    tp = np.cumsum(correct[order])
    precision = tp / np.arange(1, order.size + 1)
    recall = tp / n_revisits
    f1 = np.where(tp > 0, 2 * precision * recall / np.maximum(precision + recall, 1e-12), 0.0)
    return float(f1.max())


def evaluate(scans: list, positions: np.ndarray, overrides: dict) -> dict:
    pipe = make_pipeline("orb-hbst", {"feature_params": overrides})
    n_feats, scores, correct, hits = [], [], [], 0
    revisit_count = 0
    t0 = time.perf_counter()
    for i, scan in enumerate(scans):
        desc = pipe.describe(scan)
        n_feats.append(len(desc["keypoints"]))
        last = i - EXCLUSION_FRAMES
        if last >= 0:
            dist = np.linalg.norm(positions[: last + 1] - positions[i], axis=1)
            revisit = bool((dist <= GT_DISTANCE_M).any())
            revisit_count += revisit
            cands = pipe.query_description(desc, k=1, max_id=last, query_id=i)
            if cands:
                ok = bool(dist[cands[0].match_id] <= GT_DISTANCE_M)
                scores.append(cands[0].score)
                correct.append(ok)
                hits += ok and revisit
        pipe.add_description(i, desc)
    ms = 1e3 * (time.perf_counter() - t0) / len(scans)
    return {
        "features": round(float(np.mean(n_feats)), 1),
        "recall_at_1": round(hits / max(revisit_count, 1), 3),
        "max_f1": round(max_f1(np.array(scores, float), np.array(correct, bool), revisit_count), 3),
        "ms_per_scan": round(ms, 1),
        "revisits": revisit_count,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scans", type=int, default=None, help="scans (default: the whole default route)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    seq = SimulatedSequence(world="town", sensor="vlp16", n_scans=args.scans, seed=args.seed)
    scans = [seq[i] for i in range(len(seq))]
    positions = np.asarray(seq.poses)[:, :3, 3]
    print(f"simulated VLP-16 town sequence: {len(scans)} scans, image {scans[0].sensor.n_beams} rows")
    print(f"{'option':<28} {'features':>8} {'recall@1':>9} {'max F1':>7} {'ms/scan':>8}")
    results = {}
    for name, overrides in OPTIONS.items():
        r = results[name] = evaluate(scans, positions, overrides)
        figures = (
            f"{r['features']:>8.1f} {r['recall_at_1']:>9.3f} {r['max_f1']:>7.3f} {r['ms_per_scan']:>8.1f}"
        )
        print(f"{name:<28} {figures}")
    default = results["rows x8 (128, default)"]
    print(
        json.dumps(
            {"scans": len(scans), "revisits": default["revisits"], "default": default, "options": results}
        )
    )


if __name__ == "__main__":
    main()
