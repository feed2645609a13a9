"""Saved visual databases: the per-image features of the visual pipelines as arrays, their schema, and the
checked descriptions read back (`placerec.pipelines.visual.VisualHBST`, `placerec.pipelines.dbow.VisualDBoW`)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from placerec.errors import ArtifactError
from placerec.image import ImageParams
from placerec.io.artifact_schema import Member, check_counts, check_unique
from placerec.types import Description

if TYPE_CHECKING:
    from placerec.pipelines.visual import VisualFrontend

__all__ = ["MAX_IMAGE_WIDTH", "features_schema", "pack_features", "stored_features"]

#: Widest intensity image (px) a visual front end makes and a saved database may record (LiDARs have at most a
#: few thousand columns); a wider one is a `ScanDataError` when described, an `ArtifactError` when loaded.
MAX_IMAGE_WIDTH = 1 << 15


def pack_features(
    rec: VisualFrontend, order: list[int], descriptors: Mapping[int, np.ndarray], dim: int, dtype: type
) -> dict[str, np.ndarray]:
    """The arrays of a visual database ``rec``: per-image counts and widths, stacked keypoints, their 3D points
    and descriptors; with verification the ICP clouds (`placerec.verify.candidates.CloudStore.arrays`)."""
    kp = rec._keypoints
    arrays = {
        "ids": np.asarray(order, dtype=np.int64),
        "counts": np.array([kp[i].shape[0] for i in order], dtype=np.int64),
        "widths": np.array([rec._width[i] for i in order], dtype=np.int64),
        "keypoints": _stack([kp[i] for i in order], (0, 2), np.float32),
        # a keypoint without a 3D point is stored at the origin (never a scan point), NaN again when loaded
        "keypoint_xyz": np.nan_to_num(_stack([rec._kp_xyz[i] for i in order], (0, 3), np.float32), nan=0.0),
        "descriptors": _stack([descriptors[i] for i in order], (0, dim), dtype),
    }
    if rec.params.verify.enabled:
        arrays.update(rec._clouds.arrays(order))
    return arrays


def features_schema(dim: int, binary: bool, clouds: bool) -> dict[str, Member]:
    """The arrays of a saved visual database (`pack_features`) with ``dim``-wide binary or float descriptors,
    with ICP clouds when ``clouds``."""
    schema = {
        "ids": Member("iu", ("n_images",)),
        "counts": Member("iu", ("n_images",), min_value=0),
        "widths": Member("iu", ("n_images",), min_value=1),
        "keypoints": Member("f", ("n_features", 2), finite=True),
        "keypoint_xyz": Member("f", ("n_features", 3), finite=True),
        "descriptors": Member("u" if binary else "f", ("n_features", dim), finite=True),
    }
    if clouds:
        schema["cloud_counts"] = Member("iu", ("n_images",), min_value=0)
        schema["cloud_xyz"] = Member("f", ("n_points", 3), finite=True)
    return schema


def stored_features(
    path: str | Path, arrays: Mapping[str, np.ndarray], image: ImageParams
) -> list[tuple[int, Description]]:
    """(id, description) of every image of a saved visual database whose arrays passed `features_schema`, after
    checking that ids are unique, counts add up, widths are ``image.width`` (when set; else at most
    `MAX_IMAGE_WIDTH`) and keypoints lie in their images (`ArtifactError` otherwise)."""
    ids, counts, widths, kp = arrays["ids"], arrays["counts"], arrays["widths"], arrays["keypoints"]
    check_unique(ids, path, "ids")
    check_counts(counts, kp.shape[0], path, "counts")
    bad = widths != image.width if image.width is not None else widths > MAX_IMAGE_WIDTH
    if bad.any():
        expected = f"{image.width} (image.width)" if image.width is not None else f"at most {MAX_IMAGE_WIDTH}"
        raise ArtifactError(f"{path}: 'widths' holds {int(widths[bad][0])} px; expected {expected}")
    u = kp[:, 0]  # sub-pixel positions may reach half a pixel past the border
    if ((u < -1) | (u > np.repeat(widths, counts))).any():
        raise ArtifactError(f"{path}: 'keypoints' lie outside their images ('widths')")
    offsets = np.r_[0, np.cumsum(counts)]
    desc, xyz = arrays["descriptors"], arrays["keypoint_xyz"].astype(np.float32)
    xyz[~xyz.any(axis=1)] = np.nan  # the origin: no scan point behind the keypoint (`pack_features`)
    out: list[tuple[int, Description]] = [
        (
            int(i),
            {
                "keypoints": kp[a:b],
                "descriptors": desc[a:b],
                "width": np.array(w, np.int64),
                "keypoint_xyz": xyz[a:b],
            },
        )
        for i, a, b, w in zip(ids, offsets[:-1], offsets[1:], widths, strict=True)
    ]
    if "cloud_counts" in arrays:
        check_counts(arrays["cloud_counts"], arrays["cloud_xyz"].shape[0], path, "cloud_counts")
        bounds = np.r_[0, np.cumsum(arrays["cloud_counts"])]
        for (_, d), a, b in zip(out, bounds[:-1], bounds[1:], strict=True):
            d["cloud"] = arrays["cloud_xyz"][a:b]
    return out


def _stack(parts: list[np.ndarray], empty_shape: tuple[int, int], dtype: type) -> np.ndarray:
    return np.concatenate(parts).astype(dtype, copy=False) if parts else np.zeros(empty_shape, dtype)
