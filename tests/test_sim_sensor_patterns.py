"""Sensor models beyond the spinning presets: HDL-32E, Livox Avia / MID-360 rosettes, the E1R solid-state raster,
scans rendered while moving, and the bit-identity of the presets that benchmarks are keyed on."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from placerec.errors import ConfigError
from placerec.sim import SimulatedSequence, get_sensor, sensor_names
from placerec.sim.sensors import frame_index, frame_rays, ray_grid
from placerec.sim.sequence import frame_end_poses

NEW = ("hdl32", "avia", "mid360", "e1r")


def _digest(scan) -> str:
    h = hashlib.sha256()
    for a in (scan.xyz, scan.intensity, scan.ring, scan.time):
        h.update(np.ascontiguousarray(a).tobytes())
    h.update(repr(scan.shape).encode())
    h.update(repr(scan.sensor.to_dict()).encode())
    return h.hexdigest()


# computed with the code before the new sensor models (commit d2a22a8): town, seed 0, 3 scans, scans 0 and 2
_BEFORE = {
    "os1-64": (
        "a887786e86ed852503c5769ff04f16423c4f5394db06dabd15764d9246550d4f",
        "34ee7a2ea71ac2d1b696084bc109fe32e3bceb41bc53052279be876ad0da5f19",
    ),
    "vlp16": (
        "a0e3a691c2f006104526f8bc78c4a5660d4c2e124fcce002eaa328033786d96a",
        "b1d1a78e815d2ab0d93889148b115ccfe4bfbe41c7e18fdefd2fa1f329441fb2",
    ),
}


@pytest.mark.parametrize("name", sorted(_BEFORE))
def test_existing_presets_render_bit_identical_scans(name: str) -> None:
    seq = SimulatedSequence("town", name, n_scans=3, seed=0)
    assert (_digest(seq[0]), _digest(seq[2])) == _BEFORE[name]


@pytest.fixture(scope="module")
def scans() -> dict:
    """One static scan (scan 1 of 3, town, seed 0) of every new sensor."""
    return {s: SimulatedSequence("town", s, n_scans=3, seed=0)[1] for s in NEW}


def _angles(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p = xyz.astype(np.float64)
    return np.degrees(np.arctan2(p[:, 1], p[:, 0])), np.degrees(
        np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1]))
    )


def test_names_and_aliases() -> None:
    names = sensor_names()
    assert set(NEW) <= set(names)
    for alias, name in [("hdl-32e", "hdl32"), ("HDL32E", "hdl32"), ("hdl-32", "hdl32"), ("livox-avia", "avia"),
                        ("mid-360", "mid360"), ("livox-mid360", "mid360"), ("rs-e1r", "e1r"),
                        ("robosense-e1r", "e1r")]:  # fmt: skip
        assert get_sensor(alias).name == name
    with pytest.raises(ConfigError):
        get_sensor("mid-70")


def test_sensor_info_of_rendered_scans(scans: dict) -> None:
    hdl = scans["hdl32"].sensor
    assert hdl.pattern == "spinning" and hdl.is_spinning and hdl.rate_hz == 10.0
    assert hdl.n_beams == 32 and hdl.columns == 2170 and hdl.intensity_max == 255.0
    assert hdl.beam_elevations_deg[0] == pytest.approx(10.67) and hdl.beam_elevations_deg[
        -1
    ] == pytest.approx(-30.67)
    assert np.allclose(np.diff(hdl.beam_elevations_deg), -1.3335, atol=1e-3)
    assert hdl.elevation_fov_deg is None and hdl.horizontal_fov_deg is None
    avia = scans["avia"].sensor
    assert (avia.pattern, avia.horizontal_fov_deg, avia.elevation_fov_deg) == (
        "non-repetitive",
        70.4,
        (38.6, 38.6),
    )
    assert avia.beam_elevations_deg is None and avia.columns is None and avia.rate_hz == 10.0
    mid = scans["mid360"].sensor
    assert (mid.pattern, mid.horizontal_fov_deg, mid.elevation_fov_deg) == (
        "non-repetitive",
        None,
        (52.0, 7.0),
    )
    assert mid.vertical_fov_deg == (52.0, 7.0) and not mid.is_spinning
    e1r = scans["e1r"].sensor
    assert (e1r.pattern, e1r.horizontal_fov_deg, e1r.elevation_fov_deg) == (
        "solid-state",
        120.0,
        (45.0, 45.0),
    )
    assert e1r.beam_elevations_deg is None and e1r.columns == 192
    for s in NEW:
        assert scans[s].sensor.intensity_max == 255.0 and scans[s].sensor.rate_hz == 10.0
        assert scans[s].shape is None  # unorganised, firing order
    # the presets that existed before keep their description (no pattern fields: hashes unchanged)
    assert "pattern" not in get_sensor("os1-64").to_sensor_info().to_dict()


def test_points_lie_within_the_field_of_view(scans: dict) -> None:
    tol = 0.01
    az, el = _angles(scans["hdl32"].xyz)
    assert el.max() <= 10.67 + tol and el.min() >= -30.67 - tol
    az, el = _angles(scans["avia"].xyz)
    assert np.abs(az).max() <= 35.2 + tol and np.abs(el).max() <= 38.6 + tol
    assert ((az / 35.2) ** 2 + (el / 38.6) ** 2).max() <= 1.0 + 1e-3  # the rosette's elliptical field
    assert np.ptp(az) > 55 and np.ptp(el) > 60
    az, el = _angles(scans["mid360"].xyz)
    assert el.max() <= 52 + tol and el.min() >= -7 - tol and np.ptp(az) > 350
    az, el = _angles(scans["e1r"].xyz)
    assert np.abs(az).max() <= 60 + tol and np.abs(el).max() <= 45 + tol
    assert np.ptp(az) > 110 and np.ptp(el) > 80


def test_per_point_times_and_rings(scans: dict) -> None:
    for s in NEW:
        sc = scans[s]
        assert sc.time is not None and sc.ring is not None
        assert sc.time.min() >= 0.0 and sc.time.max() < 0.1  # seconds since the frame start, within 1 / rate
        assert np.all(np.diff(sc.time) >= 0)  # firing order
        assert sc.time.max() > 0.09  # the frame lasts the whole period
        n_rings = get_sensor(s).n_beams
        assert sc.ring.min() >= 0 and sc.ring.max() == n_rings - 1
    assert (
        get_sensor("avia").n_beams == 6
        and get_sensor("mid360").n_beams == 4
        and get_sensor("e1r").n_beams == 135
    )
    # the solid-state raster reads out row by row, top row first
    e = scans["e1r"]
    assert np.all(np.diff(e.ring) >= 0)
    _, el = _angles(e.xyz)
    assert np.median(el[e.ring < 10]) > 40 and np.median(el[e.ring > 125]) < -40


@pytest.mark.parametrize(("name", "per_frame"), [("hdl32", 69_400), ("avia", 24_000), ("mid360", 20_000),
                                                 ("e1r", 26_000)])  # fmt: skip
def test_points_per_frame_follow_the_datasheet_rate(name: str, per_frame: int, scans: dict) -> None:
    s = get_sensor(name)
    n = frame_rays(s, 7).directions.shape[0]
    assert n == s.n_rays
    assert abs(n - per_frame) / per_frame < 0.01
    assert 0.3 * n < len(scans[name]) <= n  # after dropouts and sky


def _cells(dirs: np.ndarray, cell: float = 0.5) -> set:
    az, el = _angles(dirs)
    return set(
        zip(np.floor(az / cell).astype(int).tolist(), np.floor(el / cell).astype(int).tolist(), strict=True)
    )


@pytest.mark.parametrize("name", ["avia", "mid360"])
def test_non_repetitive_coverage_grows_with_integration_time(name: str) -> None:
    s = get_sensor(name)
    one = _cells(frame_rays(s, 0).directions)
    ten: set = set()
    for k in range(10):
        ten |= _cells(frame_rays(s, k).directions)
    assert len(one) < 0.7 * len(ten)
    if name == "avia":  # after 1 s the rosette has filled almost all of its 70.4 x 77.2 deg ellipse
        ellipse_cells = np.pi * 35.2 * 38.6 / 0.25
        assert len(ten) > 0.9 * ellipse_cells


def test_frames_continue_the_pattern_and_depend_on_time() -> None:
    s = get_sensor("avia")
    a, b = frame_rays(s, 4), frame_rays(s, 5)
    assert not np.allclose(a.directions, b.directions)
    assert np.array_equal(frame_rays(s, 4).directions, a.directions)  # deterministic
    lines = s.n_beams
    # line 0's last ray of frame 4 and first ray of frame 5 are as close as two consecutive rays within a frame
    d0 = a.directions[::lines]
    step_in = np.degrees(np.arccos(np.clip(np.sum(d0[1:] * d0[:-1], axis=1), -1, 1)))
    step_across = np.degrees(np.arccos(np.clip(float(d0[-1] @ b.directions[0]), -1, 1)))
    assert step_across <= 1.5 * step_in.max()
    assert frame_index(s, 0.5) == 5 and frame_index(s, 0.52) == 5 and frame_index(s, 0.56) == 6
    # spinning and solid-state sensors have one fixed grid
    for name in ("hdl32", "e1r"):
        assert frame_rays(get_sensor(name), 3) is ray_grid(get_sensor(name))
    seq = SimulatedSequence("town", "avia", n_scans=2, seed=0)
    p = seq.poses[0]
    s0, s1 = seq.scan_at(p, timestamp=0.0), seq.scan_at(p, timestamp=0.1)
    assert len(s0) != len(s1) or not np.allclose(s0.xyz, s1.xyz)


@pytest.mark.parametrize("name", ["avia", "mid360", "e1r"])
def test_clutter_culling_of_new_patterns_loses_no_hit(name: str) -> None:
    """Culled clutter casting (static pose) gives the same scan as casting every ray at the clutter (which a
    zero-motion ``pose_end`` forces)."""
    seq = SimulatedSequence("town", name, n_scans=40, seed=0)
    for i in (10, 30):
        p, t = seq.poses[i], float(seq.timestamps[i])
        a = seq.scan_at(p, t, index=i)
        b = seq.scan_at(p, t, index=i, pose_end=p)
        assert np.array_equal(a.xyz, b.xyz) and np.array_equal(a.intensity, b.intensity)


def test_frame_end_poses_interpolate_and_extrapolate() -> None:
    T = np.tile(np.eye(4), (3, 1, 1))
    T[1, :3, :3] = Rotation.from_rotvec([0, 0, 0.2]).as_matrix()
    T[1, :3, 3] = [2.0, 0, 0]
    T[2, :3, :3] = Rotation.from_rotvec([0, 0, 0.3]).as_matrix()
    T[2, :3, 3] = [2.0, 1.0, 0]
    end = frame_end_poses(T, np.array([0.0, 0.2, 0.3]), 0.1)
    assert np.allclose(end[0, :3, 3], [1.0, 0, 0])  # halfway to the next scan
    assert np.allclose(Rotation.from_matrix(end[0, :3, :3]).as_rotvec(), [0, 0, 0.1])
    assert np.allclose(end[1, :3, 3], [2.0, 1.0, 0]) and np.allclose(end[1], T[2])  # the whole step
    assert np.allclose(end[2, :3, 3], [2.0, 2.0, 0])  # the last scan continues the previous step
    assert np.allclose(Rotation.from_matrix(end[2, :3, :3]).as_rotvec(), [0, 0, 0.4])
    assert np.array_equal(frame_end_poses(T[:1], np.zeros(1), 0.1), T[:1])


def test_scans_taken_while_moving_deskew_back_onto_the_world() -> None:
    """Points of a moving scan are in the sensor frame at their own time: mapped to the world with the pose at
    their time they lie on the surfaces; with the scan's (start) pose or the opposite motion the late ones do not."""
    import open3d as o3d

    kw = dict(n_scans=3, seed=0, clutter=False)
    mov = SimulatedSequence("town", "hdl32", sweep_motion=True, **kw)
    static = SimulatedSequence("town", "hdl32", **kw)
    assert mov.sweep_motion and mov.spec.as_dict()["sweep_motion"] is True
    assert "sweep_motion" not in static.spec.as_dict() and static.frame_end_poses is None
    i = 1
    P0, P1 = mov.poses[i], mov.frame_end_poses[i]
    assert np.array_equal(P0, static.poses[i])
    dp = P1[:3, 3] - P0[:3, 3]
    assert np.linalg.norm(dp) > 0.5  # the route moves ~0.9 m per 0.1 s frame
    omega = Rotation.from_matrix(P0[:3, :3].T @ P1[:3, :3]).as_rotvec()

    def world(scan, sign: float) -> np.ndarray:
        f = sign * scan.time.astype(np.float64) * 10.0
        R = P0[:3, :3] @ Rotation.from_rotvec(f[:, None] * omega).as_matrix()
        return np.einsum("nij,nj->ni", R, scan.xyz.astype(np.float64)) + P0[:3, 3] + f[:, None] * dp

    def off_surface(scan, sign: float) -> float:
        pw = world(scan, sign)
        d = mov.world.scene.compute_distance(o3d.core.Tensor(pw.astype(np.float32))).numpy()
        sel = (scan.time > 0.05) & (
            pw[:, 2] > 0.3
        )  # late points above the ground (ground hides along-track shifts)
        return float(np.median(d[sel]))

    sm, ss = mov[i], static[i]
    assert not np.array_equal(sm.xyz[:100], ss.xyz[:100]) or len(sm) != len(ss)
    assert off_surface(ss, 0.0) < 0.05  # control: the static scan at its pose
    assert off_surface(sm, 1.0) < 0.05  # de-skewed with the known motion
    assert off_surface(sm, 0.0) > 0.15  # not de-skewed
    assert off_surface(sm, -1.0) > 0.3  # the wrong sign
