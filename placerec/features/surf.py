"""SURF (Bay, Tuytelaars, Van Gool: ECCV 2006 / CVIU 2008) in NumPy, for OpenCV builds without the patented one.

Keypoint conventions follow OpenCV's SURF so that keypoints travel between detectors:

* ``KeyPoint.size`` is the (interpolated) box-filter side ``L`` in pixels; the SURF scale is ``s = 1.2 L / 9``.
  Keypoints of other detectors are described at the scale their size gives: FAST's ``size = 7`` means
  ``s = 0.93`` (Haar side 4 for the orientation, 2 for the descriptor, a 19 px window); scales below
  ``MIN_SCALE`` are raised to it.
* ``KeyPoint.angle`` is the dominant orientation in degrees in [0, 360), measured in image coordinates
  (x right, y down, so clockwise on screen) as ``atan2(sum dy, sum dx)``; U-SURF (``upright=True``) sets 0.
* ``response`` is det(H) of the area-normalised box filters on 0..255 intensities, ``octave`` the 0-based octave,
  ``class_id`` the sign of the Laplacian (trace of H), +1 or -1.

Float images are used as they are (no rescaling), so ``hessian_threshold`` assumes a 0..255 range.
"""

from __future__ import annotations

import logging
from typing import Any

import cv2
import numpy as np
from pydantic import Field

from placerec.errors import ConfigError, ScanDataError
from placerec.features.surf_describe import (
    PaddedIntegral,
    descriptor_extent,
    dominant_orientation,
    surf_descriptors,
)
from placerec.features.surf_detect import Detections, detect_keypoints, integral_image
from placerec.params import Params, resolve

__all__ = ["SURF", "SURFParams", "MIN_SCALE", "as_gray"]

log = logging.getLogger(__name__)

MIN_SCALE = 0.8  # smallest SURF scale s used for description (a 2 px Haar wavelet, a 16 px window)


def as_gray(image: np.ndarray) -> np.ndarray:
    """A 2D uint8 or float64 view/copy of ``image`` (3-channel BGR images are converted to gray)."""
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] in (3, 4):
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim != 2 or img.size == 0:
        raise ScanDataError(f"SURF expects a non-empty 2D grayscale image, got shape {img.shape}")
    if img.dtype == np.uint8:
        return np.ascontiguousarray(img)
    if not np.issubdtype(img.dtype, np.number) or np.issubdtype(img.dtype, np.complexfloating):
        raise ScanDataError(f"SURF expects a real-valued image, got dtype {img.dtype}")
    out = np.ascontiguousarray(img, dtype=np.float64)
    if not np.isfinite(out).all():
        raise ScanDataError("SURF image contains NaN or infinite values")
    return out


class SURFParams(Params):
    """SURF's own settings (OpenCV's parameters; defaults: VPR paper Table I)."""

    hessian_threshold: float = Field(
        400.0, ge=0, allow_inf_nan=False, description="det(H) threshold on 0..255 images (VPR paper Table I)"
    )
    n_octaves: int = Field(4, ge=1, description="VPR paper Table I")
    n_octave_layers: int = Field(3, ge=1, description="layers per octave (VPR paper Table I)")
    extended: bool = Field(False, description="128-d instead of 64-d descriptors")
    upright: bool = Field(False, description="no orientation (U-SURF)")


class SURF:
    """SURF detector and descriptor with OpenCV's parameters (`SURFParams`, a model and/or keyword overrides).

    >>> kps, desc = SURF().detect_and_compute(img)   # desc: float32 (K, 64), unit rows
    """

    def __init__(self, params: SURFParams | None = None, **overrides: Any) -> None:
        if params is not None and not isinstance(params, SURFParams):
            raise ConfigError(f"surf: params must be a SURFParams, got {type(params).__name__}")
        base = None if params is None else params.model_dump(include=set(SURFParams.model_fields))
        p = resolve(SURFParams, base, overrides, where="surf") if overrides else params or SURFParams()
        self.hessian_threshold = p.hessian_threshold
        self.n_octaves = p.n_octaves
        self.n_octave_layers = p.n_octave_layers
        self.extended = p.extended
        self.upright = p.upright

    @property
    def descriptor_size(self) -> int:
        return 128 if self.extended else 64

    def __repr__(self) -> str:
        return (
            f"SURF(hessian_threshold={self.hessian_threshold}, n_octaves={self.n_octaves}, "
            f"n_octave_layers={self.n_octave_layers}, extended={self.extended}, upright={self.upright})"
        )

    # ------------------------------------------------------------------ array API (no cv2.KeyPoint objects)
    def detect_arrays(self, image: np.ndarray, mask: np.ndarray | None = None) -> Detections:
        """Detect keypoints and return them as arrays (see :class:`Detections`)."""
        img = as_gray(image)
        det = detect_keypoints(
            img, self.hessian_threshold, self.n_octaves, self.n_octave_layers, integral=integral_image(img)
        )
        if mask is not None and len(det):
            keep = _mask_keep(mask, img.shape, det.xy)
            det = Detections(
                det.xy[keep], det.size[keep], det.response[keep], det.octave[keep], det.laplacian[keep]
            )
        return det

    def describe_arrays(
        self, image: np.ndarray, xy: np.ndarray, size: np.ndarray, angle_deg: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Descriptors at given positions/sizes; returns ``(angle_deg, descriptors)``.

        ``angle_deg`` entries < 0 (or ``None``) are computed (dominant orientation); upright mode uses 0.
        """
        img = as_gray(image)
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        size_arr = np.asarray(size, np.float64).reshape(-1)
        scale = np.maximum(1.2 * size_arr / 9.0, MIN_SCALE)
        n = len(scale)
        if n != len(xy):
            raise ScanDataError(f"SURF got {len(xy)} keypoint positions but {n} sizes")
        if n == 0:
            return np.zeros(0, np.float32), np.zeros((0, self.descriptor_size), np.float32)
        h, w = img.shape
        outside = ~(
            (xy[:, 0] >= -0.5) & (xy[:, 0] <= w - 0.5) & (xy[:, 1] >= -0.5) & (xy[:, 1] <= h - 0.5)
        ) | ~np.isfinite(scale)
        if outside.any():
            i = int(np.argmax(outside))
            raise ScanDataError(
                f"SURF keypoint {i} at {tuple(xy[i])} (size {size_arr[i]}) is not inside the {w}x{h} image"
            )
        pad = int(descriptor_extent(scale.max()))
        ii = PaddedIntegral(img, pad)
        if self.upright:
            theta = np.zeros(n)
        else:
            given = np.full(n, -1.0) if angle_deg is None else np.asarray(angle_deg, np.float64).reshape(-1)
            theta = np.deg2rad(np.mod(given, 360.0))
            todo = given < 0
            if todo.any():
                theta[todo] = dominant_orientation(ii, xy[todo], scale[todo])
        desc = surf_descriptors(ii, xy, scale, theta, self.extended)
        angle = np.mod(np.rad2deg(theta), 360.0)
        angle[angle >= 360.0] = 0.0
        return angle.astype(np.float32), desc

    # ------------------------------------------------------------------ OpenCV-like API
    def detect(self, image: np.ndarray, mask: np.ndarray | None = None) -> list[cv2.KeyPoint]:
        """Keypoints (``angle`` = -1: orientation is assigned by :meth:`compute`)."""
        det = self.detect_arrays(image, mask)
        return _to_keypoints(det, np.full(len(det), -1.0))

    def compute(
        self, image: np.ndarray, keypoints: list[cv2.KeyPoint] | tuple[cv2.KeyPoint, ...]
    ) -> tuple[list[cv2.KeyPoint], np.ndarray]:
        """Describe ``keypoints`` (from any detector); returns new keypoints with ``angle`` set and float32 (K, D)."""
        kps = list(keypoints)
        xy = np.array([kp.pt for kp in kps], np.float64).reshape(-1, 2)
        size = np.array([kp.size for kp in kps], np.float64)
        ang_in = np.array([kp.angle for kp in kps], np.float64)
        angle, desc = self.describe_arrays(image, xy, size, ang_in)
        out = [
            cv2.KeyPoint(
                float(kp.pt[0]),
                float(kp.pt[1]),
                float(kp.size),
                float(a),
                float(kp.response),
                int(kp.octave),
                int(kp.class_id),
            )
            for kp, a in zip(kps, angle, strict=True)
        ]
        return out, desc

    def detect_and_compute(
        self, image: np.ndarray, mask: np.ndarray | None = None
    ) -> tuple[list[cv2.KeyPoint], np.ndarray]:
        """Detect and describe in one call (the image is validated once)."""
        img = as_gray(image)
        det = self.detect_arrays(img, mask)
        angle, desc = self.describe_arrays(img, det.xy, det.size)
        return _to_keypoints(det, angle), desc

    # OpenCV spelling, so SURF can stand where a cv2.Feature2D is used
    detectAndCompute = detect_and_compute  # noqa: N815


def _mask_keep(mask: np.ndarray, shape: tuple[int, ...], xy: np.ndarray) -> np.ndarray:
    m = np.asarray(mask)
    if m.shape != tuple(shape[:2]):
        raise ScanDataError(f"mask shape {m.shape} differs from the image shape {tuple(shape[:2])}")
    col = np.clip(np.rint(xy[:, 0]).astype(np.intp), 0, shape[1] - 1)
    row = np.clip(np.rint(xy[:, 1]).astype(np.intp), 0, shape[0] - 1)
    return m[row, col] != 0


def _to_keypoints(det: Detections, angle: np.ndarray) -> list[cv2.KeyPoint]:
    return [
        cv2.KeyPoint(float(x), float(y), float(sz), float(a), float(r), int(o), int(c))
        for (x, y), sz, a, r, o, c in zip(
            det.xy, det.size, angle, det.response, det.octave, det.laplacian, strict=True
        )
    ]
