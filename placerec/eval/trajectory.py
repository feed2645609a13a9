"""Trajectory errors of a SLAM estimate against ground truth: ATE after rigid alignment and RPE.

* **ATE** (absolute trajectory error, Sturm et al. 2012): the estimated positions are aligned to the true ones by
  the rigid motion ``T`` (no scale: LiDAR trajectories have metric scale) minimising ``sum |T p_est - p_gt|^2``
  (Umeyama 1991 without scale, the closed form of `placerec.verify.kabsch.rigid_fit`); ATE is the RMSE of the
  remaining position errors (also mean, median, max).
* **RPE** (relative pose error) over ``delta`` frames: for every ``i``, the error of the estimated motion
  ``E_i^-1 E_{i+delta}`` against the true one ``G_i^-1 G_{i+delta}`` (translation in metres, rotation in
  degrees, as `placerec.eval.pose_error.pose_errors`); reported as RMSE and mean. Alignment does not change it.

These are evo's ``ape`` (translation part, ``--align``) and ``rpe`` (``--delta N --delta_unit f``, translation
and angle in degrees) definitions; docs/slam.md says why placerec computes them here.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from placerec.errors import ScanDataError
from placerec.eval.pose_error import pose_errors
from placerec.types import check_poses
from placerec.verify.kabsch import rigid_fit

__all__ = ["align_rigid", "ate", "rpe", "TrajectoryErrors", "trajectory_errors"]


def _pair(est: Any, gt: Any) -> tuple[np.ndarray, np.ndarray]:
    E = check_poses(est, None, "estimated trajectory")
    G = check_poses(gt, None, "true trajectory")
    if E.shape[0] != G.shape[0]:
        raise ScanDataError(f"the estimated trajectory has {E.shape[0]} poses, the true one {G.shape[0]}")
    if E.shape[0] < 3:
        raise ScanDataError(f"trajectory errors need at least 3 poses, got {E.shape[0]}")
    return E, G


def align_rigid(est: Any, gt: Any) -> np.ndarray:
    """The 4x4 rigid motion ``T`` that best maps the estimated positions onto the true ones (least squares):
    ``T @ est`` is the aligned trajectory."""
    E, G = _pair(est, gt)
    return rigid_fit(E[:, :3, 3], G[:, :3, 3])


def ate(est: Any, gt: Any, align: bool = True) -> np.ndarray:
    """(N,) position errors (m) of ``est`` after rigid alignment to ``gt`` (``align=False``: as given)."""
    E, G = _pair(est, gt)
    p = E[:, :3, 3]
    if align:
        T = rigid_fit(p, G[:, :3, 3])
        p = p @ T[:3, :3].T + T[:3, 3]
    return np.linalg.norm(p - G[:, :3, 3], axis=1)


def rpe(est: Any, gt: Any, delta: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(translation m, rotation deg) errors of the motions over ``delta`` frames, each (N - delta,)."""
    E, G = _pair(est, gt)
    if not 1 <= delta < E.shape[0]:
        raise ScanDataError(f"RPE delta must be in [1, {E.shape[0] - 1}] frames, got {delta}")
    rel_e = np.linalg.inv(E[:-delta]) @ E[delta:]
    rel_g = np.linalg.inv(G[:-delta]) @ G[delta:]
    return pose_errors(rel_e, rel_g)


def _rmse(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


@dataclass(frozen=True)
class TrajectoryErrors:
    """ATE and RPE of one trajectory (metres, degrees)."""

    ate_rmse: float
    ate_mean: float
    ate_median: float
    ate_max: float
    rpe_delta: int
    rpe_translation_rmse: float
    rpe_rotation_rmse_deg: float

    def as_dict(self) -> dict[str, float | int]:
        return dict(self.__dict__)


def trajectory_errors(est: Any, gt: Any, rpe_delta: int = 10) -> TrajectoryErrors:
    """ATE (aligned) and RPE over ``rpe_delta`` frames (capped at N - 1) of ``est`` against ``gt``."""
    e = ate(est, gt)
    delta = min(int(rpe_delta), len(e) - 1)
    rt, rr = rpe(est, gt, delta)
    return TrajectoryErrors(
        ate_rmse=_rmse(e),
        ate_mean=float(e.mean()),
        ate_median=float(np.median(e)),
        ate_max=float(e.max()),
        rpe_delta=delta,
        rpe_translation_rmse=_rmse(rt),
        rpe_rotation_rmse_deg=_rmse(rr),
    )
