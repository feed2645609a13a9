"""Model weights (`placerec.features.superpoint.weights.open_model`): a copy of the shipped SuperPoint files with
one of them replaced or damaged, or its provenance missing or lying, must be refused naming the file; the intact
copy with its provenance loads. The detailed hostile networks (random, negated head, NaN bias, 128-d) are in
tests/test_superpoint_provenance.py; here each file of the model gets the corpus' generic damage."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

from fuzz.corpus import Case
from placerec.errors import ArtifactError


def _copy(folder: Path) -> Path:
    from placerec.features.superpoint.weights import SHIPPED_WEIGHTS

    folder.mkdir(parents=True, exist_ok=True)
    for suffix in (".npz", ".onnx", ".json"):
        shutil.copyfile(SHIPPED_WEIGHTS.with_suffix(suffix), folder / f"sp{suffix}")
    return folder / "sp.npz"


def _damaged(suffix: str, change: Callable[[bytes], bytes]) -> Callable[[Path], Path]:
    def build(tmp: Path) -> Path:
        weights = _copy(tmp / "w")
        f = weights.with_suffix(suffix)
        f.write_bytes(change(f.read_bytes()))
        return weights

    return build


def _flip_middle(data: bytes) -> bytes:
    b = bytearray(data)
    for i in range(len(b) // 2, len(b) // 2 + 64):
        b[i] ^= 0x5A
    return bytes(b)


def _provenance(change: Callable[[dict], Any]) -> Callable[[Path], Path]:
    def build(tmp: Path) -> Path:
        weights = _copy(tmp / "w")
        p = weights.with_suffix(".json")
        p.write_text(json.dumps(change(json.loads(p.read_text()))))
        return weights

    return build


def _open(weights: Path, **kw: Any) -> Any:
    from placerec.features.superpoint.weights import open_model

    return open_model(weights, **kw)


def _extractor(weights: Path, **kw: Any) -> Any:
    """The SuperPoint extractor on ``weights``: `open_model`, then the probe image (`placerec.features.superpoint.
    probe`), then one real extraction."""
    import numpy as np

    from placerec.features import make_extractor

    image = np.kron(np.random.default_rng(1).integers(0, 255, (16, 128)), np.ones((4, 4))).astype(np.uint8)
    return make_extractor("superpoint", weights=str(weights), **kw).extract(image)


def cases() -> list[Case]:
    out: list[Case] = []

    def case(
        name: str, build: Callable[[Path], Path], expect: str = "error", names: Any = None, **kw: Any
    ) -> None:
        out.append(
            Case("weights", name, build, kw.pop("run", _open), expect, names=names, error=ArtifactError, **kw)
        )

    case("intact-copy", lambda t: _copy(t / "w"), "ok", check=lambda a, r: None, fast=True)
    case("intact-copy-extracts", lambda t: _copy(t / "w"), "ok", run=_extractor, check=lambda a, r: None)
    case("onnx-flipped-extractor", _damaged(".onnx", _flip_middle), run=_extractor, names="sp.onnx")
    case("onnx-flipped", _damaged(".onnx", _flip_middle), names="sp.onnx", fast=True)
    case("onnx-truncated", _damaged(".onnx", lambda b: b[: len(b) // 2]), names="sp.onnx")
    case("onnx-empty", _damaged(".onnx", lambda b: b""), names="sp.onnx")
    case("npz-flipped", _damaged(".npz", _flip_middle), names="sp.npz")
    case("npz-truncated", _damaged(".npz", lambda b: b[:-100]), names="sp.npz")
    case("provenance-missing", lambda t: (lambda w: (w.with_suffix(".json").unlink(), w)[1])(_copy(t / "w")), names="sp")  # fmt: skip
    case("provenance-not-json", _damaged(".json", lambda b: b"{not json"), names="sp.json")
    case(
        "provenance-no-hashes",
        _provenance(lambda d: {k: v for k, v in d.items() if k != "sha256"}),
        names="sp",
    )
    case("provenance-wrong-hash", _provenance(lambda d: {**d, "sha256": {**d["sha256"], "onnx": "0" * 64}}), names="sp.onnx")  # fmt: skip
    case("provenance-hash-not-text", _provenance(lambda d: {**d, "sha256": {"weights": 1, "onnx": [2]}}), names="sp")  # fmt: skip
    case("provenance-a-list", _provenance(lambda d: [d]), names="sp")
    # trusting a model skips the provenance, never the probe or the shapes: damaged files still fail
    case("trusted-onnx-truncated", _damaged(".onnx", lambda b: b[: len(b) // 2]), run=lambda w: _extractor(w, trust_model=True), names="sp.onnx")  # fmt: skip
    case("trusted-npz-flipped", _damaged(".npz", _flip_middle), "either", run=lambda w: _extractor(w, trust_model=True), names="sp.npz", check=lambda a, r: None)  # fmt: skip
    return out
