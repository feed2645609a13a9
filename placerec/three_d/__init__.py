"""The 3D modality's local features: normals, ISS-BR keypoints, SHOT LRFs, SHOT/ISHOT/FPFH descriptors.

* `normals.estimate_normals` — Open3D PCA normals oriented towards the sensor.
* `keypoints.detect_iss` — ISS keypoints with boundary removal (PCL ``ISSKeypoint3D`` semantics).
* `lrf.shot_lrf` — SHOT local reference frames.
* `shot.compute_shot` — SHOT (352) and ISHOT (1344) descriptors.
* `descriptors.describe` — registry ``"shot" | "ishot" | "fpfh"`` behind one signature, each with its
  settings model (`SHOTOptions`, `FPFHOptions`).
* `features.extract_features` — a scan to described keypoints with the ISHOT paper's settings.

All of it is vectorised over (keypoint, neighbour) pairs; importing this package loads Open3D lazily.
"""

from __future__ import annotations

from placerec.three_d.descriptors import (
    DESCRIPTOR_DIMS,
    DESCRIPTOR_OPTIONS,
    DESCRIPTORS,
    FPFHOptions,
    describe,
    get_descriptor,
)
from placerec.three_d.features import FeatureParams, LocalFeatures, extract_features, prepare_cloud
from placerec.three_d.keypoints import ISSParams, ISSResult, boundary_points, detect_iss, iss_saliency
from placerec.three_d.lrf import shot_lrf
from placerec.three_d.normals import NormalParams, estimate_normals
from placerec.three_d.shot import ISHOT_DIM, SHAPE_DIM, SHOTOptions, SHOTParams, compute_shot

__all__ = [
    "DESCRIPTOR_DIMS",
    "DESCRIPTOR_OPTIONS",
    "DESCRIPTORS",
    "FPFHOptions",
    "describe",
    "get_descriptor",
    "FeatureParams",
    "LocalFeatures",
    "extract_features",
    "prepare_cloud",
    "ISSParams",
    "ISSResult",
    "boundary_points",
    "detect_iss",
    "iss_saliency",
    "shot_lrf",
    "NormalParams",
    "estimate_normals",
    "ISHOT_DIM",
    "SHAPE_DIM",
    "SHOTOptions",
    "SHOTParams",
    "compute_shot",
]
