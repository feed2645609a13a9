"""Figures of intensity-image formation for docs/intensity_images.md.

* HDL-64 (simulated): uniform eq. 2 projection (empty rows), after empty-row interpolation, per-beam projection;
* HDL-64 (real KITTI 00 frame): uniform projection, row interpolation, row + vertical-hole interpolation;
* OS1-64 (real MulRan revisit pair, organised 64 x 1024): both images with ORB-HBST matches that agree on one yaw.

    .venv/bin/python tools/make_image_figures.py   # writes docs/figures/images_*.png
"""

from __future__ import annotations

from pathlib import Path

import cv2
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from placerec.image import ImageParams, make_image  # noqa: E402
from placerec.io import read_scan  # noqa: E402
from placerec.pipelines.visual import shift_consensus  # noqa: E402
from placerec.recognizer import make_pipeline  # noqa: E402
from placerec.sim import SimulatedSequence  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT.parent / "shared" / "data" / "real"
OUT = ROOT / "docs" / "figures"


def _panel(images: list[tuple[str, np.ndarray]], path: Path, crop: int | None = 512) -> None:
    fig, axes = plt.subplots(len(images), 1, figsize=(12, 1.35 * len(images) + 0.3), dpi=110)
    for ax, (title, img) in zip(np.atleast_1d(axes), images, strict=True):
        ax.imshow(
            img[:, :crop] if crop else img,
            cmap="gray",
            vmin=0,
            vmax=255,
            aspect="auto",
            interpolation="nearest",
        )
        ax.set_title(title, fontsize=9, loc="left")
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    print(f"wrote {path.relative_to(ROOT)}")


def hdl64_simulated() -> None:
    scan = SimulatedSequence(world="town", sensor="hdl64", n_scans=30, seed=1)[25]
    base = dict(width=1024, height=64)
    raw = make_image(scan, ImageParams(mode="uniform", fill_empty_rows=False, **base))
    filled = make_image(scan, ImageParams(mode="uniform", **base))
    beam = make_image(scan, ImageParams(mode="per-beam", width=1024))
    _panel(
        [
            (
                f"simulated HDL-64, uniform projection (eq. 2): {int((~raw.valid).all(axis=1).sum())} empty rows",
                raw.image,
            ),
            (f"after empty-row interpolation ({int(filled.filled_rows.sum())} rows filled)", filled.image),
            ("per-beam projection from the ring index (no empty rows by construction)", beam.image),
        ],
        OUT / "images_hdl64_simulated.png",
    )


def hdl64_kitti() -> None:
    scan = read_scan(REAL / "kitti00_frames" / "000094.bin")
    base = dict(mode="uniform", width=1024, height=64, fov_up_deg=3.0, fov_down_deg=25.0)
    raw = make_image(scan, ImageParams(fill_empty_rows=False, fill_holes_max_gap=0, **base))
    rows = make_image(scan, ImageParams(fill_holes_max_gap=0, **base))
    holes = make_image(scan, ImageParams(**base))  # the default for uniform images: fill_holes_max_gap=2
    _panel(
        [
            (
                "real KITTI 00 frame 94 (HDL-64), uniform projection: partly empty rows from the uneven beams",
                raw.image,
            ),
            (
                f"paper's empty-row interpolation ({int(rows.filled_rows.sum())} whole rows below 5 % fill)",
                rows.image,
            ),
            (
                "plus vertical interpolation of holes up to 2 rows (placerec's default for uniform images)",
                holes.image,
            ),
        ],
        OUT / "images_hdl64_kitti.png",
    )


def os1_pair() -> None:
    layout = (64, 1024, "column-major")
    a = read_scan(REAL / "ouster_os1_64_revisit_pair" / "32line_1.bin", organized=True, layout=layout)
    b = read_scan(REAL / "ouster_os1_64_revisit_pair" / "32line_2.bin", organized=True, layout=layout)
    rec = make_pipeline("orb-hbst")
    da, db = rec.describe(a), rec.describe(b)
    rec.add_description(0, da)
    result = rec.tree.match(db["descriptors"])
    cands = rec.query_description(db, k=1)
    ia, ib = make_image(a, rec.params.image).image, make_image(b, rec.params.image).image
    kq, kr = db["keypoints"][result.query_idx], da["keypoints"][result.keypoint_idx]
    inl, shift = shift_consensus(kq[:, 0], kq[:, 1], kr[:, 0], kr[:, 1], 1024, 8, 4)
    d = np.mod(kq[:, 0] - kr[:, 0] - shift + 512, 1024) - 512
    good = (np.abs(d) <= 8.5) & (np.abs(kq[:, 1] - kr[:, 1]) <= 4)
    stacked = cv2.cvtColor(np.vstack([ia, np.full((8, 1024), 255, np.uint8), ib]), cv2.COLOR_GRAY2RGB)
    for (uq, vq), (ur, vr), ok in zip(kq, kr, good, strict=True):
        color = (40, 200, 40) if ok else (230, 60, 60)
        cv2.line(stacked, (int(ur), int(vr)), (int(uq), int(vq) + 72), color, 1, cv2.LINE_AA)
    score = cands[0].score if cands else 0.0
    fig, ax = plt.subplots(figsize=(14, 2.6), dpi=110)
    ax.imshow(stacked, aspect="auto", interpolation="nearest")
    ax.set_title(
        f"real OS1-64 revisit pair (MulRan), organised 64 x 1024: {len(result)} HBST matches, {inl} agree on a yaw of "
        f"{360 * shift / 1024:.1f} deg (green), score {score:.2f}",
        fontsize=9,
        loc="left",
    )
    ax.axis("off")
    fig.tight_layout()
    path = OUT / "images_os1_64_pair_matches.png"
    fig.savefig(path)
    plt.close(fig)
    print(f"wrote {path.relative_to(ROOT)}")


def main() -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    hdl64_simulated()
    if REAL.is_dir():
        hdl64_kitti()
        os1_pair()
    else:
        print(f"skipping the real-data figures: {REAL} not found")


if __name__ == "__main__":
    main()
