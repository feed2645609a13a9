"""The pose ground truth (overlap revisits, closures judged by their relative pose) and the VPR paper's
ICP-confirmed ground truth, on hand-built clouds and trajectories."""

from __future__ import annotations

import numpy as np
import pytest

from placerec.errors import ScanDataError
from placerec.eval import loop_ground_truth, loop_metrics
from placerec.eval.exclusion import ExclusionWindow
from placerec.eval.icp_truth import icp_ground_truth
from placerec.eval.pose_truth import (
    PoseTruthSettings,
    correct_candidates,
    overlap_directions,
    overlap_truth,
    relative_truth,
    scan_voxels,
    with_candidates,
)


def _pose(x: float, y: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:2, 3] = x, y
    return T


def test_scan_voxels_are_world_cells_of_the_points_within_range():
    s = PoseTruthSettings(voxel=1.0, max_range=10.0)
    pts = np.array([[0.5, 0.5, 0.5], [0.6, 0.4, 0.2], [1.5, 0.5, 0.5], [20.0, 0, 0], [np.nan, 0, 0]])
    here, moved = scan_voxels(pts, np.eye(4), s), scan_voxels(pts, _pose(1.0), s)
    assert here.size == 2  # two points share a cell; the far and the NaN point are dropped
    assert (
        np.intersect1d(here, moved).size == 1
    )  # moved by 1 m: the second cell of one is the first of the other


def _wall_scan(rng: np.random.Generator, n: int = 4000) -> np.ndarray:
    """Points on the walls of a 30 x 30 m box around the sensor (sensor frame)."""
    side = rng.integers(0, 4, n)
    t = rng.uniform(-15, 15, n)
    z = rng.uniform(-1.5, 3.0, n)
    x = np.where(side == 0, 15.0, np.where(side == 1, -15.0, t))
    y = np.where(side == 2, 15.0, np.where(side == 3, -15.0, t))
    return np.stack([x, y, z], axis=1)


def test_overlap_revisits_need_an_eligible_scan_sharing_half_the_voxels():
    rng = np.random.default_rng(0)
    world = _wall_scan(rng)
    poses = np.stack([_pose(0.0), _pose(100.0), _pose(0.3)])  # scan 2 is back at scan 0's place
    scans = [world - P[:3, 3] for P in poses]  # sensor frame (no rotation)
    scans[1] = _wall_scan(rng) * 0.5  # somewhere else entirely
    s = PoseTruthSettings(voxel=1.0)
    vox = [scan_voxels(p, P, s) for p, P in zip(scans, poses, strict=True)]
    truth = overlap_truth(vox, poses, ExclusionWindow(frames=1), settings=s)
    assert truth.is_revisit.tolist() == [False, False, True]
    assert truth.best_overlap[2] > 0.5
    far = overlap_truth(vox, poses, ExclusionWindow(frames=3), settings=s)  # scan 0 is too recent for scan 2
    assert not far.is_revisit.any()


def test_a_closure_is_true_by_its_pose_whatever_the_distance():
    poses = np.stack([_pose(0.0), _pose(50.0), _pose(8.0, yaw_deg=30.0)])
    vox = [np.zeros(0, np.int64)] * 3  # no overlap anywhere: revisits only from correct closures
    base = overlap_truth(vox, poses, ExclusionWindow(frames=1))
    true_rel = relative_truth(poses, np.array([2]), np.array([0]))[0]
    assert np.allclose(true_rel, np.linalg.inv(poses[0]) @ poses[2])
    off = true_rel.copy()
    off[0, 3] += 0.6  # 0.6 m off: beyond 0.5 m
    turned = true_rel @ _pose(0.0, yaw_deg=2.5)  # 2.5 deg off
    q = np.array([1, 2])
    m = np.array([[0, -1, -1], [0, 0, 1]])
    R = np.full((2, 3, 4, 4), np.nan)
    R[0, 0] = relative_truth(poses, np.array([1]), np.array([0]))[0]
    R[1] = [true_rel, off, turned]
    keys = correct_candidates(base, poses, q, m, R)
    assert keys.tolist() == [1 * 3 + 0, 2 * 3 + 0]  # both exact poses; the 0.6 m and 2.5 deg ones are wrong
    truth = with_candidates(base, keys)
    assert truth.is_revisit.tolist() == [False, True, True]
    assert truth.is_true_match(np.array([2, 2, 2]), np.array([0, 1, -1])).tolist() == [True, False, False]
    # the same candidate with the wrong pose first: a false closure, and the query stays a missed revisit
    metrics = loop_metrics(q, np.array([0, 0]), np.array([0.9, 0.8]), with_candidates(base, keys[:1]))
    assert metrics.n_revisits == 1 and metrics.confusion_at(0.5) == {"tp": 1, "fp": 1, "fn": 0, "tn": 0}


def test_recall_stays_at_most_one_when_every_closure_is_right():
    poses = np.stack([_pose(x) for x in (0.0, 1.0, 30.0, 31.0)])
    base = overlap_truth([np.zeros(0, np.int64)] * 4, poses, ExclusionWindow(frames=2))
    q, m = np.array([2, 3]), np.array([[0], [1]])
    R = relative_truth(poses, np.array([2, 3]), np.array([0, 1]))[:, None]
    truth = with_candidates(base, correct_candidates(base, poses, q, m, R))
    metrics = loop_metrics(q, m[:, 0], np.array([0.5, 0.6]), truth)
    assert metrics.recall_at_max_f1 == 1.0 and metrics.precision_at_max_f1 == 1.0


def test_bad_settings_and_inputs_are_errors():
    with pytest.raises(ScanDataError, match="min_overlap"):
        PoseTruthSettings(min_overlap=0.0)
    with pytest.raises(ScanDataError, match="voxel"):
        PoseTruthSettings(voxel=float("nan"))
    with pytest.raises(ScanDataError, match="2 voxel sets for 3 poses"):
        overlap_truth([np.zeros(0, np.int64)] * 2, np.stack([np.eye(4)] * 3))
    bad = np.stack([np.eye(4)] * 2)
    bad[1, 0, 3] = np.inf
    with pytest.raises(ScanDataError, match="NaN or inf"):
        overlap_truth([np.zeros(0, np.int64)] * 2, bad)


def test_icp_truth_confirms_near_pairs_that_register_and_refuses_those_that_share_nothing():
    rng = np.random.default_rng(1)
    world = _wall_scan(rng, 6000)
    poses = np.stack([_pose(0.0), _pose(40.0), _pose(2.0, 1.0, 10.0), _pose(3.0)])
    clouds = [(world - P[:3, 3]) @ P[:3, :3] for P in poses]  # T_world_sensor^-1 of the same box
    clouds[3] = rng.uniform(-3, 3, (3000, 3)) + [0, 0, 40.0]  # near scan 0 but sees nothing of the box
    base = loop_ground_truth(poses, gt_distance=5.0, exclusion=ExclusionWindow(frames=2))
    assert base.is_revisit.tolist() == [False, False, True, True]
    truth = icp_ground_truth(base, [c.astype(np.float32) for c in clouds], poses)
    assert truth.is_revisit.tolist() == [False, False, True, False]
    assert truth.is_true_match(np.array([2, 3]), np.array([0, 0])).tolist() == [True, False]


def test_a_revisit_is_driven_the_same_way_when_a_scan_heading_that_way_overlaps_it():
    # out along x (scans 0-29, heading 0), back (30-59, heading 180), out again (60-89): each scan sees the 20 m of
    # road around it, so the way back overlaps the way out and the second way out overlaps both
    xs = np.r_[np.arange(30.0), np.arange(29.0, -1.0, -1.0), np.arange(30.0)]
    yaws = np.r_[np.zeros(30), np.full(30, 180.0), np.zeros(30)]
    poses = np.stack([_pose(x, 0.0, y) for x, y in zip(xs, yaws, strict=True)])
    vox = [np.arange(int(x) - 10, int(x) + 10, dtype=np.int64) for x in xs]
    s = PoseTruthSettings()
    base = overlap_truth(vox, poses, ExclusionWindow(frames=20), settings=s)
    d = overlap_directions(vox, poses, base)
    back, again = d[30:60][base.is_revisit[30:60]], d[60:][base.is_revisit[60:]]
    assert back.size > 10 and (back == 2).all()  # only the way out, the other heading, overlaps them
    assert again.size == 30 and (again == 1).all()  # the first way out heads the same way
    assert (d[~base.is_revisit] == 0).all()
    # a heading within 90 deg is the same way; past it the other
    assert (
        overlap_directions(vox, poses, base, reverse_yaw_deg=179.0)[30:60][base.is_revisit[30:60]] == 2
    ).all()
    assert (
        overlap_directions(vox, poses, base, reverse_yaw_deg=180.0)[30:60][base.is_revisit[30:60]] == 1
    ).all()
    # a revisit only a correct closure made (no scan overlaps it enough) takes the heading of the closure's match
    vox[40] = np.array([1000, 1001], dtype=np.int64)
    lone = overlap_truth(vox, poses, ExclusionWindow(frames=20), settings=s)
    assert not lone.is_revisit[40]
    closed = with_candidates(lone, np.zeros(0, dtype=np.int64), np.isin(np.arange(90), [40]))
    assert overlap_directions(vox, poses, closed, closed_by={40: 3})[40] == 2  # scan 3 heads the other way
    closed_same = {40: 5}
    poses[5] = _pose(5.0, 0.0, 170.0)
    assert overlap_directions(vox, poses, closed, closed_by=closed_same)[40] == 1
