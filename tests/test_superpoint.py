"""SuperPoint: post-processing by hand, torch / cv2.dnn agreement, weights files, the extractor, training pieces."""

from __future__ import annotations

import json

import numpy as np
import pytest

from placerec.errors import ArtifactError
from placerec.experiment.superpoint_pairs import PairData, cell_labels, repeatable
from placerec.features import make_extractor
from placerec.features.superpoint.arch import CELL, SuperPointArch, conv_layers
from placerec.features.superpoint.post import (
    cubic_weights,
    keypoint_probability,
    sample_descriptors,
    select_keypoints,
)
from placerec.features.superpoint.weights import SHIPPED_WEIGHTS, load_weights, onnx_path, save_weights
from placerec.io.atomic import save_artifact

SMALL = SuperPointArch(encoder=[4, 4, 8, 8], head=8, descriptor_dim=16)


def _random_weights(arch: SuperPointArch, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    out = {}
    for c in sum(conv_layers(arch), []):
        scale = np.sqrt(2.0 / (c.c_in * c.kernel * c.kernel))
        out[f"{c.name}.weight"] = rng.normal(0, scale, (c.c_out, c.c_in, c.kernel, c.kernel)).astype(
            np.float32
        )
        out[f"{c.name}.bias"] = rng.normal(0, 0.01, c.c_out).astype(np.float32)
    return out


@pytest.fixture(scope="module")
def small_weights(tmp_path_factory) -> str:
    pytest.importorskip("onnx")
    path = tmp_path_factory.mktemp("sp") / "small.npz"
    save_weights(path, SMALL, _random_weights(SMALL))
    return str(path)


def _image(h: int = 64, w: int = 256, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = rng.integers(0, 255, (h // 4, w // 4)).astype(np.uint8)
    return np.kron(img, np.ones((4, 4), np.uint8))


# ----------------------------------------------------------------------------- post-processing


def test_depth_to_space_puts_each_channel_at_its_pixel() -> None:
    semi = np.zeros((65, 2, 3), np.float32)
    semi[64] = 5.0  # dustbin wins everywhere ...
    semi[8 * 5 + 2, 1, 2] = 20.0  # ... except cell (1, 2), position dy=5, dx=2
    prob = keypoint_probability(semi)
    assert prob.shape == (16, 24)
    v, u = np.unravel_index(np.argmax(prob), prob.shape)
    assert (v, u) == (8 + 5, 16 + 2)
    # softmax over 65 channels: the 64 kept plus the dustbin's share sum to one in every cell
    e = np.exp(semi - semi.max(0))
    dust = e[64] / e.sum(0)
    cells = prob.reshape(2, 8, 3, 8).sum(axis=(1, 3))
    np.testing.assert_allclose(cells + dust, 1.0, rtol=1e-5)


def test_nms_threshold_mask_and_order() -> None:
    prob = np.zeros((16, 32), np.float32)
    prob[5, 5], prob[5, 8] = 0.9, 0.8  # within radius 4: only the stronger survives
    prob[5, 20] = 0.5
    prob[12, 28] = 0.04  # below min_probability
    prob[12, 2] = 0.7  # masked out
    mask = np.ones_like(prob, np.uint8)
    mask[12, 2] = 0
    uv, score = select_keypoints(prob, mask, 0.05, 4, 10)
    assert uv.tolist() == [[5, 5], [20, 5]]
    np.testing.assert_allclose(score, [0.9, 0.5])
    uv1, _ = select_keypoints(prob, mask, 0.05, 4, 1)
    assert uv1.tolist() == [[5, 5]]


def test_cubic_weights_partition_of_unity_and_interpolation() -> None:
    t = np.linspace(0, 0.99, 7)
    w = cubic_weights(t)
    np.testing.assert_allclose(w.sum(-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(cubic_weights(np.array(0.0)), [0, 1, 0, 0], atol=1e-12)


def _keys(s: float, a: float = -0.75) -> float:
    s = abs(s)
    if s <= 1:
        return (a + 2) * s**3 - (a + 3) * s**2 + 1
    return a * s**3 - 5 * a * s**2 + 8 * a * s - 4 * a if s < 2 else 0.0


def test_bicubic_sampling_by_hand() -> None:
    hc, wc = 6, 10
    desc = np.zeros((2, hc, wc), np.float32)
    f = np.array([1.0, 4.0, 2.0, 7.0, 3.0, 5.0, 6.0, 2.0, 8.0, 1.0])
    desc[0] = f[None, :]  # varies along columns only
    desc[1] = 1.0
    uv = np.array([[20.0, 20.0], [37.0, 9.0], [50.0, 30.0]])  # away from the border
    d = sample_descriptors(desc, uv)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, rtol=1e-6)
    for (u, _), got in zip(uv, d[:, 0] / d[:, 1], strict=True):
        x = (u + 0.5) / CELL - 0.5  # cell centres at pixel 8 i + 3.5
        x0 = int(np.floor(x))
        expected = sum(_keys(x - (x0 + i)) * f[x0 + i] for i in (-1, 0, 1, 2))
        assert got == pytest.approx(expected, rel=1e-5)


def test_bicubic_taps_are_the_indexed_ones_in_their_layout_and_the_descriptors_bit_for_bit() -> None:
    """`sample_descriptors` gathers its 4 x 4 taps as whole cells (`_taps`): the same values and the same memory
    layout as NumPy's indexing ``d[:, rows, cols]``, so the weighting einsum, and the descriptors, are bit for bit
    those of the indexed gather, at the border too."""
    from placerec.features.superpoint.post import _taps, cubic_weights

    rng = np.random.default_rng(11)
    for dim, hc, wc, k in ((256, 8, 128, 300), (64, 4, 9, 40), (3, 2, 2, 5)):
        desc = rng.normal(size=(dim, hc, wc)).astype(np.float32)
        uv = np.stack([rng.uniform(0, wc * CELL - 1, k), rng.uniform(0, hc * CELL - 1, k)], 1).round()
        uv[:4] = [[0, 0], [wc * CELL - 1, hc * CELL - 1], [0, hc * CELL - 1], [wc * CELL - 1, 0]]  # corners
        x = (uv[:, 0] + 0.5) / CELL - 0.5
        y = (uv[:, 1] + 0.5) / CELL - 0.5
        taps = np.arange(-1, 3)
        cols = np.clip(np.floor(x)[:, None].astype(np.int64) + taps, 0, wc - 1)
        rows = np.clip(np.floor(y)[:, None].astype(np.int64) + taps, 0, hc - 1)
        indexed = desc[:, rows[:, :, None], cols[:, None, :]]
        gathered = _taps(desc, rows, cols)
        assert gathered.shape == indexed.shape and gathered.strides == indexed.strides
        np.testing.assert_array_equal(gathered, indexed)
        wx, wy = cubic_weights(x - np.floor(x)), cubic_weights(y - np.floor(y))
        ref = np.einsum("dkij,ki,kj->kd", indexed, wy, wx).astype(np.float32)
        ref /= np.maximum(np.linalg.norm(ref, axis=1, keepdims=True), 1e-12)
        np.testing.assert_array_equal(sample_descriptors(desc, uv), ref)


def test_bicubic_sampling_matches_torch_grid_sample() -> None:
    torch = pytest.importorskip("torch")
    rng = np.random.default_rng(3)
    desc = rng.normal(size=(5, 4, 9)).astype(np.float32)
    uv = np.array([[0, 0], [71, 31], [35, 17], [3, 30], [70, 1]], np.float64)
    ours = sample_descriptors(desc, uv)
    h, w = 4 * CELL, 9 * CELL
    grid = torch.tensor(
        np.stack([(uv[:, 0] + 0.5) / w * 2 - 1, (uv[:, 1] + 0.5) / h * 2 - 1], 1), dtype=torch.float32
    )
    ref = torch.nn.functional.grid_sample(
        torch.from_numpy(desc)[None],
        grid[None, None],
        mode="bicubic",
        padding_mode="border",
        align_corners=False,
    )[0, :, 0].T
    ref = torch.nn.functional.normalize(ref, dim=1).numpy()
    np.testing.assert_allclose(ours, ref, atol=1e-5)


# ----------------------------------------------------------------------------- backends and weights


def test_torch_and_cv2_backends_agree(small_weights: str) -> None:
    pytest.importorskip("torch")
    from placerec.features.superpoint.extractor import SuperPointNet

    img = _image(64, 1024)
    semi_c, desc_c = SuperPointNet(small_weights, "cv2").forward(img)
    semi_t, desc_t = SuperPointNet(small_weights, "torch").forward(img)
    assert semi_c.shape == (65, 8, 128) and desc_c.shape == (16, 8, 128)
    np.testing.assert_allclose(semi_c, semi_t, atol=1e-4)
    np.testing.assert_allclose(desc_c, desc_t, atol=1e-4)


def test_onnxruntime_runs_the_onnx_model_as_cv2_does(real_data) -> None:
    """The onnxruntime backend runs the shipped ONNX model: the network's outputs within 1e-4 of cv2.dnn's on a
    real KITTI image, and the extractor's keypoints and descriptors with them; its session's idle threads sleep."""
    pytest.importorskip("onnxruntime")
    from placerec.features.superpoint.extractor import SuperPointNet
    from placerec.image import make_image
    from placerec.io import read_scan

    frames = sorted((real_data / "kitti_raw_hdl64_sequence").glob("*.pcd"))
    assert frames, f"the real KITTI frames are missing under {real_data}"
    img = make_image(read_scan(frames[0])).image
    ort_net, cv2_net = SuperPointNet(None, "onnxruntime"), SuperPointNet(None, "cv2")
    assert ort_net.files.sha256 == cv2_net.files.sha256  # the same model files
    options = ort_net._net.get_session_options()
    assert options.get_session_config_entry("session.intra_op.allow_spinning") == "0"
    for a, b in zip(ort_net.forward(img), cv2_net.forward(img), strict=True):
        assert a.shape == b.shape
        np.testing.assert_allclose(a, b, atol=1e-4)
    fa = make_extractor("superpoint", backend="onnxruntime").extract(img)
    fb = make_extractor("superpoint", backend="cv2").extract(img)
    assert len(fa) >= 200
    shared = {tuple(k) for k in fa.keypoints} & {tuple(k) for k in fb.keypoints}
    assert len(shared) >= 0.98 * len(fb)
    if len(fa) == len(fb) and np.array_equal(fa.keypoints, fb.keypoints):
        np.testing.assert_allclose(fa.descriptors, fb.descriptors, atol=1e-4)


def test_onnxruntime_backend_errors_name_the_fix(tmp_path, monkeypatch) -> None:
    """Without ONNX Runtime: a `DependencyError` naming the extra; a model it cannot read: an `ArtifactError`
    naming the ONNX file."""
    pytest.importorskip("onnxruntime")
    import sys

    from placerec.errors import DependencyError
    from placerec.features.superpoint.extractor import _onnxruntime_session

    with pytest.raises(ArtifactError, match=r"w\.onnx.*backend 'cv2'"):
        _onnxruntime_session(b"not an onnx model", tmp_path / "w.onnx", "w.npz")
    monkeypatch.setitem(sys.modules, "onnxruntime", None)
    with pytest.raises(DependencyError, match=r"placerec\[onnxruntime\]"):
        _onnxruntime_session(b"", tmp_path / "w.onnx", "w.npz")


def test_shipped_weights_are_small_onnx_matches_and_backends_agree() -> None:
    if not SHIPPED_WEIGHTS.is_file():
        pytest.fail(f"the shipped SuperPoint weights {SHIPPED_WEIGHTS} are missing")
    size = SHIPPED_WEIGHTS.stat().st_size + onnx_path(SHIPPED_WEIGHTS).stat().st_size
    assert size <= 5_000_000
    arch, weights = load_weights(SHIPPED_WEIGHTS)
    provenance = json.loads(SHIPPED_WEIGHTS.with_suffix(".json").read_text())
    assert provenance["format_version"] == 1 and provenance["config"]["arch"] == arch.model_dump(mode="json")
    onnx = pytest.importorskip("onnx")
    from onnx import numpy_helper

    model = onnx.load(str(onnx_path(SHIPPED_WEIGHTS)))
    inits = {t.name: numpy_helper.to_array(t) for t in model.graph.initializer}
    assert set(inits) == set(weights)
    for k, v in weights.items():
        np.testing.assert_array_equal(inits[k], v)
    pytest.importorskip("torch")
    from placerec.image import make_image
    from placerec.sim import SimulatedSequence

    img = make_image(SimulatedSequence("town", "os1-64", seed=0)[3]).image
    a = make_extractor("superpoint", backend="cv2").extract(img)
    b = make_extractor("superpoint", backend="torch").extract(img)
    assert len(a) >= 200 and a.descriptors.shape == (len(a), arch.descriptor_dim)
    np.testing.assert_array_equal(a.keypoints, b.keypoints)
    np.testing.assert_allclose(a.descriptors, b.descriptors, atol=1e-4)


def test_weights_round_trip_in_float16(tmp_path) -> None:
    pytest.importorskip("onnx")
    w = _random_weights(SMALL)
    rounded = save_weights(tmp_path / "w.npz", SMALL, w)
    arch, loaded = load_weights(tmp_path / "w.npz")
    assert arch == SMALL
    for k in w:
        np.testing.assert_array_equal(loaded[k], rounded[k])
        np.testing.assert_allclose(loaded[k], w[k], rtol=1e-3, atol=1e-4)


@pytest.mark.parametrize("fault", ["kind", "missing", "shape", "nan", "arch"])
def test_bad_weights_files_are_artifact_errors_naming_the_file(tmp_path, fault: str) -> None:
    w = {k: v.astype(np.float16) for k, v in _random_weights(SMALL).items()}
    meta = {"arch": SMALL.model_dump(mode="json")}
    kind = "superpoint-weights"
    if fault == "kind":
        kind = "visual-dbow-db"
    elif fault == "missing":
        del w["convDb.bias"]
    elif fault == "shape":
        w["conv1a.weight"] = w["conv1a.weight"][:, :, :2]
    elif fault == "nan":
        w["convPa.bias"][0] = np.nan
    else:
        meta = {"arch": {"encoder": [4, 4], "head": 8, "descriptor_dim": 16}}
    path = tmp_path / "bad.npz"
    save_artifact(path, kind, 1, w, meta)
    with pytest.raises(ArtifactError, match="bad.npz"):
        load_weights(path)


@pytest.mark.parametrize("damage", ["missing", "truncated"])
def test_a_broken_onnx_model_is_an_artifact_error(tmp_path, damage: str) -> None:
    pytest.importorskip("onnx")
    from placerec.features.superpoint.extractor import SuperPointNet

    path = tmp_path / "w.npz"
    save_weights(path, SMALL, _random_weights(SMALL))
    model = onnx_path(path)
    if damage == "missing":
        model.unlink()
    else:
        model.write_bytes(model.read_bytes()[:500])
    with pytest.raises(ArtifactError, match="w.onnx"):
        SuperPointNet(path, "cv2")


def test_missing_weights_say_how_to_train(tmp_path) -> None:
    with pytest.raises(ArtifactError, match="train_superpoint"):
        make_extractor("superpoint", weights=str(tmp_path / "none.npz"))


# ----------------------------------------------------------------------------- the extractor


def test_extractor_keeps_a_keypoint_on_the_azimuth_seam(small_weights: str) -> None:
    img = _image(64, 256)
    ext = make_extractor("superpoint", weights=small_weights, min_probability=0.016, nfeatures=1000)
    base = ext.extract(img)
    rolled = ext.extract(np.roll(img, 100, axis=1))
    # the wrap-around padding makes the extractor equivariant to azimuth shifts (up to the 8-px cell grid)
    shifted = ext.extract(np.roll(img, 96, axis=1))
    a = {(int(u), int(v)) for u, v in base.keypoints}
    b = {(int((u - 96) % 256), int(v)) for u, v in shifted.keypoints}
    assert len(a & b) >= 0.9 * len(a)
    assert len(rolled) > 0
    mask = np.zeros_like(img)
    mask[:, :128] = 1
    half = ext.extract(img, mask)
    assert len(half) > 0 and half.keypoints[:, 0].max() < 128


def test_extractor_on_a_16_row_image(small_weights: str) -> None:
    f = make_extractor("superpoint", weights=small_weights, min_probability=0.016).extract(_image(16, 512))
    assert len(f) > 0 and f.keypoints[:, 1].max() <= 15


# ----------------------------------------------------------------------------- training pieces


def test_cell_labels_by_hand() -> None:
    uv = np.array([[3, 2], [5, 6], [17, 9]])
    labels = cell_labels(uv, np.array([1.0, 2.0, 0.5]), 16, 24)
    assert labels.shape == (2, 3)
    assert labels[0, 0] == 6 * 8 + 5  # the stronger of the two in cell (0, 0)
    assert labels[1, 2] == 1 * 8 + 1
    assert (labels == 64).sum() == 4


def test_repeatable_wraps_columns_and_needs_a_partner() -> None:
    cand_a = np.array([[10, 5], [20, 5], [30, 5]])
    cand_b = np.array([[1, 5], [100, 7]])
    m = np.full((16, 104, 2), -1, np.int32)
    m[5, 10] = [103, 5]  # 2 px from (1, 5) across the seam
    m[5, 20] = [100, 4]  # 3 px from (100, 7): too far
    out = repeatable(cand_a, cand_b, m, 104, 2.0)  # (30, 5) is not seen in B
    assert out.tolist() == [True, False, False]


def test_batch_crops_keep_correspondences_aligned() -> None:
    from placerec.artifacts.superpoint import TrainingSchedule, make_batch

    img = _image(64, 512, seed=4)
    shift = 137
    img_b = np.roll(img, shift, axis=1)
    v, u = np.mgrid[0:64:3, 0:512:5]
    uv_a = np.stack([u.ravel(), v.ravel()], 1)
    uv_b = np.stack([(uv_a[:, 0] + shift) % 512, uv_a[:, 1]], 1)
    kp = np.array([[40, 10], [300, 30]])
    pair = PairData(
        img,
        img_b,
        uv_a,
        uv_b,
        kp,
        np.ones(2, np.float32),
        (kp + [shift, 0]) % [512, 64],
        np.ones(2, np.float32),
        "synthetic",
    )
    s = TrainingSchedule(crop_width=128, samples=64, shift_jitter=8)
    rng = np.random.default_rng(0)
    for augment in (False, True):
        b = make_batch([pair, pair], s, rng, augment=augment)
        assert b["xa"].shape == (2, 64, 128) and b["la"].shape == (2, 8, 16)
        for k in range(2):
            ca, cb = b["ca"][k], b["cb"][k]
            assert (ca >= 0).all() and (ca[:, 0] < 128).all() and (cb[:, 0] < 128).all()
            if not augment:
                np.testing.assert_array_equal(b["xa"][k][ca[:, 1], ca[:, 0]], b["xb"][k][cb[:, 1], cb[:, 0]])


def test_a_short_training_run_writes_weights_curves_and_provenance(tmp_path) -> None:
    pytest.importorskip("torch")
    pytest.importorskip("onnx")
    from placerec.artifacts.superpoint import load_superpoint_config, train_superpoint
    from placerec.experiment import superpoint_pairs as training_data

    img = _image(64, 256, seed=5)
    v, u = np.mgrid[0:64:2, 0:256:3]
    uv = np.stack([u.ravel(), v.ravel()], 1).astype(np.int16)
    kp = np.array([[40, 10], [200, 30]], np.int16)
    pair = PairData(img, img, uv, uv, kp, np.ones(2, np.float32), kp, np.ones(2, np.float32), "same")
    cfg = load_superpoint_config(
        None,
        arch=SMALL.model_dump(mode="json"),
        train={"steps": 3, "batch": 2, "crop_width": 64, "samples": 32, "validate_every": 2, "log_every": 1},
        cache=str(tmp_path / "cache"),
        output=str(tmp_path / "out" / "sp.npz"),
        curves=str(tmp_path / "curves"),
    )
    cache = tmp_path / "cache" / f"pairs_{training_data.data_fingerprint(cfg.data)}.npz"
    cache.parent.mkdir()
    training_data._write_pairs(cache, {"train": [pair] * 3, "validation": [pair]})
    prov = train_superpoint(cfg)
    assert prov["pairs"] == {"train": 3, "validation": 1}
    assert all(np.isfinite(v) for v in prov["final"].values())
    arch, _ = load_weights(tmp_path / "out" / "sp.npz")
    assert arch == SMALL and (tmp_path / "out" / "sp.onnx").is_file()
    assert json.loads((tmp_path / "out" / "sp.json").read_text())["train_seconds"] >= 0
    curves = json.loads((tmp_path / "curves" / "loss_curves.json").read_text())
    assert curves["step"] == [1, 2, 3] and curves["val_step"] == [2, 3]
    assert (tmp_path / "curves" / "loss_curves.png").is_file()


def test_train_tool_validates_a_steps_override_before_training() -> None:
    import importlib.util
    from pathlib import Path

    from placerec.errors import ConfigError

    root = Path(__file__).resolve().parents[1]
    spec = importlib.util.spec_from_file_location("train_superpoint", root / "tools" / "train_superpoint.py")
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    with pytest.raises(ConfigError, match="train.steps"):
        tool.main(["--config", str(root / "configs" / "superpoint.yaml"), "--steps", "0"])
