"""LiDAR odometry from the scans themselves: KISS-ICP (Vizzo et al. 2023, PyPI ``kiss-icp``), one scan at a time.

`KissIcpOdometry` wraps ``kiss_icp.kiss_icp.KissICP`` with its own defaults (adaptive threshold, voxel size
``max_range / 100``, point-to-point ICP on a voxel hash map). KISS-ICP starts at the identity; ``origin`` (e.g.
the sequence's first pose) puts its trajectory in the world frame, so that ``register`` returns ``T_world_sensor``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import Field

from placerec.errors import DependencyError, ScanDataError
from placerec.params import Params
from placerec.types import Scan, as_pose, valid_points

__all__ = ["KissIcpParams", "KissIcpOdometry"]


class KissIcpParams(Params):
    """The KISS-ICP settings placerec exposes (KISS-ICP's own defaults otherwise)."""

    max_range: float = Field(100.0, gt=0, description="points farther than this are dropped (m)")
    min_range: float = Field(0.0, ge=0, description="points nearer than this are dropped (m)")
    voxel_size: float | None = Field(None, gt=0, description="map voxel (m); None: max_range / 100")
    deskew: bool = Field(False, description="motion-compensate with the points' time (needs Scan.time)")
    max_points_per_voxel: int = Field(20, ge=1)


class KissIcpOdometry:
    """Register scans in order with KISS-ICP; ``register(scan)`` returns the scan's ``T_world_sensor``."""

    def __init__(self, params: KissIcpParams | None = None, origin: np.ndarray | None = None) -> None:
        try:
            from kiss_icp.config import KISSConfig
            from kiss_icp.kiss_icp import KissICP
        except ImportError as exc:
            raise DependencyError(
                f"odometry source 'kiss-icp' needs KISS-ICP: pip install 'placerec[slam]' (or kiss-icp) ({exc})"
            ) from None
        p = self.params = params or KissIcpParams()
        cfg = KISSConfig()
        cfg.data.max_range = p.max_range
        cfg.data.min_range = p.min_range
        cfg.data.deskew = p.deskew
        cfg.mapping.voxel_size = p.voxel_size if p.voxel_size is not None else p.max_range / 100.0
        cfg.mapping.max_points_per_voxel = p.max_points_per_voxel
        self._icp: Any = KissICP(cfg)
        self.origin = np.eye(4) if origin is None else as_pose(origin)

    def register(self, scan: Scan) -> np.ndarray:
        """Register the next scan; its pose ``T_world_sensor`` (4x4). A scan without valid points keeps the
        constant-velocity prediction."""
        keep = valid_points(scan)
        xyz = np.ascontiguousarray(scan.xyz[keep], dtype=np.float64)
        if xyz.shape[0] == 0:
            raise ScanDataError(f"{scan.source or 'scan'}: no valid points for KISS-ICP")
        if self.params.deskew:
            if scan.time is None:
                raise ScanDataError(
                    f"{scan.source or 'scan'}: kiss_icp.deskew needs per-point times (Scan.time)"
                )
            t = scan.time[keep].astype(np.float64)
            span = float(t.max() - t.min())
            stamps = (t - t.min()) / span if span > 0 else np.zeros_like(t)
        else:
            stamps = np.zeros(xyz.shape[0])
        self._icp.register_frame(xyz, stamps)
        return self.origin @ self._icp.last_pose
