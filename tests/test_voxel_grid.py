"""`placerec.verify.voxel_grid.voxel_points` is small_gicp's single-threaded voxel grid, bit for bit."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import small_gicp

from placerec.verify.voxel_grid import voxel_points


def small_gicp_voxels(points: np.ndarray, voxel: float) -> np.ndarray:
    vox = small_gicp.voxelgrid_sampling(np.ascontiguousarray(points, dtype=np.float64), voxel)
    return np.asarray(vox.points(), dtype=np.float32)[:, :3]


@pytest.mark.parametrize("scale", [0.01, 1.0, 40.0, 2000.0])
@pytest.mark.parametrize("voxel", [0.05, 0.4, 1.5])
def test_the_voxel_grid_is_small_gicps_bit_for_bit(scale: float, voxel: float) -> None:
    rng = np.random.default_rng(int(scale * 100 + voxel * 10))
    # float32 values (what scans hold) around the origin, where voxel coordinates change sign, and duplicates
    p = (rng.normal(size=(20_000, 3)) * scale).astype(np.float32).astype(np.float64)
    p = np.concatenate([p, p[:500], np.round(p[:2000] / voxel) * voxel])
    ours, theirs = voxel_points(p, voxel), small_gicp_voxels(p, voxel)
    assert ours.dtype == np.float32 and ours.shape == theirs.shape
    assert np.array_equal(ours, theirs)  # the same means in the same (key) order


def test_a_voxel_is_the_mean_of_its_points_in_key_order() -> None:
    p = np.array([[0.1, 0.1, 0.1], [0.3, 0.3, 0.3], [-0.1, 0.0, 0.0], [1.2, 0.0, 0.0], [0.2, 0.0, 0.2]])
    out = voxel_points(p, 1.0)
    # voxels (0,0,0), (-1,0,0), (1,0,0): packed x lowest, so -1 (offset 2^20 - 1) < 0 < 1
    expected = np.array([[-0.1, 0.0, 0.0], [0.2, 0.4 / 3, 0.6 / 3], [1.2, 0.0, 0.0]], np.float32)
    np.testing.assert_array_equal(out, expected)
    assert np.array_equal(out, small_gicp_voxels(p, 1.0))


def test_points_outside_the_packed_range_and_non_finite_ones_are_left_out() -> None:
    p = np.array([[1e6, 0, 0], [0.1, 0.1, 0.1], [-1e6, 5, 5], [np.nan, 0, 0], [np.inf, 1, 1], [3, 3, 3]])
    out = voxel_points(p, 0.4)
    np.testing.assert_array_equal(out, np.array([[0.1, 0.1, 0.1], [3, 3, 3]], np.float32))
    assert np.array_equal(out, small_gicp_voxels(p[[0, 1, 2, 5]], 0.4))  # small_gicp: no NaN in its input
    assert voxel_points(np.zeros((0, 3)), 0.4).shape == (0, 3)
    assert voxel_points(np.array([[1e7, 0.0, 0.0]]), 0.4).shape == (0, 3)


def test_extra_columns_are_ignored() -> None:
    rng = np.random.default_rng(3)
    p = rng.normal(size=(1000, 4)) * 5
    assert np.array_equal(voxel_points(p, 0.5), voxel_points(p[:, :3], 0.5))


def longest_stall(voxelise, p: np.ndarray) -> tuple[float, float]:
    """The longest time this thread's Python loop waited while another thread ran ``voxelise(p)`` three times, and
    the time of one such call."""
    t0 = time.perf_counter()
    voxelise(p)
    call = time.perf_counter() - t0
    worker = threading.Thread(target=lambda: [voxelise(p) for _ in range(3)])
    last, stall = time.perf_counter(), 0.0
    worker.start()
    while worker.is_alive():
        now = time.perf_counter()
        stall, last = max(stall, now - last), now
    worker.join()
    return stall, call


def test_the_voxel_grid_lets_another_thread_run() -> None:
    """While another thread voxelises, this thread's Python code keeps running: the kernel releases the GIL,
    small_gicp's call holds it for the whole call."""
    p = np.random.default_rng(0).normal(size=(1_000_000, 3)) * 30
    voxel_points(p[:10], 0.4)  # compiled before
    stall, call = longest_stall(lambda x: voxel_points(x, 0.4), p)
    theirs, their_call = longest_stall(lambda x: small_gicp_voxels(x, 0.4), p)
    assert theirs > 0.5 * their_call  # the reference: held for its call
    assert stall < 0.5 * call  # descheduling on a busy machine aside, nothing holds it up
