"""SuperPoint weights that prove what they are (issue #27): content hashes in the provenance, ``trust_model`` for a
user's files without, and the probe-image sanity check every loaded network passes. The hostile models are written
into tmp_path copies; the shipped files are only read."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from placerec.errors import ArtifactError
from placerec.features import make_extractor
from placerec.features.superpoint import extractor as sp_extractor
from placerec.features.superpoint import probe as sp_probe
from placerec.features.superpoint import weights as sp_weights
from placerec.features.superpoint.arch import SuperPointArch, conv_layers
from placerec.features.superpoint.extractor import SuperPointNet, SuperPointParams
from placerec.features.superpoint.weights import (
    SHIPPED_WEIGHTS,
    file_sha256,
    int8_path,
    load_weights,
    onnx_path,
    open_model,
    provenance_path,
    save_weights,
)

SMALL = SuperPointArch(encoder=[4, 4, 8, 8], head=8, descriptor_dim=16)
HOSTILE = ["random", "negated-descriptor-head", "nan-bias", "flipped-bytes"]


def _random_weights(arch: SuperPointArch, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    out = {}
    for c in sum(conv_layers(arch), []):
        scale = np.sqrt(2.0 / (c.c_in * c.kernel * c.kernel))
        shape = (c.c_out, c.c_in, c.kernel, c.kernel)
        out[f"{c.name}.weight"] = rng.normal(0, scale, shape).astype(np.float32)
        out[f"{c.name}.bias"] = rng.normal(0, 0.01, c.c_out).astype(np.float32)
    return out


def _image(h: int = 64, w: int = 512, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.kron(rng.integers(0, 255, (h // 4, w // 4)), np.ones((4, 4))).astype(np.uint8)


def _copy_shipped(folder: Path, stem: str = "sp") -> Path:
    """A copy of the shipped weights, ONNX model and provenance in ``folder``; returns the copy's .npz."""
    folder.mkdir(parents=True, exist_ok=True)
    for suffix in (".npz", ".onnx", ".json"):
        shutil.copyfile(SHIPPED_WEIGHTS.with_suffix(suffix), folder / f"{stem}{suffix}")
    return folder / f"{stem}.npz"


def _write_onnx(path: Path, arch: SuperPointArch, weights: dict[str, np.ndarray]) -> None:
    from placerec.features.superpoint.onnx_graph import onnx_model_bytes

    path.write_bytes(onnx_model_bytes(arch, weights))


def _hostile(tmp_path: Path, kind: str) -> Path:
    """A copy of the shipped model whose ONNX file is replaced by a valid but different network (or damaged)."""
    pytest.importorskip("onnx")
    weights = _copy_shipped(tmp_path / kind)
    arch, shipped = load_weights(SHIPPED_WEIGHTS)
    model = onnx_path(weights)
    if kind == "random":
        _write_onnx(model, arch, _random_weights(arch, seed=3))
    elif kind == "negated-descriptor-head":
        bad = dict(shipped, **{k: -shipped[k] for k in ("convDb.weight", "convDb.bias")})
        _write_onnx(model, arch, bad)
    elif kind == "nan-bias":
        bias = shipped["convPa.bias"].copy()
        bias[5] = np.nan
        _write_onnx(model, arch, dict(shipped, **{"convPa.bias": bias}))
    elif kind == "flipped-bytes":  # 100 bytes of the second half, where the initialisers' data lies
        data = bytearray(model.read_bytes())
        rng = np.random.default_rng(100)
        for i in rng.choice(np.arange(len(data) // 2, len(data)), 100, replace=False):
            data[i] ^= 0xFF
        model.write_bytes(bytes(data))
    else:
        raise AssertionError(kind)
    return weights


@pytest.fixture
def no_cv2_read(monkeypatch):
    """cv2.dnn must not read an ONNX model whose hash has not been checked."""

    def refuse(*args, **kwargs):
        raise AssertionError("cv2.dnn read an ONNX model before its hash was checked")

    monkeypatch.setattr(sp_extractor.cv2.dnn, "readNetFromONNX", refuse)


# ----------------------------------------------------------------------------- the shipped model


def test_shipped_provenance_records_the_shipped_files_hashes() -> None:
    prov = json.loads(provenance_path(SHIPPED_WEIGHTS).read_text())
    assert prov["sha256"] == {
        "weights": file_sha256(SHIPPED_WEIGHTS),
        "onnx": file_sha256(onnx_path(SHIPPED_WEIGHTS)),
        "int8": file_sha256(int8_path(SHIPPED_WEIGHTS)),
    }


def test_shipped_model_loads_checked_and_extracts() -> None:
    net = SuperPointNet(None, "cv2")
    assert net.files.accepted == "shipped" and net.files.sha256["onnx"] == file_sha256(
        onnx_path(SHIPPED_WEIGHTS)
    )
    f = make_extractor("superpoint").extract(_image())
    assert len(f) > 0 and f.descriptors.shape == (len(f), 256) and np.isfinite(f.descriptors).all()


def test_the_shipped_files_are_checked_even_when_trusted(tmp_path, monkeypatch) -> None:
    """trust_model is for a user's files: files claiming to be the shipped ones are always checked."""
    copy = _hostile(tmp_path, "negated-descriptor-head")
    monkeypatch.setattr(sp_weights, "SHIPPED_WEIGHTS", copy)
    with pytest.raises(ArtifactError, match=r"sp\.onnx.*hash mismatch.*reinstall placerec"):
        open_model(copy, trust_model=True)


# ----------------------------------------------------------------------------- hostile ONNX models


@pytest.mark.parametrize("kind", HOSTILE)
def test_a_hostile_onnx_beside_the_shipped_weights_is_refused_before_cv2_reads_it(
    tmp_path, kind: str, no_cv2_read
) -> None:
    weights = _hostile(tmp_path, kind)
    with pytest.raises(ArtifactError, match=r"sp\.onnx: content hash mismatch.*trust_model: true") as err:
        make_extractor("superpoint", weights=str(weights))
    assert "sp.json" in str(err.value)


@pytest.mark.parametrize("kind", HOSTILE)
def test_a_trusted_hostile_onnx_runs_only_if_the_probe_finds_it_sane(tmp_path, kind: str) -> None:
    weights = _hostile(tmp_path, kind)
    if kind == "nan-bias":
        with pytest.raises(ArtifactError, match=r"sp\.onnx: .* not finite"):
            make_extractor("superpoint", weights=str(weights), trust_model=True)
        return
    try:
        ext = make_extractor("superpoint", weights=str(weights), trust_model=True)
    except ArtifactError as exc:  # flipped bytes: unreadable, or an insane network
        assert kind == "flipped-bytes" and "sp.onnx" in str(exc)
        return
    assert ext._model.files.accepted == "trusted"
    f = ext.extract(_image())
    assert f.descriptors.shape == (len(f), 256) and np.isfinite(f.descriptors).all()


def test_a_replaced_npz_is_refused_for_the_torch_backend_too(tmp_path) -> None:
    """The torch backend reads only the .npz: its hash is checked all the same."""
    weights = _copy_shipped(tmp_path)
    arch, shipped = load_weights(weights)
    provenance = weights.with_suffix(".json").read_text()
    save_weights(weights, arch, dict(shipped, **{"convDb.weight": -shipped["convDb.weight"]}))
    weights.with_suffix(".json").write_text(provenance)  # the shipped provenance, now describing other files
    with pytest.raises(ArtifactError, match=r"sp\.npz: content hash mismatch"):
        open_model(weights, onnx=False)


def test_an_onnx_of_128_d_descriptors_is_refused_at_load(tmp_path) -> None:
    """Beside weights whose header says 256-d: refused by its hash, and by the probe when trusted, not later when
    a 256-d vocabulary meets 128-d descriptors."""
    pytest.importorskip("onnx")
    weights = _copy_shipped(tmp_path)
    arch, shipped = load_weights(weights)
    narrow = arch.model_copy(update={"descriptor_dim": 128})
    head = {"convDb.weight": shipped["convDb.weight"][:128], "convDb.bias": shipped["convDb.bias"][:128]}
    _write_onnx(onnx_path(weights), narrow, dict(shipped, **head))
    with pytest.raises(ArtifactError, match="hash mismatch"):
        make_extractor("superpoint", weights=str(weights))
    with pytest.raises(ArtifactError, match=r"sp\.onnx: .* gives 128-d descriptors.* says 256-d"):
        make_extractor("superpoint", weights=str(weights), trust_model=True)


# ----------------------------------------------------------------------------- a user's own model


@pytest.fixture
def own_model(tmp_path) -> Path:
    pytest.importorskip("onnx")
    path = tmp_path / "own.npz"
    save_weights(path, SMALL, _random_weights(SMALL), provenance={"what": "a test model"})
    return path


def test_save_weights_records_both_files_hashes(own_model: Path) -> None:
    prov = json.loads(provenance_path(own_model).read_text())
    assert prov["what"] == "a test model" and prov["format_version"] == 1
    assert prov["sha256"] == {"weights": file_sha256(own_model), "onnx": file_sha256(onnx_path(own_model))}
    for backend in ("cv2", "torch") if _has_torch() else ("cv2",):
        assert SuperPointNet(own_model, backend).files.accepted == "provenance"


def _has_torch() -> bool:
    try:
        import torch  # noqa: F401
    except ImportError:
        return False
    return True


@pytest.mark.parametrize("provenance", ["absent", "no-hashes", "not-json", "bad-hash"])
def test_a_model_without_vouching_provenance_needs_trust_model(own_model: Path, provenance: str) -> None:
    prov = provenance_path(own_model)
    if provenance == "absent":
        prov.unlink()
    elif provenance == "no-hashes":
        prov.write_text(json.dumps({"format_version": 1}))
    elif provenance == "not-json":
        prov.write_text("{not json")
    else:
        prov.write_text(json.dumps({"sha256": {"weights": "abc", "onnx": "abc"}}))
    with pytest.raises(ArtifactError, match=r"own\.npz: .*(trust_model: true|record-hashes)") as err:
        make_extractor("superpoint", weights=str(own_model))
    assert "save_weights" in str(err.value) and "--record-hashes" in str(err.value)
    ext = make_extractor("superpoint", weights=str(own_model), trust_model=True)
    assert ext._model.files.accepted == "trusted" and ext.descriptor_size == 16
    assert ext.extract(_image()).descriptors.shape[1] == 16


def test_trusting_a_model_once_does_not_trust_it_later(own_model: Path) -> None:
    provenance_path(own_model).unlink()
    make_extractor("superpoint", weights=str(own_model), trust_model=True)
    with pytest.raises(ArtifactError, match="trust_model"):
        make_extractor("superpoint", weights=str(own_model))


def test_files_changed_after_a_load_are_checked_again(own_model: Path) -> None:
    make_extractor("superpoint", weights=str(own_model))
    _write_onnx(onnx_path(own_model), SMALL, _random_weights(SMALL, seed=9))
    with pytest.raises(ArtifactError, match=r"own\.onnx: content hash mismatch"):
        make_extractor("superpoint", weights=str(own_model))


def test_record_hashes_tool_vouches_for_files_you_made(own_model: Path, capsys) -> None:
    import importlib.util

    root = Path(__file__).resolve().parents[1]
    spec = importlib.util.spec_from_file_location("train_superpoint", root / "tools" / "train_superpoint.py")
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    provenance_path(own_model).unlink()
    assert tool.main(["--record-hashes", str(own_model)]) == 0
    assert json.loads(capsys.readouterr().out.splitlines()[-1])["sha256"]["onnx"] == file_sha256(
        onnx_path(own_model)
    )
    assert SuperPointNet(own_model, "cv2").files.accepted == "provenance"


# ----------------------------------------------------------------------------- the probe


@pytest.mark.parametrize("fault", ["constant-detector", "constant-descriptors", "zero-descriptors"])
def test_a_degenerate_network_is_refused_by_the_probe_even_when_trusted(tmp_path, fault: str) -> None:
    pytest.importorskip("onnx")
    w = _random_weights(SMALL)
    if fault == "constant-detector":
        w["convPb.weight"][:] = 0  # logits = bias everywhere
    elif fault == "constant-descriptors":
        w["convDb.weight"][:] = 0
        w["convDb.bias"][:] = 0.5
    else:
        w["convDb.weight"][:] = 0
        w["convDb.bias"][:] = 0
    path = tmp_path / "deg.npz"
    save_weights(path, SMALL, w)
    words = {"constant-detector": "logits are the same", "constant-descriptors": "descriptors are the same"}
    with pytest.raises(ArtifactError, match=rf"deg\.onnx: .*{words.get(fault, 'all zero')}"):
        make_extractor("superpoint", weights=str(path), trust_model=True)


def test_the_probe_image_is_deterministic_and_the_probe_runs_once_per_model(
    own_model: Path, monkeypatch
) -> None:
    img = sp_probe.probe_image()
    assert img.shape == sp_probe.PROBE_SHAPE and img.dtype == np.uint8 and not img.flags.writeable
    assert len(np.unique(img)) > 100
    calls = []
    real = sp_extractor.check_outputs
    monkeypatch.setattr(sp_extractor, "check_outputs", lambda *a: calls.append(a) or real(*a))
    monkeypatch.setattr(sp_extractor, "_PROBED", set())
    SuperPointNet(own_model, "cv2")
    SuperPointNet(own_model, "cv2")
    assert len(calls) == 1


def test_trust_model_is_a_documented_parameter() -> None:
    field = SuperPointParams.model_fields["trust_model"]
    assert field.default is False and "sha256" in (field.description or "")


def test_cv2_runs_the_bytes_that_were_hashed(own_model: Path, monkeypatch) -> None:
    """The ONNX model goes to cv2.dnn as the bytes checked, not as a path it would read again."""
    seen = []
    real = cv2.dnn.readNetFromONNX
    monkeypatch.setattr(sp_extractor.cv2.dnn, "readNetFromONNX", lambda src: seen.append(src) or real(src))
    net = SuperPointNet(own_model, "cv2")
    assert len(seen) == 1 and isinstance(seen[0], np.ndarray)
    assert seen[0].tobytes() == net.files.onnx == onnx_path(own_model).read_bytes()
