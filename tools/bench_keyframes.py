"""Benchmark keyframe building (placerec.keyframes): the cost per scan of de-skewing and accumulating, and the
accuracy of the time-bin de-skew against exact per-point interpolation.

Simulated VLP-16 scans (~22k points) along the town route at 10 Hz are rendered first (not timed); then a
`KeyframeBuilder` (``seconds`` windows, odometry = the true poses) is fed every scan, best of ``--repeat`` runs, with
de-skew, without, and with de-skew and a voxel grid. The de-skew error of the time bins (`DESKEW_BIN_S`) is measured
on every scan against the exact per-point poses (`deskewed_points` with ``bin_s=None``), beside the size of the
de-skew correction itself (de-skewed against not de-skewed points). Against the simulator's own motion model: keyframes
of scans rendered while moving (``sweep_motion``), de-skewed or not, compared with the same scans rendered at rest
(`sweep_motion_p90`). Prints readable lines, then exactly one JSON line.

    python tools/bench_keyframes.py [--scans 60] [--seconds 0.5] [--repeat 3] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import numpy as np

from placerec.keyframes import (
    DESKEW_BIN_S,
    KeyframeBuilder,
    KeyframeParams,
    KeyframeSequence,
    deskewed_points,
)
from placerec.sim import SimulatedSequence
from placerec.types import Scan, valid_points


def ms_per_scan(
    params: KeyframeParams, scans: list[Scan], poses: np.ndarray, repeat: int
) -> tuple[float, int]:
    """Best-of-``repeat`` milliseconds per scan to build every keyframe of ``scans``, and the keyframe count."""
    best = np.inf
    count = 0
    for _ in range(repeat):
        builder = KeyframeBuilder(params)
        t0 = time.perf_counter()
        keyframes = [k for i, s in enumerate(scans) if (k := builder.add(s, poses[i])) is not None]
        if (last := builder.flush()) is not None:
            keyframes.append(last)
        best = min(best, (time.perf_counter() - t0) * 1e3 / len(scans))
        count = len(keyframes)
    return float(best), count


def bin_errors(scans: list[Scan], poses: np.ndarray, stamps: np.ndarray) -> dict[str, float]:
    """Per-point distance (m) of the binned de-skew to the exact one, and of the exact one to no de-skew, over
    every scan but the last (each scan de-skewed between its pose and the next one's, in its own frame), and the
    milliseconds per scan of each."""
    binned_err, correction = [], []
    binned_ms = exact_ms = 0.0
    for i in range(len(scans) - 1):
        s = scans[i].select(valid_points(scans[i]))
        assert s.time is not None
        T_frame_world = np.linalg.inv(poses[i])
        knots = stamps[i : i + 2], poses[i : i + 2]
        t0 = time.perf_counter()
        binned = deskewed_points(s.xyz, s.time, float(stamps[i]), *knots, T_frame_world)
        t1 = time.perf_counter()
        exact = deskewed_points(s.xyz, s.time, float(stamps[i]), *knots, T_frame_world, bin_s=None)
        t2 = time.perf_counter()
        binned_ms += (t1 - t0) * 1e3
        exact_ms += (t2 - t1) * 1e3
        binned_err.append(np.linalg.norm(binned - exact, axis=1))
        correction.append(np.linalg.norm(exact - s.xyz, axis=1))
    err, corr = np.concatenate(binned_err), np.concatenate(correction)
    n = len(scans) - 1
    return {
        "bin_error_max_m": float(err.max()),
        "bin_error_p99_m": float(np.percentile(err, 99)),
        "bin_error_mean_m": float(err.mean()),
        "deskew_correction_max_m": float(corr.max()),
        "deskew_correction_mean_m": float(corr.mean()),
        "binned_deskew_ms_per_scan": binned_ms / n,
        "exact_deskew_ms_per_scan": exact_ms / n,
    }


def plane_distances(cloud: np.ndarray, reference: np.ndarray, k: int = 8) -> np.ndarray:
    """Distance (m) of each point of ``cloud`` to the plane of its ``k`` nearest points of ``reference`` (the points
    with all ``k`` within 1 m): insensitive to two clouds sampling one surface at different places."""
    from scipy.spatial import cKDTree

    d, idx = cKDTree(reference).query(cloud, k=k)
    nb = reference[idx]
    centre = nb.mean(axis=1)
    spread = nb - centre[:, None]
    normal = np.linalg.eigh(np.einsum("nki,nkj->nij", spread, spread))[1][:, :, 0]
    return np.abs(np.einsum("ni,ni->n", cloud - centre, normal))[d[:, -1] < 1.0]


def sweep_motion_p90(
    n_scans: int, seconds: float, seed: int, keyframes: list[int] | None = None
) -> dict[str, float]:
    """90th percentile of `plane_distances` from keyframes of scans the simulator rendered while moving
    (``sweep_motion``: each ray from the pose at its own time) to the keyframes of the same scans rendered standing
    still (not de-skewed: exact), for keyframes de-skewed, not de-skewed, and de-skewed with time running backwards
    (a sign error); ``keyframes``: which (default all)."""
    kw = {
        "world": "town",
        "sensor": "vlp16",
        "n_scans": n_scans,
        "rate_hz": 10,
        "clutter": False,
        "seed": seed,
    }
    moving = SimulatedSequence(sweep_motion=True, **kw)  # type: ignore[arg-type]
    static = SimulatedSequence(**kw)  # type: ignore[arg-type]
    params = KeyframeParams(seconds=seconds)
    reference = KeyframeSequence(static, params.model_copy(update={"deskew": False}), static.poses)

    def flipped(s: Scan) -> Scan:
        assert s.time is not None
        return Scan(s.xyz, s.intensity, s.ring, -s.time, timestamp=s.timestamp)

    out = {}
    for label, p, prepare in (
        ("deskewed", params, None),
        ("not_deskewed", params.model_copy(update={"deskew": False}), None),
        ("time_reversed", params, flipped),
    ):
        seq = KeyframeSequence(moving, p, moving.poses, prepare=prepare)
        which = range(len(seq)) if keyframes is None else keyframes
        d = np.concatenate([plane_distances(seq[k].xyz, reference[k].xyz) for k in which])
        out[label] = float(np.percentile(d, 90))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scans", type=int, default=60)
    ap.add_argument("--seconds", type=float, default=0.5)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    seq = SimulatedSequence(world="town", sensor="vlp16", n_scans=args.scans, rate_hz=10, seed=args.seed)
    t0 = time.perf_counter()
    scans = [seq[i] for i in range(len(seq))]
    render_s = time.perf_counter() - t0
    poses, stamps = seq.poses, seq.timestamps
    points = float(np.mean([len(s) for s in scans]))
    steps = np.linalg.inv(poses[:-1]) @ poses[1:]
    speed = np.linalg.norm(steps[:, :3, 3], axis=1) / np.diff(stamps)
    yaw_rate = np.abs(np.arctan2(steps[:, 1, 0], steps[:, 0, 0])) / np.diff(stamps)
    print(
        f"{len(scans)} simulated VLP-16 scans, {points:.0f} points each on average (rendered in {render_s:.1f} s);"
        f" speed up to {speed.max():.1f} m/s, yaw rate up to {np.degrees(yaw_rate.max()):.1f} deg/s"
    )

    deskew_ms, n_kf = ms_per_scan(KeyframeParams(seconds=args.seconds), scans, poses, args.repeat)
    plain_ms, _ = ms_per_scan(KeyframeParams(seconds=args.seconds, deskew=False), scans, poses, args.repeat)
    voxel_ms, _ = ms_per_scan(KeyframeParams(seconds=args.seconds, voxel_m=0.2), scans, poses, args.repeat)
    print(f"keyframes of {args.seconds:g} s: {n_kf}; build time per scan (best of {args.repeat}):")
    print(f"  de-skew + accumulate        {deskew_ms:6.2f} ms")
    print(f"  accumulate, no de-skew      {plain_ms:6.2f} ms")
    print(f"  de-skew + accumulate + 0.2 m voxels {voxel_ms:6.2f} ms")

    acc = bin_errors(scans, poses, stamps)
    print(
        f"time bins of {DESKEW_BIN_S * 1e3:g} ms against exact per-point poses: max {acc['bin_error_max_m'] * 1e3:.2f} mm,"
        f" p99 {acc['bin_error_p99_m'] * 1e3:.2f} mm, mean {acc['bin_error_mean_m'] * 1e3:.3f} mm"
        f" (the de-skew moves points by up to {acc['deskew_correction_max_m']:.3f} m,"
        f" mean {acc['deskew_correction_mean_m']:.3f} m)"
    )
    print(
        f"de-skew of one scan: binned {acc['binned_deskew_ms_per_scan']:.2f} ms,"
        f" exact per point {acc['exact_deskew_ms_per_scan']:.2f} ms"
    )
    sweep = sweep_motion_p90(min(args.scans, 20), args.seconds, args.seed)
    print(
        "scans rendered while moving (sweep_motion), distance to the surfaces of the same scans rendered at rest,"
        f" p90: de-skewed {sweep['deskewed'] * 100:.1f} cm, not de-skewed {sweep['not_deskewed'] * 100:.1f} cm,"
        f" time reversed {sweep['time_reversed'] * 100:.1f} cm"
    )
    print(
        json.dumps(
            {
                "bench": "keyframes",
                "machine": platform.machine(),
                "scans": len(scans),
                "points_per_scan": round(points),
                "window_s": args.seconds,
                "keyframes": n_kf,
                "ms_per_scan_deskew_accumulate": round(deskew_ms, 3),
                "ms_per_scan_accumulate": round(plain_ms, 3),
                "ms_per_scan_deskew_voxel": round(voxel_ms, 3),
                "bin_s": DESKEW_BIN_S,
                **{k: round(v, 6) for k, v in acc.items()},
                **{f"sweep_motion_p90_m_{k}": round(v, 4) for k, v in sweep.items()},
            }
        )
    )


if __name__ == "__main__":
    main()
