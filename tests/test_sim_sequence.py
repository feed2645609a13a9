"""SimulatedSequence: the Sequence protocol, determinism, routes with revisits, odometry, the three presets."""

from __future__ import annotations

import time

import numpy as np
import pytest

from placerec.errors import ConfigError
from placerec.sim import SimulatedSequence, build_world, find_revisits, make_route
from placerec.types import Scan, Sequence


@pytest.fixture(scope="module")
def town() -> SimulatedSequence:
    return SimulatedSequence("town", "os1-64", seed=0)


def _bytes(scan: Scan) -> bytes:
    return scan.xyz.tobytes() + scan.intensity.tobytes() + scan.ring.tobytes()


def test_protocol_and_default_route(town: SimulatedSequence) -> None:
    assert isinstance(town, Sequence)
    assert 300 <= len(town) <= 420
    assert town.poses.shape == (len(town), 4, 4) and town.poses.dtype == np.float64
    assert np.all(np.diff(town.timestamps) > 0)
    step = np.linalg.norm(np.diff(town.poses[:, :3, 3], axis=0), axis=1)
    assert np.median(step) == pytest.approx(1.0, abs=0.02)
    R = town.poses[:, :3, :3]
    assert np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-9)
    assert town.name.startswith("sim-town-os1-64")
    assert town.odometry_poses is None
    with pytest.raises(IndexError):
        town[len(town)]
    assert town[-1].source == town[len(town) - 1].source


def test_pickles_by_construction_arguments() -> None:
    import pickle

    small = SimulatedSequence("town", "vlp16", n_scans=4, seed=0, odometry_drift=True)
    back = pickle.loads(pickle.dumps(small))
    assert _bytes(back[2]) == _bytes(small[2])
    assert np.array_equal(back.odometry_poses, small.odometry_poses)


def test_concurrent_rendering_is_deterministic() -> None:
    import threading

    seq = SimulatedSequence("town", "vlp16", n_scans=12, seed=0)
    ref = {i: _bytes(seq[i]) for i in range(0, 12, 2)}
    out: dict[int, bytes] = {}
    threads = [threading.Thread(target=lambda i=i: out.__setitem__(i, _bytes(seq[i]))) for i in ref]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert out == ref
    seq._renderer.threads = 1  # the 2-thread shading does not change the bytes
    assert _bytes(seq[4]) == ref[4]


def test_same_seed_same_bytes_different_seed_different(town: SimulatedSequence) -> None:
    again = SimulatedSequence("town", "os1-64", seed=0)
    a = _bytes(town[42])
    _ = again[7]  # rendering order must not matter
    assert _bytes(again[42]) == a
    assert _bytes(town[42]) == a
    other = SimulatedSequence("town", "os1-64", seed=1, n_scans=50)
    assert _bytes(other[42]) != a
    assert not np.allclose(other.poses[:50], town.poses[:50])


def test_revisits_exist_where_the_route_says(town: SimulatedSequence) -> None:
    kinds = {r.kind for r in town.revisits}
    assert {"same", "opposite"} <= kinds
    xy = town.poses[:, :2, 3]
    for r in town.revisits:
        for i in range(r.start, r.stop):
            d = np.linalg.norm(xy[r.ref_start : r.ref_stop] - xy[i], axis=1).min()
            assert d < 6.0
    same = max((r for r in town.revisits if r.kind == "same"), key=lambda r: r.stop - r.start)
    opposite = max((r for r in town.revisits if r.kind == "opposite"), key=lambda r: r.stop - r.start)
    assert same.stop - same.start >= 30 and opposite.stop - opposite.start >= 30
    assert 2.5 < same.mean_distance < 4.5  # second pass one lane over (lateral offset ~3.5 m)
    assert 2.5 < opposite.mean_distance < 4.5  # opposite lane
    yaw = np.arctan2(town.poses[:, 1, 0], town.poses[:, 0, 0])
    mid, ref = (opposite.start + opposite.stop) // 2, None
    ref = np.argmin(np.linalg.norm(xy[: opposite.start - 50] - xy[mid], axis=1))
    assert abs(abs(np.angle(np.exp(1j * (yaw[mid] - yaw[ref])))) - np.pi) < 0.3
    # scans before the first revisit never come back near an earlier place
    first = min(r.start for r in town.revisits)
    assert find_revisits(town.poses[:first]) == []


def _orb_matches(a: Scan, b: Scan) -> int:
    import cv2

    def img8(s: Scan) -> np.ndarray:
        it = s.organized("intensity")
        return (255 * np.clip(it / np.percentile(it[it > 0], 99), 0, 1)).astype(np.uint8)

    orb = cv2.ORB_create(nfeatures=500, edgeThreshold=15, fastThreshold=20)
    _, da = orb.detectAndCompute(img8(a), None)
    _, db = orb.detectAndCompute(img8(b), None)
    pairs = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(da, db, k=2)
    return sum(
        1 for p in pairs if len(p) == 2 and p[0].distance < 0.75 * p[1].distance and p[0].distance < 50
    )


def test_revisited_place_looks_alike(town: SimulatedSequence) -> None:
    """ORB features on the intensity images match across a same-direction revisit, not across distant places."""
    same = max((r for r in town.revisits if r.kind == "same"), key=lambda r: r.stop - r.start)
    xy = town.poses[:, :2, 3]
    pair = far = 0
    for i in (same.start + 5, (same.start + same.stop) // 2):
        j = same.ref_start + int(
            np.argmin(np.linalg.norm(xy[same.ref_start : same.ref_stop] - xy[i], axis=1))
        )
        pair += _orb_matches(town[i], town[j])
        far += _orb_matches(town[i], town[(i + 150) % len(town)])
    assert pair > 2 * far + 10


def test_route_kinds_and_extension() -> None:
    w = build_world("town", 0)
    loop = make_route(w, "loop")
    assert any(r.kind == "same" and r.stop - r.start > 100 for r in loop.revisits)
    long = SimulatedSequence("town", "vlp16", n_scans=900, seed=0, clutter=False)
    assert len(long) == 900
    rev = np.zeros(900, bool)
    for r in long.revisits:
        rev[r.start : r.stop] = True
    runs = np.diff(np.flatnonzero(np.diff(np.r_[1, rev.astype(int), 1]) != 0))
    assert runs.max() >= 150  # a long stretch without revisits
    hz = make_route(w, "default", rate_hz=10.0)
    assert np.allclose(np.diff(hz.timestamps), 0.1)
    with pytest.raises(ConfigError):
        make_route(w, "zigzag")


@pytest.mark.parametrize("preset", ["town", "campus", "industrial"])
def test_routes_stay_clear_of_obstacles(preset: str) -> None:
    w = build_world(preset, 0)
    for kind in ("default", "long"):
        xy = make_route(w, kind).poses[:, :2, 3]
        assert w.free.is_free(xy[:, 0], xy[:, 1]).all()


def test_odometry_drift() -> None:
    seq = SimulatedSequence("town", "vlp16", seed=2, odometry_drift=0.02, clutter=False)
    odo = seq.odometry_poses
    assert odo.shape == seq.poses.shape
    assert np.allclose(odo[0], seq.poses[0])
    err = np.linalg.norm(odo[:, :3, 3] - seq.poses[:, :3, 3], axis=1)
    assert err[-1] > 0.5 and err[10] < err[-1]


@pytest.mark.parametrize("preset", ["campus", "industrial"])
def test_other_presets_render(preset: str, warm_kernels: None) -> None:
    t0 = time.perf_counter()
    seq = SimulatedSequence(preset, "os1-64", seed=0, n_scans=40)
    scan = seq[20]
    valid = np.any(scan.xyz != 0, axis=1)
    assert valid.mean() > 0.3
    assert len(np.unique(scan.intensity[valid])) > 200
    assert any(r.kind == "same" for r in make_route(seq.world, "default").revisits)
    assert seq.world.build_seconds < 5.0 and time.perf_counter() - t0 < 20


def test_generation_is_fast_enough(warm_kernels: None) -> None:
    seq = SimulatedSequence("town", "os1-64", seed=0, n_scans=60)
    t0 = time.perf_counter()
    for i in range(0, 60, 6):
        seq[i]
    assert time.perf_counter() - t0 < 10.0  # 10 scans; the benchmark (tools/bench_sim.py) measures properly


def test_clutter_changes_between_visits_but_occluders_are_near() -> None:
    w = build_world("town", 0)
    base = SimulatedSequence(w, "vlp16", seed=0, n_scans=5)
    pose = base.poses[2]
    a = base.scan_at(pose, timestamp=10.0, index=2)
    b = base.scan_at(pose, timestamp=4000.0, index=2)
    assert _bytes(a) != _bytes(b)
    occ = base.scan_at(pose, timestamp=10.0, index=2, occluders=True)
    near = lambda s: np.mean(np.linalg.norm(s.xyz, axis=1) < 4.5)  # noqa: E731
    assert near(occ) > near(a) + 0.05


def test_euler_rotation_matches_zyx_convention():
    from scipy.spatial.transform import Rotation

    from placerec.sim.geometry import euler_rotation

    rng = np.random.default_rng(0)
    a = rng.uniform(-3, 3, (50, 3))
    R = euler_rotation(a[:, 0], a[:, 1], a[:, 2])
    np.testing.assert_allclose(R, Rotation.from_euler("ZYX", a).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(
        euler_rotation(0.3, 0.0, 0.0), Rotation.from_euler("z", 0.3).as_matrix(), atol=1e-12
    )
