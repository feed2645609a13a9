"""Benchmark the Scan Context baseline on synthetic data sized like KITTI.

Descriptor time on a ~120k-point scan (HDL-64-like: 64 beams x 1875 columns over a random box world), then query
time (median) on a 2000-entry database with a loop-closure style ``max_id`` bound. Prints readable lines, then
exactly one JSON line of headline figures.

    python tools/bench_scan_context.py [--points 120000] [--db 2000] [--queries 200] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from placerec.baselines.scan_context import ScanContext, make_descriptor
from placerec.types import Scan


def synthetic_scan(rng: np.random.Generator, n_points: int) -> Scan:
    """Ranges from a random world: each ray hits either the ground or a wall at a random distance per column."""
    beams = 64
    cols = max(1, n_points // beams)
    elev = np.radians(np.linspace(2.0, -24.8, beams))[:, None]
    az = np.linspace(-np.pi, np.pi, cols, endpoint=False)[None, :]
    wall = np.repeat(rng.uniform(5.0, 100.0, size=(1, cols // 25 + 1)), 25, axis=1)[:, :cols]
    ground = np.where(elev < 0, 1.73 / np.maximum(-np.sin(elev), 1e-3), np.inf)
    rng_ = np.minimum(wall / np.cos(elev), ground) + 0.02 * rng.normal(size=(beams, cols))
    xyz = np.stack(
        [rng_ * np.cos(elev) * np.cos(az), rng_ * np.cos(elev) * np.sin(az), rng_ * np.sin(elev)], axis=-1
    ).reshape(-1, 3)
    return Scan(xyz.astype(np.float32), rng.random(xyz.shape[0]).astype(np.float32))


def median_ms(fn, reps: int) -> float:
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=120_000)
    ap.add_argument("--db", type=int, default=2000)
    ap.add_argument("--queries", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)

    scan = synthetic_scan(rng, args.points)
    make_descriptor(scan)  # warm up
    desc_ms = median_ms(lambda: make_descriptor(scan), 50)
    print(f"descriptor: {len(scan)} points, median {desc_ms:.2f} ms")

    t0 = time.perf_counter()
    sc = ScanContext()
    small = [synthetic_scan(rng, 16_000) for _ in range(50)]  # 50 base scenes, turned and jittered
    for i in range(args.db):
        base = small[i % len(small)]
        a = rng.uniform(0, 2 * np.pi)
        R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]], dtype=np.float32)
        xyz = base.xyz @ R.T + rng.normal(scale=0.5, size=(1, 3)).astype(np.float32) * [1, 1, 0]
        sc.add(i, Scan(xyz, base.intensity))
    build_s = time.perf_counter() - t0
    print(f"database: {len(sc)} entries built in {build_s:.2f} s")

    qdesc = [make_descriptor(synthetic_scan(rng, 16_000)) for _ in range(20)]
    max_ids = rng.integers(args.db // 2, args.db, size=args.queries)
    it = iter(range(10**9))

    def one_query(scan_context: ScanContext) -> None:
        j = next(it)
        scan_context.query_description(qdesc[j % len(qdesc)], k=1, max_id=int(max_ids[j % args.queries]))

    query_ms = median_ms(lambda: one_query(sc), args.queries)
    query_all_ms = median_ms(lambda: sc.query_description(qdesc[0], k=1), args.queries)
    full = ScanContext(full_shift_search=True)
    with tempfile.TemporaryDirectory() as tmp:  # same database, other query parameters
        t0 = time.perf_counter()
        sc.save(Path(tmp) / "sc.npz")
        full.load(Path(tmp) / "sc.npz")
        io_s = time.perf_counter() - t0
    print(f"save + load of the database: {io_s:.2f} s")
    query_full_ms = median_ms(lambda: one_query(full), args.queries)
    end_to_end_ms = median_ms(lambda: sc.query(scan, k=1, max_id=args.db - 120), 20)
    print(
        f"query ({len(sc)} entries, max_id bound): median {query_ms:.3f} ms; without bound {query_all_ms:.3f} ms"
    )
    print(f"query with full shift search: median {query_full_ms:.3f} ms")
    print(f"query from a {len(scan)}-point scan (descriptor + search): median {end_to_end_ms:.2f} ms")
    print(
        json.dumps(
            {
                "bench": "scan_context",
                "machine": platform.machine(),
                "points": len(scan),
                "descriptor_ms_median": round(desc_ms, 3),
                "db_entries": len(sc),
                "query_ms_median": round(query_ms, 3),
                "query_no_bound_ms_median": round(query_all_ms, 3),
                "query_full_shift_ms_median": round(query_full_ms, 3),
                "query_from_scan_ms_median": round(end_to_end_ms, 3),
            }
        )
    )


if __name__ == "__main__":
    main()
