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

import logging
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import cv2
import numpy as np
from pydantic import Field

from placerec.errors import ConfigError, ScanDataError
from placerec.features import compat
from placerec.features.low_rows import row_factor, rows_back, upsample_rows, warn_few_features
from placerec.features.surf import SURF, SURFParams
from placerec.params import Params, resolve

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
    "EXTRACTORS",
    "available_extractors",
    "make_extractor",
    "extractor_params",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Features:
    """Keypoints and descriptors of one image as plain arrays (cacheable with ``np.savez``).

    ``keypoints`` (K, 2) float32 ``(u, v)`` pixel coordinates (column, row; pixel centres are integers);
    ``size`` (K,) float32 keypoint diameter in OpenCV's convention; ``angle`` (K,) float32 degrees in [0, 360),
    -1 where the descriptor has no orientation; ``response`` (K,) float32 detector score; ``octave`` (K,) int32;
    ``descriptors`` (K, bytes) uint8 for binary descriptors or (K, dim) float32.
    """

    keypoints: np.ndarray
    size: np.ndarray
    angle: np.ndarray
    response: np.ndarray
    octave: np.ndarray
    descriptors: np.ndarray

    def __post_init__(self) -> None:
        kp = np.ascontiguousarray(self.keypoints, np.float32).reshape(-1, 2)
        n = kp.shape[0]
        object.__setattr__(self, "keypoints", kp)
        for name, dtype in (
            ("size", np.float32),
            ("angle", np.float32),
            ("response", np.float32),
            ("octave", np.int32),
        ):
            arr = np.ascontiguousarray(getattr(self, name), dtype).reshape(-1)
            if arr.shape[0] != n:
                raise ScanDataError(f"Features.{name} has {arr.shape[0]} entries for {n} keypoints")
            object.__setattr__(self, name, arr)
        desc = np.asarray(self.descriptors)
        if desc.ndim != 2 or desc.shape[0] != n or desc.dtype not in (np.uint8, np.float32):
            raise ScanDataError(
                f"Features.descriptors must be (K={n}, D) uint8 or float32, got {desc.shape} {desc.dtype}"
            )
        object.__setattr__(self, "descriptors", np.ascontiguousarray(desc))

    def __len__(self) -> int:
        return int(self.keypoints.shape[0])

    @property
    def uv(self) -> np.ndarray:
        """Alias of ``keypoints``."""
        return self.keypoints

    def select(self, index: np.ndarray | slice) -> Features:
        """The features at ``index`` (mask, indices or slice)."""
        return Features(*(getattr(self, f)[index] for f in _FIELDS))

    def to_arrays(self, prefix: str = "") -> dict[str, np.ndarray]:
        """``{prefix + field: array}`` for ``np.savez``; inverse of :meth:`from_arrays`."""
        return {prefix + f: getattr(self, f) for f in _FIELDS}

    @classmethod
    def from_arrays(cls, arrays: Any, prefix: str = "") -> Features:
        try:
            return cls(*(np.asarray(arrays[prefix + f]) for f in _FIELDS))
        except KeyError as exc:
            raise ScanDataError(f"feature arrays lack {exc.args[0]!r}") from None

    def to_cv_keypoints(self) -> list[cv2.KeyPoint]:
        """``cv2.KeyPoint`` objects (for drawing or OpenCV matchers)."""
        return [
            cv2.KeyPoint(float(u), float(v), float(s), float(a), float(r), int(o))
            for (u, v), s, a, r, o in zip(
                self.keypoints, self.size, self.angle, self.response, self.octave, strict=True
            )
        ]


_FIELDS = ("keypoints", "size", "angle", "response", "octave", "descriptors")


@dataclass
class _Keypoints:
    """Keypoint arrays while an extractor runs (float64 positions in the padded image)."""

    xy: np.ndarray
    size: np.ndarray
    angle: np.ndarray
    response: np.ndarray
    octave: np.ndarray

    @classmethod
    def from_cv(cls, kps: list[cv2.KeyPoint] | tuple[cv2.KeyPoint, ...]) -> _Keypoints:
        n = len(kps)
        xy = cv2.KeyPoint_convert(kps).astype(np.float64).reshape(-1, 2) if n else np.zeros((0, 2))

        def attr(name: str, dtype: type) -> np.ndarray:
            return np.fromiter((getattr(k, name) for k in kps), dtype, count=n)

        return cls(
            xy,
            attr("size", np.float32),
            attr("angle", np.float32),
            attr("response", np.float32),
            attr("octave", np.int32),
        )

    def select(self, index: np.ndarray) -> _Keypoints:
        return _Keypoints(
            self.xy[index], self.size[index], self.angle[index], self.response[index], self.octave[index]
        )


class ExtractorParams(Params):
    """Settings of every extractor (VPR paper Table I: at most 300 features per image)."""

    nfeatures: int = Field(300, gt=0, description="features kept, strongest first (VPR paper Table I)")
    wrap_pad: bool = Field(True, description="pad the 360 degree panorama with the opposite side's columns")
    pad: int = Field(64, ge=0, description="px of wrap-around padding (a multiple of 8 keeps SURF aligned)")
    row_upsample: int | None = Field(
        None,
        ge=1,
        description="row upsampling before extraction (1 = off; None = images < 64 rows to >= 128)",
    )


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


class FastSurfParams(ExtractorParams):
    """FAST keypoints described by our SURF (VPR paper Table I)."""

    fast_threshold: int = Field(40, gt=0, description="FAST threshold (VPR paper Table I)")
    extended: bool = SURFParams.model_fields["extended"]
    upright: bool = SURFParams.model_fields["upright"]


class SurfParams(SURFParams, ExtractorParams):
    """Our SURF detector and descriptor (`placerec.features.surf.SURFParams`; VPR paper Table I)."""


class FeatureExtractor:
    """Base class of the registered extractors.

    A subclass sets ``name``, ``descriptor_kind`` and ``Params`` (an `ExtractorParams` subclass with its Table I
    defaults) and implements ``_run(image, mask) -> (_Keypoints, descriptors)`` on the (padded) image, keeping
    keypoints only where ``mask`` is non-zero and at most ``self.params.nfeatures`` of them (ideally after any
    it drops). The base class validates inputs, pads for the azimuth wrap-around, caps and orders.
    """

    name: ClassVar[str] = ""
    descriptor_kind: ClassVar[Literal["binary", "float"]] = "binary"
    Params: ClassVar[type[ExtractorParams]] = ExtractorParams

    def __init__(self, params: ExtractorParams | None = None, **overrides: Any) -> None:
        if params is not None and type(params) is not self.Params:
            raise ConfigError(
                f"features.{self.name}: params must be a {self.Params.__name__}, got {type(params).__name__}"
            )
        base = params.model_dump() if params is not None else None
        self.params = resolve(self.Params, base, overrides, where=f"features.{self.name}")
        self._setup()

    # --------------------------------------------------------------------- subclass hooks
    def _setup(self) -> None:
        """Build the OpenCV objects."""

    def _run(self, image: np.ndarray, mask: np.ndarray) -> tuple[_Keypoints, np.ndarray]:
        raise NotImplementedError

    @property
    def descriptor_size(self) -> int:
        """Bytes per descriptor (binary) or dimension (float)."""
        raise NotImplementedError

    # --------------------------------------------------------------------- public API
    @property
    def descriptor_dtype(self) -> type:
        return np.uint8 if self.descriptor_kind == "binary" else np.float32

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.params.model_dump().items())
        return f"{type(self).__name__}({args})"

    def extract(self, image: np.ndarray, mask: np.ndarray | None = None) -> Features:
        """Features of an 8-bit grayscale image (2D uint8); ``mask`` (same shape): keypoints only where non-zero."""
        img = np.asarray(image)
        if img.ndim != 2 or img.dtype != np.uint8 or img.size == 0:
            raise ScanDataError(
                f"features.{self.name}: expected a non-empty 2D uint8 image, got {img.shape} {img.dtype}"
            )
        h, w = img.shape
        if mask is None:
            m = np.full((h, w), 255, np.uint8)
        else:
            m = np.asarray(mask)
            if m.shape != img.shape:
                raise ScanDataError(
                    f"features.{self.name}: mask shape {m.shape} differs from the image's {img.shape}"
                )
            m = np.where(m != 0, 255, 0).astype(np.uint8)
        factor = row_factor(h, self.params.row_upsample)  # low images (16 beams): placerec.features.low_rows
        if factor > 1:
            img, m = upsample_rows(img, m, factor)
        pad = self.params.pad if self.params.wrap_pad else 0
        if pad:
            img = np.pad(img, ((0, 0), (pad, pad)), mode="wrap")
            m = np.pad(m, ((0, 0), (pad, pad)), mode="constant")  # no keypoint centres in the padding
        kps, desc = self._run(np.ascontiguousarray(img), m)
        # keypoints whose centre pixel lies in the original columns (pyramid levels may round into the padding)
        col = np.rint(kps.xy[:, 0])
        keep = np.flatnonzero((col >= pad) & (col < pad + w))
        order = np.lexsort((kps.xy[keep, 0], kps.xy[keep, 1], -kps.response[keep].astype(np.float64)))
        keep = keep[order][: self.params.nfeatures]
        kps = kps.select(keep)
        xy = kps.xy.copy()
        xy[:, 0] -= pad
        xy[:, 1] = rows_back(xy[:, 1], factor)
        warn_few_features(self, self.name, len(keep), (h, w), self.params.nfeatures)
        desc = (
            np.asarray(desc)[keep]
            if len(desc)
            else np.zeros((0, self.descriptor_size), self.descriptor_dtype)
        )
        return Features(
            xy, kps.size, kps.angle, kps.response, kps.octave, desc.astype(self.descriptor_dtype, copy=False)
        )

    # --------------------------------------------------------------------- helpers
    def _fast_keypoints(self, image: np.ndarray, mask: np.ndarray, keep: int) -> list[cv2.KeyPoint]:
        """FAST keypoints inside ``mask``, the ``keep`` strongest (ties broken by row, then column)."""
        kps = self._fast.detect(image, mask)
        if len(kps) <= keep:
            return list(kps)
        resp = np.fromiter((k.response for k in kps), np.float64, count=len(kps))
        xy = cv2.KeyPoint_convert(kps)
        order = np.lexsort((xy[:, 0], xy[:, 1], -resp))[:keep]
        return [kps[i] for i in order]


class OrbExtractor(FeatureExtractor):
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


class BriskExtractor(FeatureExtractor):
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


class _SurfDescribed(FeatureExtractor):
    descriptor_kind = "float"

    @property
    def descriptor_size(self) -> int:
        return 128 if self.params.extended else 64


class FastSurfExtractor(_SurfDescribed):
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


class SurfExtractor(_SurfDescribed):
    """Our SURF detector and descriptor (Table I: hessian threshold 400, 4 octaves, 3 layers per octave)."""

    name = "surf"
    Params = SurfParams

    def _setup(self) -> None:
        self._surf = SURF(self.params)  # type: ignore[arg-type]  # a SurfParams is a SURFParams

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
    cls.name: cls for cls in (OrbExtractor, BriskExtractor, FastSurfExtractor, SurfExtractor)
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
