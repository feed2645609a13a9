"""Time every registered feature extractor (Table I defaults, wrap padding on) on 64 x 1024 and 64 x 2048 images.

Images: a deterministic synthetic texture (smoothed noise, filled shapes, letters) of each size, and, when the
real KITTI samples in ``../shared/data/real`` are present, the intensity image of a KITTI scan made with
`placerec.image.make_image` (uniform cylindrical projection, empty rows and single holes filled).
For our SURF the script also times its stages on the 64 x 1024 texture (detector; orientation + descriptor of
the 300 kept keypoints). Times are wall-clock per call after a warm-up: median and minimum of ``--repeats``.
The last line printed is one JSON object with the headline figures.

Example::

    python tools/bench_features.py --repeats 15
"""

from __future__ import annotations

import argparse
import json
import os
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from placerec.features import available_extractors, make_extractor
from placerec.features.surf import SURF
from placerec.features.synthetic import textured_image

REPO = Path(__file__).resolve().parents[1]
KITTI_FRAME = REPO.parent / "shared" / "data" / "real" / "kitti00_frames" / "000094.bin"
SIZES = ((64, 1024), (64, 2048))


def kitti_image(width: int) -> np.ndarray | None:
    """8-bit intensity image of a real KITTI scan, or None when the sample data are absent."""
    if not KITTI_FRAME.is_file():
        return None
    from placerec.image import ImageParams, make_image
    from placerec.io.kitti import read_kitti_bin

    params = ImageParams(mode="uniform", width=width, height=64, fill_holes_max_gap=2)
    return make_image(read_kitti_bin(KITTI_FRAME), params).image


def timeit(fn: Callable[[], object], repeats: int) -> tuple[float, float]:
    """(median, min) milliseconds per call after two warm-up calls."""
    fn()
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3), float(np.min(times) * 1e3)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--repeats", type=int, default=15, help="timed calls per extractor and image (default 15)"
    )
    args = ap.parse_args()

    images = {f"texture {h}x{w}": textured_image(h, w) for h, w in SIZES}
    for _, w in SIZES:
        img = kitti_image(w)
        if img is not None:
            images[f"kitti {img.shape[0]}x{img.shape[1]}"] = img

    print(f"OpenCV {cv2.__version__}, {os.cpu_count()} CPUs; median / min ms per extract() call")
    print(f"{'extractor':<10} {'image':<18} {'features':>8} {'median ms':>10} {'min ms':>8}")
    headline: dict[str, object] = {"opencv": cv2.__version__, "cpus": os.cpu_count(), "repeats": args.repeats}
    ms: dict[str, dict[str, float]] = {}
    counts: dict[str, dict[str, int]] = {}
    for name in available_extractors():
        ex = make_extractor(name)
        for label, img in images.items():
            n = len(ex.extract(img))
            med, best = timeit(lambda ex=ex, img=img: ex.extract(img), args.repeats)
            print(f"{name:<10} {label:<18} {n:>8} {med:>10.1f} {best:>8.1f}")
            ms.setdefault(name, {})[label] = round(med, 2)
            counts.setdefault(name, {})[label] = n

    # SURF stages on the 64 x 1024 texture (no wrap padding here: the bare detector and descriptor)
    surf = SURF()
    img = images["texture 64x1024"]
    det = surf.detect_arrays(img)
    top = np.argsort(-det.response, kind="stable")[:300]
    xy, size = det.xy[top], det.size[top]
    stages = {
        "detect": timeit(lambda: surf.detect_arrays(img), args.repeats)[0],
        "orient+describe_300": timeit(lambda: surf.describe_arrays(img, xy, size), args.repeats)[0],
        "detect_and_compute": timeit(lambda: surf.detect_and_compute(img), args.repeats)[0],
    }
    print(
        f"SURF stages on texture 64x1024 ({len(det)} keypoints detected, 300 described): "
        + ", ".join(f"{k} {v:.1f} ms" for k, v in stages.items())
    )
    headline.update(
        {"median_ms": ms, "features": counts, "surf_stages_ms": {k: round(v, 2) for k, v in stages.items()}}
    )
    print(json.dumps(headline, separators=(",", ":")))


if __name__ == "__main__":
    main()
