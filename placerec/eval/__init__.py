"""Evaluation: loop-closure ground truth and metrics (VPR paper protocol), localisation success (ISHOT paper).

Only NumPy and SciPy are imported here.
"""

from placerec.eval.ground_truth import (
    LoopGroundTruth,
    eligible_max_index,
    loop_ground_truth,
    path_length,
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

__all__ = [
    "LoopGroundTruth",
    "eligible_max_index",
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
]
