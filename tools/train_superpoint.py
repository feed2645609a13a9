"""Train placerec's SuperPoint on simulated LiDAR intensity images (issue #14; docs/superpoint.md).

    python tools/train_superpoint.py --config configs/superpoint.yaml [--steps N] [--output PATH]
    python tools/train_superpoint.py --record-hashes WEIGHTS.npz

Needs torch (``pip install 'placerec[superpoint]'``: the CPU build, torch==2.13.0) and runs on the CPU. Renders the training pairs (cached under
``.cache/superpoint``), trains, writes the weights (``.npz`` float16 + ``.onnx``) with their provenance ``.json``
(with the sha256 of both files, checked before the extractor runs them) and the loss curves, and ends with one JSON
line: pairs, data and training seconds, final losses.

``--record-hashes`` trains nothing: it writes the sha256 of existing weights (``.npz`` and the ``.onnx`` beside) into
their provenance ``.json``, so that the extractor runs them without ``trust_model``. Only for files you made
yourself: the hashes say "these are the files this provenance describes".
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from placerec.artifacts.superpoint import load_superpoint_config, train_superpoint  # noqa: E402
from placerec.features.superpoint.weights import load_weights, provenance_path, record_hashes  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="configs/superpoint.yaml")
    ap.add_argument("--steps", type=int, default=None, help="override train.steps")
    ap.add_argument("--output", default=None, help="override output (weights .npz)")
    ap.add_argument(
        "--record-hashes",
        metavar="WEIGHTS",
        default=None,
        help="train nothing: record the sha256 of these weights (.npz + .onnx) in their provenance .json",
    )
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    if args.record_hashes is not None:
        load_weights(args.record_hashes)  # a valid weights file, or ArtifactError naming it
        prov = record_hashes(args.record_hashes)
        out = {"tool": "train_superpoint", "provenance": str(provenance_path(args.record_hashes))}
        print(json.dumps({**out, "sha256": prov["sha256"]}))
        return 0
    logging.getLogger("numba").setLevel(logging.WARNING)
    cfg = load_superpoint_config(args.config, output=args.output)
    if args.steps is not None:  # validated like the config's own value
        train = {**cfg.train.model_dump(), "steps": args.steps}
        cfg = load_superpoint_config(args.config, output=args.output, train=train)
    prov = train_superpoint(cfg, progress=sys.stderr.isatty())
    print(
        json.dumps(
            {
                "tool": "train_superpoint",
                "output": cfg.output,
                "pairs": prov["pairs"],
                "data_seconds": prov["data_seconds"],
                "train_seconds": prov["train_seconds"],
                "final": prov["final"],
            }
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
