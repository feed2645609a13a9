"""Benchmark placerec's HBST against pyhbst (srrg_hbst's C++ code) on one ORB descriptor stream.

For every image of the stream both trees run match-and-add (match against all previous images, then insert);
the script times each call, and on a sample of query images measures the recall of the true best match: the
fraction of query descriptors whose true nearest descriptor over all previous images (brute force, distance
< threshold) is among the HBST matches (a match at the true best distance counts: ties are equivalent).

pyhbst 0.2.0 is srrg_hbst compiled with N_max (leaf size) 100, delta_max 0.1 and max depth 256; these cannot be
changed from Python. The script therefore runs ours twice: with placerec's defaults (the paper's N_max 50,
max depth 75) and with pyhbst's compiled parameters (then both trees are identical and so are the matches).

Sources of descriptors (ORB, FAST threshold 40, nfeatures 300, scaleFactor 1.2, nlevels 8, edgeThreshold 15,
on 8-bit intensity images clipped at the 99th percentile):

* ``sim`` (default): scans of `placerec.sim.SimulatedSequence` (organised Ouster scans: the intensity image is
  the scan's (rows, cols) grid);
* ``kitti-real``: the real KITTI frames in ``../shared/data/real`` projected per elevation into 64 x 1024 images,
  revisited again and again with small azimuth shifts and intensity noise (a development fallback);
* ``random``: synthetic descriptors drawn from a pool of 'places' with a few flipped bits (no OpenCV needed).

Descriptor streams are cached under ``--cache-dir`` (an atomic ``.npz``), so reruns skip feature extraction.
The last line printed is one JSON object with the headline figures.

Example::

    python tools/bench_hbst.py --source sim --n-images 2000
    python tools/bench_hbst.py --source kitti-real --n-images 2000 --recall-every 20
"""

from __future__ import annotations

import argparse
import gc
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from placerec.retrieval.hbst import HBST

REPO = Path(__file__).resolve().parents[1]
REAL_DATA = REPO.parent / "shared" / "data" / "real"
STREAM_VERSION = 1
PYHBST_PARAMS = {"leaf_size": 100, "delta_max": 0.1, "max_depth": 256}


# ----------------------------------------------------------------------------------------------- descriptors
def to_uint8_image(intensity: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Intensity grid -> uint8 image, clipped at the 99th percentile of the valid pixels (invalid -> 0)."""
    img = np.zeros(intensity.shape, dtype=np.uint8)
    if valid.any():
        top = float(np.percentile(intensity[valid], 99.0)) or 1.0
        img[valid] = np.clip(intensity[valid] / top * 255.0, 0, 255).astype(np.uint8)
    return img


def orb_descriptors(img: np.ndarray, n_features: int) -> np.ndarray:
    import cv2

    orb = cv2.ORB_create(nfeatures=n_features, scaleFactor=1.2, nlevels=8, edgeThreshold=15, fastThreshold=40)
    _, desc = orb.detectAndCompute(img, None)
    return np.zeros((0, 32), dtype=np.uint8) if desc is None else desc


def project(xyz: np.ndarray, intensity: np.ndarray, rows: int = 64, cols: int = 1024) -> np.ndarray:
    """Per-elevation cylindrical projection of an unorganised HDL-64 scan (nearest return per pixel)."""
    r = np.linalg.norm(xyz, axis=1)
    ok = r > 1.0
    xyz, intensity, r = xyz[ok], intensity[ok], r[ok]
    phi = np.degrees(np.arcsin(xyz[:, 2] / r))
    up, down = 2.0, -24.9
    v = np.clip(((up - phi) / (up - down) * rows).astype(int), 0, rows - 1)
    u = np.clip((0.5 * (1.0 - np.arctan2(xyz[:, 1], xyz[:, 0]) / np.pi) * cols).astype(int), 0, cols - 1)
    grid = np.zeros((rows, cols), dtype=np.float32)
    valid = np.zeros((rows, cols), dtype=bool)
    order = np.argsort(-r)  # far first, so the nearest return is written last
    grid[v[order], u[order]] = intensity[order]
    valid[v, u] = True
    return to_uint8_image(grid, valid)


def stream_sim(n_images: int, n_features: int, seed: int) -> list[np.ndarray]:
    try:
        from placerec.sim import SimulatedSequence
    except ImportError as exc:
        sys.exit(f"--source sim needs placerec.sim ({exc}); try --source kitti-real")
    seq = SimulatedSequence(world="town", sensor="os1-64", n_scans=n_images, seed=seed)
    out = []
    for i in range(len(seq)):
        scan = seq[i]
        if scan.shape is not None:
            grid = scan.intensity.reshape(scan.shape)
            valid = np.linalg.norm(scan.xyz, axis=1).reshape(scan.shape) > 0
            img = to_uint8_image(grid, valid)
        else:
            img = project(scan.xyz, scan.intensity)
        out.append(orb_descriptors(img, n_features))
        _progress("sim features", i + 1, len(seq))
    return out


def stream_kitti_real(n_images: int, n_features: int, seed: int) -> list[np.ndarray]:
    frames = []
    for path in sorted((REAL_DATA / "kitti00_frames").glob("*.bin")):
        pts = np.fromfile(path, dtype=np.float32).reshape(-1, 4)
        frames.append(project(pts[:, :3], pts[:, 3]))
    try:
        from placerec.io.pcd import read_pcd

        for path in sorted((REAL_DATA / "kitti_raw_hdl64_sequence").glob("*.pcd")):
            scan = read_pcd(path)
            frames.append(project(scan.xyz, scan.intensity))
    except ImportError:
        pass
    if not frames:
        sys.exit(f"no KITTI frames under {REAL_DATA}")
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n_images):
        img = np.roll(frames[i % len(frames)], int(rng.integers(-24, 25)), axis=1).astype(np.int16)
        img += rng.integers(-6, 7, img.shape, dtype=np.int16) * (img > 0)
        out.append(orb_descriptors(np.clip(img, 0, 255).astype(np.uint8), n_features))
        _progress("kitti-real features", i + 1, n_images)
    return out


def stream_random(n_images: int, n_features: int, seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    places = rng.integers(0, 256, (20 * n_features, 32), dtype=np.uint8)
    out = []
    for i in range(n_images):
        centre = (i * n_features // 4) % places.shape[0]  # a slowly moving window of places: revisits
        idx = (centre + rng.choice(4 * n_features, n_features, replace=False)) % places.shape[0]
        flips = np.where(rng.random((n_features, 32)) < 0.03, rng.integers(1, 256, (n_features, 32)), 0)
        out.append(places[idx] ^ flips.astype(np.uint8))
    return out


SOURCES: dict[str, Callable[[int, int, int], list[np.ndarray]]] = {
    "sim": stream_sim,
    "kitti-real": stream_kitti_real,
    "random": stream_random,
}


def load_stream(source: str, n_images: int, n_features: int, seed: int, cache_dir: Path) -> list[np.ndarray]:
    from placerec.errors import ArtifactError
    from placerec.io.atomic import load_artifact, save_artifact

    path = cache_dir / f"hbst_stream_{source}_{n_images}x{n_features}_seed{seed}.npz"
    try:
        arrays, _ = load_artifact(path, "descriptor-stream", (STREAM_VERSION,))
        return np.split(arrays["descriptors"], arrays["offsets"][1:-1])
    except ArtifactError:
        pass
    stream = SOURCES[source](n_images, n_features, seed)
    offsets = np.concatenate([[0], np.cumsum([d.shape[0] for d in stream])])
    meta = {"source": source, "n_images": n_images, "n_features": n_features, "seed": seed}
    save_artifact(
        path,
        "descriptor-stream",
        STREAM_VERSION,
        {"descriptors": np.concatenate(stream), "offsets": offsets},
        meta,
    )
    return stream


# ---------------------------------------------------------------------------------------------------- peers
class Ours:
    def __init__(self, name: str, threshold: int, **params) -> None:
        self.name = name
        self.tree = HBST(threshold=threshold, **params)

    def prepare(self, desc: np.ndarray) -> np.ndarray:
        return desc

    def match_and_add(self, image_id: int, desc: np.ndarray) -> None:
        self.last = self.tree.match_and_add(image_id, desc)

    def best_distance(self, n: int) -> np.ndarray:
        best = np.full(n, np.iinfo(np.int32).max, dtype=np.int64)
        np.minimum.at(best, self.last.query_idx, self.last.distance)
        return best


class PyHBST:
    def __init__(self, threshold: int) -> None:
        import pyhbst

        self.name = "pyhbst"
        self.pyhbst = pyhbst
        self.tree = pyhbst.BinarySearchTree256()
        self.threshold = threshold

    def prepare(self, desc: np.ndarray) -> tuple[list, list]:
        # pyhbst takes one [x, y] 'keypoint' and 256 bools per descriptor (srrg's LSB-first bit order); the
        # keypoint x carries the descriptor's row so that matches can be traced back
        kp = np.column_stack([np.arange(desc.shape[0]), np.zeros(desc.shape[0])]).tolist()
        return kp, np.unpackbits(desc, axis=1, bitorder="little").astype(bool).tolist()

    def match_and_add(self, image_id: int, prepared: tuple[list, list]) -> None:
        kp, bits = prepared
        self.last = self.tree.matchAndAdd(kp, bits, image_id, self.threshold, self.pyhbst.SplitEven)

    def best_distance(self, n: int) -> np.ndarray:
        best = np.full(n, np.iinfo(np.int32).max, dtype=np.int64)
        for matches in self.last.values():
            for m in matches:
                q = int(m.object_query[0])
                best[q] = min(best[q], int(m.distance))
        return best


# -------------------------------------------------------------------------------------------------- helpers
def true_best_distance(query: np.ndarray, database: list[np.ndarray]) -> np.ndarray:
    """Brute-force nearest Hamming distance of every query row over all database rows (OpenCV BFMatcher)."""
    import cv2

    best = np.full(query.shape[0], np.iinfo(np.int32).max, dtype=np.int64)
    if query.shape[0] == 0:
        return best
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    chunk: list[np.ndarray] = []
    rows = 0
    for i, d in enumerate(database):
        if d.shape[0]:
            chunk.append(d)
            rows += d.shape[0]
        if chunk and (rows > 150_000 or i == len(database) - 1):
            for m in matcher.match(query, np.concatenate(chunk)):
                best[m.queryIdx] = min(best[m.queryIdx], int(m.distance))
            chunk, rows = [], 0
    return best


def _progress(what: str, done: int, total: int) -> None:
    if done % 200 == 0 or done == total:
        print(f"  {what}: {done}/{total}", file=sys.stderr, flush=True)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--source", choices=sorted(SOURCES), default="sim")
    ap.add_argument("--n-images", type=int, default=2000)
    ap.add_argument("--features", type=int, default=300)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threshold", type=int, default=25)
    ap.add_argument("--recall-start", type=int, default=200, help="first query image of the recall sample")
    ap.add_argument("--recall-every", type=int, default=10, help="sample every k-th image for recall")
    ap.add_argument("--cache-dir", type=Path, default=REPO / ".cache")
    ap.add_argument("--no-pyhbst", action="store_true", help="time ours only")
    args = ap.parse_args(argv)

    t0 = time.perf_counter()
    stream = load_stream(args.source, args.n_images, args.features, args.seed, args.cache_dir)
    n_desc = np.array([d.shape[0] for d in stream])
    print(
        f"stream: {args.source}, {len(stream)} images, {n_desc.sum()} ORB descriptors "
        f"({n_desc.mean():.0f} per image), ready in {time.perf_counter() - t0:.1f} s",
        file=sys.stderr,
    )

    peers: list = [
        Ours("ours", args.threshold),
        Ours("ours@pyhbst-params", args.threshold, **PYHBST_PARAMS),
    ]
    if not args.no_pyhbst:
        peers.append(PyHBST(args.threshold))
    times = {p.name: [] for p in peers}
    hits = {p.name: 0 for p in peers}
    n_recall = 0
    sample = set(range(args.recall_start, len(stream), args.recall_every))
    gc.disable()  # collect between images, never inside a timed call
    for i, desc in enumerate(stream):
        if i % 50 == 0:
            gc.collect()
        truth = None
        if i in sample:
            truth = true_best_distance(desc, stream[:i])
            n_recall += int((truth < args.threshold).sum())
        # interleaved, so that load changes on the machine hit every peer alike; the order rotates because the
        # call right after pyhbst's pays for its memory churn (cold caches, pages handed back to the OS)
        for peer in peers[i % len(peers) :] + peers[: i % len(peers)]:
            prepared = peer.prepare(desc)
            start = time.perf_counter()
            peer.match_and_add(i, prepared)
            times[peer.name].append(time.perf_counter() - start)
            if truth is not None:
                found = peer.best_distance(desc.shape[0])
                hits[peer.name] += int(((truth < args.threshold) & (found == truth)).sum())
            peer.last = None  # free the result here, outside the timed calls (pyhbst's takes milliseconds)
        _progress("match-and-add", i + 1, len(stream))
    gc.enable()

    rows = {}
    for peer in peers:
        t = np.array(times[peer.name]) * 1e3
        rows[peer.name] = {
            "median_ms": float(np.median(t)),
            "p95_ms": float(np.percentile(t, 95)),
            "last100_median_ms": float(np.median(t[-100:])),
            "total_s": float(t.sum() / 1e3),
            "recall": hits[peer.name] / n_recall if n_recall else float("nan"),
        }
    ours = peers[0].tree
    print(
        f"\nHBST match-and-add over {len(stream)} images ({args.source}); recall on {n_recall} query descriptors "
        f"with a true match (< {args.threshold}) in {len(sample)} sampled images"
    )
    print(f"ours tree: {ours!r}")
    print(f"{'':22s} {'median ms':>10s} {'p95 ms':>10s} {'last-100 ms':>12s} {'total s':>9s} {'recall':>8s}")
    for name, r in rows.items():
        print(
            f"{name:22s} {r['median_ms']:10.3f} {r['p95_ms']:10.3f} {r['last100_median_ms']:12.3f} "
            f"{r['total_s']:9.2f} {r['recall']:8.4f}"
        )
    same = rows["ours@pyhbst-params"]
    headline = {
        "source": args.source,
        "n_images": len(stream),
        "n_descriptors": int(n_desc.sum()),
        "ours_median_ms": round(rows["ours"]["median_ms"], 3),
        "ours_p95_ms": round(rows["ours"]["p95_ms"], 3),
        "ours_recall": round(rows["ours"]["recall"], 4),
        "ours_pyhbst_params_median_ms": round(same["median_ms"], 3),
        "ours_pyhbst_params_p95_ms": round(same["p95_ms"], 3),
        "ours_pyhbst_params_recall": round(same["recall"], 4),
    }
    if "pyhbst" in rows:
        ref = rows["pyhbst"]
        headline.update(
            {
                "pyhbst_median_ms": round(ref["median_ms"], 3),
                "pyhbst_p95_ms": round(ref["p95_ms"], 3),
                "pyhbst_recall": round(ref["recall"], 4),
                "ratio": round(rows["ours"]["median_ms"] / ref["median_ms"], 4),
                "ratio_pyhbst_params": round(same["median_ms"] / ref["median_ms"], 4),
            }
        )
    print(json.dumps(headline))
    return headline


if __name__ == "__main__":
    main()
