"""Row filling of eq. 2 (uniform) intensity images on real KITTI HDL-64E scans: which option leaves streaks.

For every real KITTI frame (kitti00_frames/*.bin and kitti_raw_hdl64_sequence/*.pcd; no ring index, so the
image is the uniform eq. 2 projection) and every row-filling option, measures

* ``empty``: fraction of empty pixels in the image;
* ``holes``: fraction of pixels that are empty although their column has valid pixels within 3 rows above
  and below (gaps inside the scanned surface; the sky above the top beam is not counted);
* ``streak_rows``: rows with a larger fraction of empty pixels than both neighbours, by more than 0.05
  (a black line across the image).

    .venv/bin/python tools/eval_row_filling.py            # table, then one JSON line of headline figures
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from placerec.image import ImageParams, make_image
from placerec.io import read_scan

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"

#: option name -> image parameters (mode uniform, as for any scan without rings)
OPTIONS: dict[str, dict] = {
    "none": {"fill_empty_rows": False, "fill_holes_max_gap": 0},
    "rows 5% (paper)": {"fill_empty_rows": True, "empty_row_threshold": 0.05, "fill_holes_max_gap": 0},
    "rows 30%": {"fill_empty_rows": True, "empty_row_threshold": 0.3, "fill_holes_max_gap": 0},
    "rows 5% + holes 1": {"fill_empty_rows": True, "fill_holes_max_gap": 1},
    "rows 5% + holes 2": {"fill_empty_rows": True, "fill_holes_max_gap": 2},
    "rows 5% + holes 3": {"fill_empty_rows": True, "fill_holes_max_gap": 3},
}


def _measures(valid: np.ndarray) -> tuple[float, float, int]:
    h = valid.shape[0]
    rows = np.arange(h)[:, None]
    above = np.maximum.accumulate(np.where(valid, rows, -h), axis=0)
    below = np.minimum.accumulate(np.where(valid, rows, 2 * h)[::-1], axis=0)[::-1]
    holes = ~valid & (rows - above <= 3) & (below - rows <= 3)
    ef = 1.0 - valid.mean(axis=1)
    streaks = ef[1:-1] - np.maximum(ef[:-2], ef[2:]) > 0.05  # emptier than both neighbours
    return float(1.0 - valid.mean()), float(holes.mean()), int(streaks.sum())


def main() -> int:
    files = sorted((REAL / "kitti00_frames").glob("*.bin"))
    files += sorted((REAL / "kitti_raw_hdl64_sequence").glob("*.pcd"))
    if not files:
        print(f"no real KITTI frames under {REAL}", file=sys.stderr)
        return 1
    scans = [read_scan(f) for f in files]
    results = {}
    print(f"{len(scans)} real KITTI HDL-64E frames, uniform eq. 2 images (default size)")
    print(f"{'option':<20} {'empty':>7} {'holes':>7} {'streak rows (mean / max)':>26}")
    for name, opts in OPTIONS.items():
        params = ImageParams(mode="uniform", **opts)
        m = np.array([_measures(make_image(s, params).valid) for s in scans])
        results[name] = {
            "empty": round(float(m[:, 0].mean()), 4),
            "holes": round(float(m[:, 1].mean()), 4),
            "streak_rows_mean": round(float(m[:, 2].mean()), 2),
            "streak_rows_max": int(m[:, 2].max()),
        }
        r = results[name]
        streaks = f"{r['streak_rows_mean']:.2f} / {r['streak_rows_max']}"
        print(f"{name:<20} {r['empty']:>7.3f} {r['holes']:>7.3f} {streaks:>26}")
    default = np.array([_measures(make_image(s).valid) for s in scans])
    headline = {"empty": round(float(default[:, 0].mean()), 4), "streak_rows_max": int(default[:, 2].max())}
    print(json.dumps({"frames": len(scans), "default": headline, "options": results}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
