"""SuperPoint's ONNX model quantised to int8, for the ``onnxruntime-int8`` backend.

`quantise_int8` writes ``<weights>.int8.onnx`` (`placerec.features.superpoint.weights.int8_path`) from the float
ONNX model beside a weights file with ONNX Runtime's static quantisation: per-channel int8 weights, uint8
activations whose ranges are calibrated on intensity images (QDQ format, so the model stays a plain ONNX graph),
and records its sha256 and how it was made in the provenance JSON (`record_hashes`). ``tools/quantise_superpoint.py``
made the shipped one from images of the SuperPoint training worlds (never the evaluation's).

`agreement` compares an int8 network's outputs with its float network's on the same image: the cosine between
their descriptors per cell and the correlation of their detector logits. The extractor requires it on the probe
image before an int8 model describes anything (`check_agreement`): on a CPU whose int8 arithmetic saturates, the
quantised network would silently compute something else.
"""

from __future__ import annotations

import tempfile
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from placerec.errors import ArtifactError, DependencyError
from placerec.features.superpoint.arch import network_input
from placerec.features.superpoint.weights import int8_path, open_model, record_hashes
from placerec.io.atomic import atomic_write

__all__ = ["MIN_COSINE", "MIN_CORRELATION", "agreement", "check_agreement", "quantise_int8"]

#: the network output holding the detector's logits (its last layer is not quantised)
DETECTOR_OUTPUT = "semi"
#: the smallest descriptor cosine (per cell, against the float network) an int8 network may give on the probe
MIN_COSINE = 0.95
#: the smallest correlation of its detector logits with the float network's on the probe
MIN_CORRELATION = 0.98


def agreement(
    semi: np.ndarray, desc: np.ndarray, semi_ref: np.ndarray, desc_ref: np.ndarray
) -> dict[str, float]:
    """How closely (65, h, w) logits ``semi`` and (D, h, w) descriptors ``desc`` follow the reference network's:
    ``cosine_min`` / ``cosine_median`` of the descriptors per cell, ``correlation`` of the logits."""
    a = np.asarray(desc, np.float64).reshape(len(desc), -1)
    b = np.asarray(desc_ref, np.float64).reshape(len(desc_ref), -1)
    norm = np.linalg.norm(a, axis=0) * np.linalg.norm(b, axis=0)
    cos = (a * b).sum(axis=0) / np.maximum(norm, 1e-12)
    corr = float(np.corrcoef(np.ravel(semi), np.ravel(semi_ref))[0, 1])
    return {"cosine_min": float(cos.min()), "cosine_median": float(np.median(cos)), "correlation": corr}


def check_agreement(
    semi: np.ndarray, desc: np.ndarray, semi_ref: np.ndarray, desc_ref: np.ndarray, model: str
) -> None:
    """`ArtifactError` naming ``model`` unless the int8 outputs follow the float network's (`agreement`) within
    `MIN_COSINE` and `MIN_CORRELATION`."""
    found = agreement(semi, desc, semi_ref, desc_ref)
    if not (found["cosine_min"] >= MIN_COSINE and found["correlation"] >= MIN_CORRELATION):
        raise ArtifactError(
            f"{model}: on the probe image the int8 network departs from its float network (descriptor cosine "
            f"down to {found['cosine_min']:.3f}, below {MIN_COSINE}; detector correlation "
            f"{found['correlation']:.3f}, below {MIN_CORRELATION} is refused): its int8 arithmetic is not what it "
            "was quantised for on this CPU, or the file is not a quantisation of these weights; use backend "
            "'onnxruntime' or 'cv2'"
        )


def _onnxruntime() -> tuple[Any, Any]:
    try:
        import onnx  # noqa: F401  (ONNX Runtime's quantisation reads the model through it)
        import onnxruntime.quantization as q
    except ImportError:
        raise DependencyError(
            "quantising SuperPoint needs ONNX Runtime and onnx (pip install 'placerec[onnxruntime,superpoint]')"
        ) from None
    return q, q.QuantFormat


def quantise_int8(weights: str | Path, images: Iterable[np.ndarray], provenance: dict[str, Any]) -> Path:
    """Write the int8 model of the weights file ``weights`` (its float ONNX model, hash-checked, calibrated on the
    uint8 ``images``, each of sides that are multiples of 8) atomically beside it, and record its hash with
    ``provenance`` under ``"int8"`` in the provenance JSON; returns its path. `ArtifactError` when there is no
    image to calibrate on."""
    q, fmt = _onnxruntime()
    weights = Path(weights)
    model = open_model(weights, onnx=True)
    assert model.onnx is not None
    ims = [np.asarray(im, np.uint8) for im in images]
    if not ims:
        raise ArtifactError(f"{weights}: no image to calibrate the int8 model on")

    reader: Any = q.CalibrationDataReader

    class _Reader(reader):
        def __init__(self, name: str) -> None:
            self.name, self.left = name, iter(ims)

        def get_next(self) -> dict[str, np.ndarray] | None:
            im = next(self.left, None)
            return None if im is None else {self.name: network_input(im)}

    import onnx

    graph = onnx.load_from_string(model.onnx)  # the bytes whose hash was checked
    for node in graph.graph.node:  # named by what they compute, so that the heads can be left out by name
        node.name = node.name or node.output[0]
    # the detector's last layer stays float: its logits are thresholded at a small probability (0.005) and
    # suppressed to the local maxima, and as uint8 steps they tie between neighbours (on the validation images
    # only 59 % of the float network's keypoints were found again within 1 px, 93 % with the layer in float)
    heads = [node.name for node in graph.graph.node if DETECTOR_OUTPUT in node.output]
    with tempfile.TemporaryDirectory() as tmp:
        source = Path(tmp) / "float.onnx"
        onnx.save(graph, str(source))
        out = Path(tmp) / "int8.onnx"
        q.quantize_static(
            str(source),
            str(out),
            _Reader(graph.graph.input[0].name),
            quant_format=fmt.QDQ,
            per_channel=True,
            activation_type=q.QuantType.QUInt8,
            weight_type=q.QuantType.QInt8,
            nodes_to_exclude=heads,
        )
        with atomic_write(int8_path(weights)) as f:
            f.write(out.read_bytes())
    record_hashes(weights, update={"int8": {**provenance, "calibration_images": len(ims)}})
    return int8_path(weights)
