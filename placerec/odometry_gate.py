"""An odometry gate for loop closures: a closure must agree with where the odometry says the query is.

A closure's relative pose ``T_match_query`` and the odometry's own ``T_odom = inv(O_match) @ O_query`` describe
the same motion; they differ by the odometry's drift over the path between the two places, plus the closure's own
error. A SLAM system that has odometry knows how far it can have drifted, so a closure that puts the query much
farther from where the odometry has it is a look-alike place (a repeated block, a second identical warehouse
aisle), however well its scans register: LIO-SAM searches loop candidates only within a radius of the current
estimate for the same reason. The gate admits a closure when

    |t(T_match_query) - t(T_odom)|       <= metres  + per_metre * L
    angle(inv(T_match_query) @ T_odom)  <= degrees + degrees_per_metre * L

where ``L`` is the odometry's path length (m) from the matched place to the query. The bound is the odometry's,
not the place recogniser's: ``per_metre`` and ``degrees_per_metre`` must cover the worst relative drift of the
odometry in use. The defaults were chosen on the tuning split (docs/protocol.md, "The odometry gate") for the
demo SLAM config's drift model (heading drift 2 deg / 100 m, 1 % translation noise per metre, 0.2 % scale error:
configs/slam_demo.yaml); an odometry that drifts more needs wider bounds.

A candidate without a 6-DoF relative pose carries nothing to check and is left to the threshold alone.
`placerec.loop_closure.LoopClosureDetector` (``odometry_gate``) applies the gate online to the poses given to
``process``; the evaluation (``evaluation.odometry_gate``) applies the same test to a run's candidates.
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from placerec.params import Params

__all__ = ["OdometryGateParams", "odometry_disagreement"]


class OdometryGateParams(Params):
    """The bounds of the odometry gate (module docstring); defaults chosen on the tuning split."""

    metres: float = Field(1.0, ge=0, allow_inf_nan=False, description="translation bound at L = 0 (m)")
    per_metre: float = Field(
        0.04, ge=0, allow_inf_nan=False, description="translation bound per metre of odometry path"
    )
    degrees: float = Field(4.0, ge=0, allow_inf_nan=False, description="rotation bound at L = 0 (deg)")
    degrees_per_metre: float = Field(
        0.05, ge=0, allow_inf_nan=False, description="rotation bound per metre of odometry path (deg)"
    )

    def admits(self, translation_m: np.ndarray, rotation_deg: np.ndarray, path_m: np.ndarray) -> np.ndarray:
        """Where a disagreement (`odometry_disagreement`) over ``path_m`` metres of odometry is within the bounds;
        NaN (no pose to compare) is admitted."""
        t = np.asarray(translation_m, dtype=np.float64)
        r = np.asarray(rotation_deg, dtype=np.float64)
        path = np.abs(np.asarray(path_m, dtype=np.float64))
        ok = (t <= self.metres + self.per_metre * path) & (r <= self.degrees + self.degrees_per_metre * path)
        return ok | np.isnan(t) | np.isnan(r)


def odometry_disagreement(
    T_match_query: np.ndarray, odom_match: np.ndarray, odom_query: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(translation m, rotation deg) between each closure's ``T_match_query`` and the odometry's motion from the
    matched place to the query, for (N, 4, 4) stacks (or single 4x4 poses); NaN where a closure has no pose."""
    T = np.asarray(T_match_query, dtype=np.float64).reshape(-1, 4, 4)
    Om = np.asarray(odom_match, dtype=np.float64).reshape(-1, 4, 4)
    Oq = np.asarray(odom_query, dtype=np.float64).reshape(-1, 4, 4)
    odom = np.linalg.solve(Om, Oq)  # inv(O_match) @ O_query
    trans = np.linalg.norm(T[:, :3, 3] - odom[:, :3, 3], axis=1)
    R = np.einsum("nji,njk->nik", T[:, :3, :3], odom[:, :3, :3])  # inv(R_closure) @ R_odom
    cos = np.clip((np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    rot = np.degrees(np.arccos(cos))
    bad = ~np.isfinite(T).all(axis=(1, 2))
    trans[bad] = np.nan
    rot[bad] = np.nan
    return trans, rot
