"""What the loop evaluation's pose and ICP ground truths need from every scan, collected while the run reads it.

`TruthClouds` is called by `placerec.experiment.runner.run_loop` with each preprocessed scan (``on_scan``): it keeps
the scan's occupied world voxels (`placerec.eval.pose_truth.scan_voxels`, placed by the true pose) when the pose
truth is on, and its points voxelised in the sensor frame when ``evaluation.gt_icp`` is on, so that the report never
reads the scans again.
"""

from __future__ import annotations

import numpy as np

from placerec.config import EvaluationConfig
from placerec.eval.icp_truth import IcpTruthSettings
from placerec.eval.pose_truth import PoseTruthSettings, scan_voxels
from placerec.types import Scan

__all__ = ["TruthClouds", "pose_truth_settings"]


def pose_truth_settings(evaluation: EvaluationConfig) -> PoseTruthSettings:
    """The ``evaluation.pose_truth`` section as `PoseTruthSettings`."""
    pt = evaluation.pose_truth
    return PoseTruthSettings(
        max_translation=pt.max_translation,
        max_rotation_deg=pt.max_rotation_deg,
        min_overlap=pt.min_overlap,
        voxel=pt.voxel,
    )


class TruthClouds:
    """Per-scan voxels (pose truth) and voxelised clouds (ICP truth) of a sequence with true ``poses``."""

    def __init__(self, evaluation: EvaluationConfig, poses: np.ndarray) -> None:
        self.poses = np.asarray(poses, dtype=np.float64)
        self.settings = pose_truth_settings(evaluation)
        self.pose_truth = evaluation.pose_truth.enabled
        self.icp_truth = evaluation.gt_icp
        self.icp_settings = IcpTruthSettings()
        self.voxels: list[np.ndarray] = []
        self.clouds: list[np.ndarray] = []
        #: (is_revisit, best_overlap) of the overlap search once made (`placerec.eval.pose_truth.overlap_truth`)
        self.overlap: tuple[np.ndarray, np.ndarray] | None = None

    def __call__(self, index: int, scan: Scan) -> None:
        if index != len(self.voxels):
            raise ValueError(f"scans must arrive in order: got {index} after {len(self.voxels)}")
        xyz = scan.xyz
        self.voxels.append(
            scan_voxels(xyz, self.poses[index], self.settings) if self.pose_truth else np.zeros(0, np.int64)
        )
        if self.icp_truth:
            from placerec.verify.voxel_grid import voxel_points

            finite = xyz[np.isfinite(xyz).all(axis=1) & (np.abs(xyz).sum(axis=1) > 0)]
            self.clouds.append(voxel_points(finite, self.icp_settings.voxel / 2))
