"""Relocalisation speed and success on a simulated session pair (issue #29's targets: tracking <= 30 ms per scan,
global fallback <= 1 s median, fixes within 1 m / 5 deg with no accepted wrong fix, a fix <= 3 scans after a
kidnap).

The map is ``--scans`` scans of ``--world``'s default route (simulator seed ``--seed``, every 0.5 m a keyframe,
the ``--pipeline`` database); the second session drives the same route in the same world with the same sensor unit
and another seed (``--seed + 100000``: other clutter, parked cars and noise). Then, with `placerec.maps.Localizer`:

* **tracking**: every scan of the second session in order (`Localizer.track`, constant-velocity prediction, or
  KISS-ICP odometry with ``--odometry kiss-icp``); time per scan of the tracking fixes;
* **global**: every ``--global-every``-th scan alone (`Localizer.localize`, no prior);
* **kidnap**: ``--kidnaps`` trials: 3 scans tracked at a random place, then a teleport (no reset: the localiser
  is not told) to a place at least 50 m away and 5 scans from there; a trial succeeds when its first accepted fix
  after the teleport comes within 3 scans and is correct;
* **other world**: ``--foreign`` scans of another world (campus): any accepted fix is a false fix.

``--tune`` prints instead what the tracking defaults were chosen on (`placerec.maps.localizer._tracking_verify`):
ICP from the true pose moved by up to 0, 0.5, 1, 2 m and 0, 3, 5, 10 deg onto the 2 nearest keyframes of every 3rd
scan, with acceptance off, against ICP onto the wrong place (a campus scan at a town keyframe; a town scan at a
prior 60 m along the route): the score and fitness of the correct and of the wrong alignments.

A fix is correct within 1 m / 5 deg of the ground truth; success counts accepted fixes only. Seeds of the test
split (placerec.experiment.protocol) are refused: the localiser's defaults were chosen on this tool's default
seed 0 (docs/maps.md, 'Relocalisation'). The last line printed is one JSON object (with the load: ``uptime``).

    python tools/bench_localize.py --scans 200
    python tools/bench_localize.py --scans 120 --tune
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from placerec.artifacts import build
from placerec.eval.metrics import timing_summary
from placerec.eval.pose_error import pose_errors
from placerec.experiment.protocol import is_test_seed
from placerec.maps import Fix, Localizer, LocalizerParams
from placerec.sim import SimulatedSequence
from placerec.slam_app.localize import CORRECT_DEG, CORRECT_M
from placerec.types import Sequence


def ok_pose(T: np.ndarray, truth: np.ndarray) -> bool:
    """Whether ``T`` is within `CORRECT_M` / `CORRECT_DEG` (1 m / 5 deg) of ``truth``."""
    te, re = pose_errors(T, truth)
    return bool(te[0] <= CORRECT_M and re[0] <= CORRECT_DEG)


def ok(fix: Fix, truth: np.ndarray) -> bool:
    """Whether ``fix`` is accepted and `ok_pose`."""
    return fix.accepted and fix.T_world_query is not None and ok_pose(fix.T_world_query, truth)


def summary(fixes: list[Fix], truth: np.ndarray | None, mode: str | None = None) -> dict:
    """Counts and times of ``fixes`` (those of ``mode`` for the times, when given)."""
    acc = np.array([f.accepted for f in fixes], bool)
    t = np.array([f.time_ms for f in fixes if mode is None or f.mode == mode])
    out: dict = {"scans": len(fixes), "accepted": int(acc.sum())}
    if truth is not None:
        good = np.array([ok(f, T) for f, T in zip(fixes, truth, strict=True)])
        out.update(correct=int(good.sum()), false_fixes=int((acc & ~good).sum()), success=float(good.mean()))
    if t.size:
        ts = timing_summary(t)
        out.update(n_timed=ts["n"], median_ms=ts["median"], p95_ms=ts["p95"])
    return out


def tune(loc: Localizer, scans: list, truth: np.ndarray, seed: int) -> dict:
    """The score and fitness of tracking ICP from perturbed priors, correct against wrong (module docstring)."""
    from placerec.preprocess import preprocess_scan
    from placerec.types import valid_points
    from placerec.verify import as_source, as_target, verify_icp

    vp = loc.params.tracking.verify
    vp = vp.model_copy(update={"score": vp.score.model_copy(update={"min_score": 0.0, "min_fitness": None})})
    m, rng = loc.map, np.random.default_rng(seed)
    other = SimulatedSequence(world="campus", sensor=scans[0].sensor.name, n_scans=len(scans), seed=seed)
    rows: list[tuple[bool, float, float]] = []  # (correct, score, fitness)

    def align(scan, prior: np.ndarray, true: np.ndarray | None, metres: float, degrees: float) -> None:
        s = preprocess_scan(scan, loc.preprocess, keep_organized=True)
        src = as_source(s.xyz[valid_points(s)], vp)
        a = np.radians(rng.uniform(-degrees, degrees))
        D = np.eye(4)
        D[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
        D[:2, 3] = rng.uniform(-metres, metres, 2)
        P = prior @ D
        for kf in m.nearest(P[:3, 3], k=2, radius=15.0)[0]:
            v = verify_icp(src, as_target(m.cloud(int(kf)), vp), np.linalg.inv(m.poses[kf]) @ P, vp)
            T = m.poses[kf] @ v.T_match_query
            good = true is not None and ok_pose(T, true)
            rows.append((good, v.score, v.fitness))

    n = len(scans)
    for i in range(0, n, 3):
        for metres, degrees in ((0.0, 0.0), (0.5, 3.0), (1.0, 5.0), (2.0, 10.0)):
            align(scans[i], truth[i], truth[i], metres, degrees)
        align(other[i], m.poses[int(rng.integers(len(m)))], None, 1.0, 5.0)
        align(scans[i], truth[(i + n // 2) % n], None, 0.0, 0.0)  # a prior far along the route
    r = np.array(rows, dtype=np.float64)
    good = r[:, 0] > 0
    return {
        "alignments": len(r),
        "correct": int(good.sum()),
        "correct_score_min": float(r[good, 1].min()),
        "correct_fitness_min": float(r[good, 2].min()),
        "wrong_score_max": float(r[~good, 1].max()),
        "wrong_fitness_max": float(r[~good, 2].max()),
    }


def load() -> str:
    """The load averages (``uptime``'s), for the record."""
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--world", default="town")
    ap.add_argument("--sensor", default="vlp16")
    ap.add_argument("--scans", type=int, default=200, help="scans of each session")
    ap.add_argument(
        "--seed", type=int, default=0, help="map session's seed (tuning split; test seeds refused)"
    )
    ap.add_argument("--pipeline", default="orb-hbst", help="the map's pipeline for global search")
    ap.add_argument("--odometry", choices=("none", "kiss-icp"), default="none")
    ap.add_argument("--global-every", type=int, default=4)
    ap.add_argument("--kidnaps", type=int, default=20)
    ap.add_argument("--foreign", type=int, default=10, help="scans of another world (campus)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="LocalizerParams key=value")
    ap.add_argument("--tune", action="store_true", help="the tracking acceptance's tuning figures only")
    ap.add_argument("--map", type=Path, help="keep the map here (default: a temporary folder)")
    args = ap.parse_args(argv)
    if is_test_seed(args.seed) or is_test_seed(args.seed + 100_000):
        sys.exit(
            f"--seed {args.seed}: a test-split seed; this tool tunes and reports on the tuning split only"
        )
    from placerec.config import apply_overrides

    params = LocalizerParams.model_validate(apply_overrides({}, args.overrides))
    tmp = tempfile.TemporaryDirectory(prefix="bench_localize_")
    out = args.map or Path(tmp.name) / "map"
    t0 = time.perf_counter()
    source = {"world": args.world, "sensor": args.sensor, "scans": args.scans, "seed": args.seed}
    build("map", {"source": {"sim": source}, "out": str(out), "pipelines": [{"name": args.pipeline}],
                  "overwrite": True})  # fmt: skip
    build_s = time.perf_counter() - t0
    q = SimulatedSequence(world=args.world, sensor=args.sensor, n_scans=args.scans, seed=args.seed + 100_000,
                          world_seed=args.seed, unit_seed=args.seed)  # fmt: skip
    scans = [q[i] for i in range(len(q))]  # rendered before any timing
    truth = np.asarray(q.poses)
    loc = Localizer(out, params)
    print(f"map: {len(loc.map)} keyframes ({build_s:.0f} s); load {load()}", flush=True)

    if args.tune:
        result = {"tool": "bench_localize --tune", "world": args.world, "sensor": args.sensor, "seed": args.seed,
                  "query_seed": args.seed + 100_000, **tune(loc, scans, truth, args.seed), "load": load()}  # fmt: skip
        tmp.cleanup()
        print(json.dumps(result))
        return result
    odo_poses = None
    if args.odometry == "kiss-icp":
        from placerec.slam.odometry import KissIcpOdometry

        kiss = KissIcpOdometry()
        odo_poses = [kiss.register(s) for s in scans]
    tracked = [loc.track(s, None if odo_poses is None else odo_poses[i]) for i, s in enumerate(scans)]
    tracking = summary(tracked, truth, "tracking")
    tracking["tracking_fixes"] = sum(f.mode == "tracking" and f.accepted for f in tracked)
    print("tracking", json.dumps(tracking), flush=True)

    idx = list(range(0, len(scans), args.global_every))
    glob = summary([loc.localize(scans[i]) for i in idx], truth[idx], "global")
    print("global", json.dumps(glob), flush=True)

    rng = np.random.default_rng(args.seed)
    xy = truth[:, :2, 3]
    found, first, kid_false, trials = 0, [], 0, 0
    for _ in range(100 * args.kidnaps):
        if trials == args.kidnaps:
            break
        i = int(rng.integers(0, len(scans) - 3))
        far = np.flatnonzero(np.linalg.norm(xy[: len(scans) - 5] - xy[i + 2], axis=1) >= 50.0)
        if not far.size:
            continue
        j = int(rng.choice(far))
        trials += 1
        loc.reset()
        for k in range(i, i + 3):
            loc.track(scans[k])
        after = [(k, loc.track(scans[k])) for k in range(j, j + 5)]
        hit = next(((n, k, f) for n, (k, f) in enumerate(after) if f.accepted), None)
        if hit is None:
            continue
        n, k, f = hit
        if not ok(f, truth[k]):
            kid_false += 1
        elif n < 3:
            found += 1
            first.append(n + 1)
    kidnap = {"trials": trials, "fixed_within_3": found, "false_first_fixes": kid_false,
              "median_scans_to_fix": float(np.median(first)) if first else None}  # fmt: skip
    print("kidnap", json.dumps(kidnap), flush=True)

    other: Sequence = SimulatedSequence(
        world="campus", sensor=args.sensor, n_scans=args.foreign, seed=args.seed
    )
    foreign = [loc.localize(other[i]) for i in range(len(other))]
    foreign_acc = sum(f.accepted for f in foreign)
    result = {
        "tool": "bench_localize",
        "world": args.world,
        "sensor": args.sensor,
        "seed": args.seed,
        "query_seed": args.seed + 100_000,
        "pipeline": args.pipeline,
        "odometry": args.odometry,
        "keyframes": len(loc.map),
        "tracking": tracking,
        "global": glob,
        "kidnap": kidnap,
        "other_world": {"scans": len(foreign), "accepted": int(foreign_acc)},
        "load": load(),
        "cpus": os.cpu_count(),
    }
    tmp.cleanup()
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
