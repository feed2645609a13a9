"""Spherical intensity images of keyframes (sensors that do not spin): how the empty-pixel filling and the pixel
size change the image and the ORB features it gives. TUNING data (town, seed 0): not a result.

For each non-spinning sensor of `placerec.experiment.protocol.CAPTURE`, keyframes of its tuning sequence (10 Hz
frames taken while moving, its keyframe length, de-skewed with the true poses) are projected with the spherical
mode (`placerec.image.projection`) at each ``fill_radius_px`` and ``density_points_per_pixel``; reported: the
image size, the fraction of pixels holding a point, the fraction after filling, ORB features per image, and the
fraction of a keyframe's ORB features matched (Hamming <= 40, mutual nearest, consistent in the image within 8 px
after removing the median shift) in the next keyframe: a crude repeatability on consecutive keyframes.

    .venv/bin/python tools/eval_spherical_images.py [--keyframes 30]

Ends with one JSON line.
"""

from __future__ import annotations

import argparse
import json
import time

import cv2
import numpy as np

from placerec.experiment.protocol import CAPTURE, TUNING_SEEDS
from placerec.features import make_extractor
from placerec.image import ImageParams, make_image
from placerec.keyframes import KeyframeParams, KeyframeSequence
from placerec.sim import SimulatedSequence

RADII = (0, 1, 2)
DENSITIES = (0.5, 1.0, 2.0)


def _matched_fraction(a, b) -> float:
    """Share of ``a``'s features with a mutual nearest neighbour in ``b`` consistent with the median image shift."""
    if len(a) < 5 or len(b) < 5:
        return 0.0
    bf = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
    m = [x for x in bf.match(a.descriptors, b.descriptors) if x.distance <= 40]
    if len(m) < 5:
        return 0.0
    pa = a.uv[[x.queryIdx for x in m]]
    pb = b.uv[[x.trainIdx for x in m]]
    d = pb - pa
    ok = np.linalg.norm(d - np.median(d, axis=0), axis=1) <= 8.0
    return float(ok.sum() / len(a))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--keyframes", type=int, default=30)
    args = ap.parse_args()
    orb = make_extractor("orb")
    out: dict = {"tool": "eval_spherical_images", "split": "tuning", "sensors": {}}
    print(
        f"{'sensor':7} {'fill':>4} {'pts/px':>6} {'image':>9} {'valid':>6} {'filled':>6} {'ORB':>6} {'matched':>7}"
    )
    for sensor, capture in CAPTURE.items():
        if "keyframes" not in capture:  # a spinning sensor's entry (its feature parameters only)
            continue
        t0 = time.perf_counter()
        seconds = capture["keyframes"]["seconds"]
        n_scans = int(round(args.keyframes * seconds * capture["rate_hz"])) + 2
        seq = SimulatedSequence(world="town", sensor=sensor, seed=TUNING_SEEDS[0], n_scans=n_scans,
                                rate_hz=capture["rate_hz"], sweep_motion=True)  # fmt: skip
        kfs = KeyframeSequence(seq, KeyframeParams(seconds=seconds), odometry_poses=seq.poses)
        scans = [kfs[i] for i in range(len(kfs))]
        rows = {}
        raw: dict[float, list[float]] = {}  # unfilled valid fraction per density (any radius's)
        for radius in RADII:
            for density in DENSITIES:
                params = ImageParams(
                    mode="spherical", fill_radius_px=radius, density_points_per_pixel=density
                )
                imgs = [make_image(s, params) for s in scans]
                if density not in raw:
                    unfilled = params.model_copy(update={"fill_radius_px": 0})
                    raw[density] = [
                        (im if radius == 0 else make_image(s, unfilled)).valid.mean()
                        for s, im in zip(scans, imgs, strict=True)
                    ]
                feats = [orb.extract(im.image, (im.valid * 255).astype(np.uint8)) for im in imgs]
                matched = [_matched_fraction(feats[i], feats[i + 1]) for i in range(len(feats) - 1)]
                row = {
                    "image": list(imgs[0].shape),
                    "valid": round(float(np.mean(raw[density])), 3),
                    "after_fill": round(float(np.mean([im.valid.mean() for im in imgs])), 3),
                    "orb": round(float(np.mean([len(f) for f in feats])), 1),
                    "matched_next": round(float(np.mean(matched)), 3),
                }
                rows[f"fill{radius}_ppp{density:g}"] = row
                print(f"{sensor:7} {radius:4d} {density:6g} {row['image'][0]:4d}x{row['image'][1]:<4d} "
                      f"{row['valid']:6.3f} {row['after_fill']:6.3f} {row['orb']:6.1f} {row['matched_next']:7.3f}")  # fmt: skip
        out["sensors"][sensor] = {
            "keyframes": len(scans),
            "seconds": round(time.perf_counter() - t0, 1),
            **rows,
        }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
