"""Benchmark the odometry gate's chain through accepted closures (`placerec.odometry_gate.LoopChain`): the time to
add a closure and to predict a candidate's motion through them, as the chain grows.

A straight route of ``--places`` places a metre apart; ``--closures`` closures (each size in turn) join random pairs
of places at least 500 m of path apart, so every place lies within reach of the search (the worst case: a real
route's closures join places on the same streets). Each prediction is a candidate 100-400 m of path back from a
random query; the first prediction after the closures were added builds the graph and is reported apart. One core.
Prints readable lines, then exactly one JSON line.

    python tools/bench_loop_chain.py [--places 100000] [--closures 100 1000 10000] [--predictions 200]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from placerec.odometry_gate import LoopChain


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--places", type=int, default=100_000)
    ap.add_argument("--closures", type=int, nargs="+", default=[100, 1000, 10_000])
    ap.add_argument("--predictions", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    n = args.places
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = np.arange(n)
    path = np.arange(n, dtype=np.float64)
    LoopChain().add(0, 1, np.eye(4))  # imports paid before timing
    LoopChain().predict(0, 1, poses, path)
    out = {}
    for count in args.closures:
        chain = LoopChain()
        t0 = time.perf_counter()
        for _ in range(count):
            q = int(rng.integers(1000, n))
            m = int(rng.integers(0, q - 500))
            chain.add(m, q, np.linalg.solve(poses[m], poses[q]))
        add_ms = (time.perf_counter() - t0) / count * 1e3
        ms = []
        for _ in range(args.predictions + 1):
            q = int(rng.integers(1000, n))
            m = q - int(rng.integers(100, 400))
            t0 = time.perf_counter()
            chain.predict(m, q, poses, path)
            ms.append((time.perf_counter() - t0) * 1e3)
        build, rest = ms[0], np.array(ms[1:])
        fig = {
            "add_ms": round(add_ms, 4),
            "first_predict_ms": round(build, 3),
            "predict_ms_median": round(float(np.median(rest)), 3),
            "predict_ms_p95": round(float(np.percentile(rest, 95)), 3),
            "predict_ms_max": round(float(rest.max()), 3),
        }
        out[str(count)] = fig
        print(
            f"{count:>6} closures: add {fig['add_ms']:.4f} ms, first prediction (builds the graph) {build:.2f} ms, "
            f"then median {fig['predict_ms_median']:.3f} / p95 {fig['predict_ms_p95']:.3f} / max "
            f"{fig['predict_ms_max']:.3f} ms"
        )
    print(json.dumps({"tool": "bench_loop_chain", "places": n, "closures": out}))


if __name__ == "__main__":
    main()
