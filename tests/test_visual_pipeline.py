"""The 2D visual pipeline: yaw from the column shift, save/load, registry presets."""

import numpy as np
import pytest

from placerec.errors import ArtifactError
from placerec.pipelines.visual import VisualHBST, shift_consensus
from placerec.recognizer import make_pipeline
from placerec.sim import SimulatedSequence


def test_shift_consensus_counts_the_dominant_circular_shift():
    rng = np.random.default_rng(0)
    uq = rng.uniform(0, 1024, 50)
    ur = np.mod(uq - 1020, 1024)  # shift of 1020 = -4 columns, across the seam for many
    v = rng.uniform(0, 64, 50)
    uq_noise = np.r_[uq, rng.uniform(0, 1024, 20)]
    ur_noise = np.r_[ur, rng.uniform(0, 1024, 20)]
    v2 = np.r_[v, rng.uniform(0, 64, 20)]
    inliers, shift = shift_consensus(uq_noise, v2, ur_noise, v2, 1024, 8, 4)
    assert 50 <= inliers <= 55 and np.mod(shift, 1024) == pytest.approx(1020, abs=0.5)
    assert shift_consensus(uq, v, ur, v + 10, 1024, 8, 4)[0] == 0  # rows too far apart


@pytest.fixture(scope="module")
def scans():
    seq = SimulatedSequence(world="town", sensor="os1-64", n_scans=2, seed=5, clutter=False)
    return seq[0], seq[1]


def _rotated(scan, yaw):
    c, s = np.cos(-yaw), np.sin(-yaw)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], np.float32)
    from dataclasses import replace

    # the sensor turned by +yaw: points appear turned by -yaw; drop the organised grid so the image is re-projected
    return replace(scan, xyz=scan.xyz @ R.T, shape=None)


@pytest.mark.parametrize("yaw_deg", [-100.0, 35.0, 170.0])
def test_relative_yaw_maps_query_into_match_frame(scans, yaw_deg):
    base = scans[0]
    from dataclasses import replace

    flat = replace(base, shape=None)  # per-beam projection for both, so only the yaw differs
    rec = make_pipeline("orb-hbst")
    rec.add(0, flat)
    (cand,) = rec.query(_rotated(base, np.radians(yaw_deg)), k=1)
    assert cand.match_id == 0 and cand.score > 0.3
    est = np.degrees(np.arctan2(cand.relative_pose[1, 0], cand.relative_pose[0, 0]))
    assert abs((est - yaw_deg + 180) % 360 - 180) < 2.0


def test_save_load_gives_identical_answers(tmp_path, scans):
    rec = make_pipeline("orb-hbst")
    rec.add(0, scans[0])
    rec.add(1, scans[1])
    before = rec.query(scans[1], k=2)
    path = tmp_path / "db.npz"
    rec.save(path)
    fresh = make_pipeline("orb-hbst")
    fresh.load(path)
    after = fresh.query(scans[1], k=2)
    assert [(c.match_id, c.score, c.inliers) for c in before] == [
        (c.match_id, c.score, c.inliers) for c in after
    ]
    with pytest.raises(ArtifactError, match="other parameters"):
        make_pipeline("brisk-hbst").load(path)


def test_the_saved_tree_is_restored_as_re_insertion_builds_it(tmp_path, scans):
    """Format 2 stores the HBST's arrays and restores them; format 1 (features only) is re-inserted. Both give the
    same tree, the same answers, and grow the same way afterwards."""
    from placerec.io.atomic import load_artifact, save_artifact

    rec = make_pipeline("orb-hbst")
    for i in range(6):  # one scan's features under several ids: leaves fill and split
        rec.add(i, scans[i % 2])
    path = tmp_path / "db.npz"
    rec.save(path)
    arrays, header = load_artifact(path, "visual-hbst-db", (2,))
    assert header["format_version"] == 2 and any(k.startswith("tree_") for k in arrays)
    old = {k: v for k, v in arrays.items() if not k.startswith("tree_")}
    save_artifact(tmp_path / "v1.npz", "visual-hbst-db", 1, old, {"params": header["meta"]["params"]})
    restored, rebuilt = make_pipeline("orb-hbst"), make_pipeline("orb-hbst")
    restored.load(path)
    rebuilt.load(tmp_path / "v1.npz")
    for other in (restored, rebuilt):
        other.add(9, scans[1])
    rec.add(9, scans[1])
    trees = [r.tree._tree.to_arrays() for r in (rec, restored, rebuilt)]
    for name in trees[0]:
        np.testing.assert_array_equal(trees[1][name], trees[0][name], err_msg=name)
        np.testing.assert_array_equal(trees[2][name], trees[0][name], err_msg=name)
    answers = [[(c.match_id, c.score) for c in r.query(scans[0], k=3)] for r in (rec, restored, rebuilt)]
    assert answers[0] == answers[1] == answers[2] and answers[0]
    # a tree that does not hold the saved images is refused
    arrays["tree_images"] = arrays["tree_images"] + 100
    save_artifact(tmp_path / "bad.npz", "visual-hbst-db", 2, arrays, header["meta"])
    with pytest.raises(ArtifactError, match="bad.npz: the saved tree does not hold the saved images"):
        make_pipeline("orb-hbst").load(tmp_path / "bad.npz")


def test_presets_and_thresholds():
    orb, brisk = make_pipeline("orb-hbst"), make_pipeline("brisk-hbst")
    # the registered pipelines match at 50 bits per 256 (docs/vpr_results.md); the class keeps srrg's 25
    assert isinstance(orb, VisualHBST) and orb.tree.threshold == 50 and brisk.tree.threshold == 100
    assert VisualHBST().tree.threshold == 25
    assert orb.frontend_key != brisk.frontend_key
    assert make_pipeline("orb-hbst", {"check": "none"}).frontend_key == orb.frontend_key
    assert make_pipeline("orb-dbow").frontend_key == orb.frontend_key  # one description for both
    unverified = make_pipeline("orb-hbst", {"verify": {"enabled": False}})
    assert unverified.frontend_key != orb.frontend_key  # its descriptions hold no ICP cloud
