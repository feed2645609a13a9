"""Quantise SuperPoint's ONNX model to int8 for the ``onnxruntime-int8`` backend (#30; docs/superpoint.md).

    python tools/quantise_superpoint.py [--weights WEIGHTS.npz] [--seed 100] [--anchors 10]

Calibrates on intensity images of the SuperPoint training worlds (`placerec.experiment.superpoint_pairs`, the
training config's worlds and sensors at one training seed; never the evaluation's worlds), writes
``WEIGHTS.int8.onnx`` beside the weights (default: the shipped ones) and records its sha256 and how it was made in
their provenance ``.json`` (`placerec.features.superpoint.quantise`). Then, on the validation images (world seed
104, not calibrated on): how closely the int8 network follows the float one (descriptor cosine per cell, logit
correlation, the float keypoints the int8 network finds again within 1 px) and the network's ms per image through
cv2.dnn, ONNX Runtime and ONNX Runtime int8, interleaved. Ends with one JSON line.

Needs ONNX Runtime and onnx (``pip install 'placerec[onnxruntime,superpoint]'``).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from placerec.artifacts.superpoint import load_superpoint_config  # noqa: E402
from placerec.experiment.superpoint_pairs import build_pairs  # noqa: E402
from placerec.features.superpoint.extractor import SuperPointExtractor, SuperPointNet  # noqa: E402
from placerec.features.superpoint.quantise import agreement, quantise_int8  # noqa: E402
from placerec.features.superpoint.weights import (  # noqa: E402
    SHIPPED_WEIGHTS,
    int8_path,
    record_hashes,
)


def _keypoints_found(a: np.ndarray, b: np.ndarray, px: float = 1.0) -> float:
    """The share of keypoints ``a`` (K, 2) with one of ``b`` within ``px``."""
    if len(a) == 0:
        return 1.0
    if len(b) == 0:
        return 0.0
    d = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=2)
    return float((d.min(axis=1) <= px).mean())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--weights", default=str(SHIPPED_WEIGHTS), help="weights .npz (default: the shipped ones)"
    )
    ap.add_argument(
        "--config", default="configs/superpoint.yaml", help="the training config (its data section)"
    )
    ap.add_argument("--seed", type=int, default=100, help="the training world seed to calibrate on")
    ap.add_argument(
        "--anchors", type=int, default=10, help="anchor scans per world and sensor (pairs: 2 images)"
    )
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    cfg = load_superpoint_config(args.config)
    data = cfg.data.model_copy(
        update={
            "seeds": [args.seed],
            "anchors": args.anchors,
            "revisit_pairs": 0,
            "validation_revisit_pairs": 0,
        }
    )
    t0 = time.perf_counter()
    pairs = build_pairs(data, cfg.cache, progress=sys.stderr.isatty())
    calib = [im for p in pairs["train"] for im in (p.image_a, p.image_b)]
    held = [im for p in pairs["validation"] for im in (p.image_a, p.image_b)]
    data_s = time.perf_counter() - t0

    import onnx
    import onnxruntime

    made = {
        "what": "int8 quantisation of the ONNX model (tools/quantise_superpoint.py): ONNX Runtime static "
        "quantisation, QDQ format, per-channel int8 weights, uint8 activations (min-max calibration); the detector's "
        "last layer stays float",
        "onnxruntime": onnxruntime.__version__,
        "onnx": onnx.__version__,
        "calibration": {
            "worlds": data.worlds,
            "sensors": data.sensors,
            "seed": args.seed,
            "anchors": args.anchors,
        },
    }
    t1 = time.perf_counter()
    out = quantise_int8(args.weights, calib, made)
    quantise_s = time.perf_counter() - t1

    nets = {b: SuperPointNet(args.weights, b) for b in ("cv2", "onnxruntime", "onnxruntime-int8")}
    extractors = {
        b: SuperPointExtractor(backend=b, weights=args.weights) for b in ("onnxruntime", "onnxruntime-int8")
    }
    cos_min, cos_med, corr, found, n_kp = [], [], [], [], []
    ms: dict[str, list[float]] = {b: [] for b in nets}
    for im in held:
        h, w = (s - s % 8 for s in im.shape)
        crop = np.ascontiguousarray(im[:h, :w])
        outs = {}
        for b, net in nets.items():  # interleaved: each image through every backend in turn
            tb = time.perf_counter()
            outs[b] = net.forward(crop)
            ms[b].append((time.perf_counter() - tb) * 1e3)
        a = agreement(*outs["onnxruntime-int8"], *outs["onnxruntime"])
        cos_min.append(a["cosine_min"])
        cos_med.append(a["cosine_median"])
        corr.append(a["correlation"])
        pf = np.asarray(extractors["onnxruntime"].extract(im).uv, np.float64).reshape(-1, 2)
        p8 = np.asarray(extractors["onnxruntime-int8"].extract(im).uv, np.float64).reshape(-1, 2)
        found.append(_keypoints_found(pf, p8))
        n_kp.append((len(pf), len(p8)))
    figures = {
        "descriptor_cosine_median": round(float(np.median(cos_med)), 5),
        "descriptor_cosine_min": round(float(np.min(cos_min)), 5),
        "logit_correlation_min": round(float(np.min(corr)), 5),
        "keypoints_found_within_1px": round(float(np.mean(found)), 4),
        "keypoints_float_int8": [
            round(float(np.mean([k[0] for k in n_kp])), 1),
            round(float(np.mean([k[1] for k in n_kp])), 1),
        ],
        "validation_images": len(held),
    }
    timing = {b: round(float(np.median(v)), 2) for b, v in ms.items()}
    section = {**made, "calibration_images": len(calib)}  # what quantise_int8 recorded, and the figures
    record_hashes(
        args.weights,
        update={"int8": {**section, "agreement_on_validation": figures, "ms_per_image_median": timing}},
    )
    print(f"int8 model: {out} ({out.stat().st_size / 1e6:.1f} MB), from {len(calib)} calibration images")
    print(f"against the float network on {len(held)} validation images: {figures}")
    print(f"network ms per image (median, interleaved; load {os.getloadavg()[0]:.2f}): {timing}")
    line = {
        "tool": "quantise_superpoint",
        "output": str(int8_path(args.weights)),
        "calibration_images": len(calib),
        "data_s": round(data_s, 1),
        "quantise_s": round(quantise_s, 1),
        "agreement": figures,
        "ms_per_image": timing,
        "image_shapes": sorted({tuple(int(s) for s in im.shape) for im in held}),
    }
    print(json.dumps(line))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
