"""Evaluation: loop-closure ground truth and metrics (VPR paper protocol), retrieval recall@1 / @1% and the
same- / reverse-direction split, localisation success (ISHOT paper), errors of the closures' relative poses.

Only NumPy and SciPy are imported here; the repeatability and matching score of 2D features, which need the
feature extractors, are in `placerec.eval.features` (import it on its own).
"""

from placerec.eval.exclusion import DEFAULT_EXCLUSION_FRAMES, ExclusionWindow, path_length
from placerec.eval.ground_truth import (
    LoopGroundTruth,
    loop_ground_truth,
    positions_from_poses,
    yaws_from_poses,
)
from placerec.eval.metrics import (
    LocalizationMetrics,
    LoopMetrics,
    evaluate_loop,
    localization_metrics,
    loop_metrics,
    timing_summary,
)
from placerec.eval.pose_error import (
    ClosurePoseErrors,
    closure_pose_errors,
    error_stats,
    full_pose_mask,
    pose_errors,
)
from placerec.eval.retrieval import (
    RetrievalMetrics,
    direction_summary,
    recall_by_direction,
    retrieval_metrics,
    revisit_directions,
)

__all__ = [
    "DEFAULT_EXCLUSION_FRAMES",
    "ExclusionWindow",
    "LoopGroundTruth",
    "loop_ground_truth",
    "path_length",
    "positions_from_poses",
    "yaws_from_poses",
    "LoopMetrics",
    "loop_metrics",
    "evaluate_loop",
    "LocalizationMetrics",
    "localization_metrics",
    "timing_summary",
    "ClosurePoseErrors",
    "closure_pose_errors",
    "error_stats",
    "full_pose_mask",
    "pose_errors",
    "RetrievalMetrics",
    "retrieval_metrics",
    "revisit_directions",
    "direction_summary",
    "recall_by_direction",
]
