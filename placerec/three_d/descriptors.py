"""A registry of 3D local descriptors behind one call signature.

Every entry is ``describe(points, normals, intensity, keypoint_indices, support_radius, options)
-> (descriptors (K, D) float32, valid (K,) bool)``; rows with ``valid=False`` are all zero. ``options`` is the
descriptor's own settings model (`DESCRIPTOR_OPTIONS`; None = its defaults).

* ``"shot"``  — SHOT, 352-d (`placerec.three_d.shot`), intensity ignored; options `SHOTOptions`.
* ``"ishot"`` — ISHOT, 1344-d: SHOT + 31-bin intensity-difference signature (Guo et al. 2019); `SHOTOptions`.
* ``"fpfh"``  — FPFH, 33-d, Open3D's ``compute_fpfh_feature`` on the keypoints (geometric reference);
  options `FPFHOptions`.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

import numpy as np
from pydantic import Field

from placerec.errors import ConfigError, ScanDataError
from placerec.params import Params
from placerec.three_d._neighbors import check_points
from placerec.three_d.shot import ISHOT_DIM, SHAPE_DIM, SHOTOptions, SHOTParams, compute_shot

__all__ = [
    "DESCRIPTORS",
    "DESCRIPTOR_DIMS",
    "DESCRIPTOR_OPTIONS",
    "FPFHOptions",
    "describe",
    "get_descriptor",
]

Describer = Callable[..., tuple[np.ndarray, np.ndarray]]


class FPFHOptions(Params):
    """FPFH settings besides the support radius."""

    max_nn: int | None = Field(
        None, ge=1, description="neighbours at most (None = every point within the support, as SHOT)"
    )


def describe_shot(
    points: np.ndarray,
    normals: np.ndarray,
    intensity: np.ndarray | None,
    keypoint_indices: np.ndarray,
    support_radius: float = 7.0,
    options: SHOTOptions | None = None,
    *,
    with_intensity: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """SHOT (352-d), or with ``with_intensity`` ISHOT (1344-d), which needs ``intensity`` in [0, 1]."""
    if with_intensity and intensity is None:
        raise ScanDataError("ISHOT needs per-point intensity (calibrated, in [0, 1])")
    params = SHOTParams(support_radius=support_radius, **(options or SHOTOptions()).model_dump())
    return compute_shot(
        points, normals, keypoint_indices, params, intensity=intensity if with_intensity else None
    )


#: ISHOT (1344-d): `describe_shot` with the intensity signature
describe_ishot = partial(describe_shot, with_intensity=True)


def describe_fpfh(
    points: np.ndarray,
    normals: np.ndarray,
    intensity: np.ndarray | None,
    keypoint_indices: np.ndarray,
    support_radius: float = 7.0,
    options: FPFHOptions | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """FPFH (33-d) of the keypoints with Open3D; invalid where a keypoint has no neighbour."""
    import open3d as o3d

    max_nn = (options or FPFHOptions()).max_nn
    P = check_points(points)
    Nrm = np.asarray(normals, dtype=np.float64)
    if Nrm.shape != P.shape:
        raise ScanDataError(f"normals must have shape {P.shape}, got {Nrm.shape}")
    kp = np.asarray(keypoint_indices, dtype=np.int64).reshape(-1)
    if kp.size == 0:
        return np.zeros((0, 33), dtype=np.float32), np.zeros(0, dtype=bool)
    if kp.min() < 0 or kp.max() >= P.shape[0]:
        raise ScanDataError(f"keypoint indices out of range for {P.shape[0]} points")
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P))
    pcd.normals = o3d.utility.Vector3dVector(Nrm)
    param = (
        o3d.geometry.KDTreeSearchParamRadius(support_radius)
        if max_nn is None
        else o3d.geometry.KDTreeSearchParamHybrid(support_radius, int(max_nn))
    )
    feat = o3d.pipelines.registration.compute_fpfh_feature(pcd, param, kp.tolist())
    desc = np.asarray(feat.data, dtype=np.float32).T.copy()
    valid = np.isfinite(desc).all(axis=1) & (desc.sum(axis=1) > 0)
    desc[~valid] = 0.0
    return desc, valid


DESCRIPTORS: dict[str, Describer] = {
    "shot": describe_shot,
    "ishot": describe_ishot,
    "fpfh": describe_fpfh,
}
DESCRIPTOR_DIMS: dict[str, int] = {"shot": SHAPE_DIM, "ishot": ISHOT_DIM, "fpfh": 33}
#: the settings model of each descriptor (its ``options``)
DESCRIPTOR_OPTIONS: dict[str, type[Params]] = {"shot": SHOTOptions, "ishot": SHOTOptions, "fpfh": FPFHOptions}


def get_descriptor(name: str) -> Describer:
    """The describe function registered as ``name`` (`ConfigError` listing the names otherwise)."""
    try:
        return DESCRIPTORS[name]
    except KeyError:
        raise ConfigError(f"unknown 3D descriptor {name!r}; allowed: {sorted(DESCRIPTORS)}") from None


def describe(
    name: str,
    points: np.ndarray,
    normals: np.ndarray,
    intensity: np.ndarray | None,
    keypoint_indices: np.ndarray,
    support_radius: float = 7.0,
    options: Params | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Describe the keypoints with the registered descriptor ``name``: ``(descriptors, valid)``.

    ``options``: an instance of ``DESCRIPTOR_OPTIONS[name]`` (None = its defaults), else `ConfigError`.
    """
    fn = get_descriptor(name)
    model = DESCRIPTOR_OPTIONS[name]
    if options is not None and not isinstance(options, model):
        raise ConfigError(
            f"3D descriptor {name!r} takes {model.__name__} options, got {type(options).__name__}"
        )
    return fn(points, normals, intensity, keypoint_indices, support_radius, options)
