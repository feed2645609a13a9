"""Per-scan time of the visual pipeline (ORB-HBST) with a large database.

The database is filled with the descriptions of the first ``--db`` scans of a simulated OS1-64 sequence (cached
under ``.cache/bench_visual``, so reruns skip the simulation); then, for the next ``--queries`` scans, we time
what a SLAM loop-closure call costs: image formation + features + query (retrieval, then the verification of the
top-k candidates, reported apart as ``verify``) + insert (simulation excluded), and report the median against the
issue's target (<= 25 ms on 64 x 1024 images, verification included).

    .venv/bin/python tools/bench_visual.py [--db 2000] [--queries 100] [--pipeline orb-hbst]
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import numpy as np

from placerec.experiment.cache import DescriptionCache, config_hash
from placerec.recognizer import make_pipeline
from placerec.sim import SimulatedSequence


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--db", type=int, default=2000)
    ap.add_argument("--queries", type=int, default=100)
    ap.add_argument("--pipeline", default="orb-hbst")
    ap.add_argument("--sensor", default="os1-64")
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args()

    seq = SimulatedSequence(world="town", sensor=args.sensor, n_scans=args.db + args.queries, seed=args.seed)
    rec = make_pipeline(args.pipeline)
    cache = DescriptionCache(".cache/bench_visual", config_hash(seq.name, args.db + args.queries))
    t0 = time.perf_counter()
    from rich.progress import track

    for i in track(range(args.db), description="filling the database"):
        hit = cache.get(rec.frontend_key, i)
        if hit is None:
            t_describe = time.perf_counter()
            desc = rec.describe(seq[i])
            cache.put(rec.frontend_key, i, desc, (time.perf_counter() - t_describe) * 1e3)
        else:
            desc = hit[0]
        rec.add_description(i, desc)
    fill_s = time.perf_counter() - t0

    stages: dict[str, list[float]] = {
        "image+features": [],
        "query": [],
        "verify": [],
        "insert": [],
        "total": [],
    }
    for i in track(range(args.db, args.db + args.queries), description="timing queries"):
        scan = seq[i]
        t0 = time.perf_counter()
        desc = rec.describe(scan)
        t1 = time.perf_counter()
        cands = rec.query_description(desc, k=5, max_id=i - 120, query_id=i)
        t2 = time.perf_counter()
        rec.add_description(i, desc)
        t3 = time.perf_counter()
        verify_s = sum(c.extra.get("verify_ms", 0.0) for c in cands) / 1e3
        for key, dt in (
            ("image+features", t1 - t0),
            ("query", t2 - t1 - verify_s),
            ("verify", verify_s),
            ("insert", t3 - t2),
            ("total", t3 - t0),
        ):
            stages[key].append(dt * 1e3)

    print(
        f"{args.pipeline} on simulated {args.sensor} ({scan.shape or len(scan)}), database {args.db} scans "
        f"({len(rec.tree) if hasattr(rec, 'tree') else '?'} descriptors), filled in {fill_s:.1f} s"
    )
    print(f"{'stage':<16}{'median ms':>10}{'p95 ms':>10}")
    for key, vals in stages.items():
        print(f"{key:<16}{np.median(vals):>10.2f}{np.percentile(vals, 95):>10.2f}")
    median = float(np.median(stages["total"]))
    print(f"target <= 25 ms: {'met' if median <= 25 else 'NOT met'}")
    print(
        json.dumps(
            {
                "bench": "visual",
                "pipeline": args.pipeline,
                "sensor": args.sensor,
                "db_scans": args.db,
                "queries": args.queries,
                "machine": platform.machine(),
                "median_ms": round(median, 2),
                "p95_ms": round(float(np.percentile(stages["total"], 95)), 2),
                **{
                    f"{k.replace('+', '_')}_median_ms": round(float(np.median(v)), 2)
                    for k, v in stages.items()
                    if k != "total"
                },
                "target_ms": 25,
                "target_met": median <= 25,
            }
        )
    )


if __name__ == "__main__":
    main()
