"""Query time and memory of place-recognition databases against their size, and parallel description on Dask.

Databases: the ORB-HBST and ORB-DBoW pipelines (`placerec.pipelines.visual.VisualHBST`,
`placerec.pipelines.dbow.VisualDBoW`, retrieval only: ``verify.enabled: false, check: none``) and Scan Context
(`placerec.baselines.scan_context.ScanContext`, ``verify.enabled: false``), at 1k, 10k and 100k scans.

The ISHOT store (``--ishot-queries``; 0 skips it) is measured on the places database of the localisation benchmark
(simulated town, VLP-16, places 2.5 m apart, one sweep each: 121 places, ~126 ISHOT keypoints per place;
docs/localization.md), built once and saved in each store: ``float32`` (descriptors and clouds float32) and
``sq8`` (`placerec.retrieval.descriptor_store`: 8-bit descriptor codes; int16 clouds). Per store: the saved file's
bytes per place; the anonymous memory of an ``ishot-prob`` pipeline loading it (memory-mapped, as ``places.database``
does; a fresh process each, after a warm-up pipeline and a garbage collection) at 121 places and at
``--ishot-copies`` (8) copies of them side by side, whose difference per added place is what a place costs
(fixed costs such as faiss's index objects left out), and the file pages the load left resident (its CRC check
reads every page once; the kernel may drop them); the median time of ``query_description`` (probabilistic
voting, verification included) and of its matching against the database (``match_ms``) over the first
``--ishot-queries`` gator queries of the benchmark, and the anonymous memory after them (the posterior table and
up to 128 prepared ICP targets the verification caches). Replicating ISHOT places to 100k would not fit this
machine in float32 (754 kB a place: 75 GB).

Descriptions: ``--base`` scans of the simulator (town, OS1-64, 1 m apart) are described once by each front end;
a database of N scans holds them replicated with perturbation, since simulating 100k scans would take hours. Copy
``r`` of a base scan is a distinct place: all its ORB descriptors get the same ``--place-bits`` (40) of their 256
bits flipped, chosen for that copy (copies of one scan are then further apart than HBST's match threshold of 25,
as different places are, and fall into other DBoW words); then each keeps a random 90 % of its features, every
bit flipped with probability ``--flip`` (3 %: about 8 bits, the noise of a revisit), keypoints moved by up to
1 px. A copy's Scan Context is scaled cell by cell by a pattern ``1 + N(0, 0.3)`` of its own (the place), then by
``1 + N(0, 0.05)`` (noise), and turned by a random number of sectors.
Queries are revisits: a random copy of a base scan, with fresh noise; ``top1_hit`` is the fraction whose best
candidate is that copy.

Per database size and pipeline, each in a fresh process (so memory freed by an earlier measurement cannot be
reused): bytes of anonymous memory per scan (``RssAnon`` growth while adding, so NumPy buffers, Python objects and
allocator slack all count), add time, and the median / p95 time of
``query_description(k=5)`` over ``--queries`` queries. Then, at ``--saved-scans`` scans, the full ORB-HBST pipeline (and
ORB-DBoW with ``--saved-pipelines orb-hbst orb-dbow``) *with*
verification (its ICP clouds make most of a scan's bytes) is saved and loaded again memory-mapped
(`placerec.io.atomic.load_artifact` with ``mmap=True``) to show what a saved database costs in RAM; its ICP clouds
are kept as ``--cloud-store`` (``verify.cloud_store``: int16-zlib, the default, int16 or float32).

Last, description of ``--dask-scans`` scans by every front end with 1 and with 2 Dask workers
(`placerec.experiment.parallel.describe_chunk` tasks of two scans on a LocalCluster, empty caches, after a warm-up
task per worker so that start-up is not timed): the speed-up, with the load average (other processes share the
machine). The scans are simulated once and written as a KITTI-style folder that the workers read, as they would a
user's dataset.

The last line printed is one JSON object with the headline figures. Example::

    python tools/bench_scale.py --sizes 1000 10000 100000
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from placerec.config import experiment_preprocess, load_config
from placerec.experiment.preprocessing import preprocessed_scan
from placerec.recognizer import make_pipeline
from placerec.sim import SimulatedSequence

RETRIEVAL_ONLY = {"verify": {"enabled": False}, "check": "none"}
PIPELINES = {
    "orb-hbst": ("orb-hbst", RETRIEVAL_ONLY),
    "orb-dbow": ("orb-dbow", RETRIEVAL_ONLY),
    "scan-context": ("scan-context", {"verify": {"enabled": False}}),
}


def rss_anon_bytes(field: str = "RssAnon") -> int:
    """Anonymous resident memory of this process (Linux /proc), after a garbage collection; ``field="VmRSS"``:
    all resident memory, pages of memory-mapped files included."""
    gc.collect()
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(f"{field}:"):
                return int(line.split()[1]) * 1024
    raise SystemExit(f"bench_scale needs Linux /proc/self/status ({field})")


def base_descriptions(n: int) -> tuple[list[dict], list[dict], list[dict]]:
    """Visual descriptions (with verification clouds), retrieval-only visual ones and Scan Contexts of ``n``
    simulated scans."""
    seq = SimulatedSequence("town", "os1-64", seed=0, n_scans=n, spacing=1.0)
    full = make_pipeline("orb-hbst", {})
    sc = make_pipeline("scan-context", {"verify": {"enabled": False}})
    visual, scs = [], []
    for i in range(n):
        scan, _ = preprocessed_scan(seq, i, experiment_preprocess())
        visual.append(full.describe(scan))
        scs.append(sc.describe(scan))
    slim = [{k: v for k, v in d.items() if k != "cloud"} for d in visual]
    return visual, slim, scs


def place_mask(copy: int, n_bits: int, place_bits: int) -> np.ndarray:
    """The bits flipped in every descriptor of copy ``copy`` (copy 0: none)."""
    mask = np.zeros(n_bits, np.uint8)
    if copy:
        mask[np.random.default_rng(10_000 + copy).choice(n_bits, place_bits, replace=False)] = 1
    return mask


def perturb_visual(d: dict, rng: np.random.Generator, flip: float, mask: np.ndarray | None = None) -> dict:
    n = d["descriptors"].shape[0]
    keep = np.sort(rng.choice(n, size=max(1, int(round(0.9 * n))), replace=False)) if n else np.zeros(0, int)
    desc = d["descriptors"][keep]
    bits = np.unpackbits(desc, axis=1)
    bits ^= (rng.random(bits.shape) < flip).astype(np.uint8)
    if mask is not None:
        bits ^= mask
    out = dict(d)
    out["descriptors"] = np.packbits(bits, axis=1)
    out["keypoints"] = (d["keypoints"][keep] + rng.uniform(-1, 1, (keep.size, 2))).astype(np.float32)
    out["keypoint_xyz"] = d["keypoint_xyz"][keep]
    return out


def perturb_sc(d: dict, rng: np.random.Generator, copy: int) -> dict:
    shape = d["scan_context"].shape
    place = 1.0 + np.random.default_rng(20_000 + copy).normal(0.0, 0.3, shape) if copy else 1.0
    sc = np.maximum(d["scan_context"] * place * (1.0 + rng.normal(0.0, 0.05, shape)), 0.0).astype(np.float32)
    return {**d, "scan_context": np.roll(sc, int(rng.integers(sc.shape[1])), axis=1).astype(np.float32)}


def bench_database(
    name: str, size: int, base: list[dict], n_queries: int, flip: float, place_bits: int, seed: int
) -> dict:
    pipeline, params = PIPELINES[name]
    rng = np.random.default_rng(seed)
    n_bits = 8 * base[0]["descriptors"].shape[1] if "descriptors" in base[0] else 0

    def copy_of(i: int) -> dict:
        d = base[i % len(base)]
        if name == "scan-context":
            return perturb_sc(d, rng, i // len(base))
        return perturb_visual(d, rng, flip, place_mask(i // len(base), n_bits, place_bits))

    rec = make_pipeline(pipeline, params)
    before = rss_anon_bytes()
    t0 = time.perf_counter()
    for i in range(size):
        rec.add_description(i, copy_of(i))
    add_s = time.perf_counter() - t0
    grown = rss_anon_bytes() - before
    times, hits = [], 0
    for q in rng.integers(0, size, n_queries):
        d = copy_of(int(q))
        t1 = time.perf_counter()
        cands = rec.query_description(d, k=5, query_id=size)
        times.append((time.perf_counter() - t1) * 1e3)
        hits += bool(cands) and cands[0].match_id == int(q)
    del rec
    gc.collect()
    return {
        "pipeline": name,
        "scans": size,
        "bytes_per_scan": grown / size,
        "ram_mb": grown / 2**20,
        "add_ms_per_scan": add_s * 1e3 / size,
        "query_ms_median": float(np.median(times)),
        "query_ms_p95": float(np.percentile(times, 95)),
        "top1_hit": hits / n_queries,
    }


def _ishot_child(path: str, store: str, queries: list, warm_scan: object) -> dict:
    """Memory of an ``ishot-prob`` pipeline loading the places file ``path`` in ``store``, then query times."""
    warm = make_pipeline("ishot-prob", {})  # imports and native pools (faiss, Open3D, small_gicp) are not the
    warm.describe(warm_scan)  # database's
    del warm
    before, before_file = rss_anon_bytes(), rss_anon_bytes("RssFile")
    rec = make_pipeline(
        "ishot-prob",
        {
            "places": {"database": path},
            "search": {"descriptor_store": store},
            "verify": {"cloud_store": _CLOUDS[store]},
        },
    )
    loaded, loaded_file = rss_anon_bytes() - before, rss_anon_bytes("RssFile") - before_file
    n = len(rec)
    total, match = [], []
    for scan in queries:
        d = rec.describe(scan)
        t0 = time.perf_counter()
        cands = rec.query_description(d, k=1)
        total.append((time.perf_counter() - t0) * 1e3)
        match.append(cands[0].extra["match_ms"] if cands else np.nan)
    return {
        "places": n,
        "ram_bytes": loaded,
        "file_ram_bytes": loaded_file,
        "descriptor_bytes": rec.entries.store.nbytes,
        "cloud_bytes": rec.clouds.nbytes,
        "ram_bytes_after_queries": rss_anon_bytes() - before,
        "query_ms_median": float(np.median(total)) if total else None,
        "match_ms_median": float(np.nanmedian(match)) if match else None,
    }


_CLOUDS = {"float32": "float32", "sq8": "int16"}


def replicate_places(db: object, copies: int) -> object:
    """``copies`` of the places of ``db`` side by side in one database (copy k's scans and ids offset by k times
    the map's scans); only its size is meant to differ."""
    from dataclasses import replace

    from placerec.retrieval.descriptor_store import DescriptorStore

    n_scans, counts = db.scan_poses.shape[0], np.diff(db.kp_offsets)
    arrays = db.descriptors.arrays()
    arrays["descriptors"] = np.tile(arrays["descriptors"], (copies, 1))
    return replace(
        db,
        ids=np.concatenate([db.ids + k * n_scans for k in range(copies)]),
        poses=np.tile(db.poses, (copies, 1, 1)),
        sources=[s + k * n_scans for k in range(copies) for s in db.sources],
        kp_offsets=np.r_[0, np.cumsum(np.tile(counts, copies))],
        keypoints=np.tile(db.keypoints, (copies, 1)),
        descriptors=DescriptorStore.from_arrays(
            arrays, db.descriptors.dtype, db.descriptors.dim, "replicated"
        ),
        scan_poses=np.tile(db.scan_poses, (copies, 1, 1)),
        clouds=None if db.clouds is None else list(db.clouds) * copies,
    )


def bench_ishot(n_queries: int, copies: int) -> list[dict]:
    """The ISHOT places database in float32 and in sq8 + int16 clouds: file bytes per place, then (each in a fresh
    process) the pipeline's memory and query times on it, and its memory on ``copies`` copies of it: the growth
    from one to ``copies`` copies per added place is the memory a place costs (module docstring)."""
    import multiprocessing

    from placerec.artifacts.places import build_places
    from placerec.sim import make_localization_split
    from placerec.three_d.places import PlacesParams

    split = make_localization_split("town", "vlp16", 0, n_queries=max(n_queries, 1))
    queries = [
        preprocessed_scan(split.queries["gator"], i, experiment_preprocess())[0] for i in range(n_queries)
    ]
    warm_scan = preprocessed_scan(split.map, 0, experiment_preprocess())[0]
    params = PlacesParams(window_m=0.0, spacing_m=2.5, descriptor_store="float32", cloud_store="float32")
    db = build_places(split.map, params)  # float32, saved in each store below
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for store in ("float32", "sq8"):
            one, many = str(Path(tmp) / f"{store}_1.npz"), str(Path(tmp) / f"{store}_{copies}.npz")
            stored = db.stored_as(store, _CLOUDS[store])
            stored.save(one)
            replicate_places(stored, copies).save(many)
            ctx = multiprocessing.get_context("spawn")
            with ctx.Pool(1) as pool:
                a = pool.apply(_ishot_child, (one, store, queries, warm_scan))
            with ctx.Pool(1) as pool:
                b = pool.apply(_ishot_child, (many, store, [], warm_scan))
            n = a["places"]
            rows.append(
                {
                    "store": store,
                    "places": n,
                    "keypoints_per_place": int(db.kp_offsets[-1]) / n,
                    "file_bytes_per_place": Path(one).stat().st_size / n,
                    "ram_bytes_per_place": (b["ram_bytes"] - a["ram_bytes"]) / (b["places"] - n),
                    "ram_bytes_per_place_at_121": a["ram_bytes"] / n,
                    "mapped_bytes_per_place": (b["file_ram_bytes"] - a["file_ram_bytes"]) / (b["places"] - n),
                    "descriptor_bytes_per_place": a["descriptor_bytes"] / n,
                    "cloud_bytes_per_place": a["cloud_bytes"] / n,
                    "ram_bytes_after_queries_per_place_at_121": a["ram_bytes_after_queries"] / n,
                    "replicated_places": b["places"],
                    "query_ms_median": a["query_ms_median"],
                    "match_ms_median": a["match_ms_median"],
                }
            )
    return rows


def _bench_in_child(args: tuple) -> dict:
    base_file, name, *rest = args
    with np.load(base_file, allow_pickle=True) as z:
        base = list(z[name if name == "scan-context" else "visual"])
    return bench_database(name, rest[0], base, *rest[1:])


def bench_database_fresh(base_file: str, name: str, size: int, *rest: object) -> dict:
    """`bench_database` in a fresh spawned process (the base descriptions are read from ``base_file``)."""
    import multiprocessing

    with multiprocessing.get_context("spawn").Pool(1) as pool:
        return pool.apply(_bench_in_child, ((base_file, name, size, *rest),))


def _build_and_save(
    base_file: str,
    path: str,
    size: int,
    flip: float,
    clouds: str,
    pipeline: str = "orb-hbst",
    save: bool = True,
) -> tuple[float, float]:
    """(bytes per scan while built, file MiB) of ``pipeline`` with verification clouds, saved to ``path`` (not
    saved, file 0, with ``save=False``)."""
    with np.load(base_file, allow_pickle=True) as z:
        full = list(z["full"])
    rng = np.random.default_rng(1)
    rec = make_pipeline(pipeline, {"verify": {"cloud_store": clouds}})
    before = rss_anon_bytes()
    for i in range(size):
        d = perturb_visual(full[i % len(full)], rng, flip)
        cloud = full[i % len(full)]["cloud"]  # every copy its own cloud, as every scan has
        d["cloud"] = (cloud + rng.normal(0.0, 0.01, cloud.shape)).astype(np.float32)
        rec.add_description(i, d)
    built = (rss_anon_bytes() - before) / size
    if not save:
        return built, 0.0
    rec.save(path)
    return built, Path(path).stat().st_size / 2**20


def _load_saved(path: str, clouds: str, pipeline: str = "orb-hbst") -> float:
    """Anonymous memory growth (bytes) of loading ``path`` (memory-mapped) into a ``pipeline`` pipeline."""
    rec = make_pipeline(pipeline, {"verify": {"cloud_store": clouds}})
    before = rss_anon_bytes()
    rec.load(path)
    return rss_anon_bytes() - before


def bench_saved(
    base_file: str,
    size: int,
    flip: float,
    clouds: str = "float32",
    pipeline: str = "orb-hbst",
    save: bool = True,
) -> dict:
    """``pipeline`` (orb-hbst or orb-dbow) with verification clouds: RAM while built, file size, RAM after a
    memory-mapped load (each in a fresh process)."""
    import multiprocessing

    ctx = multiprocessing.get_context("spawn")
    with tempfile.TemporaryDirectory() as tmp:
        path = str(Path(tmp) / f"{pipeline}.npz")
        with ctx.Pool(1) as pool:
            built, file_mb = pool.apply(
                _build_and_save, (base_file, path, size, flip, clouds, pipeline, save)
            )
        loaded = None
        if save:
            with ctx.Pool(1) as pool:
                loaded = pool.apply(_load_saved, (path, clouds, pipeline))
    return {
        "pipeline": pipeline,
        "scans": size,
        "built_bytes_per_scan": built,
        "file_mb": file_mb,
        "loaded_mmap_bytes_per_scan": None if loaded is None else loaded / size,
    }


def bench_dask(n_scans: int) -> dict:
    """Wall time of describing ``n_scans`` scans with 1 and 2 Dask workers (a LocalCluster each), after a warm-up
    task per worker (start-up, imports, opening the dataset are not timed). The scans are simulated once and
    written as a KITTI-style folder first: workers read them from files, as they would a user's dataset (the
    simulator's renderer shades on two threads, so workers rendering their own scans would share the cores
    before any description runs)."""
    from placerec.experiment.parallel import _dask_pool, describe_chunk
    from placerec.sim.export import write_kitti_sequence

    folder = tempfile.mkdtemp(prefix="bench_scale_scans_")
    write_kitti_sequence(SimulatedSequence("town", "os1-64", n_scans=n_scans, seed=0), folder, progress=False)
    cfg = load_config(
        None,
        [
            "dataset.source=path",
            f"dataset.path={folder}",
            "pipelines=[{name: orb-hbst}, {name: scan-context}]",
        ],
    )
    cfg_json, ds_json = cfg.model_dump(mode="json"), cfg.dataset.model_dump(mode="json")
    out = {}
    for workers in (1, 2):
        with tempfile.TemporaryDirectory() as tmp, _dask_pool(workers, None) as submit:
            warm = [(cfg_json, ds_json, tmp, "warm", [w]) for w in range(workers)]
            submit(describe_chunk, warm, lambda r: None)
            chunks = [(cfg_json, ds_json, tmp, "bench", [i, i + 1]) for i in range(0, n_scans, 2)]
            t0 = time.perf_counter()
            submit(describe_chunk, chunks, lambda r: None)
            out[workers] = time.perf_counter() - t0
    shutil.rmtree(folder, ignore_errors=True)
    return {
        "scans": n_scans,
        "seconds_1_worker": out[1],
        "seconds_2_workers": out[2],
        "speedup": out[1] / out[2],
        "load_average": os.getloadavg()[0],
        "cpus": os.cpu_count(),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="*", default=[1000, 10000, 100000], help="none: skip")
    ap.add_argument("--base", type=int, default=60, help="simulated scans replicated into the databases")
    ap.add_argument("--queries", type=int, default=100)
    ap.add_argument("--flip", type=float, default=0.03, help="probability of flipping a descriptor bit")
    ap.add_argument(
        "--place-bits", type=int, default=40, help="bits flipped to make each copy a distinct place"
    )
    ap.add_argument("--pipelines", nargs="+", default=list(PIPELINES), choices=list(PIPELINES))
    ap.add_argument("--saved-scans", type=int, default=1000, help="ORB-HBST with clouds saved; 0 = skip")
    ap.add_argument(
        "--cloud-store",
        default="int16-zlib",
        choices=["float32", "int16", "int16-zlib"],
        help="verify.cloud_store of those pipelines",
    )
    ap.add_argument(
        "--saved-pipelines",
        nargs="+",
        default=["orb-hbst"],
        choices=["orb-hbst", "orb-dbow"],
        help="pipelines measured with verification at --saved-scans",
    )
    ap.add_argument(
        "--build-only",
        action="store_true",
        help="measure those pipelines built in RAM, without saving and loading them (a saved 100k database "
        "needs a float32 copy of its clouds while saving: ~16 GB)",
    )
    ap.add_argument("--dask-scans", type=int, default=120, help="0 = skip the Dask measurement")
    ap.add_argument(
        "--ishot-queries", type=int, default=30, help="ISHOT store queries; 0 = skip the ISHOT store"
    )
    ap.add_argument(
        "--ishot-copies", type=int, default=8, help="copies of the ISHOT places for the memory slope"
    )
    args = ap.parse_args()
    print(f"load average {os.getloadavg()}; describing {args.base} simulated scans ...", flush=True)
    full, slim, scs = base_descriptions(args.base)
    tmp = tempfile.TemporaryDirectory()
    base_file = str(Path(tmp.name) / "base.npz")
    np.savez(
        base_file,
        full=np.array(full, dtype=object),
        visual=np.array(slim, dtype=object),
        **{"scan-context": np.array(scs, dtype=object)},
    )
    rows = []
    for size in args.sizes:
        for name in args.pipelines:
            row = bench_database_fresh(base_file, name, size, args.queries, args.flip, args.place_bits, size)
            rows.append(row)
            print(
                f"{name:>13} {size:>7} scans: {row['bytes_per_scan'] / 1024:8.1f} KiB/scan "
                f"({row['ram_mb']:8.1f} MiB), add {row['add_ms_per_scan']:6.2f} ms/scan, query median "
                f"{row['query_ms_median']:7.2f} ms, p95 {row['query_ms_p95']:7.2f} ms, top-1 hit {row['top1_hit']:.2f}  "
                f"(load {os.getloadavg()[0]:.1f})",
                flush=True,
            )
    saves = [
        bench_saved(base_file, args.saved_scans, args.flip, args.cloud_store, p, not args.build_only)
        for p in (args.saved_pipelines if args.saved_scans else [])
    ]
    for saved in saves:
        mapped = saved["loaded_mmap_bytes_per_scan"]
        print(
            f"{saved['pipeline']} with verification clouds ({args.cloud_store}), {saved['scans']} scans: "
            f"{saved['built_bytes_per_scan'] / 1024:.1f} KiB/scan built ("
            f"{saved['built_bytes_per_scan'] * saved['scans'] / 1e9:.2f} GB)"
            + (
                f", file {saved['file_mb']:.0f} MiB, {mapped / 1024:.1f} KiB/scan after a memory-mapped load"
                if mapped is not None
                else ", not saved"
            ),
            flush=True,
        )
    ishot = bench_ishot(args.ishot_queries, args.ishot_copies) if args.ishot_queries else []
    for r in ishot:
        print(
            f"ishot-prob, {r['store']:>7} store, {r['places']} places ({r['keypoints_per_place']:.0f} keypoints each): "
            f"file {r['file_bytes_per_place'] / 1e3:.1f} kB/place; RAM {r['ram_bytes_per_place'] / 1e3:.1f} kB per "
            f"added place ({r['places']} -> {r['replicated_places']} places; descriptors "
            f"{r['descriptor_bytes_per_place'] / 1e3:.1f} kB, ICP clouds {r['cloud_bytes_per_place'] / 1e3:.1f} kB), "
            f"{r['ram_bytes_per_place_at_121'] / 1e3:.1f} kB/place at {r['places']} places; resident pages of the "
            f"memory-mapped file {r['mapped_bytes_per_place'] / 1e3:.1f} kB per added place; "
            f"{r['ram_bytes_after_queries_per_place_at_121'] / 1e3:.1f} kB/place after the queries (prepared ICP "
            f"targets); query median {r['query_ms_median']:.0f} ms (matching {r['match_ms_median']:.1f} ms)  "
            f"(load {os.getloadavg()[0]:.1f})",
            flush=True,
        )
    dask = bench_dask(args.dask_scans) if args.dask_scans else None
    if dask:
        print(
            f"Dask description of {dask['scans']} scans: 1 worker {dask['seconds_1_worker']:.1f} s, 2 workers "
            f"{dask['seconds_2_workers']:.1f} s: speed-up {dask['speedup']:.2f}x (load average "
            f"{dask['load_average']:.1f} on {dask['cpus']} CPUs)",
            flush=True,
        )
    largest = {r["pipeline"]: r for r in rows if r["scans"] == max(args.sizes, default=0)}
    print(
        json.dumps(
            {
                "sizes": args.sizes,
                "largest": max(args.sizes, default=None),
                **{
                    f"{n}_{k}": round(largest[n][k], 3)
                    for n in largest
                    for k in ("ram_mb", "bytes_per_scan", "query_ms_median", "top1_hit")
                },
                **{
                    f"{s['pipeline'].replace('-', '_')}_verified_kib_per_scan_{k}": round(s[f] / 1024, 1)
                    if s[f] is not None
                    else None
                    for s in saves
                    for k, f in (
                        ("built", "built_bytes_per_scan"),
                        ("mmap_loaded", "loaded_mmap_bytes_per_scan"),
                    )
                },
                **{
                    f"ishot_{r['store']}_{k}": round(r[k], 1)
                    for r in ishot
                    for k in (
                        "file_bytes_per_place",
                        "ram_bytes_per_place",
                        "ram_bytes_per_place_at_121",
                        "mapped_bytes_per_place",
                        "query_ms_median",
                        "match_ms_median",
                    )
                },
                "dask_speedup_2_workers": None if dask is None else round(dask["speedup"], 3),
                "dask_load_average": None if dask is None else round(dask["load_average"], 2),
            }
        )
    )


if __name__ == "__main__":
    main()
