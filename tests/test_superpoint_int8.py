"""SuperPoint's int8 model (`placerec.features.superpoint.quantise`, the ``onnxruntime-int8`` backend, #30): the
shipped one is vouched for by its hash and follows the float network; quantising writes a checked file whose
detector layer stays float; a tampered, missing or departing int8 model is refused naming the file."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from placerec.errors import ArtifactError
from placerec.features import make_extractor
from placerec.features.superpoint.arch import SuperPointArch, conv_layers
from placerec.features.superpoint.extractor import SuperPointNet
from placerec.features.superpoint.probe import probe_image
from placerec.features.superpoint.quantise import DETECTOR_OUTPUT, agreement, check_agreement, quantise_int8
from placerec.features.superpoint.weights import (
    SHIPPED_WEIGHTS,
    file_sha256,
    int8_path,
    onnx_path,
    open_model,
    provenance_path,
    save_weights,
)

pytest.importorskip("onnxruntime")
pytest.importorskip("onnx")

SMALL = SuperPointArch(encoder=[4, 4, 8, 8], head=8, descriptor_dim=16)


def _images(n: int, h: int = 64, w: int = 256, seed: int = 0) -> list[np.ndarray]:
    """Blocky uint8 images with corners at several scales (the probe's kind of texture)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        fine = np.kron(rng.integers(0, 256, (h // 4, w // 4)), np.ones((4, 4)))
        coarse = np.kron(rng.integers(0, 256, (h // 16, w // 16)), np.ones((16, 16)))
        out.append((0.5 * fine + 0.5 * coarse).round().astype(np.uint8))
    return out


def _found_within(a: np.ndarray, b: np.ndarray, px: float = 1.0) -> float:
    d = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=2)
    return float((d.min(axis=1) <= px).mean())


@pytest.fixture
def small_model(tmp_path) -> Path:
    rng = np.random.default_rng(4)
    weights = {}
    for c in sum(conv_layers(SMALL), []):
        scale = np.sqrt(2.0 / (c.c_in * c.kernel * c.kernel))
        weights[f"{c.name}.weight"] = rng.normal(0, scale, (c.c_out, c.c_in, c.kernel, c.kernel))
        weights[f"{c.name}.bias"] = rng.normal(0, 0.01, c.c_out)
    path = tmp_path / "small.npz"
    save_weights(path, SMALL, weights, provenance={"what": "a test model"})
    return path


def test_the_shipped_int8_model_is_vouched_for_and_follows_the_float_network() -> None:
    prov = json.loads(provenance_path(SHIPPED_WEIGHTS).read_text())
    assert prov["sha256"]["int8"] == file_sha256(int8_path(SHIPPED_WEIGHTS))
    assert (
        prov["int8"]["calibration"]["seed"] >= 100
    )  # a training world, never an evaluation one (0-9, 4601..)
    net = SuperPointNet(None, "onnxruntime-int8")
    assert net.files.accepted == "shipped" and net.files.int8 == int8_path(SHIPPED_WEIGHTS).read_bytes()
    ref = SuperPointNet(None, "onnxruntime")
    found = agreement(*net.forward(probe_image()), *ref.forward(probe_image()))
    assert found["cosine_median"] > 0.995 and found["correlation"] > 0.999
    f8 = make_extractor("superpoint", backend="onnxruntime-int8").extract(np.asarray(probe_image()))
    ff = make_extractor("superpoint", backend="onnxruntime").extract(np.asarray(probe_image()))
    assert abs(len(f8) - len(ff)) <= 0.1 * len(ff)
    assert _found_within(np.asarray(ff.uv), np.asarray(f8.uv)) > 0.85


def test_quantising_writes_a_checked_model_whose_detector_layer_stays_float(small_model: Path) -> None:
    import onnx

    out = quantise_int8(small_model, _images(6), {"what": "test"})
    assert out == int8_path(small_model) and out.is_file()
    prov = json.loads(provenance_path(small_model).read_text())
    assert prov["what"] == "a test model" and prov["int8"] == {"what": "test", "calibration_images": 6}
    assert prov["sha256"] == {
        "weights": file_sha256(small_model),
        "onnx": file_sha256(onnx_path(small_model)),
        "int8": file_sha256(out),
    }
    graph = onnx.load(str(out)).graph
    ops = [n.op_type for n in graph.node]
    assert "QuantizeLinear" in ops and "DequantizeLinear" in ops
    (head,) = [n for n in graph.node if DETECTOR_OUTPUT in n.output]
    floats = {i.name for i in graph.initializer if i.data_type == onnx.TensorProto.FLOAT}
    assert head.op_type == "Conv" and head.input[1] in floats  # its weights are not dequantised int8
    net = SuperPointNet(small_model, "onnxruntime-int8")
    assert net.files.accepted == "provenance"
    semi, desc = net.forward(_images(1, seed=9)[0])
    assert semi.shape == (65, 8, 32) and desc.shape == (16, 8, 32)


def test_a_tampered_or_missing_int8_model_is_refused_naming_it(small_model: Path, tmp_path) -> None:
    quantise_int8(small_model, _images(4), {"what": "test"})
    copy = tmp_path / "copy"
    copy.mkdir()
    for f in small_model.parent.glob("small.*"):
        shutil.copyfile(f, copy / f.name)
    model = int8_path(copy / "small.npz")
    data = bytearray(model.read_bytes())
    data[-20] ^= 0xFF
    model.write_bytes(bytes(data))
    with pytest.raises(ArtifactError, match=r"small\.int8\.onnx: content hash mismatch.*int8"):
        open_model(copy / "small.npz", int8=True)
    open_model(copy / "small.npz")  # the float backends do not read it
    model.unlink()
    with pytest.raises(ArtifactError, match=r"small\.int8\.onnx: no such file.*quantise_superpoint"):
        make_extractor("superpoint", weights=str(copy / "small.npz"), backend="onnxruntime-int8")


def test_an_int8_network_that_departs_from_its_float_one_is_refused() -> None:
    ref = SuperPointNet(None, "onnxruntime")
    semi, desc = ref.forward(probe_image())
    check_agreement(semi, desc, semi, desc, "m.int8.onnx")
    flipped = desc.copy()
    flipped[:, 2, 5] *= -1  # one cell's descriptor reversed, as a saturated accumulator can give
    with pytest.raises(
        ArtifactError, match=r"m\.int8\.onnx: .*departs from its float network.*cosine down to -1"
    ):
        check_agreement(semi, flipped, semi, desc, "m.int8.onnx")
    noisy = semi + np.random.default_rng(0).normal(0, 3 * semi.std(), semi.shape)
    with pytest.raises(ArtifactError, match="detector correlation"):
        check_agreement(noisy, desc, semi, desc, "m.int8.onnx")
