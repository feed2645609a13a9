"""Make the figures of ``docs/sensors.md`` (``docs/figures/sensors_*.png``) and print the numbers quoted there.

Usage::

    python tools/make_sensor_figures.py [--out docs/figures]

* ``sensors_images.png``: one simulated scan of every sensor preset at the same place of the town (tuning world,
  seed 0), as the intensity image the 2D pipelines see (`placerec.image.make_image`, ``auto`` mode: per-beam for
  the spinning sensors, spherical for the others), and for the non-spinning sensors the image of a 0.5 s keyframe.
* ``sensors_coverage.png``: the fraction of the field of view (0.5 deg cells) a non-repetitive or solid-state
  sensor has covered after integrating ``t`` seconds, standing still (the scan pattern alone) — why a single Livox
  frame is too sparse for a place descriptor and a keyframe is not.
* with ``--sweep FILE`` (the ``tools/sweep_keyframes.py`` JSON), ``sensors_recall_vs_keyframe.png``: recall at the
  fixed threshold against keyframe length on the tuning cells.

Ends with one JSON line of the coverage figures and image sizes.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from placerec.image import ImageParams, make_image  # noqa: E402
from placerec.keyframes import KeyframeParams, KeyframeSequence  # noqa: E402
from placerec.sim import SimulatedSequence, frame_rays, get_sensor, sensor_names  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CELL_DEG = 0.5
NON_SPINNING = ("avia", "mid360", "e1r")


def coverage(sensor: str, seconds: list[float]) -> list[float]:
    """Fraction of the sensor's field of view (CELL_DEG cells) hit by its rays within each integration time."""
    model = get_sensor(sensor)
    info = model.to_sensor_info()
    h = info.horizontal_fov_deg or 360.0
    up, down = info.vertical_fov_deg or (0.0, 0.0)
    n_az, n_el = int(np.ceil(h / CELL_DEG)), int(np.ceil((up + down) / CELL_DEG))
    hit = np.zeros(n_az * n_el, bool)
    out, frame, t_done = [], 0, 0.0
    period = 1.0 / model.rotation_hz
    for t in seconds:
        while t_done + period <= t + 1e-9:
            d = frame_rays(model, frame).directions.astype(np.float64)
            az = np.degrees(np.arctan2(d[:, 1], d[:, 0]))
            el = np.degrees(np.arcsin(np.clip(d[:, 2], -1, 1)))
            u = np.floor((0.5 * h - az) / CELL_DEG).astype(np.int64)
            v = np.floor((up - el) / CELL_DEG).astype(np.int64)
            ok = (u >= 0) & (u < n_az) & (v >= 0) & (v < n_el)
            hit[v[ok] * n_az + u[ok]] = True
            frame += 1
            t_done += period
        out.append(float(hit.mean()))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=str(ROOT / "docs" / "figures"))
    ap.add_argument("--sweep", default=None, help="tools/sweep_keyframes.py JSON for the recall figure")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    summary: dict = {"tool": "make_sensor_figures", "coverage": {}, "image_shapes": {}}

    seconds = [0.1, 0.2, 0.3, 0.5, 0.7, 1.0, 1.5, 2.0]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    for name in NON_SPINNING:
        cov = coverage(name, seconds)
        summary["coverage"][name] = dict(
            zip([str(s) for s in seconds], [round(c, 3) for c in cov], strict=True)
        )
        ax.plot(seconds, cov, marker="o", label=name)
    ax.set_xlabel("integration time [s]")
    ax.set_ylabel(f"field of view covered ({CELL_DEG} deg cells)")
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "sensors_coverage.png", dpi=120)
    plt.close(fig)

    names = sensor_names()
    rows = len(names) + len(NON_SPINNING)
    fig, axes = plt.subplots(rows, 1, figsize=(10, 1.25 * rows + 1))
    k = 0
    for name in names:
        rate = 10.0 if name in NON_SPINNING else None
        seq = SimulatedSequence(world="town", sensor=name, seed=0, n_scans=40, rate_hz=rate,
                                sweep_motion=name in NON_SPINNING)  # fmt: skip
        scan = seq[len(seq) - 1]
        img = make_image(scan, ImageParams())
        summary["image_shapes"][name] = list(img.shape)
        axes[k].imshow(img.image, cmap="gray", aspect="auto", interpolation="nearest")
        axes[k].set_title(f"{name}: one scan, {img.mode} image {img.shape[0]} x {img.shape[1]}", fontsize=8)
        axes[k].axis("off")
        k += 1
        if name in NON_SPINNING:
            kf = KeyframeSequence(seq, KeyframeParams(seconds=0.5), odometry_poses=seq.poses)
            kimg = make_image(kf[len(kf) - 1], ImageParams())
            summary["image_shapes"][f"{name}_keyframe_0.5s"] = list(kimg.shape)
            summary["coverage"][f"{name}_valid_pixels_scan"] = round(float(img.valid.mean()), 3)
            summary["coverage"][f"{name}_valid_pixels_keyframe"] = round(float(kimg.valid.mean()), 3)
            axes[k].imshow(kimg.image, cmap="gray", aspect="auto", interpolation="nearest")
            axes[k].set_title(f"{name}: keyframe of 0.5 s, {kimg.shape[0]} x {kimg.shape[1]}", fontsize=8)
            axes[k].axis("off")
            k += 1
    fig.tight_layout()
    fig.savefig(out / "sensors_images.png", dpi=110)
    plt.close(fig)

    if args.sweep:
        sweep = json.loads(Path(args.sweep).read_text().strip().splitlines()[-1])
        fig, ax = plt.subplots(figsize=(6, 3.5))
        for key, curve in sweep["recall"].items():
            xs = sorted(float(x) for x in curve)
            ax.plot(xs, [curve[str(x) if str(x) in curve else f"{x:g}"] for x in xs], marker="o", label=key)
        ax.set_xlabel("keyframe length [s]")
        ax.set_ylabel("recall at the fixed threshold")
        ax.set_ylim(0, 1.02)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / "sensors_recall_vs_keyframe.png", dpi=120)
        plt.close(fig)
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
