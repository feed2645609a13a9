"""The simulator's intensity model: directions of the physical effects, per-beam ground truth, saturation.

Half of the checks call the model functions directly; the other half ray-cast constructed scenes (walls of known
reflectance, angle and distance in front of the sensor) through the full renderer.
"""

from __future__ import annotations

import numpy as np
import pytest

from placerec.sim import BeamResponse, IntensityModel, SimulatedSequence, get_sensor, surface_response
from placerec.sim.geometry import MeshBuilder
from placerec.sim.materials import M
from placerec.sim.routes import Route, poses_from_xy_yaw
from placerec.sim.world import World, world_from_mesh


def test_surface_response_reflectance_and_incidence() -> None:
    cos = np.array([1.0, 0.7, 0.3, 0.05])
    low = surface_response(np.full(4, 0.2), cos)
    high = surface_response(np.full(4, 0.6), cos)
    assert np.all(high > low)
    assert np.all(np.diff(low) < 0)  # grazing -> lower (Lambertian)
    retro = surface_response(np.full(4, 200.0), cos)
    assert np.all(retro > 5.0) and retro[-1] / retro[0] > 0.2  # retro-reflectors stay bright when oblique
    spec = surface_response(np.full(2, 0.2), np.array([1.0, 0.8]), specular=0.5)
    assert (
        spec[0] > surface_response(np.array([0.2]), np.array([1.0]))[0]
    )  # specular lobe at normal incidence


def test_range_compensation_and_degradation_beyond_30m() -> None:
    m = IntensityModel.for_sensor(get_sensor("vlp16"))
    r = np.array([5.0, 10.0, 20.0, 29.0, 40.0, 60.0, 80.0])
    a = m.apparent(np.full(len(r), 0.5), r)
    assert np.all(np.diff(a[1:]) < 0)  # farther -> lower
    assert a[3] / a[1] > 0.85  # compensated: mild falloff inside 30 m
    assert a[5] / a[3] < 0.6  # degraded well beyond 30 m
    assert np.all(m.speckle_sigma(np.array([60.0])) > m.speckle_sigma(np.array([10.0])))
    signal = IntensityModel(range_10pct=40.0, range_compensated=False)
    s = signal.apparent(np.full(2, 0.5), np.array([10.0, 20.0]))
    assert s[1] / s[0] == pytest.approx(0.25, rel=0.02)  # an uncompensated channel falls as 1/R^2


def test_detection_falls_with_range_and_darkness() -> None:
    m = IntensityModel.for_sensor(get_sensor("os1-64"))
    assert m.detection_probability(np.array([0.1]), np.array([m.range_10pct]))[0] == pytest.approx(
        0.5, abs=0.01
    )
    p = m.detection_probability(np.array([0.1, 0.1, 0.8, 0.03]), np.array([10.0, 80.0, 80.0, 60.0]))
    assert p[0] > 0.99 and p[1] < 0.05 and p[2] > 0.5 and p[3] < 0.01


@pytest.mark.parametrize("name", ["vlp16", "hdl64", "os1-64"])
def test_beam_response_ground_truth(name: str) -> None:
    s = get_sensor(name)
    resp = BeamResponse.draw(s, seed=3)
    x = np.linspace(0.0, 1.0, 50)
    curves = np.stack([resp.expected_raw(x, b) for b in range(s.n_beams)])
    steps = np.diff(curves[:, 5:], axis=1)
    assert np.all(steps >= 0) and np.all(
        steps[curves[:, 6:] < s.intensity_max] > 0
    )  # monotone until saturation
    assert np.ptp(curves[:, -1]) > 0.05 * s.intensity_scale  # beams differ (ISHOT Fig. 7)
    assert np.ptp(resp.gamma) > 0.1
    inside = (curves > 1.0) & (curves < s.intensity_max - 1)
    back = np.stack([resp.to_apparent(curves[b], b) for b in range(s.n_beams)])
    assert np.allclose(back[inside], np.broadcast_to(x, curves.shape)[inside], atol=1e-6)
    assert np.all(resp.expected_raw(np.full(s.n_beams, 500.0), np.arange(s.n_beams)) == s.intensity_max)
    assert BeamResponse.draw(s, 3).gain.tolist() == resp.gain.tolist()
    assert BeamResponse.draw(s, 4).gain.tolist() != resp.gain.tolist()


def test_measure_quantises_and_clips() -> None:
    s = get_sensor("vlp16")
    resp = BeamResponse.draw(s, 0)
    m = IntensityModel.for_sensor(s)
    raw = m.measure(
        np.array([0.0, 0.3, 0.6, 50.0]),
        np.full(4, 10.0),
        np.array([0, 1, 2, 3]),
        resp,
        np.random.default_rng(0),
    )
    assert np.array_equal(raw, np.rint(raw)) and raw.min() >= 0 and raw.max() <= 255
    assert raw[3] == 255 and 10 < raw[1] < raw[2] < 100


# ----------------------------------------------------------------------------------------------------------------
# constructed scenes: walls of plain material in front of an OS1-64 / VLP-16 at the origin, looking along +x


def _walls(specs: list[tuple[float, float, float, float, int, float]]) -> tuple[World, Route]:
    """specs: (azimuth deg, distance m, wall yaw offset deg, reflectance, material, width m)."""
    b = MeshBuilder()
    b.add_mesh(
        np.array([[-500, -500, 0], [500, -500, 0], [500, 500, 0], [-500, 500, 0]]),
        np.array([[0, 1, 2], [0, 2, 3]]),
        M.GROUND,
        b.add_objects(np.zeros((1, 3)))[0],
    )
    for az, dist, tilt, refl, mat, width in specs:
        a = np.radians(az)
        centre = dist * np.array([np.cos(a), np.sin(a)])
        facing = a + np.pi + np.radians(tilt)  # local +x looks back towards the sensor (tilted by `tilt`)
        style = 3 if mat == M.SIGN else 0
        b.add_boxes(
            np.r_[centre, 0.0], [0.2, width, 6.0], facing, mat, params=[[refl, 0, 0, 0, 0, style]], seed=1
        )
    world = world_from_mesh(b.build())
    pose = poses_from_xy_yaw(np.zeros((1, 2)), np.array([1.8]), np.zeros(1))
    return world, Route(poses=pose, timestamps=np.zeros(1), name="static")


def _wall_intensity(scan, az: float, half_width_deg: float = 2.0, rows: slice = slice(20, 40)) -> np.ndarray:
    xyz = scan.xyz
    theta = np.degrees(np.arctan2(xyz[:, 1], xyz[:, 0]))
    ring = scan.ring
    sel = (
        (np.abs(theta - az) < half_width_deg)
        & np.any(xyz != 0, axis=1)
        & (ring >= rows.start)
        & (ring < rows.stop)
        & (xyz[:, 2] > -1.5)
    )
    return scan.intensity[sel]


@pytest.fixture(scope="module")
def wall_scene():
    specs = [
        (30.0, 12.0, 0.0, 0.15, M.RUBBER, 4.0),  # dark wall
        (60.0, 12.0, 0.0, 0.6, M.RUBBER, 4.0),  # bright wall, same range and angle
        (-30.0, 12.0, 0.0, 0.4, M.RUBBER, 4.0),  # normal incidence
        (-60.0, 12.0, 70.0, 0.4, M.RUBBER, 12.0),  # same reflectance, grazing (70 deg)
        (150.0, 10.0, 0.0, 0.4, M.RUBBER, 4.0),  # near
        (-150.0, 55.0, 0.0, 0.4, M.RUBBER, 14.0),  # far, beyond the degradation range
        (100.0, 12.0, 0.0, 200.0, M.SIGN, 3.0),  # retro-reflective sheeting
    ]
    world, route = _walls(specs)
    out = {}
    for name in ("os1-64", "vlp16"):
        seq = SimulatedSequence(world=world, sensor=name, route=route, clutter=False, seed=5)
        out[name] = seq[0]
    return out


@pytest.mark.parametrize("name", ["os1-64", "vlp16"])
def test_constructed_scene_directions(wall_scene, name: str) -> None:
    scan = wall_scene[name]
    rows = slice(20, 44) if name == "os1-64" else slice(4, 12)
    med = {
        az: np.median(_wall_intensity(scan, az, rows=rows))
        for az in (30.0, 60.0, -30.0, -60.0, 150.0, -150.0)
    }
    assert med[60.0] > 1.8 * med[30.0]  # reflectance
    assert med[-60.0] < 0.6 * med[-30.0]  # incidence
    assert med[-150.0] < 0.8 * med[150.0]  # range (degraded beyond 30 m)
    retro = _wall_intensity(scan, 100.0, 1.0, rows=rows)
    assert len(retro) > 10 and np.mean(retro == scan.sensor.intensity_max) > 0.9  # retro-reflectors saturate
    diffuse = _wall_intensity(scan, 60.0, rows=rows)
    assert diffuse.max() < 0.5 * scan.sensor.intensity_max  # diffuse surfaces stay far below saturation


def test_beam_response_truth_calibrates_simulated_scans(wall_scene) -> None:
    """Inverting the ground-truth per-beam curves removes the beam-to-beam differences of a uniform wall."""
    scan = wall_scene["os1-64"]
    xyz = scan.xyz
    theta = np.degrees(np.arctan2(xyz[:, 1], xyz[:, 0]))
    sel = (
        (np.abs(theta + 30.0) < 6.0)
        & (scan.intensity > 0)
        & (xyz[:, 2] > -1.5)
        & (scan.intensity < scan.sensor.intensity_max)
    )
    ring = scan.ring[sel]
    raw = scan.intensity[sel]
    seq_resp = BeamResponse.draw(get_sensor("os1-64"), 5)  # the wall scene's unit_seed is its seed (5)
    cal = seq_resp.to_apparent(raw, ring)
    rings = [r for r in np.unique(ring) if np.sum(ring == r) >= 8]
    assert len(rings) >= 10
    med_raw = np.array([np.median(raw[ring == r]) for r in rings])
    med_cal = np.array([np.median(cal[ring == r]) for r in rings])
    cv = lambda v: np.std(v) / np.mean(v)  # noqa: E731
    assert cv(med_cal) < 0.6 * cv(med_raw)
    rng = np.linalg.norm(xyz[sel], axis=1)
    expected = IntensityModel.for_sensor(get_sensor("os1-64")).apparent(np.full(len(rng), 0.4), rng)
    assert np.median(cal) == pytest.approx(
        np.median(expected), rel=0.15
    )  # cos(incidence) ~ 1 across the wall
