"""Verified visual pipelines on the demo sequence: HBST recall at N per match threshold, and max F1 / recall at
100 % precision / pose errors per pipeline setting (the 'Why ORB-HBST proposed so few candidates' and 'Choices
measured' tables of docs/vpr_results.md).

Describes the scans of ``configs/demo.yaml`` once (ORB front end, ~40 s), then replays loop mode (exclusion window
120 frames, a revisit within 5 m) for every setting on the same descriptions, top candidate per query.

    .venv/bin/python tools/bench_verified_2d.py [--thresholds 25 40 50 60 70] \\
        [--settings '{"name": "orb-hbst", "params": {"verify": {"top_k": 3}}}' ...]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from placerec.config import load_config
from placerec.eval.exclusion import ExclusionWindow
from placerec.eval.metrics import evaluate_loop
from placerec.eval.pose_error import pose_errors
from placerec.experiment.preprocessing import preprocessed_scan
from placerec.experiment.runner import loop_sequence
from placerec.recognizer import make_pipeline
from placerec.retrieval.hbst import HBST, HBSTParams
from placerec.types import relative_pose

EXCLUSION = 120
GT_DISTANCE = 5.0
DEFAULT_SETTINGS = [
    {"name": "orb-hbst", "params": {}},
    {"name": "orb-hbst", "params": {"verify": {"icp_top_k": None}}},
    {"name": "orb-hbst", "params": {"verify": {"icp_top_k": 1}}},
    {"name": "orb-hbst", "params": {"verify": {"top_k": 10}}},
    {"name": "orb-hbst", "params": {"verify": {"ransac": {"mode": "4dof"}}}},
    {"name": "orb-dbow", "params": {}},
    {"name": "orb-dbow", "params": {"verify": {"top_k": 5, "icp_top_k": None}}},
    {"name": "orb-dbow", "params": {"verify": {"top_k": 10}}},
    {"name": "orb-dbow", "params": {"verify_matches": "retrieval"}},
]


def hbst_recall(descs: list, poses: np.ndarray, threshold: int) -> dict:
    """Recall at N of HBST's votes over the revisit queries, images voted per query, ms per query."""
    tree = HBST(HBSTParams(threshold=threshold))
    P = poses[:, :3, 3]
    ranks, voted, ms = [], [], []
    for i, d in enumerate(descs):
        if i > EXCLUSION:
            dist = np.linalg.norm(P[: i - EXCLUSION] - P[i], axis=1)
            if dist.min() < GT_DISTANCE:
                t0 = time.perf_counter()
                votes = tree.match(d["descriptors"], max_image_id=i - EXCLUSION - 1).scores_per_image()
                ms.append((time.perf_counter() - t0) * 1e3)
                voted.append(len(votes))
                true = set(np.flatnonzero(dist < GT_DISTANCE).tolist())
                ranks.append(next((r for r, j in enumerate(votes.image_ids[:20]) if int(j) in true), 99))
        tree.add(i, d["descriptors"])
    r = np.asarray(ranks)
    out = {f"R@{n}": round(float((r < n).mean()), 3) for n in (1, 5, 10, 20)}
    return {
        "threshold": threshold,
        "voted": round(float(np.mean(voted)), 1),
        **out,
        "ms": round(float(np.mean(ms)), 2),
    }


def run_setting(descs: list, poses: np.ndarray, name: str, params: dict) -> dict:
    rec = make_pipeline(name, params)
    qs, ms, ss, cands, t = [], [], [], [], 0.0
    for i, d in enumerate(descs):
        if i > EXCLUSION:
            t0 = time.perf_counter()
            c = rec.query_description(d, k=1, max_id=i - EXCLUSION - 1, query_id=i)
            t += time.perf_counter() - t0
            qs.append(i)
            ms.append(c[0].match_id if c else -1)
            ss.append(c[0].score if c else 0.0)
            cands.append(c[0] if c else None)
        rec.add_description(i, d)
    m, _ = evaluate_loop(
        qs, ms, ss, poses, gt_distance=GT_DISTANCE, exclusion=ExclusionWindow(frames=EXCLUSION)
    )
    tp = m.outcomes_at(m.threshold_at_max_f1)["tp"]
    est = np.array([c.relative_pose for c, ok in zip(cands, tp, strict=True) if ok])
    gt = np.array(
        [relative_pose(poses[c.match_id], poses[c.query_id]) for c, ok in zip(cands, tp, strict=True) if ok]
    )
    t_err, r_err = pose_errors(est, gt) if len(est) else (np.zeros(0), np.zeros(0))
    return {
        "name": name,
        "params": params,
        "max_f1": round(m.max_f1, 3),
        "recall_at_100_precision": round(m.recall_at_100_precision, 3),
        "tp": int(tp.sum()),
        "t_err_median": round(float(np.median(t_err)), 3) if len(t_err) else None,
        "r_err_median": round(float(np.median(r_err)), 3) if len(r_err) else None,
        "ms_per_query": round(t * 1e3 / len(qs), 1),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="configs/demo.yaml")
    ap.add_argument("--thresholds", type=int, nargs="*", default=[25, 40, 50, 60, 70])
    ap.add_argument("--settings", nargs="*", default=None, help="JSON objects {name, params}")
    args = ap.parse_args()
    settings = [json.loads(s) for s in args.settings] if args.settings else DEFAULT_SETTINGS
    cfg = load_config(args.config)
    seq = loop_sequence(cfg, None)
    front = make_pipeline("orb-hbst")  # the ORB front end every setting shares (same frontend_key)
    descs = [front.describe(preprocessed_scan(seq, i, cfg.preprocess)[0]) for i in range(len(seq))]
    result = {"bench": "verified_2d", "hbst": [hbst_recall(descs, seq.poses, t) for t in args.thresholds]}
    for row in result["hbst"]:
        print(row)
    result["settings"] = []
    for s in settings:
        row = run_setting(descs, seq.poses, s["name"], s.get("params", {}))
        print(row)
        result["settings"].append(row)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
