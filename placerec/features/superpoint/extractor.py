"""The ``superpoint`` feature extractor: our SuperPoint network on the intensity image, run by ``cv2.dnn`` from
the ONNX model (default; no torch needed), by ONNX Runtime from the same model or from its int8 quantisation
(`placerec.features.superpoint.quantise`), or by torch.

Keypoints where the probability reaches ``min_probability`` (0.005 for our model; VPR paper Table I: 0.05 for
Magic Leap's, see `SuperPointParams`), non-maximum suppression, at most ``nfeatures`` 300 (Table I). The image is padded around (azimuth wrap-around, as for every extractor:
`placerec.features.base`), then on the right and bottom to a multiple of 8 pixels.

A model runs only once its files are vouched for (`placerec.features.superpoint.weights.open_model`: the hashes
in its provenance, or ``trust_model``) and its outputs on a probe image are sane
(`placerec.features.superpoint.probe`; an int8 model's also follow its float model's,
`placerec.features.superpoint.quantise.check_agreement`); docs/superpoint.md, "Provenance and trust".
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
from pydantic import Field

from placerec.errors import ArtifactError, DependencyError
from placerec.features.base import ExtractorParams, FeatureExtractor, _Keypoints
from placerec.features.superpoint.arch import CELL, SuperPointArch, network_input
from placerec.features.superpoint.post import keypoint_probability, sample_descriptors, select_keypoints
from placerec.features.superpoint.probe import check_outputs, probe_image
from placerec.features.superpoint.quantise import check_agreement
from placerec.features.superpoint.weights import (
    CheckedModel,
    int8_path,
    onnx_path,
    open_model,
    resolve_weights,
)
from placerec.threads import available_threads

log = logging.getLogger(__name__)

__all__ = ["SuperPointParams", "SuperPointExtractor", "SuperPointNet"]


class SuperPointParams(ExtractorParams):
    """SuperPoint (VPR paper Table I: minProbability 0.05, nFeatures 300).

    ``min_probability`` defaults to 0.005, not Table I's 0.05: that threshold suits Magic Leap's model, whose
    detector was trained on synthetic shapes with exact corners. Ours learns the repeatable corners of LiDAR
    intensity images, which are less sharply placed, so it spreads a cell's probability over neighbouring
    pixels: its peaks stay below 0.03 and Table I's threshold keeps no keypoint. 0.005 keeps ~250 per 64 x 1024
    image (docs/superpoint.md has the measurements).
    """

    min_probability: float = Field(
        0.005,
        gt=0,
        lt=1,
        description="keypoint probability (VPR paper Table I: 0.05, for Magic Leap's model)",
    )
    nms_radius: int = Field(
        4, ge=0, description="px; non-maximum suppression window (2r+1)^2 (SuperPoint's 4)"
    )
    weights: str | None = Field(None, description="weights .npz (None: the shipped placerec/vocab one)")
    backend: Literal["cv2", "onnxruntime", "onnxruntime-int8", "torch"] = Field(
        "cv2",
        description="cv2: the ONNX model through cv2.dnn (no torch); onnxruntime: the same ONNX model through ONNX "
        "Runtime, the network alone ~1.6x faster on two idle cores, outputs within 1e-5 of cv2's (needs "
        "placerec[onnxruntime]); onnxruntime-int8: its int8 quantisation (the .int8.onnx beside the weights, "
        "docs/superpoint.md); torch: needs placerec[superpoint]",
    )
    trust_model: bool = Field(
        False,
        description="run user-supplied weights whose provenance .json does not record their files' sha256 "
        "(or records others) as they are; the shipped weights are always checked, and every model must "
        "pass the probe-image sanity check (docs/superpoint.md, Provenance and trust)",
    )


class SuperPointNet:
    """The network with one backend: ``forward(image_u8)`` -> (65, H/8, W/8) logits, (D, H/8, W/8) descriptors
    for an image whose sides are multiples of 8.

    Loading checks the files' hashes against their provenance (`open_model`; ``trust_model`` accepts a user's
    files without) before the ONNX bytes reach ``cv2.dnn``, then the network's outputs on the probe image
    (`check_outputs`, once per backend and file hashes in a process); `ArtifactError` naming the file if not."""

    def __init__(
        self, weights: str | Path | None = None, backend: str = "cv2", trust_model: bool = False
    ) -> None:
        t0 = time.perf_counter()
        path = resolve_weights(None if weights is None else str(weights))
        files = open_model(
            path, onnx=backend in ONNX_BACKENDS, int8=backend == "onnxruntime-int8", trust_model=trust_model
        )
        self.files: CheckedModel = files
        self.arch: SuperPointArch = files.arch
        self.weights = files.weights
        self.backend = backend
        self._lock = threading.Lock()  # a cv2.dnn.Net is not safe to share between threads
        self._net: Any  # a cv2.dnn.Net, an ONNX Runtime session or a torch module
        if backend in ORT_BACKENDS:
            model_bytes = files.int8 if backend == "onnxruntime-int8" else files.onnx
            assert model_bytes is not None
            self._net = _onnxruntime_session(model_bytes, self._model_file(), path.name)
            self._input = self._net.get_inputs()[0].name
        elif backend == "cv2":
            model = onnx_path(path)
            assert files.onnx is not None
            try:  # from the bytes that were hashed, not the file again
                self._net = cv2.dnn.readNetFromONNX(np.frombuffer(files.onnx, np.uint8))
            except cv2.error as exc:
                raise ArtifactError(
                    f"{model}: not a readable SuperPoint ONNX model (write it again from {path.name} with "
                    f"placerec.features.superpoint.weights.save_weights, or use backend 'torch'): "
                    f"{str(exc).strip().splitlines()[-1]}"
                ) from None
        else:
            from placerec.features.superpoint.torch_model import build_torch_model, import_torch

            self._torch = import_torch()
            self._net = build_torch_model(self.arch, self.weights).eval()
        t1 = time.perf_counter()
        self._probe()
        log.debug(
            "SuperPoint %s (%s, %s): loaded and checked in %.1f ms, probe %.1f ms",
            path,
            backend,
            files.accepted,
            (t1 - t0) * 1e3,
            (time.perf_counter() - t1) * 1e3,
        )

    def _probe(self) -> None:
        """`check_outputs` on the probe image, unless this backend already passed it with these files."""
        key = (
            self.backend,
            self.files.sha256["weights"],
            self.files.sha256.get("onnx", ""),
            self.files.sha256.get("int8", ""),
        )
        if key in _PROBED:
            return
        path = self.files.path
        name = str(self._model_file())
        semi, desc = self.forward(probe_image())
        check_outputs(semi, desc, self.arch, name)
        if self.backend == "onnxruntime-int8":  # and against its float network, whose bytes were checked too
            assert self.files.onnx is not None
            ref = _onnxruntime_session(self.files.onnx, onnx_path(path), path.name)
            x = network_input(probe_image())
            semi_ref, desc_ref = ref.run(["semi", "desc"], {ref.get_inputs()[0].name: x})
            check_agreement(semi, desc, semi_ref[0], desc_ref[0], name)
        _PROBED.add(key)

    def _model_file(self) -> Path:
        """The file whose network this backend runs: the int8 ONNX model, the ONNX model or the weights."""
        path = self.files.path
        if self.backend == "onnxruntime-int8":
            return int8_path(path)
        return onnx_path(path) if self.backend in ONNX_BACKENDS else path

    def forward(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = network_input(image)
        if self.backend == "cv2":
            with self._lock:
                self._net.setInput(x)
                semi, desc = self._net.forward(["semi", "desc"])
        elif self.backend in ORT_BACKENDS:  # a session may run from several threads at once
            semi, desc = self._net.run(["semi", "desc"], {self._input: x})
        else:
            with self._torch.inference_mode():
                semi, desc = (t.numpy() for t in self._net(self._torch.from_numpy(x)))
        return semi[0], desc[0]


def _onnxruntime_session(model: bytes, file: Path, weights_name: str) -> Any:
    """An ONNX Runtime session of the ONNX ``model`` bytes (those hashed, not the file again) on this process's
    threads (`placerec.threads.available_threads`), idle threads sleeping instead of spinning after each run (a
    spinning pool takes the other core from the verification); `DependencyError` when ONNX Runtime is missing,
    `ArtifactError` naming ``file`` when it cannot read the model."""
    try:
        import onnxruntime as ort
    except ImportError:
        raise DependencyError(
            "SuperPoint's onnxruntime backend needs ONNX Runtime (pip install 'placerec[onnxruntime]'); the cv2 "
            "backend runs the same ONNX model without it"
        ) from None
    options = ort.SessionOptions()
    options.intra_op_num_threads = available_threads()
    options.inter_op_num_threads = 1
    options.log_severity_level = 3  # errors only
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    try:
        return ort.InferenceSession(model, options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # ONNX Runtime's own exception types differ between its versions
        raise ArtifactError(
            f"{file}: not a readable SuperPoint ONNX model (write it again from {weights_name} with "
            f"placerec.features.superpoint.weights.save_weights, or use backend 'cv2'): "
            f"{str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__}"
        ) from None


#: backends that run the ONNX model written beside the weights (the int8 one checks its outputs against it)
ONNX_BACKENDS = ("cv2", "onnxruntime", "onnxruntime-int8")
#: backends that run an ONNX model through an ONNX Runtime session
ORT_BACKENDS = ("onnxruntime", "onnxruntime-int8")
#: (backend, weights sha256, ONNX sha256, int8 ONNX sha256) of the networks that passed the probe in this process
_PROBED: set[tuple[str, str, str, str]] = set()
_NETS: dict[tuple[Any, ...], SuperPointNet] = {}
_NETS_LOCK = threading.Lock()


def _stamp(path: Path) -> tuple[int, int] | None:
    try:
        st = path.stat()
    except OSError:
        return None
    return st.st_size, st.st_mtime_ns


def _net(weights: str | None, backend: str, trust_model: bool = False) -> SuperPointNet:
    """One checked `SuperPointNet` per (weights file, backend, trust_model) and process; loaded and checked again
    when the files' sizes or times change."""
    path = resolve_weights(weights).resolve()
    key = (
        str(path),
        backend,
        trust_model,
        _stamp(path),
        _stamp(onnx_path(path)),
        _stamp(int8_path(path)),
        _stamp(path.with_suffix(".json")),
    )
    with _NETS_LOCK:
        if key not in _NETS:
            net = SuperPointNet(path, backend, trust_model)
            for old in [k for k in _NETS if k[:3] == key[:3]]:  # the same files before they changed
                del _NETS[old]
            _NETS[key] = net
        return _NETS[key]


class SuperPointExtractor(FeatureExtractor[SuperPointParams]):
    """SuperPoint keypoints and 256-d unit descriptors (float)."""

    name = "superpoint"
    descriptor_kind = "float"
    Params = SuperPointParams

    def _setup(self) -> None:
        self._model = _net(self.params.weights, self.params.backend, self.params.trust_model)

    @property
    def descriptor_size(self) -> int:
        return self._model.arch.descriptor_dim

    def _run(self, image: np.ndarray, mask: np.ndarray) -> tuple[_Keypoints, Any]:
        h, w = image.shape
        ph, pw = -h % CELL, -w % CELL
        semi, desc = self._model.forward(np.pad(image, ((0, ph), (0, pw))) if ph or pw else image)
        prob = keypoint_probability(semi)[:h, :w]
        p = self.params
        uv, score = select_keypoints(prob, mask, p.min_probability, p.nms_radius, p.nfeatures)
        n = len(uv)
        kps = _Keypoints(
            uv,
            np.full(n, 2 * p.nms_radius + 1, np.float32),
            np.full(n, -1, np.float32),
            score.astype(np.float32),
            np.zeros(n, np.int32),
        )
        return kps, sample_descriptors(desc, uv)
