"""Drifting odometry poses for SLAM-style use of simulated sequences.

Odometry is integrated from the true relative motions between consecutive scans, each perturbed by noise that
grows with the distance travelled (a random walk) plus systematic errors (a scale error and a heading bias), as a
LiDAR or wheel odometry would drift. The first odometry pose equals the first true pose.
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from placerec.params import Params
from placerec.sim.geometry import euler_rotation
from placerec.types import check_poses

__all__ = ["OdometryDrift", "drift_poses", "slam_demo_drift"]


class OdometryDrift(Params):
    """Drift parameters: noise that grows with the distance travelled and systematic errors (module docstring)."""

    translation: float = Field(0.01, ge=0, description="relative translation noise per metre (1 sigma)")
    rotation_deg: float = Field(0.03, ge=0, description="yaw noise, deg per sqrt(metre)")
    yaw_bias_deg_per_100m: float = Field(0.5, description="heading drift")
    scale_bias: float = Field(0.005, description="relative scale error")

    @classmethod
    def coerce(cls, value: OdometryDrift | float | bool | None) -> OdometryDrift | None:
        """None/False: no odometry; True: defaults; a float: ``translation`` (others scaled with it)."""
        if value is None or value is False:
            return None
        if value is True:
            return cls()
        if isinstance(value, OdometryDrift):
            return value
        base = cls()
        f = float(value) / base.translation
        return cls(
            translation=float(value),
            rotation_deg=base.rotation_deg * f,
            yaw_bias_deg_per_100m=base.yaw_bias_deg_per_100m * f,
            scale_bias=base.scale_bias * f,
        )


def slam_demo_drift() -> OdometryDrift:
    """The drift of configs/slam_demo.yaml's odometry, a LiDAR odometry's: heading drift 2 deg / 100 m, 0.2 %
    scale error, 1 % translation noise per metre (the evaluation's odometry gate assumes it)."""
    return OdometryDrift(translation=0.01, rotation_deg=0.03, yaw_bias_deg_per_100m=2.0, scale_bias=0.002)


def drift_poses(poses: np.ndarray, drift: OdometryDrift, seed: int) -> np.ndarray:
    """Odometry poses (N, 4, 4) that drift away from the true ``poses`` as described in the module docstring;
    `ScanDataError` when ``poses`` are no rigid motions (`placerec.types.check_poses`)."""
    poses = check_poses(poses, None, "drift_poses")
    n = len(poses)
    out = np.empty_like(poses)
    if n == 0:
        return out
    out[0] = poses[0]
    rng = np.random.default_rng([int(seed), 0x0D0])
    noise = rng.standard_normal((n, 6))
    for k in range(1, n):
        delta = np.linalg.solve(poses[k - 1], poses[k])
        step = float(np.linalg.norm(delta[:3, 3]))
        d = delta.copy()
        d[:3, 3] = delta[:3, 3] * (1.0 + drift.scale_bias) + noise[
            k, :3
        ] * drift.translation * step * np.array([1.0, 1.0, 0.3])
        rs = np.radians(drift.rotation_deg) * np.sqrt(step)
        yaw = np.radians(drift.yaw_bias_deg_per_100m) * step / 100.0 + noise[k, 3] * rs
        d[:3, :3] = euler_rotation(yaw, noise[k, 4] * rs * 0.3, noise[k, 5] * rs * 0.3) @ delta[:3, :3]
        out[k] = out[k - 1] @ d
    return out
