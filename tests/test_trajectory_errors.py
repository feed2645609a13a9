"""ATE and RPE (placerec.eval.trajectory) on hand-computed cases and invariances."""

import numpy as np
import pytest

from placerec.errors import ScanDataError
from placerec.eval.trajectory import align_rigid, ate, rpe, trajectory_errors
from placerec.sim.geometry import euler_rotation


def _pose(x, y, z=0.0, yaw=0.0):
    T = np.eye(4)
    T[:3, :3] = euler_rotation(yaw, 0.0, 0.0)
    T[:3, 3] = (x, y, z)
    return T


@pytest.fixture
def square():
    """A 40-pose drive around a 10 m square, turning at the corners."""
    poses = []
    for side in range(4):
        yaw = side * np.pi / 2
        start = np.array([[0, 0], [10, 0], [10, 10], [0, 10]][side], float)
        d = np.array([np.cos(yaw), np.sin(yaw)])
        poses += [_pose(*(start + d * k), 0.0, yaw) for k in range(10)]
    return np.stack(poses)


def test_a_rigidly_moved_trajectory_has_no_ate_and_no_rpe(square):
    T = _pose(5.0, -3.0, 1.0, 0.7)
    moved = T @ square
    assert ate(moved, square).max() < 1e-9
    assert np.allclose(align_rigid(moved, square), np.linalg.inv(T), atol=1e-9)
    t, r = rpe(moved, square, delta=3)
    assert t.max() < 1e-9 and r.max() < 1e-6
    # without alignment the ATE is the offset itself
    assert ate(moved, square, align=False).min() > 1.0


def test_ate_of_one_displaced_pose_hand_computed():
    """Poses on a line, one moved 1 m sideways: the least-squares rigid fit keeps a known residual."""
    gt = np.stack([_pose(float(x), 0.0) for x in range(5)])
    est = gt.copy()
    est[4, 1, 3] = 1.0
    e = ate(est, gt, align=False)
    assert e.tolist() == [0, 0, 0, 0, 1.0]
    aligned = ate(est, gt)
    # the fit can only reduce the squared sum; a line rotated about its centre spreads the 1 m offset
    assert np.sum(aligned**2) < 1.0 and aligned.max() < 1.0


def test_rpe_of_a_constant_step_error():
    """Every step 1 m long instead of 1.1 m: over delta frames the error is 0.1 * delta, rotation 0."""
    gt = np.stack([_pose(1.0 * k, 0.0) for k in range(20)])
    est = np.stack([_pose(1.1 * k, 0.0) for k in range(20)])
    t, r = rpe(est, gt, delta=4)
    assert np.allclose(t, 0.4) and np.allclose(r, 0.0, atol=1e-6)
    errs = trajectory_errors(est, gt, rpe_delta=4)
    assert errs.rpe_translation_rmse == pytest.approx(0.4)
    assert errs.rpe_delta == 4


def test_rpe_of_a_heading_error_in_degrees(square):
    est = square.copy()
    est[5:] = _pose(0, 0, 0, np.radians(2.0)) @ est[5:]  # a 2 deg jump between poses 4 and 5
    t, r = rpe(est, square, delta=1)
    assert r[4] == pytest.approx(2.0, abs=1e-9)
    assert np.delete(r, 4).max() < 1e-6


def test_bad_input_is_a_clear_error(square):
    with pytest.raises(ScanDataError, match="40 poses, the true one 39"):
        ate(square, square[:-1])
    with pytest.raises(ScanDataError, match="delta"):
        rpe(square, square, delta=40)
    with pytest.raises(ScanDataError, match="at least 3"):
        ate(square[:2], square[:2])
