"""``placerec localize``: every scan of a sequence localised against a map artifact, and the results folder.

`localize_sequence` runs a `placerec.maps.localizer.Localizer` over a sequence, in order: ``mode="tracking"``
(`Localizer.track`: tracking from the last fix moved by the odometry, ``odometry="kiss-icp"``, or by a constant
velocity, ``"none"``; global search when tracking fails) or ``mode="global"`` (`Localizer.localize` on each scan
alone, no prior). With ``keyframes`` (`placerec.keyframes.KeyframeParams`: a Livox-style or solid-state scanner's
frames, each too little of a place) the queries are keyframes of the sequence (`placerec.keyframes.keyframes_along`:
accumulated along its poses, or KISS-ICP's with ``odometry="kiss-icp"``, whose keyframe poses are then tracking's
motion), each fixed at its window's last scan; the outputs' rows are keyframes. `report_localize` writes what it
found into a folder:

* ``poses_tum.txt`` — the accepted fixes with their scans' times (the scan index when the sequence has none);
* ``poses_kitti.txt`` — the accepted fixes only (KITTI has no time column and no "missing" row), and
  ``fixed_scans.txt`` — the scan index of each of its lines, one a line;
* ``fixes.csv`` — every scan: ``index, time, accepted, mode, reason, x, y, z, roll, pitch, yaw`` (the fix;
  empty when not accepted), ``keyframe, score, fitness, candidates, time_ms``, and with ground truth
  ``translation_error, rotation_error_deg, correct`` (an accepted fix within 1 m and 5 deg);
* ``metrics.json`` — scans, accepted, correct, false fixes (accepted but beyond 1 m / 5 deg), the success rate
  (correct / scans: accepted answers only), the time per scan of each mode (median, p95, ...);
* ``fixes.mcap`` — the fixes and an edge from each scan to the keyframe its answer was verified against, for
  Foxglove (`write_fixes_mcap`; topics in docs/slam.md);
* ``fixes.png`` — the map's keyframes (grey), correct fixes (green), false fixes (red), and the true positions of
  the scans without a fix (black x; with no ground truth, accepted fixes are blue).
"""

from __future__ import annotations

import csv
import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from datetime import datetime
from pathlib import Path
from typing import Any, Literal

import numpy as np

from placerec.errors import ConfigError
from placerec.eval.metrics import timing_summary
from placerec.eval.pose_error import error_stats, pose_errors
from placerec.experiment.candidates import pose_to_xyzrpy
from placerec.experiment.run_folder import finite_or_null, json_default, slug
from placerec.io import write_kitti_poses, write_tum_poses
from placerec.io.atomic import atomic_write
from placerec.io.mcap_export import LoopEdge, write_closures_mcap
from placerec.keyframes import KeyframeParams, keyframes_along
from placerec.maps.artifact import MapArtifact
from placerec.maps.localizer import Fix, Localizer, LocalizerParams, search_pipelines
from placerec.types import Sequence, relative_pose
from placerec.viewer import active

__all__ = [
    "CORRECT_M",
    "CORRECT_DEG",
    "LocalizeRun",
    "localize_sequence",
    "report_localize",
    "default_out",
    "FIX_COLUMNS",
]

log = logging.getLogger(__name__)

#: an accepted fix is correct within this distance and angle of the ground truth (issue #29's targets)
CORRECT_M, CORRECT_DEG = 1.0, 5.0
FIX_COLUMNS = ("index", "time", "accepted", "mode", "reason", "x", "y", "z", "roll", "pitch", "yaw", "keyframe",
               "score", "fitness", "candidates", "time_ms")  # fmt: skip
TRUTH_COLUMNS = ("translation_error", "rotation_error_deg", "correct")


@dataclass(frozen=True, eq=False)
class LocalizeRun:
    """A localised sequence: every scan's `Fix`, the scans' times (None: unknown), the ground truth (None: the
    sequence has no poses), the map and how the run was made (``mode``, ``odometry``, parameters)."""

    name: str
    map: MapArtifact
    fixes: list[Fix]
    timestamps: np.ndarray | None
    ground_truth: np.ndarray | None
    mode: str
    odometry: str
    params: LocalizerParams
    keyframes: KeyframeParams | None = None

    def errors(self) -> tuple[np.ndarray, np.ndarray]:
        """(translation m, rotation deg) of every scan's accepted fix against the ground truth (NaN: no fix or no
        ground truth)."""
        n = len(self.fixes)
        te, re = np.full(n, np.nan), np.full(n, np.nan)
        fixed = [i for i, f in enumerate(self.fixes) if f.accepted and f.T_world_query is not None]
        if self.ground_truth is None or not fixed:
            return te, re
        est = np.stack([self.fixes[i].T_world_query for i in fixed])  # type: ignore[misc]
        te[fixed], re[fixed] = pose_errors(est, self.ground_truth[fixed])
        return te, re

    def correct(self) -> np.ndarray | None:
        """(N,) True where the accepted fix is within `CORRECT_M` / `CORRECT_DEG` (None: no ground truth)."""
        if self.ground_truth is None:
            return None
        te, re = self.errors()
        with np.errstate(invalid="ignore"):
            return (te <= CORRECT_M) & (re <= CORRECT_DEG)


def localize_sequence(
    map: MapArtifact | str | Path,
    seq: Sequence,
    params: LocalizerParams | None = None,
    mode: Literal["tracking", "global"] = "tracking",
    odometry: Literal["none", "kiss-icp"] = "none",
    progress: Callable[[int, int], None] | None = None,
    keyframes: KeyframeParams | None = None,
) -> LocalizeRun:
    """Localise every scan of ``seq`` in ``map`` (module docstring), or with ``keyframes`` every keyframe of it.
    The `Localizer` checks the first scan's sensor against the map's (`MapArtifact.check_query`, unless
    ``params.allow_other_sensor``) before localising it."""
    if mode not in ("tracking", "global"):
        raise ConfigError(f"mode must be 'tracking' or 'global', got {mode!r}")
    if odometry not in ("none", "kiss-icp"):
        raise ConfigError(f"odometry must be 'none' or 'kiss-icp', got {odometry!r}")
    if odometry != "none" and mode == "global" and keyframes is None:
        raise ConfigError("odometry is for mode 'tracking' (global search uses no prior)")
    params = params or LocalizerParams()
    loc = Localizer(map, params)
    if len(seq) == 0:
        raise ConfigError(f"{seq.name}: the sequence has no scans")
    mismatch = loc.map.places_mismatch(keyframes is not None)
    if mismatch:
        log.warning("%s: give the queries the map's kind of places (--keyframes-seconds / -metres)", mismatch)
    moves = None  # with keyframes and KISS-ICP: the keyframes' own odometry poses move tracking
    if keyframes is not None:
        kseq = keyframes_along(seq, keyframes, kiss_icp=odometry == "kiss-icp")
        moves = kseq.keyframe_poses if odometry == "kiss-icp" else None
        seq = kseq
    n = len(seq)
    odo = None
    if odometry == "kiss-icp" and keyframes is None:
        from placerec.slam.odometry import KissIcpOdometry

        odo = KissIcpOdometry()
    fixes = []
    viewer = active()
    truth = None if seq.poses is None else np.asarray(seq.poses, np.float64)
    stamps = None if seq.timestamps is None else np.asarray(seq.timestamps, np.float64)
    if viewer is not None:
        viewer.points("world/map/keyframes", loc.map.positions(), (150, 150, 150), static=True)
        if truth is not None:
            viewer.trajectory("gt", truth, static=True)
    for i in range(n):
        scan = seq[i]
        if moves is not None:
            fix = loc.track(scan, moves[i]) if mode == "tracking" else loc.localize(scan)
        elif odo is None:
            fix = loc.track(scan) if mode == "tracking" else loc.localize(scan)
        else:
            t0 = time.perf_counter()
            pose = odo.register(scan)
            odo_ms = (time.perf_counter() - t0) * 1e3
            fix = loc.track(scan, pose)
            fix = _with_odometry_time(fix, odo_ms)
        fixes.append(fix)
        if viewer is not None:  # the scan at its true pose, else at its fix (else at the origin)
            at = fix.T_world_query if truth is None else truth[i]
            viewer.scan(i, scan, at, None if stamps is None else stamps[i])
            viewer.fix("localizer", fix.T_world_query, _fix_text(fix), fix.accepted)
        if progress is not None:
            progress(i + 1, n)
    return LocalizeRun(seq.name, loc.map, fixes, stamps, truth, mode, odometry, params, keyframes)


def _fix_text(fix: Fix) -> str:
    """A fix in words (the recording's ``localize/localizer``): mode, reason, keyframe, score, fitness, time."""
    head = "**fixed**" if fix.accepted else "**no fix**"
    return (
        f"{head} ({fix.mode}): {fix.reason}  \nkeyframe {fix.keyframe_id}, score {fix.score:.3g}, "
        f"fitness {fix.fitness:.3g}, {fix.candidates_tried} tried, {fix.time_ms:.0f} ms"
    )


def _with_odometry_time(fix: Fix, ms: float) -> Fix:
    """``fix`` with the odometry's time as a stage of its own (``time_ms`` stays the localiser's)."""
    return replace(fix, timing_ms={**fix.timing_ms, "odometry": ms})


def default_out(name: str, root: str | Path = "results") -> Path:
    """``<root>/localize_<name>_<timestamp>``: where ``placerec localize`` writes without ``--out``."""
    return Path(root) / f"localize_{slug(name)}_{datetime.now().strftime('%Y%m%d-%H%M%S')}"


def localize_metrics(run: LocalizeRun) -> dict[str, Any]:
    """The ``metrics.json`` payload (module docstring)."""
    fixes = run.fixes
    n = len(fixes)
    accepted = np.array([f.accepted for f in fixes], bool)
    modes = np.array([f.mode for f in fixes])
    times = np.array([f.time_ms for f in fixes], np.float64)
    payload: dict[str, Any] = {
        "mode": "localize",
        "sequence": run.name,
        "map": str(run.map.path),
        "pipelines": [p.name for p in search_pipelines(run.map, run.params)],
        "localize_mode": run.mode,
        "odometry": run.odometry,
        "keyframes": None if run.keyframes is None else run.keyframes.model_dump(mode="json"),
        "scans": n,
        "accepted": int(accepted.sum()),
        "accepted_by_mode": {m: int((accepted & (modes == m)).sum()) for m in ("tracking", "global")},
        "time_ms": {
            "all": timing_summary(times),
            **{m: timing_summary(times[modes == m]) for m in ("tracking", "global")},
        },
        "params": run.params.model_dump(mode="json"),
    }
    correct = run.correct()
    if correct is not None:
        te, re = run.errors()
        wrong = accepted & ~correct
        payload.update(
            correct=int(correct.sum()),
            false_fixes=int(wrong.sum()),
            success_rate=float(correct.sum()) / n,
            correct_within={"metres": CORRECT_M, "degrees": CORRECT_DEG},
            translation_error_m=error_stats(te[accepted]),
            rotation_error_deg=error_stats(re[accepted]),
        )
    return payload


def _rows(run: LocalizeRun) -> tuple[list[str], list[list[Any]]]:
    """``fixes.csv``'s header and rows (module docstring)."""
    te, re = run.errors()
    correct = run.correct()
    header = list(FIX_COLUMNS) + (list(TRUTH_COLUMNS) if correct is not None else [])
    rows = []
    for i, f in enumerate(run.fixes):
        t = float(run.timestamps[i]) if run.timestamps is not None else float(i)
        pose = pose_to_xyzrpy(f.T_world_query) if f.T_world_query is not None else [None] * 6
        row: list[Any] = [i, f"{t:.9f}", int(f.accepted), f.mode, f.reason]
        row += ["" if v is None else f"{v:.6f}" for v in pose]
        row += [f.keyframe_id, _g(f.score), _g(f.fitness), f.candidates_tried, f"{f.time_ms:.3f}"]
        if correct is not None:
            row += [_g(te[i]), _g(re[i]), int(correct[i])]
        rows.append(row)
    return header, rows


def _g(v: float) -> str:
    return f"{v:.6g}" if np.isfinite(v) else ""


def report_localize(run: LocalizeRun, out_dir: str | Path, figure: bool = True) -> dict[str, Any]:
    """Write the results folder of ``run`` into ``out_dir`` (module docstring); returns the metrics dict."""
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"--out {out}: cannot make the results folder: {exc.strerror or exc}") from None
    fixed = [i for i, f in enumerate(run.fixes) if f.accepted]
    poses = np.array([run.fixes[i].T_world_query for i in fixed], np.float64).reshape(-1, 4, 4)
    stamps = run.timestamps if run.timestamps is not None else np.arange(len(run.fixes), dtype=np.float64)
    write_tum_poses(out / "poses_tum.txt", poses, stamps[fixed])
    write_kitti_poses(out / "poses_kitti.txt", poses)
    with atomic_write(out / "fixed_scans.txt", "w") as fh:
        fh.write("".join(f"{i}\n" for i in fixed))
    header, rows = _rows(run)
    with atomic_write(out / "fixes.csv", "w") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(header)
        w.writerows(rows)
    write_fixes_mcap(run, out / "fixes.mcap")
    payload = localize_metrics(run)
    with atomic_write(out / "metrics.json", "w") as fh:
        json.dump(finite_or_null(payload), fh, indent=2, default=json_default, allow_nan=False)
    if figure:
        plot_fixes(run, out / "fixes.png")
    return payload


def write_fixes_mcap(run: LocalizeRun, path: Path) -> Path:
    """``fixes.mcap``: the accepted fixes as the poses, and an edge from each scan to the keyframe its answer was
    verified against (accepted, or rejected with the fix's reason), in the map's frame (`write_closures_mcap`)."""
    n = len(run.fixes)
    valid = np.array([f.accepted and f.T_world_query is not None for f in run.fixes], bool).reshape(n)
    poses = np.full((n, 4, 4), np.nan)
    for i in np.flatnonzero(valid):
        poses[i] = run.fixes[i].T_world_query
    keyframes = run.map.poses
    edges = [
        LoopEdge(
            i,
            f.keyframe_id,
            f.score,
            relative_pose(keyframes[f.keyframe_id], poses[i]) if valid[i] else None,
            accepted=bool(valid[i]),
            rejection=None if valid[i] else f.reason,
        )
        for i, f in enumerate(run.fixes)
        if f.keyframe_id >= 0
    ]
    return write_closures_mcap(
        path,
        poses,
        edges,
        timestamps=run.timestamps,
        ground_truth=run.ground_truth,
        valid=valid,
        match_poses=keyframes,
    )


def plot_fixes(run: LocalizeRun, path: Path) -> Path:
    """``fixes.png``: the fixes on the map (module docstring)."""
    from placerec.experiment.figures import _finish, _frame, _pyplot

    fig, ax = _pyplot().subplots(figsize=(6.5, 6.5), dpi=110)
    kf = run.map.positions()
    ax.plot(kf[:, 0], kf[:, 1], ".", color="0.7", ms=3, label=f"map keyframes ({len(kf)})", zorder=1)
    accepted = np.array([f.accepted for f in run.fixes], bool)
    xy = np.array(
        [f.T_world_query[:2, 3] if f.T_world_query is not None else (np.nan, np.nan) for f in run.fixes]
    )
    correct = run.correct()
    if correct is None:
        groups = [(accepted, "tab:blue", "o", "fixes")]
    else:
        groups = [
            (correct, "tab:green", "o", "correct fixes"),
            (accepted & ~correct, "tab:red", "o", "false fixes"),
        ]
    for mask, color, marker, label in groups:
        if mask.any():
            ax.plot(xy[mask, 0], xy[mask, 1], marker, color=color, ms=3.5, label=f"{label} ({int(mask.sum())})",
                    zorder=3)  # fmt: skip
    missing = ~accepted
    if missing.any() and run.ground_truth is not None:
        g = run.ground_truth[missing, :2, 3]
        ax.plot(g[:, 0], g[:, 1], "x", color="k", ms=4, label=f"no fix ({int(missing.sum())})", zorder=4)
    elif missing.any():
        ax.plot([], [], " ", label=f"no fix: {int(missing.sum())} scans")
    ax.set(xlabel="x [m]", ylabel="y [m]")
    n = len(run.fixes)
    ax.set_title(f"{run.name} in map {run.map.manifest.name}\n{int(accepted.sum())} of {n} scans fixed "
                 f"({run.mode}, odometry {run.odometry})", fontsize=9)  # fmt: skip
    truth = run.ground_truth[:, :3, 3] if run.ground_truth is not None else np.zeros((0, 3))
    _frame(ax, kf, xy, truth)
    return _finish(fig, ax, path, loc="best")
