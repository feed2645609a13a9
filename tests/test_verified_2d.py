"""Verified 2D visual pipelines (issue #12): keypoints' 3D points, RANSAC + ICP on feature matches, 6-DoF poses."""

from dataclasses import replace

import numpy as np
import pytest

from placerec.errors import ScanDataError
from placerec.image import make_image
from placerec.image.correspondence import keypoint_points
from placerec.pipelines.visual import mutual_nearest
from placerec.recognizer import make_pipeline
from placerec.sim import SimulatedSequence
from placerec.types import REJECTIONS, relative_pose


@pytest.fixture(scope="module")
def sim():
    seq = SimulatedSequence(world="town", sensor="os1-64", n_scans=40, seed=5, clutter=False)
    return {i: seq[i] for i in (0, 2, 30)}, seq.poses


def _errors(T_est, T_gt):
    E = np.linalg.inv(T_gt) @ T_est
    angle = np.degrees(np.arccos(np.clip((np.trace(E[:3, :3]) - 1) / 2, -1, 1)))
    return float(np.linalg.norm(E[:3, 3])), float(angle)


def test_keypoint_points_take_the_pixel_then_the_nearest_neighbour():
    pidx = np.full((4, 6), -1, np.int32)
    pidx[1, 2] = 7  # the keypoint's own pixel
    pidx[2, 0] = 9  # left of (2, 1); (2, 5)'s right neighbour across the seam is (2, 0)
    kp = np.array([[2.2, 0.8], [1.4, 2.0], [5.0, 2.0], [4.0, 0.0]], np.float32)  # (u, v)
    assert keypoint_points(kp, pidx).tolist() == [7, 9, 9, -1]


def test_keypoint_xyz_are_the_scan_points_of_their_pixels(sim):
    scans, _ = sim
    scan = replace(scans[0], shape=None)
    rec = make_pipeline("orb-hbst")
    desc = rec.describe(scan)
    img = make_image(scan, rec.params.image)
    kp, xyz = desc["keypoints"], desc["keypoint_xyz"]
    assert xyz.shape == (kp.shape[0], 3) and kp.shape[0] > 50
    found = np.isfinite(xyz).all(axis=1)
    assert found.mean() > 0.9
    idx = keypoint_points(kp, img.point_index)
    np.testing.assert_array_equal(xyz[found], scan.xyz[idx[found]])
    # the point lies in the keypoint's pixel or a neighbour: its azimuth column is within one of the keypoint's
    w = img.shape[1]
    p = xyz[found].astype(np.float64)
    col = 0.5 * (1.0 - np.arctan2(p[:, 1], p[:, 0]) / np.pi) * w
    dcol = np.abs((col - kp[found, 0] + w / 2) % w - w / 2)
    assert dcol.max() <= 2.0
    cloud = desc["cloud"]
    assert cloud.dtype == np.float32 and 1000 < cloud.shape[0] < len(scan) // 2
    seen, image = rec.last_image  # the image describe made, kept for a viewer
    assert seen is scan
    np.testing.assert_array_equal(image, img.image)


def test_mutual_nearest_matches_a_brute_force_reference():
    rng = np.random.default_rng(1)
    a = rng.integers(0, 256, (40, 32), dtype=np.uint8)
    b = np.concatenate(
        [
            a[:25] ^ (rng.random((25, 32)) < 0.05).astype(np.uint8),
            rng.integers(0, 256, (30, 32), dtype=np.uint8),
        ]
    )
    D = np.unpackbits(a[:, None, :] ^ b[None, :, :], axis=2).sum(2)
    ref = [(i, int(D[i].argmin())) for i in range(40) if D[:, D[i].argmin()].argmin() == i]
    qi, mi, dist = mutual_nearest(a, b)
    assert list(zip(qi.tolist(), mi.tolist(), strict=True)) == ref
    np.testing.assert_array_equal(dist, D[qi, mi])
    f = rng.normal(size=(10, 8)).astype(np.float32)
    qi, mi, dist = mutual_nearest(f, f[::-1] + 1e-3)
    assert mi.tolist() == (9 - qi).tolist() and len(qi) == 10


def _unit(x: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(x / np.linalg.norm(x, axis=1, keepdims=True), np.float32)


def _mirrored(q: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Two columns per row of ``q`` at the same distance from it: a nearby point and its mirror image about a
    random plane through the row."""
    near = q + rng.normal(scale=0.02, size=q.shape)
    u = _unit(rng.normal(size=q.shape)).astype(np.float64)
    mirror = near - 2 * np.einsum("ij,ij->i", near - q, u)[:, None] * u
    return np.ascontiguousarray(np.concatenate([near, mirror]), np.float32)


def test_the_approximate_distances_are_every_pairs_squared_distance():
    from placerec.verify.matching import _approx_distances

    rng = np.random.default_rng(5)
    for n, m, d in ((300, 300, 256), (299, 253, 256), (3, 17, 64), (18, 5, 64)):
        a, b = rng.normal(size=(n, d)).astype(np.float32), rng.normal(size=(m, d)).astype(np.float32)
        a_sq, b_sq = np.einsum("ij,ij->i", a, a), np.einsum("ij,ij->i", b, b)
        exact = ((a[:, None, :].astype(np.float64) - b[None, :, :]) ** 2).sum(2)
        np.testing.assert_allclose(
            _approx_distances(a, b, a_sq, b_sq), exact, atol=1e-5 * (a_sq.max() + b_sq.max())
        )


def test_screened_float_matching_is_the_all_pairs_loop_bit_for_bit():
    from placerec.verify.matching import _nearest_both_ways_l2, _nearest_both_ways_screened

    rng = np.random.default_rng(4)
    a = _unit(rng.normal(size=(300, 256)))  # SuperPoint's size
    cases = {
        "revisit": (a, _unit(a[rng.permutation(300)] + rng.normal(scale=0.05, size=(300, 256)))),
        "unrelated": (a, _unit(rng.normal(size=(250, 256)))),
        # exact ties: repeated rows on both sides (the first index of equal distances wins, as in the loop)
        "ties": (np.repeat(a[:60], 3, axis=0), np.repeat(a[30:90], 2, axis=0)),
        # near ties: each row's two nearest columns mirror each other about a plane through it, so their exact
        # distances differ by float rounding only and the approximate distances alone pick the wrong one about half the time
        "mirrored": (a[:200], _mirrored(a[:200], rng)),
        "large norms": (a * 300.0, np.ascontiguousarray(a[::-1] * 290.0 + 0.1, np.float32)),
        "SURF-sized": (_unit(rng.normal(size=(200, 64))), _unit(rng.normal(size=(180, 64)))),
        # a NaN row matches nothing and hides nothing (the loop's own answer)
        "NaN": (np.where(np.arange(300)[:, None] == 7, np.nan, a).astype(np.float32), a[::-1].copy()),
        # sizes that leave rows and columns beyond the last whole 4 x 4 block of the approximate distances
        "ragged": (a[:299], _unit(rng.normal(size=(253, 256)))),
    }
    for name, (q, m) in cases.items():
        loop, screened = _nearest_both_ways_l2(q, m), _nearest_both_ways_screened(q, m)
        for x, y in zip(loop, screened, strict=True):
            np.testing.assert_array_equal(x, y, err_msg=name)
    # mutual_nearest screens from 16 rows on, the loop below; both give the brute-force matches
    for n in (10, 300):
        q, m = a[:n], _unit(a[:n][::-1] + rng.normal(scale=0.02, size=(n, 256)))
        D = ((q[:, None, :].astype(np.float64) - m[None, :, :]) ** 2).sum(2)
        ref = [(i, int(D[i].argmin())) for i in range(n) if D[:, D[i].argmin()].argmin() == i]
        qi, mi, dist = mutual_nearest(q, m)
        assert list(zip(qi.tolist(), mi.tolist(), strict=True)) == ref and len(ref) == n
        np.testing.assert_allclose(dist, np.sqrt(D[qi, mi]), rtol=1e-5)


@pytest.mark.parametrize("name", ["orb-hbst", "orb-dbow"])
def test_true_loop_gets_the_6dof_pose_and_a_wrong_place_ranks_lower(sim, name):
    scans, poses = sim
    rec = make_pipeline(name)
    rec.add(0, scans[0])
    rec.add(30, scans[30])  # ~30 m along the route: another place
    cands = rec.query(scans[2], k=2, query_id=2)
    assert [c.match_id for c in cands] == [0, 30]
    best = cands[0]
    assert best.accepted
    t_err, r_err = _errors(best.relative_pose, relative_pose(poses[0], poses[2]))
    assert (
        np.linalg.norm(relative_pose(poses[0], poses[2])[:3, 3]) > 1.5
    )  # a translation a yaw-only pose misses
    assert t_err < 0.3 and r_err < 2.0
    assert best.inliers >= 8 and best.verification.correspondences >= best.inliers
    assert 0 < best.score <= 1 and best.score == best.verification.score
    min_score = rec.params.verify.score.min_score
    assert all(c.score < min_score and not c.accepted for c in cands[1:])


def test_candidate_matches_are_the_keypoint_pairs_verification_was_given(sim):
    """``matches`` index the two descriptions' keypoints, row-aligned with the inlier mask: the inliers' 3D points
    agree under the verified pose, and a rejected candidate says why."""
    scans, _ = sim
    rec = make_pipeline("orb-hbst")
    descs = {i: rec.describe(scans[i]) for i in (0, 2, 30)}
    rec.add_description(0, descs[0])
    rec.add_description(30, descs[30])
    best, other = rec.query_description(descs[2], k=2, query_id=2)
    v = best.verification
    assert best.accepted and v.rejection is None
    m = best.matches
    assert m.dtype == np.int32 and m.shape == (v.correspondences, 2) and v.inlier_mask.shape == (m.shape[0],)
    assert m[:, 0].max() < len(descs[2]["keypoints"]) and m[:, 1].max() < len(descs[0]["keypoints"])
    src = descs[2]["keypoint_xyz"][m[:, 0]].astype(np.float64)
    dst = descs[0]["keypoint_xyz"][m[:, 1]].astype(np.float64)
    moved = src @ best.relative_pose[:3, :3].T + best.relative_pose[:3, 3]
    err = np.linalg.norm(moved - dst, axis=1)
    assert np.median(err[v.inlier_mask]) < 0.3 < np.median(err[~v.inlier_mask])
    assert not other.accepted and other.verification.rejection in REJECTIONS


def test_verification_needs_the_descriptions_3d_parts(sim):
    scans, _ = sim
    rec = make_pipeline("orb-hbst")
    desc = rec.describe(scans[0])
    with pytest.raises(ScanDataError, match="keypoint_xyz"):
        rec.add_description(0, {k: v for k, v in desc.items() if k != "keypoint_xyz"})
    with pytest.raises(ScanDataError, match="cloud"):
        rec.add_description(1, {k: v for k, v in desc.items() if k != "cloud"})
    rec.add_description(2, desc)
    with pytest.raises(ScanDataError, match="cloud"):
        rec.query_description({k: v for k, v in desc.items() if k != "cloud"})


def test_saved_database_keeps_the_3d_points_and_clouds(sim, tmp_path):
    scans, _ = sim
    rec = make_pipeline("orb-hbst")
    descs = {i: rec.describe(scans[i]) for i in (0, 30)}
    for i, d in descs.items():
        rec.add_description(i, d)
    rec.save(tmp_path / "db.npz")
    arrays = np.load(tmp_path / "db.npz")
    xyz = np.concatenate([descs[0]["keypoint_xyz"], descs[30]["keypoint_xyz"]])
    assert np.isnan(xyz).any()  # some keypoints lie in interpolated pixels
    np.testing.assert_array_equal(arrays["keypoint_xyz"], np.nan_to_num(xyz, nan=0.0))
    assert arrays["cloud_counts"].tolist() == [len(descs[0]["cloud"]), len(descs[30]["cloud"])]
    fresh = make_pipeline("orb-hbst")
    fresh.load(tmp_path / "db.npz")
    np.testing.assert_array_equal(fresh._kp_xyz[0], descs[0]["keypoint_xyz"])  # NaN again where it was NaN
    q = rec.describe(scans[2])
    before, after = rec.query_description(q, k=2), fresh.query_description(q, k=2)
    assert [(c.match_id, c.score) for c in before] == [(c.match_id, c.score) for c in after]
    np.testing.assert_array_equal(before[0].relative_pose, after[0].relative_pose)


@pytest.mark.parametrize("name", ["orb-dbow", "orb-hbst"])
def test_candidates_matched_on_the_helper_thread_are_those_of_one_thread(sim, name, monkeypatch):
    """Every other candidate's binary features are matched on the helper thread (`VisualFrontend._retrieved_all`):
    the candidates, their matches, inliers, poses and scores are the same as with one thread (no helper)."""

    def run(n_threads: str):
        monkeypatch.setenv("OMP_NUM_THREADS", n_threads)
        rec = make_pipeline(name)
        for i in (0, 30):
            rec.add(i, scans[i])
        return rec.query(scans[2], k=2, query_id=2)

    scans, _ = sim
    one, two = run("1"), run("2")
    assert len(one) == len(two) == 2
    for a, b in zip(one, two, strict=True):
        assert (a.match_id, a.score, a.inliers, a.accepted) == (b.match_id, b.score, b.inliers, b.accepted)
        np.testing.assert_array_equal(a.matches, b.matches)
        np.testing.assert_array_equal(a.relative_pose, b.relative_pose)


def test_candidates_reach_verification_hypothesised_on_the_thread_that_matched_them(sim, monkeypatch):
    """`VisualFrontend._retrieved_all` makes each candidate's RANSAC hypothesis where it matched it; those are the
    hypotheses `verify_candidates` would make, and it takes them as they are (it makes none itself)."""
    import placerec.pipelines.visual as visual
    import placerec.verify.candidates as candidates
    from placerec.verify.verify import hypothesise

    scans, _ = sim
    seen = []
    real = visual.verify_candidates

    def spy(cloud, retrieved, *args, **kwargs):
        seen.append((cloud, list(retrieved), args, kwargs))
        return real(cloud, retrieved, *args, **kwargs)

    monkeypatch.setattr(visual, "verify_candidates", spy)
    rec = make_pipeline("orb-dbow")
    for i in (0, 30):
        rec.add(i, scans[i])
    answer = rec.query(scans[2], k=2, query_id=2)
    ((cloud, retrieved, args, kwargs),) = seen
    assert len(retrieved) == 2 and all(r.hypothesis is not None for r in retrieved)
    vp = rec.params.verify
    for r in retrieved:
        h = hypothesise(r.src_kp, r.dst_kp, r.init, vp, r.quality)
        assert (h.inliers, h.correspondences, h.rejected_at) == (
            r.hypothesis.inliers,
            r.hypothesis.correspondences,
            r.hypothesis.rejected_at,
        )
        np.testing.assert_array_equal(h.T_match_query, r.hypothesis.T_match_query)

    def refused(*args, **kwargs):
        raise AssertionError("verify_candidates hypothesised a candidate that came with its hypothesis")

    monkeypatch.setattr(candidates, "hypothesise", refused)
    again = candidates.verify_candidates(cloud, retrieved, *args, **kwargs)
    assert [(c.match_id, c.score, c.inliers) for c in again] == [
        (c.match_id, c.score, c.inliers) for c in answer
    ]


def test_binary_matching_of_large_sets_with_ties_is_the_first_argmin_both_ways():
    """500 x 450 ORB-sized descriptors with few bits set, so that equal distances abound: each side's nearest is
    the first of its equal distances (``argmin``), as the pairwise loop gave."""
    rng = np.random.default_rng(7)
    a = np.packbits(rng.random((500, 256)) < 0.03, axis=1)
    b = np.packbits(rng.random((450, 256)) < 0.03, axis=1)
    D = np.unpackbits(a[:, None, :] ^ b[None, :, :], axis=2).sum(2)
    nn, back = D.argmin(1), D.argmin(0)
    assert (D == D.min(1, keepdims=True)).sum(1).max() > 1  # ties exist
    ref_q = np.flatnonzero(back[nn] == np.arange(500))
    qi, mi, dist = mutual_nearest(a, b)
    np.testing.assert_array_equal(qi, ref_q)
    np.testing.assert_array_equal(mi, nn[ref_q])
    np.testing.assert_array_equal(dist, D[ref_q, nn[ref_q]])
