"""Figures of an experiment: PR curves, trajectories with loop closures, stage timings (matplotlib, Agg).

Every figure is drawn for any number of scans, queries or candidates, none included (an empty or one-point
trajectory gets a 2 m frame around what there is)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "plot_pr_curves",
    "plot_trajectory_closures",
    "plot_timing",
    "plot_localization",
    "plot_slam_trajectories",
    "plot_feature_matches",
    "plot_heatmap",
]


#: PNG compression of the figures: zlib level 1 writes them ~4x faster than matplotlib's default (6) for files
#: ~1.3x larger, which matters for a report's dozens of evidence figures
PNG_OPTIONS = {"compress_level": 1}


def _save(fig: Any, path: Path) -> Path:
    """Lay out, write and close a figure; returns its path."""
    fig.tight_layout()
    fig.savefig(path, pil_kwargs=PNG_OPTIONS)
    _pyplot().close(fig)
    return path


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _frame(ax: Any, *points: np.ndarray) -> None:
    """Square, equal-aspect limits around ``points`` (N, >=2) with a margin of at least 1 m, so that an empty or
    one-point trajectory does not give a singular frame."""
    xy = np.concatenate([np.asarray(p, np.float64).reshape(-1, p.shape[-1])[:, :2] for p in points])
    xy = xy[np.isfinite(xy).all(axis=1)]
    lo, hi = (xy.min(axis=0), xy.max(axis=0)) if len(xy) else (np.zeros(2), np.zeros(2))
    centre, half = (lo + hi) / 2, 0.525 * float(np.max(hi - lo)) + 1.0
    ax.set(xlim=(centre[0] - half, centre[0] + half), ylim=(centre[1] - half, centre[1] + half))
    ax.set_aspect("equal", adjustable="box")


def plot_pr_curves(curves: dict[str, dict[str, Any]], path: Path, title: str = "Precision-recall") -> Path:
    """``curves``: label -> {"precision": array, "recall": array, "max_f1": float}."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 4.5), dpi=120)
    for label, c in curves.items():
        ax.plot(c["recall"], c["precision"], lw=1.8, label=f"{label} (max F1 {c['max_f1']:.3f})")
        if c.get("best") is not None:
            ax.plot([c["best"][0]], [c["best"][1]], "o", color=ax.lines[-1].get_color(), ms=5)
    ax.set(xlabel="recall", ylabel="precision", xlim=(0, 1.02), ylim=(0, 1.02), title=title)
    return _finish(fig, ax, path, loc="lower left")


def plot_trajectory_closures(
    positions: np.ndarray,
    query_ids: np.ndarray,
    match_ids: np.ndarray,
    correct: np.ndarray,
    accepted: np.ndarray,
    revisit: np.ndarray,
    path: Path,
    title: str,
) -> Path:
    """Trajectory (x, y) with accepted closures drawn: true in green, false in red; missed revisits in orange."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 6), dpi=120)
    ax.plot(positions[:, 0], positions[:, 1], color="0.6", lw=1, zorder=1)
    ok = accepted & correct
    bad = accepted & ~correct
    missed = revisit & ~ok
    for mask, color, label in ((ok, "tab:green", "true closure"), (bad, "tab:red", "false closure")):
        q, m = query_ids[mask], match_ids[mask]
        if q.size:
            segs = np.stack([positions[q, :2], positions[m, :2]], axis=1)
            from matplotlib.collections import LineCollection

            ax.add_collection(LineCollection(list(segs), colors=color, lw=1.2, alpha=0.8, zorder=3))
            ax.plot(
                positions[q, 0],
                positions[q, 1],
                ".",
                color=color,
                ms=4,
                zorder=4,
                label=f"{label} ({q.size})",
            )
    if missed.any():
        q = query_ids[missed]
        ax.plot(
            positions[q, 0],
            positions[q, 1],
            "x",
            color="tab:orange",
            ms=3,
            zorder=2,
            label=f"missed revisit ({q.size})",
        )
    if len(positions):
        ax.plot(*positions[0, :2], "k^", ms=7, label="start")
    return _finish_map(fig, ax, path, title, (positions,), loc="best")


def plot_timing(
    timing: dict[str, dict[str, float]], path: Path, preprocess_ms: float | None = None, includes: str = ""
) -> Path:
    """Stacked bars of mean ms per stage; ``timing``: label -> {stage: mean_ms}, the stages of the time per scan
    (`placerec.experiment.runner.PipelineRecord.stage_means_ms`), so a bar's total is the table's ms/scan mean;
    ``includes`` says what that time includes, ``preprocess_ms`` the shared preprocessing it leaves out."""
    plt = _pyplot()
    labels = list(timing)
    stages = [
        s
        for s in ("preprocess", "describe", "query", "insert", "verify")
        if any(timing[lab].get(s, 0) for lab in labels)
    ]
    fig, ax = plt.subplots(figsize=(max(4.5, 1.3 * len(labels) + 2), 4), dpi=120)
    x = np.arange(len(labels))
    bottom = np.zeros(len(labels))
    for stage in stages:
        vals = np.array([timing[lab].get(stage, 0.0) for lab in labels])
        ax.bar(x, vals, bottom=bottom, label=stage)
        bottom += vals
    for col, total in zip(x, bottom, strict=True):
        ax.text(col, total, f"{total:.1f}", ha="center", va="bottom", fontsize=8)
    ax.set_xticks(x, labels, rotation=20, ha="right")
    title = "Time per scan (the table's ms/scan mean)"
    if includes:
        title += f"\n{includes}"
    if preprocess_ms is not None and np.isfinite(preprocess_ms):
        title += f": {preprocess_ms:.1f} ms"
    ax.set(ylabel="mean time per scan [ms]", ylim=(0, max(1.0, 1.1 * bottom.max(initial=0))))
    ax.set_title(title, fontsize=9)
    _legend(ax, fontsize=8)
    return _save(fig, path)


def plot_localization(
    map_positions: np.ndarray,
    query_positions: np.ndarray,
    estimates: np.ndarray,
    success: np.ndarray,
    path: Path,
    title: str,
    answered: np.ndarray | None = None,
) -> Path:
    """Map trajectory, query positions and estimates: green localised (within the success distance), red answered
    wrongly (a line to the answer), grey no answer (``answered`` False; every query answered when None)."""
    from matplotlib.collections import LineCollection

    plt = _pyplot()
    success = np.asarray(success, bool)
    answered = np.ones_like(success) if answered is None else np.asarray(answered, bool)
    fig, ax = plt.subplots(figsize=(6, 6), dpi=120)
    ax.plot(map_positions[:, 0], map_positions[:, 1], color="0.6", lw=1, label="map route")
    classes = (
        (success, "tab:green", "o", "localised"),
        (answered & ~success, "tab:red", "o", "wrong answer"),
        (~answered, "0.3", "x", "no answer"),
    )
    for mask, color, marker, label in classes:
        if mask.any():
            if label != "no answer":
                segs = np.stack([query_positions[mask, :2], estimates[mask, :2]], axis=1)
                ax.add_collection(LineCollection(list(segs), colors=color, lw=1))
            ax.plot(
                query_positions[mask, 0],
                query_positions[mask, 1],
                marker,
                color=color,
                ms=3 if marker == "o" else 4,
                label=f"{label} ({mask.sum()})",
            )
    return _finish_map(fig, ax, path, title, (map_positions, query_positions, estimates))


def _finish(fig: Any, ax: Any, path: Path, **legend: Any) -> Path:
    """Grid, legend (small font) and save: the last steps of every plot."""
    ax.grid(alpha=0.3)
    _legend(ax, fontsize=8, **legend)
    return _save(fig, path)


def _finish_map(
    fig: Any, ax: Any, path: Path, title: str, points: tuple[np.ndarray, ...], **legend: Any
) -> Path:
    """`_finish` for a top view in metres, framed around ``points``."""
    ax.set(xlabel="x [m]", ylabel="y [m]", title=title)
    _frame(ax, *points)
    return _finish(fig, ax, path, **legend)


def _legend(ax: Any, **kwargs: Any) -> None:
    """A legend when something is labelled (matplotlib warns on an empty one)."""
    if ax.get_legend_handles_labels()[0]:
        ax.legend(**kwargs)


def plot_slam_trajectories(
    trajectories: dict[str, np.ndarray],
    loops: np.ndarray,
    loop_ok: np.ndarray,
    path: Path,
    title: str,
    loops_on: str | None = None,
) -> Path:
    """Trajectories (x, y) of a SLAM run (``label -> (N, 3) positions``, drawn in order: e.g. ground truth,
    odometry, optimised) with its loop edges (``loops`` (L, 2) scan ids) drawn on the trajectory ``loops_on``
    (default: the last): green where ``loop_ok``, red where not."""
    from matplotlib.collections import LineCollection

    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 6.5), dpi=120)
    styles = {0: ("0.2", "--", 1.0), 1: ("tab:orange", "-", 1.2), 2: ("tab:blue", "-", 1.4)}
    for k, (label, pos) in enumerate(trajectories.items()):
        color, ls, lw = styles.get(k, (None, "-", 1.2))
        ax.plot(pos[:, 0], pos[:, 1], ls, color=color, lw=lw, label=label, zorder=2 + k)
    base = trajectories[loops_on] if loops_on else list(trajectories.values())[-1]
    loops = np.asarray(loops, dtype=np.int64).reshape(-1, 2)
    ok = np.asarray(loop_ok, dtype=bool).reshape(-1)
    for mask, color, label in ((ok, "tab:green", "loop edge"), (~ok, "tab:red", "false loop edge")):
        if mask.any():
            segs = np.stack([base[loops[mask, 0], :2], base[loops[mask, 1], :2]], axis=1)
            ax.add_collection(LineCollection(list(segs), colors=color, lw=0.9, alpha=0.7, zorder=6))
            ax.plot([], [], color=color, lw=0.9, label=f"{label} ({int(mask.sum())})")
    return _finish_map(fig, ax, path, title, tuple(trajectories.values()), loc="best")


def plot_feature_matches(
    image_a: np.ndarray,
    image_b: np.ndarray,
    matches: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]],
    path: Path,
    title: str = "",
) -> Path:
    """One panel per extractor: image A above image B, each mutual match a line from its keypoint in A
    (``uv_a`` (M, 2)) to its keypoint in B (``uv_b``), green where ``correct`` (M,) is true, red where not.
    ``matches``: ``{name: (uv_a, uv_b, correct)}``."""
    plt = _pyplot()
    h_a, w = image_a.shape
    gap = max(4, h_a // 4)
    canvas = np.full((h_a + gap + image_b.shape[0], max(w, image_b.shape[1])), 255, np.uint8)
    canvas[:h_a, :w] = image_a
    canvas[h_a + gap :, : image_b.shape[1]] = image_b
    n = max(len(matches), 1)
    fig, axes = plt.subplots(n, 1, figsize=(14, 1.2 + 1.9 * n * canvas.shape[0] / 140), squeeze=False)
    for ax, (name, (uv_a, uv_b, correct)) in zip(axes[:, 0], matches.items(), strict=False):
        ax.imshow(canvas, cmap="gray", aspect="auto", interpolation="nearest")
        for ok, colour in ((False, "#d62728"), (True, "#2ca02c")):
            sel = np.flatnonzero(np.asarray(correct, bool) == ok)
            for k in sel:
                ax.plot([uv_a[k, 0], uv_b[k, 0]], [uv_a[k, 1], uv_b[k, 1] + h_a + gap], color=colour, lw=0.6)
        ax.set_title(f"{name}: {int(np.sum(correct))} correct of {len(correct)} mutual matches", fontsize=9)
        ax.set_axis_off()
    if title:
        fig.suptitle(title, fontsize=10)
    return _save(fig, path)


def plot_heatmap(
    values: np.ndarray,
    rows: list[str],
    columns: list[str],
    path: Path,
    title: str,
    marks: np.ndarray | None = None,
) -> Path:
    """A (rows x columns) heatmap of figures in [0, 1] with each value written in its cell (NaN: blank, ``-``);
    ``marks`` (same shape, bool) draws an ``x`` over the cells to flag (e.g. a false closure accepted there)."""
    plt = _pyplot()
    v = np.asarray(values, dtype=np.float64).reshape(len(rows), len(columns))
    fig, ax = plt.subplots(
        figsize=(1.2 + 0.55 * max(len(columns), 1), 1.4 + 0.45 * max(len(rows), 1)), dpi=110
    )
    im = ax.imshow(np.ma.masked_invalid(v), cmap="viridis", vmin=0.0, vmax=1.0, aspect="auto")
    for i in range(v.shape[0]):
        for j in range(v.shape[1]):
            text = "-" if not np.isfinite(v[i, j]) else f"{v[i, j]:.2f}"
            dark = np.isfinite(v[i, j]) and v[i, j] < 0.6
            ax.text(j, i, text, ha="center", va="center", fontsize=7, color="white" if dark else "black")
            if marks is not None and marks[i][j]:
                ax.plot([j - 0.45, j + 0.45], [i - 0.45, i + 0.45], color="red", lw=1.2)
                ax.plot([j - 0.45, j + 0.45], [i + 0.45, i - 0.45], color="red", lw=1.2)
    ax.set_xticks(range(len(columns)), columns, rotation=60, ha="right", fontsize=7)
    ax.set_yticks(range(len(rows)), rows, fontsize=8)
    ax.set_title(title, fontsize=9)
    fig.colorbar(im, ax=ax, fraction=0.03, pad=0.02)
    return _save(fig, path)
