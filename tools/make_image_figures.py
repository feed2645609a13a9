"""Figures of intensity-image formation for docs/intensity_images.md.

* HDL-64 (simulated): uniform eq. 2 projection (empty rows), after empty-row interpolation, per-beam projection;
* HDL-64 (real KITTI 00 frame): uniform projection, row interpolation, row + vertical-hole interpolation;

    .venv/bin/python tools/make_image_figures.py   # writes docs/figures/images_*.png
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from placerec.image import ImageParams, make_image  # noqa: E402
from placerec.io import read_scan  # noqa: E402
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


def main() -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    hdl64_simulated()
    if REAL.is_dir():
        hdl64_kitti()
    else:
        print(f"skipping the real-data figures: {REAL} not found")


if __name__ == "__main__":
    main()
