"""Geometric verification of loop-closure candidates and their 6-DoF relative pose (``docs/verification.md``).

::

    from placerec.verify import VerifyParams, verify, verify_icp
    v = verify(query_xyz, match_xyz, query_kp_xyz, match_kp_xyz)     # correspondences -> RANSAC -> ICP
    v.T_match_query, v.score, v.accepted, v.inliers, v.fitness, v.rmse, v.timings_ms
    v = verify_icp(query_xyz, match_xyz, init=T_yaw)                  # ICP only (e.g. Scan Context)

Building blocks: `rigid_fit` (Kabsch/Umeyama, 6-DoF or 4-DoF), `ransac_pose`, `group_correspondences` (the
ISHOT paper's geometric consistency grouping), `prepare_source` / `prepare_target` / `refine` (ICP through
small_gicp or Open3D), `verified_score`.
"""

from __future__ import annotations

import logging

from placerec.verify.consistency import consistency_matrix, group_correspondences
from placerec.verify.icp import IcpCloud, IcpResult, alignment_stats, prepare_source, prepare_target, refine
from placerec.verify.kabsch import kabsch_batch, rigid_fit, yaw_batch
from placerec.verify.params import ConsistencyParams, IcpParams, RansacParams, ScoreParams, VerifyParams
from placerec.verify.ransac import RansacResult, ransac_pose, required_iterations
from placerec.verify.score import is_accepted, verified_score
from placerec.verify.verify import Verification, as_source, as_target, verify, verify_icp

logging.getLogger(__name__).addHandler(logging.NullHandler())

__all__ = [
    "Verification",
    "verify",
    "verify_icp",
    "as_source",
    "as_target",
    "VerifyParams",
    "RansacParams",
    "ConsistencyParams",
    "IcpParams",
    "ScoreParams",
    "rigid_fit",
    "kabsch_batch",
    "yaw_batch",
    "ransac_pose",
    "RansacResult",
    "required_iterations",
    "group_correspondences",
    "consistency_matrix",
    "IcpCloud",
    "IcpResult",
    "prepare_source",
    "prepare_target",
    "refine",
    "alignment_stats",
    "verified_score",
    "is_accepted",
]
