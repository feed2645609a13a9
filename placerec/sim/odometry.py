"""Drifting odometry poses for SLAM-style use of simulated sequences.

Odometry is integrated from the true relative motions between consecutive scans, each perturbed by noise that
grows with the distance travelled (a random walk) plus systematic errors (a scale error and a heading bias), as a
LiDAR or wheel odometry would drift. The first odometry pose equals the first true pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from placerec.sim.geometry import euler_rotation

__all__ = ["OdometryDrift", "drift_poses"]


@dataclass(frozen=True)
class OdometryDrift:
    """Drift parameters: ``translation`` (1-sigma relative translation noise per metre), ``rotation_deg`` (yaw noise,
    deg per sqrt(metre)), ``yaw_bias_deg_per_100m`` and ``scale_bias`` (relative)."""

    translation: float = 0.01
    rotation_deg: float = 0.03
    yaw_bias_deg_per_100m: float = 0.5
    scale_bias: float = 0.005

    @classmethod
    def coerce(cls, value: OdometryDrift | float | bool | None) -> OdometryDrift | None:
        """None/False: no odometry; True: defaults; a float: ``translation`` (others scaled with it)."""
        if value is None or value is False:
            return None
        if value is True:
            return cls()
        if isinstance(value, OdometryDrift):
            return value
        f = float(value) / cls.translation
        return cls(
            translation=float(value),
            rotation_deg=cls.rotation_deg * f,
            yaw_bias_deg_per_100m=cls.yaw_bias_deg_per_100m * f,
            scale_bias=cls.scale_bias * f,
        )


def drift_poses(poses: np.ndarray, drift: OdometryDrift, seed: int) -> np.ndarray:
    """Odometry poses (N, 4, 4) that drift away from the true ``poses`` as described in the module docstring."""
    poses = np.asarray(poses, dtype=np.float64)
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
