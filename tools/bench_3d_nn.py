"""Benchmark 2-nearest-neighbour search for 3D descriptors (ISHOT, 1344-d): faiss vs scipy's cKDTree vs NumPy.

The voting pipeline (`placerec.pipelines.keypoint_voting`) needs, for every query descriptor, its two nearest
database descriptors (the ratio tau = d1/d2). Backends timed on the same float32 data:

* ``faiss-knn``: ``faiss.knn`` brute force on a plain array (exact; what the pipeline uses: a ``max_id`` filter
  is then just a prefix slice of the database, no index to rebuild);
* ``faiss-flat``: ``IndexFlatL2`` add + search (exact; same kernel);
* ``faiss-knn-1t``: the same with one OpenMP thread (on a loaded 2-core machine OpenMP's spinning threads
  cost more than they give);
* ``faiss-hnsw`` (``--hnsw``, off by default: building it over 100k x 1344 takes minutes): ``IndexHNSWFlat``
  (M=32, efConstruction 40, efSearch 64/256; approximate, recall@1 against the exact answer reported);
* ``kdtree``: ``scipy.spatial.cKDTree`` build + ``query(k=2, workers=-1)`` (exact) on the first
  ``--kdtree-queries`` queries, scaled linearly to all queries (at 1344-d it visits nearly every leaf);
* ``numpy``: BLAS ``q @ x.T`` + ``argpartition`` (exact).

Data (``--source``):

* ``synthetic`` (default): ``--n-db`` sparse non-negative L2-normalised vectors (a SHOT-like histogram has
  most bins empty) and ``--n-queries`` queries that are noisy copies of database rows (so each has a close true
  neighbour, the case a k-d tree prunes best);
* ``sim``: real ISHOT descriptors of simulated VLP-16 scans (``--sim-scans`` map scans as the database, queries
  from a query set), a smaller database but the real distribution.

Prints one line per backend and ends with exactly one JSON line::

    python tools/bench_3d_nn.py [--n-db 100000] [--n-queries 300] [--source synthetic|sim] [--hnsw] [--no-kdtree]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import numpy as np

DIM = 1344


def synthetic(n_db: int, n_q: int, dim: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Sparse non-negative unit vectors (~15% non-zero bins) and noisy copies of random rows as queries."""
    rng = np.random.default_rng(seed)
    db = np.empty((n_db, dim), np.float32)
    for a in range(0, n_db, 10000):
        b = min(n_db, a + 10000)
        block = rng.exponential(1.0, (b - a, dim)).astype(np.float32)
        block *= rng.random((b - a, dim), dtype=np.float32) < 0.15
        db[a:b] = block
    db /= np.maximum(np.linalg.norm(db, axis=1, keepdims=True), 1e-12)
    q = db[rng.choice(n_db, n_q, replace=False)] + rng.normal(0, 0.01, (n_q, dim)).astype(np.float32)
    q = np.maximum(q, 0)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return db, np.ascontiguousarray(q, np.float32)


def from_sim(n_scans: int, n_q: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Real ISHOT descriptors: map scans of a simulated VLP-16 town sequence, queries from its gator set."""
    from placerec.intensity import normalize_intensity
    from placerec.sim import make_localization_split
    from placerec.three_d import extract_features

    split = make_localization_split(
        "town", "vlp16", seed=seed, n_queries=max(3, n_q // 100 + 1), conditions=("gator",)
    )
    step = max(1, len(split.map) // n_scans)
    db = [
        extract_features(normalize_intensity(split.map[i])).descriptors
        for i in range(0, len(split.map), step)
    ]
    qs = [extract_features(normalize_intensity(s)).descriptors for s in split.queries["gator"]]
    q = np.concatenate(qs)[:n_q]
    return np.ascontiguousarray(np.concatenate(db[:n_scans])), np.ascontiguousarray(q)


def timed(fn, repeats: int = 3) -> tuple[float, object]:
    best, out = np.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def numpy_knn2(db: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    xx = np.einsum("ij,ij->i", db, db)
    d2 = xx[None, :] - 2.0 * (q @ db.T)
    idx = np.argpartition(d2, 1, axis=1)[:, :2]
    dd = np.take_along_axis(d2, idx, axis=1)
    o = np.argsort(dd, axis=1)
    qq = np.einsum("ij,ij->i", q, q)[:, None]
    return np.maximum(np.take_along_axis(dd, o, 1) + qq, 0), np.take_along_axis(idx, o, 1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n-db", type=int, default=100_000)
    ap.add_argument("--n-queries", type=int, default=300)
    ap.add_argument("--source", choices=("synthetic", "sim"), default="synthetic")
    ap.add_argument("--sim-scans", type=int, default=60)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-kdtree", action="store_true", help="skip cKDTree (slow at 1344-d)")
    ap.add_argument("--hnsw", action="store_true", help="also build and time HNSW (minutes at 100k)")
    ap.add_argument("--kdtree-queries", type=int, default=30)
    args = ap.parse_args()

    import faiss
    from scipy.spatial import cKDTree

    t0 = time.perf_counter()
    if args.source == "synthetic":
        db, q = synthetic(args.n_db, args.n_queries, DIM, args.seed)
    else:
        db, q = from_sim(args.sim_scans, args.n_queries, args.seed)
    print(
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, faiss {faiss.__version__} "
        f"({faiss.omp_get_max_threads()} threads), load {os.getloadavg()[0]:.2f}; data {args.source}: "
        f"db {db.shape}, queries {q.shape} ({time.perf_counter() - t0:.1f} s to make)"
    )
    res: dict[str, object] = {
        "bench": "3d_nn",
        "source": args.source,
        "n_db": int(db.shape[0]),
        "n_queries": int(q.shape[0]),
        "dim": int(db.shape[1]),
        "cores": os.cpu_count(),
    }

    t, (d_ref, i_ref) = timed(lambda: faiss.knn(q, db, 2))
    res["faiss_knn_s"] = round(t, 4)
    print(f"faiss.knn (exact)        : query {t * 1e3:9.1f} ms ({faiss.omp_get_max_threads()} threads)")
    threads = faiss.omp_get_max_threads()
    faiss.omp_set_num_threads(1)
    t, _ = timed(lambda: faiss.knn(q, db, 2))
    faiss.omp_set_num_threads(threads)
    res["faiss_knn_1t_s"] = round(t, 4)
    print(f"faiss.knn (exact)        : query {t * 1e3:9.1f} ms (1 thread)")
    tn, (d_np, i_np) = timed(lambda: numpy_knn2(db, q))
    res["numpy_s"] = round(tn, 4)
    res["numpy_agree"] = float(np.mean(i_np[:, 0] == i_ref[:, 0]))
    print(
        f"numpy BLAS (exact)       : query {tn * 1e3:9.1f} ms  (1st NN agrees with faiss {res['numpy_agree']:.3f})"
    )

    def flat():
        index = faiss.IndexFlatL2(db.shape[1])
        index.add(db)
        return index.search(q, 2)

    t, _ = timed(flat)
    res["faiss_flat_s"] = round(t, 4)
    print(f"faiss IndexFlatL2        : add+query {t * 1e3:9.1f} ms")

    if args.hnsw:
        index = faiss.IndexHNSWFlat(db.shape[1], 32)
        index.hnsw.efConstruction = 40
        tb, _ = timed(lambda: index.add(db), repeats=1)
        res["faiss_hnsw_build_s"] = round(tb, 3)
        for ef in (64, 256):
            index.hnsw.efSearch = ef
            t, (_, i_h) = timed(lambda: index.search(q, 2))
            rec = float(np.mean(i_h[:, 0] == i_ref[:, 0]))
            res[f"faiss_hnsw_ef{ef}_s"] = round(t, 4)
            res[f"faiss_hnsw_ef{ef}_recall1"] = round(rec, 4)
            print(
                f"faiss HNSW M32 ef{ef:<4d}     : build {tb:7.2f} s, query {t * 1e3:9.1f} ms, recall@1 {rec:.3f}"
            )

    if not args.no_kdtree:
        tb, tree = timed(lambda: cKDTree(db), repeats=1)
        nk = min(args.kdtree_queries, q.shape[0])
        t, (d_kd, i_kd) = timed(lambda: tree.query(q[:nk], k=2, workers=-1), repeats=1)
        t *= q.shape[0] / nk
        res["kdtree_build_s"] = round(tb, 3)
        res["kdtree_query_s"] = round(t, 4)
        res["kdtree_timed_queries"] = nk
        res["kdtree_agree"] = float(np.mean(i_kd[:, 0] == i_ref[:nk, 0]))
        print(
            f"scipy cKDTree (exact)    : build {tb:7.2f} s, query {t * 1e3:9.1f} ms (timed on {nk}, scaled)"
        )
        best_faiss = min(res["faiss_knn_s"], res["faiss_knn_1t_s"])
        res["kdtree_vs_faiss_query_x"] = round(t / max(best_faiss, 1e-9), 1)

    exact = {"faiss-knn": res["faiss_knn_s"], "faiss-knn-1t": res["faiss_knn_1t_s"], "numpy": res["numpy_s"]}
    if "kdtree_query_s" in res:
        exact["kdtree"] = res["kdtree_query_s"]
    res["load_avg"] = round(os.getloadavg()[0], 2)
    res["fastest_exact"] = min(exact, key=exact.get)
    print(f"fastest exact 2-NN: {res['fastest_exact']}")
    print(json.dumps(res))


if __name__ == "__main__":
    main()
