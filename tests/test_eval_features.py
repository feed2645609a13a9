"""Feature repeatability / matching score (placerec/eval/features.py, tools/eval_features.py) and the pixel
correspondences they rest on (placerec/image/correspondence.py), on scans with known answers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from tool_modules import load_tool

from placerec.eval.features import (
    PairTruth,
    View,
    coincidence,
    evaluate_pair,
    ground_truth_pixels,
    keypoint_pixels,
    mean_scores,
)
from placerec.features import Features, make_extractor
from placerec.features.synthetic import textured_image
from placerec.image.correspondence import pixel_correspondences, pixel_points
from placerec.image.projection import make_image
from placerec.types import Scan

H, W = 64, 1024
ROOT = Path(__file__).resolve().parents[1]


def _yaw(angle: float) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(angle), np.sin(angle)
    T[:2, :2] = [[c, -s], [s, c]]
    return T


def _room_xyz(seed: int = 0) -> np.ndarray:
    """(H, W, 3) points of an organised 64 x 1024 scan (+15..-15 deg) in an irregular room: walls 6-14 m away,
    changing every few degrees (nothing rotationally symmetric), ground 1.7 m below the sensor."""
    rng = np.random.default_rng(seed)
    theta = np.pi * (
        1 - 2 * (np.arange(W) + 0.5) / W
    )  # the projection's column convention, u = 0.5 (1 - t/pi) W
    elev = np.radians(np.linspace(15.0, -15.0, H))
    wall = np.repeat(rng.uniform(6.0, 14.0, W // 16), 16) + 0.5 * np.sin(5 * theta)
    r = np.broadcast_to(wall, (H, W)).copy()
    below = elev < 0
    ground = 1.7 / np.sin(-elev[below])
    r[below] = np.minimum(r[below], ground[:, None])
    ce = np.cos(elev)[:, None]
    return np.stack([r * ce * np.cos(theta), r * ce * np.sin(theta), r * np.sin(elev)[:, None]], axis=2)


def _scan(xyz: np.ndarray, intensity: np.ndarray) -> Scan:
    return Scan(xyz.reshape(-1, 3).astype(np.float32), intensity.reshape(-1).astype(np.float32), shape=(H, W))


@pytest.fixture(scope="module")
def room() -> tuple[np.ndarray, np.ndarray]:
    return _room_xyz(), textured_image(H, W, seed=3).astype(np.float32)


def _rolled(xyz: np.ndarray, inten: np.ndarray, k: int) -> tuple[Scan, np.ndarray]:
    """The same room seen by a sensor yawed by -k columns: its organised scan is A's rolled by k columns.
    Returns (scan B, a_to_b)."""
    a_to_b = _yaw(-2 * np.pi * k / W)
    xyz_b = np.roll(xyz, k, axis=1) @ a_to_b[:3, :3].T
    return _scan(xyz_b, np.roll(inten, k, axis=1)), a_to_b


def _view(scan: Scan) -> View:
    return View.from_scan(scan)


# -- pixel correspondences ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("k", [0, 37, 512, 1000])
def test_correspondences_of_a_yawed_scan_are_the_column_shift(room, k: int) -> None:
    xyz, inten = room
    a = _scan(xyz, inten)
    b, a_to_b = _rolled(xyz, inten, k)
    pa, pb = pixel_points(make_image(a), a), pixel_points(make_image(b), b)
    corr = pixel_correspondences(pa, pb, a_to_b)
    assert len(corr) == H * W  # every pixel, one-to-one
    np.testing.assert_array_equal(corr.uv_b[:, 0], (corr.uv_a[:, 0] + k) % W)
    np.testing.assert_array_equal(corr.uv_b[:, 1], corr.uv_a[:, 1])
    assert corr.dist.max() < 1e-3
    # the same map as flat pixel indices, both ways
    gt = ground_truth_pixels(pa, pb, a_to_b)
    u, v = np.arange(H * W) % W, np.arange(H * W) // W
    np.testing.assert_array_equal(gt, v * W + (u + k) % W)


def test_occluded_points_get_no_partner(room) -> None:
    """A wall 2 m in front of scan B (columns 300-399) hides what A sees there: those pixels of A have no
    partner, nor have the wall's pixels in B; everything else keeps its partner."""
    xyz, inten = room
    xyz_b = xyz.copy()
    cols = slice(300, 400)
    unit = xyz[:, cols] / np.linalg.norm(xyz[:, cols], axis=2, keepdims=True)
    xyz_b[:, cols] = unit * 2.0
    a, b = _scan(xyz, inten), _scan(xyz_b, inten)
    pa, pb = pixel_points(make_image(a), a), pixel_points(make_image(b), b)
    corr = pixel_correspondences(pa, pb, np.eye(4))
    assert not ((corr.uv_a[:, 0] >= 300) & (corr.uv_a[:, 0] < 400)).any()
    assert not ((corr.uv_b[:, 0] >= 300) & (corr.uv_b[:, 0] < 400)).any()
    assert len(corr) == H * (W - 100)
    np.testing.assert_array_equal(corr.uv_a, corr.uv_b)
    # without the mutual check only A's pixels next to the wall's edge (within 0.3 m of B's last visible
    # column) find a partner, never those well behind it
    loose = pixel_correspondences(pa, pb, np.eye(4), mutual=False)
    assert not ((loose.uv_a[:, 0] >= 310) & (loose.uv_a[:, 0] < 390)).any()
    assert not ((loose.uv_b[:, 0] >= 300) & (loose.uv_b[:, 0] < 400)).any()


def test_wrong_pose_leaves_few_correspondences(room) -> None:
    xyz, inten = room
    a = _scan(xyz, inten)
    b, _ = _rolled(xyz, inten, 200)
    pa, pb = pixel_points(make_image(a), a), pixel_points(make_image(b), b)
    corr = pixel_correspondences(pa, pb, np.eye(4))  # the frames mixed up: identity instead of the yaw
    right = (corr.uv_b[:, 0] == (corr.uv_a[:, 0] + 200) % W) & (corr.uv_b[:, 1] == corr.uv_a[:, 1])
    assert not right.any()


# -- the measures ---------------------------------------------------------------------------------------------------


def test_keypoint_pixels_takes_a_neighbour_in_a_hole() -> None:
    points = np.full((4, 8, 3), np.nan, np.float32)
    points[1, 2] = 1.0
    points[3, 7] = 2.0
    kp = np.array(
        [[2, 1], [3, 2], [0, 3], [5, 0]], np.float32
    )  # on it, diagonal neighbour, wraps to col 7, none
    np.testing.assert_array_equal(keypoint_pixels(kp, points), [1 * 8 + 2, 1 * 8 + 2, 3 * 8 + 7, -1])


def _features(uv: list[tuple[float, float]], desc: list[int]) -> Features:
    """Binary features whose descriptors differ in their first byte only (``desc``; 255 = all 32 bytes 255)."""
    n = len(uv)
    d = np.zeros((n, 32), np.uint8)
    d[:, 0] = desc
    d[np.asarray(desc) == 255] = 255
    return Features(np.array(uv, np.float32), np.ones(n), np.zeros(n), np.ones(n), np.zeros(n), d)


def test_hand_computed_pair(room) -> None:
    """Identity pose, identical views; keypoints chosen so the answer is known:
    A: a0 (10, 40), a1 (200, 40), a2 (500, 40), a3 (700, 40) with no 3D point behind it (a hole in A);
    B: b0 (11, 41) (1.4 px from a0), b1 (600, 40) (far from everything), b2 (500, 42) (2 px from a2),
       b3 (900, 40).
    Descriptors: a0<->b0, a1<->b1 (wrong), a2<->b3 (wrong) are mutual nearest; a3 and b2 are left over.
    A->B: overlap a0, a1, a2 (a3 has no point): repeated a0, a2 -> 2/3; correct matches a0-b0 -> 1/3; judged
    matches a0-b0, a1-b1, a2-b3 -> precision 1/3.
    B->A: overlap b0..b3: repeated b0 (a0), b2 (a2) -> 2/4; correct b0-a0 -> 1/4; judged 3 -> precision 1/3."""
    xyz, inten = room
    view = _view(_scan(xyz, inten))
    pts_a = view.points.copy()
    pts_a[38:43, 698:703] = np.nan  # a hole around a3
    a = View(view.image, pts_a)
    truth = PairTruth.from_views(a, view, np.eye(4))
    # Hamming: a0-b0 1 bit, a1-b1 1, a2-b3 1; a3 (all bytes 255) is far from everything, so b2's nearest (a1 or
    # a2, 5 bits) is taken: a3 and b2 stay unmatched
    fa = _features([(10, 40), (200, 40), (500, 40), (700, 40)], [0, 64, 128, 255])
    fb = _features([(11, 41), (600, 40), (500, 42), (900, 40)], [1, 65, 250, 129])
    s = evaluate_pair(fa, fb, truth)
    assert s.repeatability == pytest.approx((2 / 3 + 2 / 4) / 2)
    assert s.matching_score == pytest.approx((1 / 3 + 1 / 4) / 2)
    assert s.precision == pytest.approx(1 / 3)
    assert s.overlap_keypoints == pytest.approx((3 + 4) / 2)
    assert s.matches == 3 and s.keypoints == 4
    # half a turn away (u + 512) no keypoint of the other image is near: chance repeatability 0
    assert s.chance_repeatability == 0.0


def test_coincidence_wraps_columns_and_uses_3d(room) -> None:
    xyz, inten = room
    v = _view(_scan(xyz, inten))
    gt = ground_truth_pixels(v.points, v.points, np.eye(4))
    eye = np.eye(4)
    # pixels: column 0 and column 1022 are 2 px apart across the seam, 1018 is 6 px away (3D test off)
    overlap, C = coincidence(
        np.array([[0, 50]]), np.array([[1022, 50], [1018, 50]]), v.points, v.points, gt, eye, 3.0, 1e-3
    )
    assert overlap.tolist() == [True] and C.tolist() == [[True, False]]
    # 3D: two keypoints 5 px apart coincide exactly when their points are within max_dist
    kp_a, kp_b = np.array([[100, 20]]), np.array([[105, 20]])
    d = float(np.linalg.norm(xyz[20, 100] - xyz[20, 105]))
    assert coincidence(kp_a, kp_b, v.points, v.points, gt, eye, 3.0, d * 1.01)[1][0, 0]
    assert not coincidence(kp_a, kp_b, v.points, v.points, gt, eye, 3.0, d * 0.99)[1][0, 0]
    assert coincidence(kp_a, kp_b, v.points, v.points, gt, eye, 5.0, 1e-3)[1][0, 0]


def test_identical_images_score_one(room) -> None:
    xyz, inten = room
    v = _view(_scan(xyz, inten))
    truth = PairTruth.from_views(v, v, np.eye(4))
    assert truth.overlap == 1.0
    ex = make_extractor("orb")
    f = ex.extract(v.image)
    assert len(f) > 100
    s = evaluate_pair(f, f, truth)
    assert s.repeatability == 1.0
    assert s.matching_score > 0.97 and s.precision > 0.97


@pytest.mark.parametrize("name", ["orb", "fast-surf"])
def test_yawed_scan_scores_high_and_a_wrong_pose_near_zero(room, name: str) -> None:
    xyz, inten = room
    a = _scan(xyz, inten)
    b, a_to_b = _rolled(xyz, inten, 128)
    va, vb = _view(a), _view(b)
    ex = make_extractor(name)
    fa, fb = ex.extract(va.image), ex.extract(vb.image)
    good = evaluate_pair(fa, fb, PairTruth.from_views(va, vb, a_to_b))
    assert good.repeatability > 0.9 and good.matching_score > 0.8 and good.precision > 0.9
    assert good.chance_repeatability < 0.35
    wrong = evaluate_pair(fa, fb, PairTruth.from_views(va, vb, np.eye(4)))  # frames mixed up
    assert wrong.matching_score < 0.05 and wrong.precision < 0.1
    # repeatability keeps its chance level: ~300 keypoints in 64 x 1024 px put a random pixel within 3 px of
    # one with probability ~12 %, and the few keypoints a wrong pose leaves in the overlap are a small sample
    assert wrong.overlap_keypoints < 0.3 * good.overlap_keypoints and wrong.repeatability < 0.3
    summary = mean_scores([good, wrong])
    assert summary["pairs"] == 2 and summary["matching_score"] == pytest.approx(
        (good.matching_score + wrong.matching_score) / 2
    )


def test_judged_matches_agree_with_the_scores_and_draw(room, tmp_path: Path) -> None:
    from placerec.eval.features import judged_matches
    from placerec.experiment.figures import plot_feature_matches

    xyz, inten = room
    b, a_to_b = _rolled(xyz, inten, 128)
    va, vb = _view(_scan(xyz, inten)), _view(b)
    ex = make_extractor("orb")
    fa, fb = ex.extract(va.image), ex.extract(vb.image)
    truth = PairTruth.from_views(va, vb, a_to_b)
    qi, mi, judged, correct = judged_matches(fa, fb, truth)
    assert len(qi) > 100 and judged.all() and correct.mean() > 0.9
    # A -> B half of evaluate_pair's count
    s = evaluate_pair(fa, fb, truth)
    assert correct.sum() / judged.sum() == pytest.approx(s.precision, abs=0.05)
    _, _, _, wrong = judged_matches(fa, fb, PairTruth.from_views(va, vb, np.eye(4)))
    assert wrong.sum() < 0.1 * correct.sum()
    path = plot_feature_matches(
        va.image, vb.image, {"orb": (fa.keypoints[qi], fb.keypoints[mi], correct)}, tmp_path / "m.png", "room"
    )
    assert path.is_file() and path.stat().st_size > 10_000


def test_chance_repeatability_of_crowded_keypoints(room) -> None:
    """Keypoints on two rows, one every 8 columns, 'repeat' under any pose: their chance repeatability says so,
    while the matching score of unrelated descriptors stays ~0."""
    xyz, inten = room
    v = _view(_scan(xyz, inten))
    u = np.arange(0, W, 8, dtype=np.float32)
    kp = np.concatenate([np.stack([u, np.full_like(u, r)], 1) for r in (20.0, 40.0)])
    rng = np.random.default_rng(0)
    n = len(kp)
    fa = Features(
        kp, np.ones(n), np.zeros(n), np.ones(n), np.zeros(n), rng.integers(0, 256, (n, 32), np.uint8)
    )
    fb = Features(
        kp, np.ones(n), np.zeros(n), np.ones(n), np.zeros(n), rng.integers(0, 256, (n, 32), np.uint8)
    )
    wrong = evaluate_pair(fa, fb, PairTruth.from_views(v, v, _yaw(0.3)))
    assert wrong.chance_repeatability > 0.6 and wrong.repeatability > 0.6
    assert wrong.matching_score < 0.05


def test_empty_features_give_nan_not_errors(room) -> None:
    xyz, inten = room
    v = _view(_scan(xyz, inten))
    none = Features(np.zeros((0, 2)), [], [], [], [], np.zeros((0, 32), np.uint8))
    s = evaluate_pair(none, none, PairTruth.from_views(v, v, np.eye(4)))
    assert np.isnan(s.repeatability) and np.isnan(s.matching_score) and np.isnan(s.precision)
    assert np.isnan(s.chance_repeatability)
    assert s.keypoints == 0


# -- the tool on the real files -------------------------------------------------------------------------------------


def _tool():
    return load_tool("eval_features", "eval_features_tool")


def test_kitti_pair_scores_and_frame_mixup(real_data: Path) -> None:
    """KITTI 00 frames 94/95 with the ground-truth poses: ORB matches mostly correct; the pose of frames
    198/199 instead (a frame mix-up) gives near-zero scores."""
    from placerec.io import read_poses, read_scan

    tool = _tool()
    folder = real_data / "kitti00_frames"
    P, _ = read_poses(folder / "poses_00.txt")
    Tr, Tr_inv = tool.KITTI_TR_00, np.linalg.inv(tool.KITTI_TR_00)
    lidar = {k: Tr_inv @ P[k] @ Tr for k in (94, 95, 198, 199)}
    va, vb = (tool.view_of(read_scan(folder / f"{k:06d}.bin"), tool.KITTI_IMAGE) for k in (94, 95))
    ex = make_extractor("orb")
    fa, fb = ex.extract(va.image), ex.extract(vb.image)
    good = evaluate_pair(fa, fb, PairTruth.from_views(va, vb, np.linalg.inv(lidar[95]) @ lidar[94]))
    assert good.repeatability > 0.6 and good.matching_score > 0.2 and good.precision > 0.5
    mixed = evaluate_pair(fa, fb, PairTruth.from_views(va, vb, np.linalg.inv(lidar[95]) @ lidar[198]))
    assert mixed.matching_score < 0.05 and mixed.precision < 0.1


def test_tool_skips_superpoint_without_weights(tmp_path: Path) -> None:
    tool = _tool()
    log: list[str] = []
    extractors = tool.make_extractors(["orb", "superpoint"], str(tmp_path / "absent.npz"), log)
    assert list(extractors) == ["orb"]
    assert len(log) == 1 and log[0].startswith("superpoint skipped") and "absent.npz" in log[0]


def test_tool_simulator_pairs_are_ahead_or_revisits() -> None:
    from placerec.sim import SimulatedSequence

    tool = _tool()
    seq = SimulatedSequence("town", "os1-64", seed=200)
    xyz = seq.poses[:, :3, 3]
    pairs = tool._pose_pairs(seq, np.random.default_rng(0), 3, 2)
    assert pairs == tool._pose_pairs(seq, np.random.default_rng(0), 3, 2)  # deterministic
    kinds = [k.split()[0] for _, _, k in pairs]
    assert kinds == ["ahead"] * 3 + ["revisit"] * 2
    for a, b, kind in pairs:
        d = float(np.linalg.norm(xyz[b] - xyz[a]))
        if kind.startswith("ahead"):
            assert b > a and 0.9 < d < 8.5
        else:
            r = next(r for r in seq.revisits if r.start <= a < r.stop)
            assert r.ref_start <= b < r.ref_stop and d < 10


@pytest.mark.slow
def test_tool_on_the_real_pairs(real_data: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import csv
    import json

    out = tmp_path / "pairs.csv"
    args = ["--no-sim", "--extractors", "orb", "--repeats", "1", "--real", str(real_data), "--csv", str(out),
            "--figure", str(tmp_path / "matches.png")]  # fmt: skip
    headline = _tool().main(args)
    rows = list(csv.DictReader(out.open()))
    assert [r["set"] for r in rows] == ["os1", "kitti", "kitti"]
    kitti = [float(r["matching_score"]) for r in rows if r["set"] == "kitti"]
    assert headline["scores"]["orb"]["kitti"]["matching_score"] == pytest.approx(np.mean(kitti), abs=1e-4)
    assert headline["pairs"] == {"os1": 1, "kitti": 2, "real": 3}
    real = headline["scores"]["orb"]["real"]
    assert real["matching_score"] > 0.3 and real["precision"] > 0.6
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1]) == headline
    assert (tmp_path / "matches.png").is_file()
    # --figure '' draws none (it once wrote './.png' into the working folder)
    none = tmp_path / "none"
    none.mkdir()
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(none)
        _tool().main([*args[:-2], "--figure", ""])
    assert list(none.iterdir()) == []


def test_tool_view_cache_round_trip_and_broken_entry(room, tmp_path: Path) -> None:
    tool = _tool()
    xyz, inten = room
    seq = [_scan(xyz, inten)]
    first = tool._cached_view(seq, 0, "k", tmp_path)
    entry = tmp_path / "k_0.npz"
    assert entry.is_file()
    again = tool._cached_view([None], 0, "k", tmp_path)  # read back: the sequence is not touched
    np.testing.assert_array_equal(again.image, first.image)
    np.testing.assert_array_equal(again.points, first.points)
    entry.write_bytes(b"not an npz")
    remade = tool._cached_view(seq, 0, "k", tmp_path)
    np.testing.assert_array_equal(remade.image, first.image)
