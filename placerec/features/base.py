"""The base of every 2D feature extractor: `Features` (the arrays an extractor returns), `ExtractorParams` (the
settings all share: at most 300 features, azimuth wrap-around padding, row upsampling of low images) and
`FeatureExtractor`, which validates, pads, caps and orders around each extractor's own detection.

The registered extractors and their VPR paper Table I defaults are in `placerec.features.registry`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, Generic, Literal, TypeVar, cast

import cv2
import numpy as np
from pydantic import Field

from placerec.errors import ConfigError, ScanDataError
from placerec.features.compat import keypoint_xy
from placerec.features.low_rows import row_factor, rows_back, upsample_rows, warn_few_features
from placerec.params import Params, resolve

__all__ = ["Features", "ExtractorParams", "FeatureExtractor"]


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
        xy = keypoint_xy(kps).astype(np.float64).reshape(-1, 2) if n else np.zeros((0, 2))

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

    nfeatures: int = Field(
        300,
        gt=0,
        le=100_000,
        description="features kept, strongest first (VPR paper Table I; at most 100,000)",
    )
    wrap_pad: bool = Field(True, description="pad the 360 degree panorama with the opposite side's columns")
    pad: int = Field(64, ge=0, description="px of wrap-around padding (a multiple of 8 keeps SURF aligned)")
    row_upsample: int | None = Field(
        None,
        ge=1,
        description="row upsampling before extraction (1 = off; None = images < 64 rows to >= 128)",
    )


#: the parameters class of an extractor
EP = TypeVar("EP", bound=ExtractorParams)


class FeatureExtractor(Generic[EP]):
    """Base class of the registered extractors.

    A subclass sets ``name``, ``descriptor_kind`` and ``Params`` (an `ExtractorParams` subclass with its Table I
    defaults) and implements ``_run(image, mask) -> (_Keypoints, descriptors)`` on the (padded) image, keeping
    keypoints only where ``mask`` is non-zero and at most ``self.params.nfeatures`` of them (ideally after any
    it drops). The base class validates inputs, pads for the azimuth wrap-around, caps and orders.
    """

    name: ClassVar[str] = ""
    descriptor_kind: ClassVar[Literal["binary", "float"]] = "binary"
    Params: ClassVar[type[ExtractorParams]] = ExtractorParams
    params: EP
    #: the FAST detector of the extractors that run `_fast_keypoints` (built in their ``_setup``)
    _fast: Any

    def __init__(self, params: ExtractorParams | None = None, **overrides: Any) -> None:
        if params is not None and type(params) is not self.Params:
            raise ConfigError(
                f"features.{self.name}: params must be a {self.Params.__name__}, got {type(params).__name__}"
            )
        base = params.model_dump() if params is not None else None
        self.params = cast(EP, resolve(self.Params, base, overrides, where=f"features.{self.name}"))
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
        xy = keypoint_xy(kps)
        order = np.lexsort((xy[:, 0], xy[:, 1], -resp))[:keep]
        return [kps[i] for i in order]
