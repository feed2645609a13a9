import numpy as np
import pytest

from placerec.errors import PlacerecError, ScanDataError
from placerec.types import (
    Candidate,
    ListSequence,
    PlaceRecognizer,
    Scan,
    SensorInfo,
    Sequence,
    as_pose,
    relative_pose,
)


def _scan(n=10, **kw):
    rng = np.random.default_rng(0)
    return Scan(rng.normal(size=(n, 3)), rng.random(n), **kw)


def test_scan_coerces_dtypes_and_validates_lengths():
    s = _scan(5, ring=np.arange(5))
    assert s.xyz.dtype == np.float32 and s.intensity.dtype == np.float32 and s.ring.dtype == np.int16
    with pytest.raises(ScanDataError, match="intensity has 4 values for 5 points"):
        Scan(np.zeros((5, 3)), np.zeros(4))
    with pytest.raises(ScanDataError, match=r"shape \(N, 3\)"):
        Scan(np.zeros((5, 4)), np.zeros(5))
    with pytest.raises(ScanDataError, match="organised shape 2x2"):
        _scan(5, shape=(2, 2))
    assert issubclass(ScanDataError, PlacerecError)


def test_select_and_organized_view():
    s = _scan(6, ring=[0, 0, 0, 1, 1, 1], shape=(2, 3))
    assert s.organized("ring").tolist() == [[0, 0, 0], [1, 1, 1]]
    sub = s.select(s.ring == 1)
    assert len(sub) == 3 and sub.shape is None and sub.ring.tolist() == [1, 1, 1]


def test_transformed_and_relative_pose_convention():
    yaw = np.deg2rad(30)
    T_wm = np.eye(4)
    T_wq = np.eye(4)
    T_wq[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    T_wq[:3, 3] = [2.0, 1.0, 0.0]
    T_mq = relative_pose(T_wm, T_wq)
    assert np.allclose(T_wm @ T_mq, T_wq)
    s = Scan([[1.0, 0.0, 0.0]], [0.5])
    assert np.allclose(s.transformed(T_wq).xyz[0], [2 + np.cos(yaw), 1 + np.sin(yaw), 0], atol=1e-6)
    assert as_pose(np.eye(4)[:3]).shape == (4, 4)
    with pytest.raises(ScanDataError):
        as_pose(np.full((4, 4), np.nan))


def test_sensor_info_roundtrip_and_fov():
    info = SensorInfo("os1-64", beam_elevations_deg=(16.6, 0.0, -16.6), columns=1024, intensity_max=65535.0)
    assert info.n_beams == 3 and info.vertical_fov_deg == (16.6, 16.6)
    assert SensorInfo.from_dict(info.to_dict()) == info
    with pytest.raises(ScanDataError, match="unknown keys"):
        SensorInfo.from_dict({"nmae": "x"})


def test_list_sequence_is_a_sequence():
    seq = ListSequence([_scan(), _scan()], poses=np.stack([np.eye(4)] * 2), timestamps=[0.0, 0.1])
    assert isinstance(seq, Sequence) and len(seq) == 2 and seq.poses.shape == (2, 4, 4)
    with pytest.raises(ScanDataError, match="3 poses for 2 scans"):
        ListSequence([_scan(), _scan()], poses=np.stack([np.eye(4)] * 3))


def test_candidate_and_protocol_shape():
    c = Candidate(query_id=5, match_id=1, score=0.9)
    assert c.relative_pose is None and c.extra == {}

    class ScanOnly:
        name = "scan-only"

        def add(self, scan_id, scan, pose=None): ...
        def query(self, scan, k=1, max_id=None, query_id=-1):
            return []

        def save(self, path): ...
        def load(self, path): ...

    class Full(ScanOnly):
        frontend_key = "full"

        def describe(self, scan):
            return {}

        def add_description(self, scan_id, description, pose=None): ...
        def query_description(self, description, k=1, max_id=None, query_id=-1):
            return []

    assert isinstance(Full(), PlaceRecognizer)
    assert not isinstance(ScanOnly(), PlaceRecognizer)  # the one protocol includes the front end split
