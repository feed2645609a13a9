"""One pose validator at every entry point (issue #27 item 1): poses given through the API (`as_pose`: the online
detector, `add_description`) and the poses a saved map or database holds must be rigid motions too."""

from __future__ import annotations

import numpy as np
import pytest
from fuzz.artifacts import _places

from placerec.errors import ArtifactError, ScanDataError
from placerec.io.atomic import peek_artifact, save_artifact
from placerec.types import as_pose

SCALED = np.diag([1000.0, 1000.0, 1000.0, 1.0])
MIRRORED = np.diag([1.0, 1.0, -1.0, 1.0])
SHEARED = np.eye(4) + np.eye(4, k=1) * 0.5


@pytest.mark.parametrize(
    ("pose", "why"),
    [
        (SCALED, "not a rotation"),
        (MIRRORED, "reflection"),
        (SHEARED[:3], "not a rotation"),
        (np.zeros((4, 4)), "bottom row"),
    ],
)
def test_as_pose_refuses_what_is_no_rigid_motion(pose, why):
    with pytest.raises(ScanDataError, match=f"no rigid motion: .*{why}"):
        as_pose(pose)
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    np.testing.assert_array_equal(as_pose(T[:3]), T)


def test_the_online_detector_refuses_a_scaled_pose():
    from placerec.loop_closure import LoopClosureDetector
    from placerec.recognizer import make_pipeline

    det = LoopClosureDetector(make_pipeline("scan-context", {"verify": {"enabled": False}}), threshold=0.5)
    desc = {"scan_context": np.ones((20, 60), np.float32)}
    with pytest.raises(ScanDataError, match="no rigid motion"):
        det.process(None, pose=SCALED, description=desc)
    assert det.n_processed == 0  # nothing recorded


def test_a_places_database_with_a_pose_that_is_no_rigid_motion_is_refused(tmp_path):
    from placerec.three_d.places import PlacesDatabase

    _places(tmp_path / "p.npz")
    arrays, header = peek_artifact(tmp_path / "p.npz")
    arrays = {k: np.array(v) for k, v in arrays.items()}
    arrays["scan_poses"][2, :3, :3] *= 1000.0
    arrays["poses"][1] = arrays["scan_poses"][2]  # ids [0, 2, 4]: place 1 is scan 2
    save_artifact(tmp_path / "bad.npz", header["kind"], header["format_version"], arrays, header["meta"])
    with pytest.raises(ArtifactError, match=r"bad.npz: 'scan_poses' row 2 is no rigid motion"):
        PlacesDatabase.load(tmp_path / "bad.npz")


def test_saved_entries_with_a_mirrored_pose_are_refused():
    from placerec.retrieval.descriptor_store import DescriptorStore
    from placerec.three_d.entries import EntryTable

    poses = np.stack([np.eye(4), MIRRORED])
    arrays = {
        "ids": np.array([0, 1]),
        "poses": poses,
        "counts": np.array([1, 1]),
        "keypoints": np.zeros((2, 3)),
    }
    with pytest.raises(ArtifactError, match=r"db.npz: 'poses' row 1 is no rigid motion: .*reflection"):
        EntryTable.from_arrays(arrays, DescriptorStore(4), "db.npz")
