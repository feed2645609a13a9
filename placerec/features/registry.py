"""Registry of 2D feature extractors with the VPR paper's Table I defaults.

==============  ===========================================================================  ===============
name            keypoints -> descriptors                                                     descriptor
==============  ===========================================================================  ===============
``orb``         ``cv2.ORB`` (its own FAST, ``fast_threshold`` 40, Harris ranking), pyramid    binary, 32 bytes
                ``scale_factor`` 1.2, ``n_levels`` 8, ``edge_threshold`` 15
``brisk``       FAST (threshold 40) -> BRISK (``threshold`` 30, ``octaves`` 3,                binary, 64 bytes
                ``pattern_scale`` 1; threshold/octaves only matter with ``detector="brisk"``)
``fast-surf``   FAST (threshold 40) -> our SURF descriptor at the FAST size (7 px: s = 0.93)  float, 64 (128)
``surf``        our SURF detector (``hessian_threshold`` 400, ``n_octaves`` 4,                float, 64 (128)
                ``n_octave_layers`` 3) -> SURF descriptor
==============  ===========================================================================  ===============

ORB is run the usual way, with the FAST detector inside ``cv2.ORB`` (``fastThreshold=40``), which is how the
paper's "FAST keypoints for ORB" is obtained with OpenCV. Every extractor keeps at most ``nfeatures`` (300)
features, the strongest by detector response, ordered by decreasing response.

Azimuth wrap-around: intensity images are 360 degree panoramas, so with ``wrap_pad`` (default on) the image is
padded left and right with ``pad`` columns copied from the opposite side; keypoints are only taken in the original
columns (the padding is masked out), so a keypoint at the seam has its full patch, and ``u`` is shifted back.
Keep ``pad`` a multiple of 8 so SURF's sampling grid stays aligned with the image columns.

Low images: an image with fewer than 64 rows (16- and 32-beam sensors) has its rows interpolated linearly
(``row_upsample``; default: the smallest integer factor reaching 128 rows) before extraction, and ``v`` is
mapped back to its rows; an image that gives fewer than 20 features is reported once per extractor
(`placerec.features.low_rows`).
"""

from __future__ import annotations

from typing import Any, Literal, TypeVar

import numpy as np
from pydantic import Field

from placerec.errors import ConfigError
from placerec.features import compat
from placerec.features.base import ExtractorParams, FeatureExtractor, Features, _Keypoints
from placerec.features.superpoint.extractor import SuperPointExtractor, SuperPointParams
from placerec.features.surf import SURF, SURFParams

__all__ = [
    "Features",
    "ExtractorParams",
    "OrbParams",
    "BriskParams",
    "FastSurfParams",
    "SurfParams",
    "FeatureExtractor",
    "OrbExtractor",
    "BriskExtractor",
    "FastSurfExtractor",
    "SurfExtractor",
    "SuperPointExtractor",
    "SuperPointParams",
    "EXTRACTORS",
    "available_extractors",
    "make_extractor",
    "extractor_params",
]


class OrbParams(ExtractorParams):
    """ORB (VPR paper Table I; the other values are OpenCV's defaults)."""

    fast_threshold: int = Field(40, gt=0, description="FAST threshold inside cv2.ORB (VPR paper Table I)")
    scale_factor: float = Field(1.2, gt=1, description="pyramid scale (VPR paper Table I)")
    n_levels: int = Field(8, gt=0, description="pyramid levels (VPR paper Table I)")
    edge_threshold: int = Field(15, ge=0, description="px border without keypoints (VPR paper Table I)")
    first_level: int = Field(0, ge=0, description="OpenCV default")
    wta_k: Literal[2, 3, 4] = Field(2, description="points per BRIEF comparison (OpenCV default)")
    score_type: Literal["harris", "fast"] = Field("harris", description="keypoint ranking (OpenCV default)")
    patch_size: int = Field(31, gt=0, description="px (OpenCV default)")


class BriskParams(ExtractorParams):
    """FAST keypoints described by BRISK (VPR paper Table I)."""

    fast_threshold: int = Field(40, gt=0, description="FAST threshold (VPR paper Table I)")
    threshold: int = Field(30, gt=0, description="BRISK AGAST threshold, detector=brisk only (Table I)")
    octaves: int = Field(3, ge=0, description="BRISK octaves, detector=brisk only (VPR paper Table I)")
    pattern_scale: float = Field(1.0, gt=0, description="BRISK sampling pattern scale (VPR paper Table I)")
    detector: Literal["fast", "brisk"] = Field("fast", description="fast: Table I; brisk: BRISK's own AGAST")


def _surf_field(name: str) -> Any:
    """The field of `SURFParams` called ``name`` (its default, constraints and description)."""
    return SURFParams.model_fields[name]


class FastSurfParams(ExtractorParams):
    """FAST keypoints described by our SURF (VPR paper Table I)."""

    fast_threshold: int = Field(40, gt=0, description="FAST threshold (VPR paper Table I)")
    extended: bool = _surf_field("extended")
    upright: bool = _surf_field("upright")


class SurfParams(SURFParams, ExtractorParams):
    """Our SURF detector and descriptor (`placerec.features.surf.SURFParams`; VPR paper Table I)."""


class OrbExtractor(FeatureExtractor[OrbParams]):
    """ORB (oriented FAST + rotated BRIEF) as in the VPR paper's Table I."""

    name = "orb"
    descriptor_kind = "binary"
    Params = OrbParams

    def _setup(self) -> None:
        p = self.params
        self._orb = compat.orb_create(
            p.nfeatures,
            p.scale_factor,
            p.n_levels,
            p.edge_threshold,
            p.first_level,
            p.wta_k,
            p.score_type,
            p.patch_size,
            p.fast_threshold,
        )

    @property
    def descriptor_size(self) -> int:
        return 32

    def _run(self, image: np.ndarray, mask: np.ndarray) -> tuple[_Keypoints, np.ndarray]:
        kps, desc = self._orb.detectAndCompute(image, mask)
        return _Keypoints.from_cv(kps), (np.zeros((0, 32), np.uint8) if desc is None else desc)


class BriskExtractor(FeatureExtractor[BriskParams]):
    """FAST keypoints described by BRISK (Table I); ``detector="brisk"`` uses BRISK's own AGAST detector."""

    name = "brisk"
    descriptor_kind = "binary"
    Params = BriskParams

    def _setup(self) -> None:
        p = self.params
        self._brisk = compat.brisk_create(p.threshold, p.octaves, p.pattern_scale)
        self._fast = compat.fast_create(p.fast_threshold)

    @property
    def descriptor_size(self) -> int:
        return 64

    def _run(self, image: np.ndarray, mask: np.ndarray) -> tuple[_Keypoints, np.ndarray]:
        n = self.params.nfeatures
        if self.params.detector == "fast":
            kps = self._fast_keypoints(image, mask, 2 * n)  # slack: BRISK drops points near the top/bottom
        else:
            kps = list(self._brisk.detect(image, mask))
        if not kps:
            return _Keypoints.from_cv([]), np.zeros((0, 64), np.uint8)
        kps, desc = self._brisk.compute(image, kps)
        return _Keypoints.from_cv(kps), (np.zeros((0, 64), np.uint8) if desc is None else desc)


#: the parameters of an extractor with the SURF descriptor
SP = TypeVar("SP", FastSurfParams, SurfParams)


class _SurfDescribed(FeatureExtractor[SP]):
    descriptor_kind = "float"

    @property
    def descriptor_size(self) -> int:
        return 128 if self.params.extended else 64


class FastSurfExtractor(_SurfDescribed[FastSurfParams]):
    """FAST keypoints (Table I threshold 40) described by our SURF at the FAST keypoint size (7 px)."""

    name = "fast-surf"
    Params = FastSurfParams

    def _setup(self) -> None:
        self._fast = compat.fast_create(self.params.fast_threshold)
        self._surf = SURF(extended=self.params.extended, upright=self.params.upright)  # describing only

    def _run(self, image: np.ndarray, mask: np.ndarray) -> tuple[_Keypoints, np.ndarray]:
        kps = _Keypoints.from_cv(self._fast_keypoints(image, mask, self.params.nfeatures))
        kps.angle, desc = self._surf.describe_arrays(image, kps.xy, kps.size)
        return kps, desc


class SurfExtractor(_SurfDescribed[SurfParams]):
    """Our SURF detector and descriptor (Table I: hessian threshold 400, 4 octaves, 3 layers per octave)."""

    name = "surf"
    Params = SurfParams

    def _setup(self) -> None:
        self._surf = SURF(self.params)

    def _run(self, image: np.ndarray, mask: np.ndarray) -> tuple[_Keypoints, np.ndarray]:
        det = self._surf.detect_arrays(image, mask)
        order = np.lexsort((det.xy[:, 0], det.xy[:, 1], -det.response.astype(np.float64)))[
            : self.params.nfeatures
        ]
        kps = _Keypoints(
            det.xy[order].astype(np.float64),
            det.size[order],
            np.zeros(len(order), np.float32),
            det.response[order],
            det.octave[order],
        )
        kps.angle, desc = self._surf.describe_arrays(image, kps.xy, kps.size)
        return kps, desc


EXTRACTORS: dict[str, type[FeatureExtractor]] = {
    cls.name: cls
    for cls in (OrbExtractor, BriskExtractor, FastSurfExtractor, SurfExtractor, SuperPointExtractor)
}


def available_extractors() -> list[str]:
    """Registered extractor names."""
    return sorted(EXTRACTORS)


def _extractor_class(name: str) -> type[FeatureExtractor]:
    cls = EXTRACTORS.get(str(name).lower())
    if cls is None:
        raise ConfigError(f"features: unknown extractor {name!r}; allowed: {available_extractors()}")
    return cls


def extractor_params(name: str) -> type[ExtractorParams]:
    """The parameter model of the extractor registered as ``name`` (`ConfigError` for an unknown name)."""
    return _extractor_class(name).Params


def make_extractor(name: str, params: ExtractorParams | None = None, **overrides: Any) -> FeatureExtractor:
    """The extractor registered as ``name`` with Table I defaults (or ``params``) overridden by ``overrides``.

    Raises `ConfigError` for an unknown name (listing the allowed ones) or an unknown/invalid parameter.
    """
    return _extractor_class(name)(params, **overrides)
