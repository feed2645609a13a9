"""How long a big map takes to open and to answer, and how much of it ends up in RAM (issue #29's target: a
10k-keyframe map opens in <= 2 s and queries without loading everything into RAM).

For each ``--keyframes`` count a map folder is written (`placerec.maps.MapWriter`) holding ``orb-hbst`` and
``scan-context`` databases and a cloud per keyframe. Simulating 10k scans would take hours, so keyframe ``i`` is a
variant of one of ``--base`` simulated OS1-64 town scans, as in ``tools/bench_stream_memory.py`` (its twelve
30-degree azimuth segments permuted per copy, descriptor bits flipped per copy, fresh noise), at its own pose on a
1 m grid of streets. Then, in a fresh process per pipeline: ``MapArtifact.open`` (manifest, files' sizes, the small
files' hashes, keyframes, the clouds' memory map), the pipeline's database load, then ``--queries`` global
queries with base scans (described once) and the tracking step's cloud access; times, resident memory (``VmRSS``
after each step, peak ``VmHWM``), the private part of it (``RssAnon``: what the process itself holds, not pages
of the map's files that the kernel may drop again) and the folder's size on disk. The last line printed is one JSON object.

    python tools/bench_map_scale.py --keyframes 1000 10000
    python tools/bench_map_scale.py --keyframes 10000 --cold --dir /tmp/maps   # as after a reboot; keeps the maps
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import pickle
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from bench_stream_memory import base_descriptions, segment_turn, status_kb, stream_description  # noqa: E402

from placerec.maps import MapArtifact, MapWriter  # noqa: E402
from placerec.recognizer import PIPELINES, make_pipeline  # noqa: E402

PIPES = ("orb-hbst", "scan-context")


def grid_pose(i: int) -> np.ndarray:
    """Keyframe ``i``'s pose: streets 100 m long, 20 m apart, 1 m between keyframes."""
    T = np.eye(4)
    T[0, 3], T[1, 3] = i % 100, 20.0 * (i // 100)
    return T


def write(base: dict[str, list[dict]], n: int, out: Path) -> float:
    t0 = time.perf_counter()
    recs = {name: make_pipeline(name) for name in PIPES}
    rng = np.random.default_rng(3)
    with MapWriter(out, {k: (r, PIPELINES[k].threshold) for k, r in recs.items()}, name=f"scale-{n}") as w:
        for i in range(n):
            T = grid_pose(i)
            for name, rec in recs.items():
                rec.add_description(i, stream_description(name, base[name], i, i, rng), T)
            d = base["orb-hbst"][i % len(base["orb-hbst"])]
            w.add_keyframe(T, segment_turn(d["cloud"], i // len(base["orb-hbst"])))
        w.finish()
    return time.perf_counter() - t0


def drop_page_cache() -> bool:
    """Empty the kernel's page cache (needs root), so the map is read from disk as after a reboot."""
    import os

    try:
        os.sync()
        with open("/proc/sys/vm/drop_caches", "w") as fh:
            fh.write("1\n")
        return True
    except OSError:
        return False


def measure(args: tuple) -> dict:
    path, name, base_file, n_queries, cold = args
    cold = cold and drop_page_cache()
    with open(base_file, "rb") as fh:
        base = pickle.load(fh)[name]
    rss0, anon0 = status_kb("VmRSS"), status_kb("RssAnon")
    t0 = time.perf_counter()
    m = MapArtifact.open(path)
    t_open = time.perf_counter() - t0
    rss_open, anon_open = status_kb("VmRSS"), status_kb("RssAnon")
    t0 = time.perf_counter()
    rec = m.recognizer(name)
    t_load = time.perf_counter() - t0
    rss_load, anon_load = status_kb("VmRSS"), status_kb("RssAnon")
    times, hits = [], 0
    for q in range(n_queries):
        d = base[(q * 7) % len(base)]
        t0 = time.perf_counter()
        cands = rec.query_description(d, k=3)
        times.append((time.perf_counter() - t0) * 1e3)
        hits += bool(cands and cands[0].accepted)
    t0 = time.perf_counter()
    ids, _ = m.nearest(m.poses[len(m) // 2, :3, 3], k=3)
    clouds = [m.cloud(int(i)) for i in ids]
    t_cloud = (time.perf_counter() - t0) * 1e3
    return {
        "pipeline": name,
        "cold": cold,
        "open_s": t_open,
        "load_s": t_load,
        "first_query_ms": times[0],
        "query_ms_median": float(np.median(times)),
        "accepted": hits,
        "nearest_clouds_ms": t_cloud,
        "cloud_points": sum(len(c) for c in clouds),
        "rss_start_mb": rss0 / 1024,
        "rss_after_open_mb": rss_open / 1024,
        "rss_after_load_mb": rss_load / 1024,
        "anon_start_mb": anon0 / 1024,
        "anon_after_open_mb": anon_open / 1024,
        "anon_after_load_mb": anon_load / 1024,
        "anon_after_queries_mb": status_kb("RssAnon") / 1024,
        "peak_rss_mb": status_kb("VmHWM") / 1024,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--keyframes", type=int, nargs="+", default=[1000, 10_000])
    ap.add_argument("--base", type=int, default=120)
    ap.add_argument("--queries", type=int, default=20)
    ap.add_argument("--cold", action="store_true", help="drop the page cache before each open (needs root)")
    ap.add_argument("--dir", type=Path, help="keep the maps here and reuse those already there")
    args = ap.parse_args()
    results: list[dict] = []
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        base = base_descriptions(args.base)
        base_file = str(Path(tmp) / "base.pkl")
        with open(base_file, "wb") as fh:
            pickle.dump(base, fh)
        print(f"{args.base} base scans described in {time.perf_counter() - t0:.0f} s", flush=True)
        for n in args.keyframes:
            out = (args.dir or Path(tmp)) / f"map{n}"
            build_s = float("nan") if out.exists() else write(base, n, out)
            size = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
            print(f"{n} keyframes: written in {build_s:.0f} s, {size / 1e6:.0f} MB on disk", flush=True)
            for name in PIPES:
                with multiprocessing.get_context("spawn").Pool(1) as pool:
                    r = pool.apply(measure, ((str(out), name, base_file, args.queries, args.cold),))
                r.update(keyframes=n, map_mb=size / 1e6, build_s=build_s)
                results.append(r)
                print(
                    f"  {name:13s} {'cold' if r['cold'] else 'warm'} open {r['open_s']:.2f} s, database load {r['load_s']:.2f} s, first query "
                    f"{r['first_query_ms']:.0f} ms (median {r['query_ms_median']:.0f} ms, {r['accepted']}/"
                    f"{args.queries} accepted), 3 nearest clouds {r['nearest_clouds_ms']:.1f} ms; resident MB: "
                    f"start {r['rss_start_mb']:.0f}, opened {r['rss_after_open_mb']:.0f}, loaded "
                    f"{r['rss_after_load_mb']:.0f}, peak {r['peak_rss_mb']:.0f} (map {size / 1e6:.0f} MB); private "
                    f"(RssAnon, not file pages the kernel can drop): start {r['anon_start_mb']:.0f}, opened "
                    f"{r['anon_after_open_mb']:.0f}, loaded {r['anon_after_load_mb']:.0f}, after queries "
                    f"{r['anon_after_queries_mb']:.0f}",
                    flush=True,
                )
            if args.dir is None:
                import shutil

                shutil.rmtree(out)
    print(json.dumps({"bench": "map_scale", "results": results}))


if __name__ == "__main__":
    main()
