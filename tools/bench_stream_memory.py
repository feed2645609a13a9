"""Resident memory of a long loop-closure stream with verification on: a one-hour drive at 10 Hz (36k scans).

Each run feeds ``--scans`` descriptions through `placerec.loop_closure.LoopClosureDetector` (the online module: query
the older scans, then add) with the pipeline's operating threshold and its verification, in a fresh process, and
records the peak resident memory (``VmHWM``: everything resident, libraries included) and the accepted closures.
Each pipeline runs twice: with the default ``verify.cloud_budget_mb`` (clouds beyond it in the spill file) and with
``cloud_budget_mb: null`` (everything in RAM); the accepted closures (query, match, score, pose) of the two runs
must be identical.

The stream (simulating 36k scans would take hours): ``--base`` simulated OS1-64 town scans, 1 m apart, described
once; scan ``i`` of the stream is copy ``i // base`` of base scan ``i % base``, a distinct place: its ICP cloud and
keypoints' 3D points are the base scan's with its twelve 30-degree azimuth segments permuted (a permutation per
copy, so copies differ in geometry), its ORB descriptors have the same 40 of 256 bits flipped (per copy, as in
`tools/bench_scale.py`), its Scan Context is scaled cell by cell by a pattern of its own; every scan then gets fresh
noise (1 cm on the cloud, 3 % of descriptor bits, 10 % of features dropped, 5 % on Scan Context cells). Every
``--revisit-every``-th scan is instead a revisit of a random earlier scan (its copy and base scan, fresh noise):
the closures to find. Scan Context verifies its three best candidates on every query it makes (~0.1-0.3 s here),
so it queries every ``--sc-query-every``-th scan (a keyframe; every scan is added) to keep the run under an hour.

The last line printed is one JSON object. Example (~25 min on 2 cores)::

    python tools/bench_stream_memory.py --scans 36000
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import pickle
import tempfile
import time
from pathlib import Path

import numpy as np

from placerec.config import experiment_preprocess
from placerec.experiment.preprocessing import preprocessed_scan
from placerec.loop_closure import LoopClosureDetector
from placerec.recognizer import make_pipeline
from placerec.sim import SimulatedSequence

SEGMENTS = 12


def status_kb(field: str) -> int:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(f"{field}:"):
                return int(line.split()[1])
    raise SystemExit(f"bench_stream_memory needs Linux /proc/self/status ({field})")


def base_descriptions(n: int) -> dict[str, list[dict]]:
    seq = SimulatedSequence("town", "os1-64", seed=0, n_scans=n, spacing=1.0)
    recs = {name: make_pipeline(name) for name in ("orb-hbst", "scan-context")}
    out: dict[str, list[dict]] = {name: [] for name in recs}
    for i in range(n):
        scan, _ = preprocessed_scan(seq, i, experiment_preprocess())
        for name, rec in recs.items():
            out[name].append(rec.describe(scan))
    return out


def segment_turn(points: np.ndarray, copy: int) -> np.ndarray:
    """``points`` with their azimuth segments moved by copy ``copy``'s permutation (copy 0: unchanged)."""
    if copy == 0:
        return points
    perm = np.random.default_rng(30_000 + copy).permutation(SEGMENTS)
    p = np.asarray(points, np.float64)
    azimuth = np.nan_to_num(np.arctan2(p[:, 1], p[:, 0]))  # NaN keypoint points (no scan point) stay NaN
    seg = np.floor((azimuth + np.pi) / (2 * np.pi / SEGMENTS)).astype(int) % SEGMENTS
    angle = (perm[seg] - seg) * (2 * np.pi / SEGMENTS)
    c, s = np.cos(angle), np.sin(angle)
    out = p.copy()
    out[:, 0] = c * p[:, 0] - s * p[:, 1]
    out[:, 1] = s * p[:, 0] + c * p[:, 1]
    return out.astype(np.float32)


def stream_description(name: str, base: list[dict], i: int, place: int, rng: np.random.Generator) -> dict:
    """Scan ``i`` of the stream, showing place ``place`` (``i`` itself, or the earlier scan it revisits)."""
    d = base[place % len(base)]
    copy = place // len(base)
    cloud = segment_turn(d["cloud"], copy)
    out = dict(d)
    out["cloud"] = (cloud + rng.normal(0.0, 0.01, cloud.shape)).astype(np.float32)
    if name == "scan-context":
        shape = d["scan_context"].shape
        pattern = 1.0 + np.random.default_rng(20_000 + copy).normal(0.0, 0.3, shape) if copy else 1.0
        noise = 1.0 + rng.normal(0.0, 0.05, shape)
        out["scan_context"] = np.maximum(d["scan_context"] * pattern * noise, 0.0).astype(np.float32)
        return out
    n = d["descriptors"].shape[0]
    keep = np.sort(rng.choice(n, size=max(1, int(round(0.9 * n))), replace=False))
    bits = np.unpackbits(d["descriptors"][keep], axis=1)
    bits ^= (rng.random(bits.shape) < 0.03).astype(np.uint8)
    if copy:
        mask = np.zeros(bits.shape[1], np.uint8)
        mask[np.random.default_rng(10_000 + copy).choice(bits.shape[1], 40, replace=False)] = 1
        bits ^= mask
    out["descriptors"] = np.packbits(bits, axis=1)
    out["keypoints"] = (d["keypoints"][keep] + rng.uniform(-1, 1, (keep.size, 2))).astype(np.float32)
    out["keypoint_xyz"] = segment_turn(d["keypoint_xyz"][keep], copy)
    return out


def run_stream(args: tuple) -> dict:
    base_file, name, budget, n_scans, revisit_every, query_every, seed = args
    with open(base_file, "rb") as fh:
        base = pickle.load(fh)[name]
    rng = np.random.default_rng(seed)
    places = np.random.default_rng(seed + 1)
    det = LoopClosureDetector.for_pipeline(name, {"verify": {"cloud_budget_mb": budget}})
    rec = det.recognizer
    start_kb = status_kb("VmRSS")
    t0 = time.perf_counter()
    revisits, samples = 0, []
    for i in range(n_scans):
        place = i
        if revisit_every and i >= 2 * len(base) and i % revisit_every == 0:
            place = int(places.integers(0, i - len(base)))
            revisits += 1
        d = stream_description(name, base, i, place, rng)
        if i % query_every == 0:
            det.process(None, description=d)
        else:  # a scan that is not a keyframe: added, not queried (the detector's id order is kept)
            rec.add_description(det.skip(), d)
        if (i + 1) % 2000 == 0:
            samples.append((i + 1, status_kb("VmRSS")))
    elapsed = time.perf_counter() - t0
    store = rec._clouds
    closures = [
        (c.query_id, c.match_id, round(c.score, 9), np.round(c.relative_pose, 9).tolist())
        for c in det.closures
    ]
    found = sum(1 for c in det.closures if c.query_id % revisit_every == 0) if revisit_every else 0
    return {
        "pipeline": name,
        "budget_mb": budget,
        "scans": n_scans,
        "revisits": revisits,
        "closures": closures,
        "revisits_closed": found,
        "peak_rss_mb": status_kb("VmHWM") / 1024,
        "final_rss_mb": status_kb("VmRSS") / 1024,
        "start_rss_mb": start_kb / 1024,
        "rss_samples_mb": [(n, kb / 1024) for n, kb in samples],
        "clouds_in_ram_mb": store.nbytes / 1e6,
        "clouds_spilled": store.spilled[0],
        "spill_file_mb": store.spilled[1] / 1e6,
        "prepared_mb": store.prepared_bytes / 1e6,
        "seconds": elapsed,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scans", type=int, default=36_000)
    ap.add_argument("--base", type=int, default=120)
    ap.add_argument("--revisit-every", type=int, default=50)
    ap.add_argument("--sc-query-every", type=int, default=10)
    ap.add_argument("--pipelines", nargs="+", default=["orb-hbst", "scan-context"])
    ap.add_argument(
        "--budgets", nargs="+", default=["default", "none"], help="MB, 'default' or 'none' (all RAM)"
    )
    args = ap.parse_args()
    from placerec.verify.candidates import VerifiedParams

    default_budget = VerifiedParams().cloud_budget_mb
    budgets = [default_budget if b == "default" else None if b == "none" else float(b) for b in args.budgets]
    with tempfile.TemporaryDirectory() as tmp:
        base_file = str(Path(tmp) / "base.pkl")
        t0 = time.perf_counter()
        with open(base_file, "wb") as fh:
            pickle.dump(base_descriptions(args.base), fh)
        print(f"{args.base} base scans described in {time.perf_counter() - t0:.0f} s", flush=True)
        results = []
        for name in args.pipelines:
            every = args.sc_query_every if name == "scan-context" else 1
            for budget in budgets:
                job = (base_file, name, budget, args.scans, args.revisit_every, every, 7)
                with multiprocessing.get_context("spawn").Pool(1) as pool:
                    r = pool.apply(run_stream, (job,))
                results.append(r)
                print(
                    f"{name:13s} budget {budget!s:>6} MB: peak RSS {r['peak_rss_mb']:.0f} MB (final {r['final_rss_mb']:.0f}, start "
                    f"{r['start_rss_mb']:.0f}), clouds in RAM {r['clouds_in_ram_mb']:.0f} MB, spilled "
                    f"{r['clouds_spilled']} ({r['spill_file_mb']:.0f} MB), prepared targets {r['prepared_mb']:.0f} MB, "
                    f"{len(r['closures'])} closures ({r['revisits_closed']} of {r['revisits']} revisits), "
                    f"{r['seconds']:.0f} s",
                    flush=True,
                )
                print(
                    "  resident MB after n scans:", " ".join(f"{n}:{mb:.0f}" for n, mb in r["rss_samples_mb"])
                )
    summary: dict[str, object] = {"bench": "stream_memory", "scans": args.scans}
    for name in args.pipelines:
        runs = [r for r in results if r["pipeline"] == name]
        for r in runs:
            key = f"{name.replace('-', '_')}_{'ram' if r['budget_mb'] is None else 'budget'}"
            summary[f"{key}_peak_rss_mb"] = round(r["peak_rss_mb"], 1)
            summary[f"{key}_closures"] = len(r["closures"])
        if len(runs) > 1:
            summary[f"{name.replace('-', '_')}_same_closures"] = all(
                r["closures"] == runs[0]["closures"] for r in runs
            )
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
