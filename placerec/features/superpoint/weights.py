"""SuperPoint weights files: an uncompressed ``.npz`` artifact (no pickle) with a JSON header holding the format
version and the architecture, float16 arrays ``<layer>.weight`` / ``<layer>.bias``; the ONNX model beside it
(same stem, ``.onnx``) is written from the same arrays for the cv2 backend.

The shipped weights are ``placerec/vocab/superpoint_lidar.npz`` (+ ``.onnx`` and the provenance ``.json``),
trained by ``tools/train_superpoint.py --config configs/superpoint.yaml``.
"""

from __future__ import annotations

import importlib.resources
from pathlib import Path
from typing import Any

import numpy as np

from placerec.errors import ArtifactError, ConfigError
from placerec.features.superpoint.arch import SuperPointArch, conv_layers
from placerec.io.artifact_schema import Member, check_members
from placerec.io.atomic import atomic_write, load_artifact, save_artifact

__all__ = ["SHIPPED_WEIGHTS", "save_weights", "load_weights", "resolve_weights", "onnx_path"]

KIND = "superpoint-weights"
VERSION = 1
#: The shipped weights (package data).
SHIPPED_WEIGHTS = Path(str(importlib.resources.files("placerec").joinpath("vocab", "superpoint_lidar.npz")))


def _schema(arch: SuperPointArch) -> dict[str, Member]:
    out = {}
    for c in sum(conv_layers(arch), []):
        out[f"{c.name}.weight"] = Member("f", (c.c_out, c.c_in, c.kernel, c.kernel), finite=True)
        out[f"{c.name}.bias"] = Member("f", (c.c_out,), finite=True)
    return out


def onnx_path(weights: str | Path) -> Path:
    """The ONNX model that goes with a weights file."""
    return Path(weights).with_suffix(".onnx")


def save_weights(
    path: str | Path, arch: SuperPointArch, weights: dict[str, np.ndarray], meta: dict[str, Any] | None = None
) -> dict[str, np.ndarray]:
    """Write ``weights`` as float16 with ``arch`` in the header, and the ONNX model beside them (needs the
    ``onnx`` package); returns the float16-rounded float32 arrays both files hold."""
    from placerec.features.superpoint.onnx_graph import onnx_model_bytes

    schema = _schema(arch)
    missing = sorted(set(schema) - set(weights))
    if missing:
        raise ArtifactError(f"{path}: weights lack {missing}")
    half = {k: np.asarray(weights[k], np.float32).astype(np.float16) for k in schema}
    save_artifact(path, KIND, VERSION, half, {"arch": arch.model_dump(mode="json"), **(meta or {})})
    rounded = {k: v.astype(np.float32) for k, v in half.items()}
    with atomic_write(onnx_path(path)) as f:
        f.write(onnx_model_bytes(arch, rounded))
    return rounded


def load_weights(path: str | Path) -> tuple[SuperPointArch, dict[str, np.ndarray]]:
    """(architecture, float32 weights) of a weights file; `ArtifactError` naming the file when it is not a valid
    one (wrong kind or version, missing or misshapen layers, non-finite values)."""
    arrays, header = load_artifact(path, KIND, (VERSION,))
    try:
        arch = SuperPointArch.model_validate(header["meta"].get("arch"))
    except ConfigError as exc:
        raise ArtifactError(f"{path}: invalid architecture in the header: {exc}") from None

    check_members(arrays, _schema(arch), path)
    return arch, {k: np.asarray(v, np.float32) for k, v in arrays.items()}


def resolve_weights(path: str | None) -> Path:
    """The weights file for a ``weights`` parameter (None: the shipped one); `ArtifactError` if absent."""
    found = SHIPPED_WEIGHTS if path is None else Path(path).expanduser()
    if not found.is_file():
        raise ArtifactError(
            f"SuperPoint weights {found} not found (train them: python tools/train_superpoint.py "
            "--config configs/superpoint.yaml)"
        )
    return found
