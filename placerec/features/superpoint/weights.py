"""SuperPoint weights files: an uncompressed ``.npz`` artifact (no pickle) with a JSON header holding the format
version and the architecture, float16 arrays ``<layer>.weight`` / ``<layer>.bias``; the ONNX model beside it
(same stem, ``.onnx``) is written from the same arrays for the cv2 backend, and its int8 quantisation (``.int8.onnx``,
`placerec.features.superpoint.quantise`) may lie beside it for the ``onnxruntime-int8`` backend; the provenance
``.json`` records the sha256 of each file's bytes (``"sha256": {"weights": ..., "onnx": ..., "int8": ...}``), which
ties the ONNX models to the ``.npz`` they were made from.

The shipped weights are ``placerec/vocab/superpoint_lidar.npz`` (+ ``.onnx`` and the provenance ``.json``),
trained by ``tools/train_superpoint.py --config configs/superpoint.yaml``.

`open_model` is how a model is loaded to be run: the files' hashes are checked against the provenance (always for
the shipped files), or, for a user's files without a provenance that vouches for them, ``trust_model`` must say so.
"""

from __future__ import annotations

import hashlib
import importlib.resources
import json
import logging
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from placerec.errors import ArtifactError, ConfigError
from placerec.features.superpoint.arch import SuperPointArch, conv_layers
from placerec.io.artifact_schema import Member, check_members
from placerec.io.atomic import atomic_write, load_artifact, save_artifact

log = logging.getLogger(__name__)

__all__ = [
    "SHIPPED_WEIGHTS",
    "CheckedModel",
    "save_weights",
    "load_weights",
    "resolve_weights",
    "onnx_path",
    "int8_path",
    "provenance_path",
    "file_sha256",
    "record_hashes",
    "open_model",
]

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


def int8_path(weights: str | Path) -> Path:
    """The int8 quantisation of the ONNX model that goes with a weights file."""
    return Path(weights).with_suffix(".int8.onnx")


def provenance_path(weights: str | Path) -> Path:
    """The provenance JSON that goes with a weights file."""
    return Path(weights).with_suffix(".json")


def file_sha256(path: str | Path) -> str:
    """Hex sha256 of a file's bytes."""
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def record_hashes(
    path: str | Path, provenance: dict[str, Any] | None = None, update: dict[str, Any] | None = None
) -> dict[str, Any]:
    """Write the provenance JSON beside the weights ``path``: ``provenance`` (None: the JSON there now, if any),
    the keys of ``update`` set on it, with ``sha256`` set to the hashes of the ``.npz`` and of the ``.onnx`` and
    ``.int8.onnx`` (those there are); returns it.

    Only for files you made: the hashes say "these are the files this provenance describes"."""
    path = Path(path)
    if provenance is None:
        found = provenance_path(path)
        provenance = json.loads(found.read_text()) if found.is_file() else {"format_version": 1}
        if not isinstance(provenance, dict):
            raise ArtifactError(f"{found}: the provenance is not a JSON object")
    hashes = {"weights": file_sha256(path)}
    if onnx_path(path).is_file():
        hashes["onnx"] = file_sha256(onnx_path(path))
    if int8_path(path).is_file():
        hashes["int8"] = file_sha256(int8_path(path))
    out = {**provenance, **(update or {}), "sha256": hashes}
    with atomic_write(provenance_path(path), "w") as fh:
        json.dump(out, fh, indent=2)
        fh.write("\n")
    return out


def save_weights(
    path: str | Path,
    arch: SuperPointArch,
    weights: dict[str, np.ndarray],
    meta: dict[str, Any] | None = None,
    provenance: dict[str, Any] | None = None,
) -> dict[str, np.ndarray]:
    """Write ``weights`` as float16 with ``arch`` in the header, the ONNX model beside them (needs the ``onnx``
    package) and the provenance JSON (``provenance``, None: just the format version) with both files' sha256
    (`record_hashes`); returns the float16-rounded float32 arrays both files hold."""
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
    record_hashes(path, {"format_version": 1, **(provenance or {})})
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


# ----------------------------------------------------------------------------- provenance and trust

_SHA256 = re.compile(r"[0-9a-f]{64}")
_HOW_TO_FIX = (
    "write the weights with placerec.features.superpoint.weights.save_weights or tools/train_superpoint.py (they "
    "record the hashes), record the hashes of files you made yourself with `python tools/train_superpoint.py "
    "--record-hashes {weights}`, or set trust_model: true in the superpoint feature parameters to run them as they "
    "are"
)


@dataclass(frozen=True)
class CheckedModel:
    """A model's files as read and checked by `open_model`."""

    path: Path  #: the weights ``.npz``
    arch: SuperPointArch
    weights: dict[str, np.ndarray]  #: float32
    onnx: bytes | None  #: the ONNX model's bytes, exactly those hashed (None when not asked for)
    sha256: dict[str, str]  #: {"weights": ..., "onnx": ..., "int8": ...} of the bytes read
    accepted: Literal["shipped", "provenance", "trusted"]  #: what vouches for the files
    int8: bytes | None = None  #: the int8 ONNX model's bytes, exactly those hashed (None when not asked for)


def _is_shipped(path: Path) -> bool:
    try:
        return path.resolve() == SHIPPED_WEIGHTS.resolve() or path.samefile(SHIPPED_WEIGHTS)
    except OSError:
        return False


def _read_provenance(path: Path) -> tuple[dict[str, Any], str]:
    """(recorded hashes, "" ) or ({}, why there are none) for the weights ``path``."""
    found = provenance_path(path)
    if not found.is_file():
        return {}, f"there is no provenance {found.name} beside it"
    try:
        prov = json.loads(found.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        return {}, f"its provenance {found} is not readable JSON ({exc})"
    hashes = prov.get("sha256") if isinstance(prov, dict) else None
    if not isinstance(hashes, dict):
        return {}, f"its provenance {found} records no content hashes ('sha256')"
    return hashes, ""


def _check_hash(
    file: Path, got: str, role: str, weights: Path, hashes: dict[str, Any], why: str, shipped: bool
) -> str | None:
    """None when ``got`` is the sha256 recorded for ``role``, else what is wrong (a message naming ``file``)."""
    expected = hashes.get(role)
    prov = provenance_path(weights)
    if why:
        problem = f"{file}: {why}, so nothing shows it is the network it claims to be"
    elif not isinstance(expected, str) or not _SHA256.fullmatch(expected):
        problem = (
            f"{file}: {prov} records no valid sha256 for the {role} file, so nothing shows it is the network"
        )
    elif got != expected:
        problem = (
            f"{file}: content hash mismatch, sha256 {got[:16]}... but {prov.name} records {expected[:16]}... for "
            f"the {role} file: it is not the file its provenance describes (damaged, or replaced after it was "
            "written)"
        )
    else:
        return None
    if shipped:
        return f"{problem}; these are the shipped SuperPoint weights: reinstall placerec to restore them"
    return f"{problem}; {_HOW_TO_FIX.format(weights=weights)}"


def _stamp(file: Path) -> tuple[int, int, int, int] | None:
    try:
        st = file.stat()
    except OSError:
        return None
    return st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns


def _read_bytes(file: Path, what: str) -> bytes:
    try:
        return file.read_bytes()
    except OSError as exc:
        raise ArtifactError(f"{file}: cannot read the {what} ({exc.strerror or exc})") from None


def open_model(
    path: str | Path, *, onnx: bool = True, int8: bool = False, trust_model: bool = False
) -> CheckedModel:
    """Read and check a SuperPoint model to run it: the weights ``path`` (`load_weights`) and, with ``onnx``, the
    ONNX model beside it, with ``int8`` also its int8 quantisation (`int8_path`), whose bytes are returned so that
    the checked bytes are the ones run.

    The sha256 of each file read must equal the one its provenance JSON records (`record_hashes`). The shipped
    files are always checked. A user's files whose provenance does not vouch for them (no JSON, no hashes, a
    mismatch) are refused with `ArtifactError` naming the file and saying how to fix it, unless ``trust_model``:
    then they are accepted as they are, with a warning. Nothing here runs the network: the extractor checks the
    outputs on a probe image (`placerec.features.superpoint.probe`)."""
    path = Path(path)
    shipped = _is_shipped(path)
    hashes, why = _read_provenance(path)
    stamp = _stamp(path)
    sha = {"weights": hashlib.sha256(_read_bytes(path, "SuperPoint weights")).hexdigest()}
    problems = [_check_hash(path, sha["weights"], "weights", path, hashes, why, shipped)]

    def checked(file: Path, role: str, what: str, missing: str) -> bytes:
        """The bytes of the model file ``file``, its hash recorded under ``role`` and checked."""
        if not file.is_file():
            raise ArtifactError(f"{file}: no such file, {missing}")
        data = _read_bytes(file, what)
        sha[role] = hashlib.sha256(data).hexdigest()
        problems.append(_check_hash(file, sha[role], role, path, hashes, why, shipped))
        return data

    model = quantised = None
    if onnx:
        model = checked(
            onnx_path(path),
            "onnx",
            "SuperPoint ONNX model",
            f"the ONNX model of {path.name} for the cv2 backend (write it with "
            "placerec.features.superpoint.weights.save_weights, or use backend 'torch')",
        )
    if int8:
        quantised = checked(
            int8_path(path),
            "int8",
            "SuperPoint int8 ONNX model",
            f"the int8 ONNX model of {path.name} for the onnxruntime-int8 backend (make it with python "
            "tools/quantise_superpoint.py, or use backend 'onnxruntime')",
        )
    found = [p for p in problems if p is not None]
    if found and (shipped or not trust_model):
        raise ArtifactError(found[0])
    for p in found:
        log.warning("trust_model: running it anyway: %s", p.split("; ")[0])
    arch, weights = load_weights(path)
    if _stamp(path) != stamp:  # replaced between the hash and the load
        raise ArtifactError(f"{path}: the file changed while it was being loaded; load it again")
    accepted: Literal["shipped", "provenance", "trusted"] = (
        "trusted" if found else "shipped" if shipped else "provenance"
    )
    return CheckedModel(path, arch, weights, model, sha, accepted, quantised)
