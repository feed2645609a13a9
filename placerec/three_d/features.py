"""From a scan to described keypoints: crop, voxelise, normals, ISS-BR, descriptor (ISHOT paper, Sec. V-B).

``extract_features(scan)`` runs the paper's chain with its settings: drop points beyond 40 m, voxel grid
0.4 m with the intensity averaged per voxel (`placerec.preprocess.voxel_downsample`), normals
(`normals.estimate_normals`), ISS-BR keypoints (salient radius 2.4 m), ISHOT with a 7 m support. The scan's
intensity must already be calibrated to [0, 1] (`placerec.intensity.normalize_intensity`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import Field

from placerec.errors import ScanDataError
from placerec.params import Params
from placerec.preprocess import crop, remove_invalid, voxel_downsample
from placerec.three_d.descriptors import FPFHOptions, describe
from placerec.three_d.keypoints import ISSParams, detect_iss
from placerec.three_d.normals import NormalParams, estimate_normals
from placerec.three_d.shot import SHOTOptions
from placerec.types import Scan

log = logging.getLogger(__name__)

__all__ = ["FeatureParams", "LocalFeatures", "extract_features", "prepare_cloud"]


class FeatureParams(Params):
    """The 3D modality's feature settings (defaults: ISHOT paper Sec. V-B; ``max_keypoints`` ~ its 296 per scan)."""

    max_range: float | None = Field(
        40.0, gt=0, description="m; points beyond are dropped (ISHOT paper Sec. V-B)"
    )
    voxel_size: float = Field(0.4, gt=0, description="m; voxel grid (ISHOT paper Sec. V-B)")
    normals: NormalParams = Field(default_factory=NormalParams)
    iss: ISSParams = Field(default_factory=lambda: ISSParams(max_keypoints=300))
    descriptor: Literal["ishot", "shot", "fpfh"] = Field("ishot", description="ISHOT paper Sec. III")
    support_radius: float = Field(7.0, gt=0, description="m; descriptor support (ISHOT paper Sec. V-B)")
    shot: SHOTOptions = Field(default_factory=SHOTOptions)
    fpfh: FPFHOptions = Field(default_factory=FPFHOptions)

    def descriptor_options(self) -> SHOTOptions | FPFHOptions:
        """The settings of the chosen descriptor: ``shot`` for SHOT and ISHOT, ``fpfh`` for FPFH."""
        return self.fpfh if self.descriptor == "fpfh" else self.shot


@dataclass(frozen=True)
class LocalFeatures:
    """Described keypoints of one scan; only keypoints with a valid descriptor are kept.

    ``points``/``normals``/``intensity`` are the voxelised cloud, ``keypoint_indices`` index into it,
    ``keypoints`` (K, 3) and ``saliency`` (K,) belong to the kept keypoints, ``descriptors`` is (K, D) float32.
    """

    points: np.ndarray
    normals: np.ndarray
    intensity: np.ndarray
    keypoint_indices: np.ndarray
    keypoints: np.ndarray
    saliency: np.ndarray
    descriptors: np.ndarray
    descriptor: str

    def __len__(self) -> int:
        return int(self.keypoint_indices.shape[0])


def prepare_cloud(scan: Scan, params: FeatureParams) -> Scan:
    """Invalid-point removal, range crop and voxel downsampling (averaged intensity)."""
    scan, _ = remove_invalid(scan)
    if params.max_range is not None:
        scan = crop(scan, max_range=params.max_range)
    return voxel_downsample(scan, params.voxel_size)


def extract_features(scan: Scan, params: FeatureParams | None = None) -> LocalFeatures:
    """Keypoints and descriptors of ``scan``; `ScanDataError` if too few points survive preprocessing."""
    params = params or FeatureParams()
    cloud = prepare_cloud(scan, params)
    n = len(cloud)
    if n < params.iss.min_neighbors:
        raise ScanDataError(
            f"{scan.source or 'scan'}: only {n} points left after cropping to {params.max_range} m and "
            f"voxelising at {params.voxel_size} m; ISS needs at least {params.iss.min_neighbors}"
        )
    points = cloud.xyz.astype(np.float64)
    normals = estimate_normals(points, params.normals)
    iss = detect_iss(points, normals, params.iss)
    desc, valid = describe(
        params.descriptor,
        points,
        normals,
        cloud.intensity,
        iss.indices,
        params.support_radius,
        params.descriptor_options(),
    )
    kp = iss.indices[valid]
    return LocalFeatures(
        points=cloud.xyz,
        normals=normals,
        intensity=cloud.intensity,
        keypoint_indices=kp,
        keypoints=cloud.xyz[kp],
        saliency=iss.saliency[valid],
        descriptors=desc[valid],
        descriptor=params.descriptor,
    )
