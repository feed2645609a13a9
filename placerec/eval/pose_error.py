"""Errors of estimated relative poses against ground truth (issue #12: verified loop closures).

A loop closure's ``relative_pose`` is ``T_match_query`` (`placerec.types`); its ground truth is
``relative_pose(T_world_match, T_world_query)``. For an estimate ``T_est`` and the truth ``T_gt``:

* **translation error** ``||t_est - t_gt||`` (metres): how far the closure puts the query from where it was,
  expressed in the match frame (the same distance as ``T_world_match @ T_est`` against ``T_world_query``);
* **rotation error** the angle of ``R_gt^T R_est`` (degrees), computed as ``atan2(|v| / 2, (tr - 1) / 2)`` with
  ``v`` the skew part of that matrix, which stays exact near 0 and 180 degrees (``arccos`` of the trace does not).

Only a *6-DoF estimate* is scored: a finite pose with a non-zero translation. A pose with exactly zero translation
is an orientation-only guess (Scan Context's yaw, an image column shift), not a position estimate, and a candidate
without a pose has none; both are reported as missing (``null`` in ``metrics.json``), never as an error equal to
the true offset.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from placerec.errors import ScanDataError
from placerec.types import relative_pose

if TYPE_CHECKING:
    from placerec.eval.metrics import LoopMetrics

__all__ = ["pose_errors", "full_pose_mask", "ClosurePoseErrors", "closure_pose_errors", "error_stats"]


def _as_poses(T: Any, name: str) -> np.ndarray:
    P = np.asarray(T, dtype=np.float64)
    if P.shape == (4, 4):
        P = P[None]
    if P.ndim != 3 or P.shape[1:] != (4, 4):
        raise ScanDataError(f"{name} must be 4x4 poses, shape (N, 4, 4), got {P.shape}")
    return P


def full_pose_mask(T: Any) -> np.ndarray:
    """(N,) True where a (N, 4, 4) pose (NaN rows = none) is a 6-DoF estimate: finite, translation non-zero."""
    P = _as_poses(T, "poses")
    finite = np.isfinite(P).all(axis=(1, 2))
    return finite & np.any(np.where(finite[:, None], P[:, :3, 3], 0.0) != 0.0, axis=1)


def pose_errors(T_est: Any, T_gt: Any) -> tuple[np.ndarray, np.ndarray]:
    """(translation error m, rotation error deg), each (N,), of estimated against true (N, 4, 4) poses (a single
    4x4 is one row). Rows of ``T_est`` with NaN give NaN errors; the truth must be finite."""
    est, gt = _as_poses(T_est, "T_est"), _as_poses(T_gt, "T_gt")
    if est.shape != gt.shape:
        raise ScanDataError(f"{est.shape[0]} estimated poses for {gt.shape[0]} true ones")
    if not np.isfinite(gt).all():
        raise ScanDataError("true poses contain NaN or inf")
    trans = np.linalg.norm(est[:, :3, 3] - gt[:, :3, 3], axis=1)
    D = np.einsum("nji,njk->nik", gt[:, :3, :3], est[:, :3, :3])  # R_gt^T R_est
    skew = np.stack([D[:, 2, 1] - D[:, 1, 2], D[:, 0, 2] - D[:, 2, 0], D[:, 1, 0] - D[:, 0, 1]], axis=1)
    cos = (np.trace(D, axis1=1, axis2=2) - 1.0) / 2.0
    rot = np.degrees(np.arctan2(np.linalg.norm(skew, axis=1) / 2.0, cos))
    return trans, rot


def error_stats(errors: np.ndarray) -> dict[str, float]:
    """``{"median", "p95", "max"}`` of the finite errors (NaN each when there are none)."""
    e = np.asarray(errors, dtype=np.float64)
    e = e[np.isfinite(e)]
    if e.size == 0:
        return {"median": float("nan"), "p95": float("nan"), "max": float("nan")}
    return {"median": float(np.median(e)), "p95": float(np.percentile(e, 95)), "max": float(e.max())}


@dataclass(frozen=True, eq=False)
class ClosurePoseErrors:
    """Pose errors of the top candidates accepted at ``threshold`` (see `closure_pose_errors`).

    ``translation_m`` / ``rotation_deg`` (Q,) per query, aligned with the metrics' ``query_ids``: NaN where the
    query's top candidate has no 6-DoF pose (or no candidate). ``tp`` / ``accepted`` (Q,) masks at the threshold.
    """

    threshold: float
    translation_m: np.ndarray
    rotation_deg: np.ndarray
    tp: np.ndarray
    accepted: np.ndarray

    def summary(self) -> dict[str, Any]:
        """JSON-friendly: statistics over accepted true positives (``tp_*``) and the worst accepted closure, true
        or false (``accepted_max_*``); NaN (null in JSON) where no such closure has a 6-DoF pose."""
        has = np.isfinite(self.translation_m)
        acc = self.accepted & has
        worst = (
            (float(self.translation_m[acc].max()), float(self.rotation_deg[acc].max()))
            if acc.any()
            else (float("nan"), float("nan"))
        )
        return {
            "threshold": self.threshold,
            "n_tp": int(self.tp.sum()),
            "n_tp_with_pose": int((self.tp & has).sum()),
            "tp_translation_m": error_stats(self.translation_m[self.tp]),
            "tp_rotation_deg": error_stats(self.rotation_deg[self.tp]),
            "n_accepted": int(self.accepted.sum()),
            "n_accepted_with_pose": int(acc.sum()),
            "accepted_max_translation_m": worst[0],
            "accepted_max_rotation_deg": worst[1],
        }


def closure_pose_errors(
    metrics: LoopMetrics, relative_poses: Any, poses: Any, threshold: float | None = None
) -> ClosurePoseErrors:
    """Errors of the top candidates' ``relative_pose`` (``T_match_query``) against the ground truth.

    ``relative_poses`` (Q, 4, 4) is aligned with ``metrics.query_ids`` (NaN rows: no pose); ``poses`` (N, 4, 4)
    are the ``T_world_sensor`` the ids index into. ``threshold`` defaults to the operating point, the max-F1
    threshold (nothing is accepted when there is no candidate). Errors are computed for every top candidate with
    a 6-DoF pose (`full_pose_mask`); the summary keeps the accepted ones.
    """
    R = _as_poses(relative_poses, "relative_poses")
    P = _as_poses(poses, "poses")
    q, m = metrics.query_ids, metrics.match_ids
    if R.shape[0] != q.size:
        raise ScanDataError(f"{R.shape[0]} relative poses for {q.size} evaluated queries")
    t = metrics.threshold_at_max_f1 if threshold is None else float(threshold)
    out = metrics.outcomes_at(t) if np.isfinite(t) else {"accepted": np.zeros(q.size, bool)}
    accepted = out["accepted"]
    tp = accepted & metrics.correct
    trans = np.full(q.size, np.nan)
    rot = np.full(q.size, np.nan)
    scored = full_pose_mask(R) & (m >= 0)
    if scored.any():
        truth = np.stack([relative_pose(P[j], P[i]) for i, j in zip(q[scored], m[scored], strict=True)])
        trans[scored], rot[scored] = pose_errors(R[scored], truth)
    return ClosurePoseErrors(t, trans, rot, tp, accepted)
