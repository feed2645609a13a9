"""The loop-closure detector and the evaluation's ground truth apply the same exclusion window."""

import itertools

import numpy as np
import pytest

from placerec.errors import ScanDataError
from placerec.eval import ExclusionWindow, loop_ground_truth
from placerec.loop_closure import LoopClosureDetector
from placerec.recognizer import make_pipeline
from placerec.types import Scan

N = 14


@pytest.fixture(scope="module")
def trajectory():
    """Irregular motion: steps of 0-3 m with stops, timestamps with gaps and repeated values, small scans."""
    rng = np.random.default_rng(7)
    steps = rng.choice([0.0, 0.4, 1.0, 2.7], size=N - 1)
    poses = np.tile(np.eye(4), (N, 1, 1))
    poses[1:, 0, 3] = np.cumsum(steps)
    poses[1:, 1, 3] = np.cumsum(rng.normal(0, 0.3, N - 1))
    stamps = np.r_[0.0, np.cumsum(rng.choice([0.0, 0.5, 1.0, 2.5], size=N - 1))]
    scans = [Scan(rng.normal(size=(150, 3)) * [20, 20, 2], np.ones(150)) for _ in range(N)]
    return poses, stamps, scans


LIMITS = list(
    itertools.product(
        [None, 0, 3],  # frames
        [None, 0.0, 2.5],  # seconds
        [None, 0.0, 3.0],  # metres
        [True, False],  # timestamps given
        [True, False],  # poses given
    )
)


@pytest.mark.parametrize("frames,seconds,metres,with_times,with_poses", LIMITS)
def test_detector_and_ground_truth_agree(trajectory, frames, seconds, metres, with_times, with_poses):
    poses, stamps, scans = trajectory
    times = stamps if with_times else None
    window = ExclusionWindow(frames, seconds, metres)
    detector = LoopClosureDetector(
        make_pipeline("scan-context"),
        threshold=0.0,
        exclusion_frames=frames,
        exclusion_seconds=seconds,
        exclusion_metres=metres,
        k=N,
    )
    no_times, no_poses = seconds is not None and not with_times, metres is not None and not with_poses
    if no_times or no_poses:  # both refuse, naming what they need
        with pytest.raises(ScanDataError, match="timestamp" if no_times else "pose"):
            detector.process(
                scans[0], pose=poses[0] if with_poses else None, timestamp=times[0] if with_times else None
            )
        with pytest.raises(ScanDataError, match="needs the"):
            window.sequence_bounds(N, times, poses[:, :3, 3] if with_poses else None)
        assert detector.n_processed == 0  # a refused scan does not use up an id
        return
    if with_poses:
        expected = loop_ground_truth(poses, exclusion=window, timestamps=times).max_eligible
    else:
        expected = window.sequence_bounds(N, times, None)
    used = []
    for i in range(N):
        detector.process(
            scans[i],
            pose=poses[i] if with_poses else None,
            timestamp=None if times is None else float(times[i]),
        )
        used.append(detector.last_max_id)
        assert all(c.match_id <= detector.last_max_id for c in detector.last_candidates)
    assert used == expected.tolist()


def test_metres_window_binds_where_the_frame_window_does_not(trajectory):
    """The case that disagreed before: frames and metres both set; the ground truth used only the metres."""
    poses, _, _ = trajectory
    both = loop_ground_truth(poses, exclusion=ExclusionWindow(frames=3, metres=3.0)).max_eligible
    frames_only = ExclusionWindow(frames=3).sequence_bounds(N)
    metres_only = ExclusionWindow(frames=None, metres=3.0).sequence_bounds(N, positions=poses[:, :3, 3])
    assert np.array_equal(both, np.minimum(frames_only, metres_only))
    assert not np.array_equal(both, metres_only) and not np.array_equal(both, frames_only)
