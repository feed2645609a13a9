"""``placerec detect``: loop closure on one's own sequence in one command, no config and no ground truth needed.

`detect` opens whatever `placerec.io.open_sequence` opens (a scan folder, a dataset layout, a bag or an Ouster
capture), feeds its scans in acquisition order to a `placerec.loop_closure.LoopClosureDetector` over a registered
pipeline at its preset's operating threshold (or ``threshold``), and writes the accepted closures to a results
folder: ``closures.csv`` and ``closures.json`` (ids, times, files, score, inliers, ``T_match_query`` as
x y z roll pitch yaw and as the 4x4), ``closures.png`` (the closures over the path when there are poses — the
sequence's own, ``--poses``, or KISS-ICP odometry —, else as scan indices) and ``config.yaml``. The exclusion
window is the detector's 120 frames, or half the scans of a shorter sequence (`exclusion_frames`). When the sequence has ground-truth poses
each closure is also judged (true when the matched scan lies within ``gt_distance`` of the query, the evaluation's
rule: `placerec.eval.ground_truth`) and the precision and the revisits found are reported.

With ``keyframes`` (``--keyframes-seconds`` / ``--keyframes-metres``) the places are keyframes of the sequence
(`placerec.keyframes.KeyframeSequence`, docs/keyframes.md): ids, times, poses and the exclusion window's frames are
those of keyframes, each closure's files name the scan range of its keyframes (``name[10:15]``).
"""

from __future__ import annotations

import csv
import json
import logging
import re
from collections.abc import Callable
from contextlib import nullcontext
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field

from placerec.errors import ConfigError, PlacerecError, ScanDataError
from placerec.eval.exclusion import DEFAULT_EXCLUSION_FRAMES
from placerec.keyframes import KeyframeParams, KeyframeSequence, keyframes_along
from placerec.params import Params

log = logging.getLogger(__name__)

__all__ = ["DEFAULT_PIPELINE", "DetectConfig", "detect", "options_config", "summary_lines"]

#: The pipeline `placerec detect` runs unless told otherwise: of the pipelines with an operating threshold, the one
#: with the highest mean max F1 (0.906) and the highest mean recall at its fixed threshold (0.648) on the held-out
#: benchmark's test split (docs/benchmarks.md, 'Held-out loop-closure benchmark', test split table; README).
DEFAULT_PIPELINE = "superpoint-dbow"
#: Rows of the closures table `summary_lines` prints.
SUMMARY_ROWS = 5
#: Columns of closures.csv (``T00``..``T33``: ``T_match_query`` row-major).
CSV_COLUMNS = (
    "query_id", "match_id", "query_time", "match_time", "query_file", "match_file", "score", "inliers",
    "x", "y", "z", "roll", "pitch", "yaw", *(f"T{r}{c}" for r in range(4) for c in range(4)), "true",
)  # fmt: skip


class DetectOutput(Params):
    """Where the results folder goes (`placerec.experiment.run_folder.make_run_dir`'s ``output.dir``)."""

    dir: str = "results"


class DetectConfig(Params):
    """What `detect` runs (``placerec detect``'s options; written to the results folder as config.yaml)."""

    name: str = Field("detect", description="results folder name: <name>_<timestamp>")
    source: str = Field(..., description="the sequence: a folder, a dataset layout, a bag, an Ouster capture")
    format: str | None = Field(None, description="scan reader (--format)")
    dataset: str | None = Field(None, description="dataset layout (--dataset)")
    poses: str | None = Field(None, description="poses file (--poses), taken as ground truth")
    pipeline: str = Field(DEFAULT_PIPELINE, description="registered pipeline (--pipeline)")
    threshold: float | None = Field(
        None, description="accept score >= this; None: the preset's (--threshold)"
    )
    exclusion_frames: int | None = Field(
        None,
        ge=0,
        le=1_000_000,
        description="--exclusion-frames; None: 120 (the detector's), or half the scans of a shorter sequence",
    )
    exclusion_seconds: float | None = Field(None, ge=0, description="--exclusion-seconds (needs times)")
    exclusion_metres: float | None = Field(None, ge=0, description="--exclusion-metres (needs poses)")
    odometry: Literal["none", "kiss-icp"] = Field("none", description="poses from the scans (--odometry)")
    keyframes: KeyframeParams | None = Field(
        None,
        description="--keyframes-seconds / --keyframes-metres: closures between keyframes (docs/keyframes.md)",
    )
    gt_distance: float = Field(5.0, gt=0, description="a closure is true within this distance (m)")
    output: DetectOutput = Field(default_factory=DetectOutput)


def options_config(options: dict[str, Any]) -> DetectConfig:
    """The `DetectConfig` of ``placerec detect``'s options (field names spelt as options in its errors)."""
    try:
        return DetectConfig.model_validate(options)
    except ConfigError as exc:
        text = str(exc).replace("DetectConfig: ", "")
        for key in DetectConfig.model_fields:
            text = re.sub(rf"\b{key}\b(?=:)", "--" + key.replace("_", "-"), text)
        raise ConfigError(text) from None


def _check_pipeline(cfg: DetectConfig) -> float:
    """The threshold to accept at; `ConfigError` naming --pipeline / --threshold when there is none."""
    from placerec.recognizer import PIPELINES

    entry = PIPELINES.get(cfg.pipeline)
    if entry is None:
        raise ConfigError(
            f"--pipeline: unknown pipeline {cfg.pipeline!r}; registered: {', '.join(PIPELINES)}"
        )
    if cfg.threshold is not None:
        return cfg.threshold
    if entry.threshold is None:
        with_one = ", ".join(n for n, e in PIPELINES.items() if e.threshold is not None)
        raise ConfigError(
            f"--pipeline {cfg.pipeline}: no operating threshold in its preset; give --threshold, or pick one of "
            f"{with_one}"
        )
    return entry.threshold


def _open(cfg: DetectConfig) -> Any:
    """The sequence of SOURCE; `ConfigError` naming SOURCE when it is none or holds no scans."""
    from placerec.io import open_sequence

    options = {k: v for k, v in (("format", cfg.format), ("poses", cfg.poses)) if v is not None}
    try:
        seq = open_sequence(cfg.source, dataset=cfg.dataset, **options)
    except ConfigError:
        raise
    except PlacerecError as exc:
        raise ConfigError(f"SOURCE: not a sequence placerec can open: {exc}") from exc
    if len(seq) == 0:
        raise ConfigError(f"SOURCE {cfg.source}: a sequence without scans")
    if cfg.exclusion_seconds is not None and seq.timestamps is None:
        raise ConfigError(f"--exclusion-seconds: {seq.name} has no scan times")
    if cfg.exclusion_metres is not None and seq.poses is None and cfg.odometry == "none":
        raise ConfigError(
            f"--exclusion-metres: {seq.name} has no poses; give --poses FILE or --odometry kiss-icp"
        )
    return seq if cfg.keyframes is None else _keyframes(cfg, cfg.keyframes, seq)


def _keyframes(cfg: DetectConfig, params: KeyframeParams, seq: Any) -> KeyframeSequence:
    """The keyframes of SOURCE (docs/keyframes.md, `placerec.keyframes.keyframes_along`), each scan preprocessed
    as a single scan is before it is accumulated."""
    from functools import partial

    from placerec.config import experiment_preprocess
    from placerec.preprocess import preprocess_scan

    prepare = partial(preprocess_scan, params=experiment_preprocess())
    return keyframes_along(seq, params, cfg.odometry == "kiss-icp", prepare)


def _file_name(source: str | None) -> str | None:
    if not source:
        return None
    p = Path(source)
    return p.name if p.is_file() else source


def _row(c: Any, times: list[float | None], files: list[str | None]) -> dict[str, Any]:
    from placerec.experiment.candidates import pose_to_xyzrpy

    q, m = int(c.query_id), int(c.match_id)
    row: dict[str, Any] = {
        "query_id": q,
        "match_id": m,
        "query_time": times[q],
        "match_time": times[m],
        "query_file": files[q],
        "match_file": files[m],
        "score": float(c.score),
        "inliers": None if c.inliers is None else int(c.inliers),
        "T_match_query": None,
        "true": None,  # judged by `detect` when the sequence has ground-truth poses
    }
    for k in ("x", "y", "z", "roll", "pitch", "yaw"):
        row[k] = None
    if c.relative_pose is not None:
        T = np.asarray(c.relative_pose, np.float64)
        row.update(zip(("x", "y", "z", "roll", "pitch", "yaw"), map(float, pose_to_xyzrpy(T)), strict=True))
        row["T_match_query"] = T.tolist()
    return row


def _write_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    from placerec.io.atomic import atomic_write

    with atomic_write(path, "w") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(CSV_COLUMNS)
        for r in rows:
            T = np.asarray(r["T_match_query"]).reshape(-1) if r["T_match_query"] is not None else [None] * 16
            cells = [r[k] for k in CSV_COLUMNS[:14]] + list(T) + [r["true"]]
            w.writerow(["" if v is None else repr(float(v)) if isinstance(v, float) else v for v in cells])


def _plot(path: Path, positions: np.ndarray, rows: list[dict[str, Any]], title: str) -> Path:
    from matplotlib.collections import LineCollection

    from placerec.experiment.figures import _frame, _pyplot

    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 6), dpi=120)
    ax.plot(positions[:, 0], positions[:, 1], color="0.6", lw=1, zorder=1)
    groups = (
        (True, "tab:green", "true closure"),
        (False, "tab:red", "false closure"),
        (None, "tab:blue", "closure"),
    )
    for flag, color, label in groups:
        pick = [r for r in rows if r.get("true") is flag]
        if not pick:
            continue
        q = np.array([r["query_id"] for r in pick])
        m = np.array([r["match_id"] for r in pick])
        segs = np.stack([positions[q, :2], positions[m, :2]], axis=1)
        ax.add_collection(LineCollection(list(segs), colors=color, lw=1.2, alpha=0.8, zorder=3))
        ax.plot(
            positions[q, 0], positions[q, 1], ".", color=color, ms=5, zorder=4, label=f"{label} ({q.size})"
        )
    ax.plot(*positions[0, :2], "k^", ms=7, label="start")
    _frame(ax, positions)
    ax.set(xlabel="x [m]", ylabel="y [m]", title=title)
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def _register(kiss: Any, scan: Any, previous: np.ndarray | None) -> np.ndarray:
    """KISS-ICP's pose of ``scan``; the previous one (the origin first) for a scan it cannot register."""
    try:
        return np.asarray(kiss.register(scan))
    except ScanDataError as exc:
        log.warning("%s: odometry kept the previous pose: %s", scan.source or "scan", exc)
        return np.asarray(kiss.origin if previous is None else previous)


def _run_dir(cfg: DetectConfig, out: Path | None) -> tuple[Path, bool]:
    """The results folder: ``out`` itself when given, else a new ``<output.dir>/<name>_<timestamp>``; whether it
    was made here (only such a folder is removed when the run is interrupted before writing anything)."""
    from placerec.config import config_to_yaml
    from placerec.experiment.run_folder import make_run_dir
    from placerec.io.atomic import atomic_write

    if out is None:
        return make_run_dir(cfg), True
    made = not out.exists()
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out}: not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"--out: cannot make the results folder {out}: {exc.strerror or exc}") from None
    with atomic_write(out / "config.yaml", "w") as fh:
        fh.write(config_to_yaml(cfg))
    return out, made


def detect(
    cfg: DetectConfig,
    out: str | Path | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[Path, dict[str, Any]]:
    """Run ``cfg`` (see the module docstring); returns the results folder and the summary written to
    closures.json. ``out``: the results folder itself (default: a new one under ``cfg.output.dir``).
    Everything that can be checked (pipeline, threshold, sequence) is checked before a folder is made."""
    from placerec.config import experiment_preprocess
    from placerec.experiment.run_folder import finite_or_null, interruptible, json_default
    from placerec.io.atomic import atomic_write
    from placerec.loop_closure import LoopClosureDetector
    from placerec.preprocess import preprocess_scan

    threshold = _check_pipeline(cfg)
    seq = _open(cfg)
    if cfg.name == "detect":
        cfg = cfg.model_copy(update={"name": f"detect_{seq.name}"})
    n = len(seq)
    detector = LoopClosureDetector.for_pipeline(
        cfg.pipeline,
        threshold=threshold,
        exclusion_frames=exclusion_frames(cfg.exclusion_frames, n),
        exclusion_seconds=cfg.exclusion_seconds,
        exclusion_metres=cfg.exclusion_metres,
    )
    truth = seq.poses
    kiss = None
    keyframed = isinstance(seq, KeyframeSequence)  # then the odometry is known: the keyframes' poses
    keyframe_poses = seq.keyframe_poses if keyframed else None
    if cfg.odometry == "kiss-icp" and not keyframed:
        from placerec.slam.odometry import KissIcpOdometry

        kiss = KissIcpOdometry(origin=None if truth is None else truth[0])
    stamps = None if seq.timestamps is None else np.asarray(seq.timestamps, np.float64)
    run, made = _run_dir(cfg, None if out is None else Path(out))
    with interruptible(run) if made else nullcontext(run):
        pre = experiment_preprocess()
        poses = np.empty((n, 4, 4)) if kiss is not None or truth is not None or keyframed else None
        times: list[float | None] = []
        files: list[str | None] = []
        skipped: list[int] = []
        queried = 0
        for i in range(n):
            raw = seq[i]
            t = float(stamps[i]) if stamps is not None else raw.timestamp
            times.append(None if t is None else float(t))
            files.append(_file_name(raw.source))
            pose = None
            if poses is not None:
                if keyframe_poses is not None:
                    poses[i] = keyframe_poses[i]
                else:
                    poses[i] = truth[i] if kiss is None else _register(kiss, raw, poses[i - 1] if i else None)
                pose = poses[i]
            ts = None if stamps is None else float(stamps[i])
            try:
                scan = raw if keyframed else preprocess_scan(raw, pre, keep_organized=True)  # keyframes: done
                detector.process(scan, pose=pose, timestamp=ts)
                queried += detector.last_max_id >= 0
            except ScanDataError as exc:  # a blank or tiny scan: no place, but it keeps its frame number
                log.warning("scan %d (%s) skipped: %s", i, raw.source or seq.name, exc)
                detector.skip(pose=pose, timestamp=ts)
                skipped.append(i)
            if progress is not None:
                progress(i + 1, n)
        rows = [_row(c, times, files) for c in detector.closures]
        scored = None
        if truth is not None:
            from placerec.eval.ground_truth import loop_ground_truth

            gt = loop_ground_truth(truth, cfg.gt_distance, exclusion=detector.exclusion, timestamps=stamps)
            q = np.array([r["query_id"] for r in rows], np.int64)
            m = np.array([r["match_id"] for r in rows], np.int64)
            true = gt.is_true_match(q, m) if rows else np.zeros(0, bool)
            for r, ok in zip(rows, true, strict=True):
                r["true"] = bool(ok)
            found = {int(x) for x in q[true]}
            scored = {
                "gt_distance": cfg.gt_distance,
                "n_true": int(true.sum()),
                "n_false": int((~true).sum()),
                "precision": float(true.mean()) if rows else None,
                "n_revisits": gt.n_revisits,
                "revisits_found": len(found),
            }
        summary: dict[str, Any] = {
            "sequence": seq.name,
            "source": cfg.source,
            "pipeline": cfg.pipeline,
            "threshold": threshold,
            "exclusion": detector.exclusion.model_dump(),
            "n_scans": n,
            "n_queried": int(queried),
            "skipped": skipped,
            "poses": "kiss-icp"
            if cfg.odometry == "kiss-icp"
            else "ground truth"
            if truth is not None
            else None,
            "keyframes": seq.params.model_dump(mode="json") if keyframed else None,
            "n_closures": len(rows),
            "scored": scored,
            "closures": rows,
        }
        _write_csv(run / "closures.csv", rows)
        with atomic_write(run / "closures.json", "w") as fh:
            json.dump(finite_or_null(summary), fh, indent=1, default=json_default, allow_nan=False)
        title = f"{seq.name}: {cfg.pipeline}"
        if poses is not None:
            title += " (path: KISS-ICP)" if cfg.odometry == "kiss-icp" else ""
            summary["figure"] = str(_plot(run / "closures.png", poses[:, :3, 3], rows, title))
        else:
            summary["figure"] = str(_plot_ids(run / "closures.png", n, rows, title))
        return run, summary


def exclusion_frames(given: int | None, n_scans: int) -> int:
    """The exclusion window in frames: ``given``, else the detector's default (`DEFAULT_EXCLUSION_FRAMES`) or,
    for a sequence of fewer than twice that, half its scans (at least 1): a handful of scans is still queried."""
    if given is not None:
        return given
    return min(DEFAULT_EXCLUSION_FRAMES, max(1, n_scans // 2))


def _plot_ids(path: Path, n_scans: int, rows: list[dict[str, Any]], title: str) -> Path:
    """The closures as (query, match) scan indices, for a sequence without poses."""
    from placerec.experiment.figures import _pyplot

    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5, 5), dpi=120)
    ax.plot([0, n_scans - 1], [0, n_scans - 1], color="0.8", lw=1, zorder=1, label="query = match")
    if rows:
        q = [r["query_id"] for r in rows]
        m = [r["match_id"] for r in rows]
        ax.scatter(
            q, m, s=14, c=[r["score"] for r in rows], cmap="viridis", zorder=3, label=f"closure ({len(rows)})"
        )
    ax.set(xlim=(-0.5, n_scans - 0.5), ylim=(-0.5, n_scans - 0.5), xlabel="query scan", ylabel="matched scan")
    ax.set_title(f"{title} (no poses: scan indices)", fontsize=9)
    ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}{'' if n == 1 else 's'}"


def summary_lines(run: Path, summary: dict[str, Any], rows: int = SUMMARY_ROWS) -> list[str]:
    """The console summary of a `detect` run (lines of at most 100 characters)."""
    s = summary
    ex = s["exclusion"]
    window = (
        ", ".join(
            f"{v:g} {unit}"
            for v, unit in ((ex["frames"], "frames"), (ex["seconds"], "s"), (ex["metres"], "m"))
            if v is not None
        )
        or "none"
    )
    lines = [
        f"{s['sequence'][:60]}: {_count(s['n_scans'], 'scan')} ({s['n_queried']} queried), "
        f"{_count(s['n_closures'], 'closure')}",
        f"pipeline {s['pipeline']}, threshold {s['threshold']:g}, exclusion window {window}",
    ]
    if s["skipped"]:
        lines.append(f"{len(s['skipped'])} scans skipped (no place in them): see the log (-v)")
    if s["n_queried"] == 0:
        lines.append(f"nothing queried: {s['n_scans']} scans, none outside the exclusion window")
        lines.append("(a smaller --exclusion-frames queries more scans)")
    if s["closures"]:
        header = f"{'query':>6} {'match':>6} {'score':>6} {'inl':>4} {'x':>7} {'y':>7} {'z':>6} {'yaw':>7}"
        scored = s["scored"] is not None
        lines.append(header + ("  true" if scored else "") + "  files")
        for r in s["closures"][:rows]:
            pose = (
                f"{r['x']:7.2f} {r['y']:7.2f} {r['z']:6.2f} {r['yaw']:7.1f}"
                if r["T_match_query"] is not None
                else f"{'-':>7} {'-':>7} {'-':>6} {'-':>7}"
            )
            inl = "-" if r["inliers"] is None else str(r["inliers"])
            line = f"{r['query_id']:>6} {r['match_id']:>6} {r['score']:6.3f} {inl:>4} {pose}"
            if scored:
                line += "  " + ("yes " if r["true"] else "no  ")
            names = f"{r['query_file'] or ''} -> {r['match_file'] or ''}" if r["query_file"] else ""
            line = f"{line}  {names}".rstrip()
            lines.append(line if len(line) <= 100 else line[:97] + "...")
        if len(s["closures"]) > rows:
            lines.append(f"... and {len(s['closures']) - rows} more")
    sc = s["scored"]
    if sc is None:
        lines.append("no ground-truth poses: closures not scored (give --poses FILE to score them)")
    else:
        prec = "-" if sc["precision"] is None else f"{sc['precision']:.2f}"
        lines.append(
            f"ground truth (within {sc['gt_distance']:g} m): precision {prec} ({sc['n_true']} true, "
            f"{sc['n_false']} false); revisits found {sc['revisits_found']} of {sc['n_revisits']}"
        )
    files = "closures.csv, closures.json" + (", closures.png" if "figure" in s else "")
    lines.append(f"wrote {files} in:")
    lines.append(f"  {run}")
    return lines
