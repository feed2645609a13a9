"""Places database: partition along a trajectory, accumulation into the place frame, save/load and its checks."""

from __future__ import annotations

import numpy as np
import pytest

from placerec.artifacts.places import build_places
from placerec.errors import ArtifactError, ConfigError
from placerec.io.atomic import save_artifact
from placerec.three_d import FeatureParams, ISSParams
from placerec.three_d.places import (
    PlacesDatabase,
    PlacesParams,
    partition_places,
    place_cloud,
)
from placerec.types import Scan


def line_poses(xs: np.ndarray, yaw: float = 0.0) -> np.ndarray:
    P = np.tile(np.eye(4), (len(xs), 1, 1))
    c, s = np.cos(yaw), np.sin(yaw)
    P[:, :2, :2] = [[c, -s], [s, c]]
    P[:, 0, 3] = xs
    return P


def test_partition_spacing_windows_and_overlap():
    poses = line_poses(np.arange(41.0))
    part = partition_places(poses, None, PlacesParams(spacing_m=5.0, window_m=3.0, member_spacing=0.0))
    assert part.centres.tolist() == list(range(0, 41, 5))
    assert part.members[2].tolist() == list(range(7, 14))  # centre 10, +-3 m of travel
    assert part.members[0].tolist() == [0, 1, 2, 3]  # clipped at the start
    shared = np.intersect1d(part.members[1], part.members[2])
    assert shared.tolist() == [7, 8]  # neighbouring places overlap


def test_partition_revisit_adds_no_place_and_windows_stay_on_one_pass():
    xs = np.r_[np.arange(21.0), np.arange(20.0, -1.0, -1.0)]  # out and back along the same line
    part = partition_places(
        line_poses(xs), None, PlacesParams(spacing_m=5.0, window_m=4.0, member_spacing=0.0)
    )
    assert part.centres.tolist() == [0, 5, 10, 15, 20]
    # place 10 (x = 10 on the way out) holds scans 6..14 only, not the return pass at the same spot (x = 10: 31)
    assert part.members[2].tolist() == list(range(6, 15))


def test_partition_time_window_and_member_spacing():
    xs = np.r_[np.arange(10.0), np.full(20, 10.0), np.arange(11.0, 20.0)]  # a 20-scan stop at x = 10
    t = np.arange(len(xs), dtype=float)
    p = PlacesParams(spacing_m=5.0, window_m=2.0, member_spacing=0.0)
    centre = int(np.flatnonzero(xs == 10.0)[0])
    no_time = partition_places(line_poses(xs), t, p)
    i = no_time.centres.tolist().index(centre)
    assert len(no_time.members[i]) == 2 + 20 + 2  # the whole stop is within 2 m of travel
    timed = partition_places(
        line_poses(xs), t, PlacesParams(spacing_m=5.0, window_m=2.0, member_spacing=0.0, window_s=3.0)
    )
    assert timed.members[i].tolist() == list(range(centre - 2, centre + 4))
    thin = partition_places(
        line_poses(np.arange(41.0)), None, PlacesParams(spacing_m=5.0, window_m=4.0, member_spacing=2.0)
    )
    assert thin.members[2].tolist() == [6, 8, 10, 12, 14]  # one scan per 2 m of travel, shared by all places
    with pytest.raises(ConfigError):
        partition_places(line_poses(xs), None, PlacesParams(window_s=1.0))


def test_place_cloud_maps_points_into_the_place_frame():
    poses = line_poses(np.array([0.0, 4.0]), yaw=np.pi / 2)
    world_point = np.array([1.0, 2.0, 0.5])
    scans = {}
    for j in (0, 1):
        local = np.linalg.inv(poses[j]) @ np.r_[world_point, 1.0]
        scans[j] = Scan(local[None, :3], np.array([0.2 * (j + 1)]), ring=np.array([j]))
    cloud = place_cloud(scans, poses, 1, np.array([0, 1]))
    expected = (np.linalg.inv(poses[1]) @ np.r_[world_point, 1.0])[:3]
    np.testing.assert_allclose(cloud.xyz, np.tile(expected, (2, 1)), atol=1e-5)
    np.testing.assert_allclose(cloud.intensity, [0.2, 0.4])


FAST = FeatureParams(descriptor="shot", iss=ISSParams(max_keypoints=60))


@pytest.fixture(scope="module")
def small_db():
    from placerec.sim import SimulatedSequence

    seq = SimulatedSequence("town", "vlp16", n_scans=9, seed=1, spacing=2.0, clutter=False)
    params = PlacesParams(spacing_m=6.0, window_m=4.0, member_spacing=2.0, features=FAST)
    return seq, build_places(seq, params)


def test_build_places_on_the_simulator(small_db):
    seq, db = small_db
    assert len(db) == 3 and db.ids.tolist() == [0, 3, 6]
    np.testing.assert_allclose(db.poses, seq.poses[db.ids])
    assert db.descriptors.shape == (db.kp_offsets[-1], 352) and db.keypoints.shape == (db.kp_offsets[-1], 3)
    assert np.all(np.diff(db.kp_offsets) > 20)
    assert db.sources[1].tolist() == [1, 2, 3, 4, 5]
    assert db.row_place.shape[0] == db.descriptors.shape[0]
    # keypoints are in the place frame: within the 40 m crop around the place origin
    assert np.linalg.norm(db.keypoints, axis=1).max() <= 40.0 + 1e-3
    assert db.clouds is not None and len(db.clouds) == 3


def test_save_load_identity_and_config_checks(small_db, tmp_path):
    _, db = small_db
    path = tmp_path / "places.npz"
    db.save(path)
    again = PlacesDatabase.load(path, features=FAST, intensity="sensor-default")
    for name in ("ids", "poses", "kp_offsets", "keypoints", "descriptors", "scan_poses"):
        np.testing.assert_array_equal(getattr(again, name), getattr(db, name), err_msg=name)
    assert [s.tolist() for s in again.sources] == [s.tolist() for s in db.sources]
    assert again.params == db.params
    # int16 clouds (the default): each coordinate within half a step (reach / 32767 / 2), intensity within 1/510;
    # saving what was read writes the same codes again
    for (a, b), (c, d) in zip(again.clouds, db.clouds, strict=True):
        reach = np.abs(c - 0.5 * (c.min(0) + c.max(0))).max()
        np.testing.assert_allclose(a, c, rtol=0, atol=reach / 32767 / 2 + 1e-5)
        np.testing.assert_allclose(b, d, rtol=0, atol=1 / 510 + 1e-7)
    again.save(tmp_path / "again.npz")
    twice = PlacesDatabase.load(tmp_path / "again.npz")
    for (a, b), (c, d) in zip(twice.clouds, again.clouds, strict=True):
        np.testing.assert_array_equal(a, c)
        np.testing.assert_array_equal(b, d)
    with pytest.raises(ArtifactError, match="other feature settings"):
        PlacesDatabase.load(path, features=FeatureParams(descriptor="ishot"))
    with pytest.raises(ArtifactError, match="intensity"):
        PlacesDatabase.load(path, intensity="calibrated")
    save_artifact(tmp_path / "other.npz", "visual-hbst-db", 1, {"a": np.zeros(1)})
    with pytest.raises(ArtifactError, match="expected a 'places-db'"):
        PlacesDatabase.load(tmp_path / "other.npz")
    assert not list(tmp_path.glob(".*.tmp"))  # atomic writes leave no temporary files


def test_a_version_1_file_is_read_and_its_descriptor_options_must_be_empty(small_db, tmp_path):
    """Version 1 stored the descriptors' settings as an ``descriptor_options`` list (always empty in practice);
    version 2 on stores the ``shot`` / ``fpfh`` sections."""
    from placerec.io.atomic import load_artifact

    _, db = small_db
    db.save(tmp_path / "v4.npz")
    arrays, header = load_artifact(tmp_path / "v4.npz", "places-db", (4,))
    meta = header["meta"]
    # versions 1-3 named the spacing place_spacing
    spacing = meta["params"].pop("spacing_m")
    meta["params"]["place_spacing"] = spacing
    save_artifact(tmp_path / "v3.npz", "places-db", 3, arrays, meta)
    assert PlacesDatabase.load(tmp_path / "v3.npz").params == db.params
    save_artifact(tmp_path / "v4-old-name.npz", "places-db", 4, arrays, meta)
    with pytest.raises(ArtifactError, match="place_spacing: unknown key"):
        PlacesDatabase.load(tmp_path / "v4-old-name.npz")
    assert meta["params"]["features"]["shot"] == {
        "lrf_radius": None,
        "normalization": "joint",
        "pcl_bin_wrap": False,
    }
    features = {k: v for k, v in meta["params"]["features"].items() if k not in ("shot", "fpfh")}
    for options, ok in (([], True), ([["max_nn", 30]], False)):
        v1 = {**meta, "params": {**meta["params"], "features": {**features, "descriptor_options": options}}}
        save_artifact(tmp_path / "v1.npz", "places-db", 1, arrays, v1)
        if ok:
            assert PlacesDatabase.load(tmp_path / "v1.npz", features=FAST).params == db.params
        else:
            with pytest.raises(ArtifactError, match="descriptor_options other than"):
                PlacesDatabase.load(tmp_path / "v1.npz")
    bad = {
        **meta,
        "params": {**meta["params"], "features": {**meta["params"]["features"], "shot": {"lrf": 1}}},
    }
    save_artifact(tmp_path / "bad.npz", "places-db", 2, arrays, bad)
    with pytest.raises(ArtifactError, match=r"features\.shot\.lrf: unknown key"):
        PlacesDatabase.load(tmp_path / "bad.npz")


@pytest.mark.parametrize(
    "member, value, match",
    [
        ("cloud_intensity", np.nan, "'cloud_intensity' holds NaN"),
        (
            "cloud_intensity",
            1e9,
            r"'cloud_intensity' holds 1e\+09 \(place 0\); expected normalised intensities",
        ),
        ("cloud_intensity", -0.5, r"'cloud_intensity' holds -0.5, expected values >= 0"),
        ("cloud_scale", 0.0, r"'cloud_scale' of place 0 is 0; expected a positive step"),
        ("cloud_scale", -0.01, "'cloud_scale' holds -0.01, expected values >= 0"),
        ("cloud_scale", np.inf, "'cloud_scale' holds NaN or infinite"),
        ("cloud_scale", 1e300, r"'cloud_scale' 1e\+300 and 'cloud_centre' of place 0 put its points"),
    ],
)
def test_place_cloud_values_are_checked_on_load(small_db, tmp_path, member, value, match):
    """A database whose cloud intensities are NaN or 1e9, or whose int16 clouds have a zero, negative or huge
    step, is refused on load naming the file and the member (a zero step failed only at query time, in ICP)."""
    from placerec.io.atomic import load_artifact

    _, db = small_db
    store = "float32" if member == "cloud_intensity" else "int16"
    db.stored_as(db.params.descriptor_store, store).save(tmp_path / "db.npz")
    arrays, header = load_artifact(tmp_path / "db.npz", "places-db", (4,))
    assert PlacesDatabase.load(tmp_path / "db.npz").clouds is not None
    arrays[member] = arrays[member].copy()
    arrays[member][0] = value
    save_artifact(tmp_path / "bad.npz", "places-db", header["format_version"], arrays, header["meta"])
    with pytest.raises(ArtifactError, match=rf"bad\.npz: (array )?{match}"):
        PlacesDatabase.load(tmp_path / "bad.npz")
