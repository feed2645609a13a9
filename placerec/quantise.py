"""Lossy compact encodings of stored float arrays, with their error bounds.

* `ScalarQuantiser` — 8 bits per dimension of a descriptor on a uniform grid of 256 values from the dimension's
  smallest value ``lo`` to its largest ``hi`` (fitted on the rows to store), step ``(hi - lo) / 255``: each value
  is rounded to the nearest grid value, so one inside the fitted range comes back at most half a step,
  ``(hi - lo) / 510``, away, and ``lo`` and ``hi`` exactly (the zeros that make up most of a SHOT / ISHOT
  descriptor are not moved; values outside the range are clipped to it). It is stored in the layout of faiss's
  ``ScalarQuantizer`` ``QT_8bit`` (``c = floor(255 (x - vmin) / vdiff)``, decoded to ``vmin + (c + 0.5) vdiff /
  255``) with ``vmin = lo - step / 2`` and ``vdiff = hi - lo``, which is the same rounding, so faiss searches
  the codes directly.
* `FixedPointCloud` — a point cloud as int16 offsets from its bounding-box centre, one step ``scale`` for the cloud
  (the largest offset maps to 32767): each coordinate comes back at most ``scale / 2`` away (0.6 mm for a cloud
  within 40 m of its centre).
* `PackedCloud` — a `FixedPointCloud` compressed losslessly in memory: each coordinate column delta-coded (int16,
  wrapping), the bytes split into a high-byte and a low-byte plane (the high bytes of neighbouring points agree,
  the low bytes are noise), then zlib (its size and speed: docs/benchmarks.md, databases at scale). `unpack` gives
  back the very same codes.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np

__all__ = ["ScalarQuantiser", "FixedPointCloud", "PackedCloud", "encode_unit", "decode_unit"]

_LEVELS = 255
_INT16_MAX = 32767
#: the range given to a dimension every fitted row has the same value in (any positive width decodes it to
#: within half of it)
_MIN_VDIFF = 1e-12


@dataclass(frozen=True)
class ScalarQuantiser:
    """Per-dimension 8-bit uniform quantiser (module docstring); ``vmin`` and ``vdiff`` (faiss's layout) are (D,)
    float32, ``vdiff`` positive."""

    vmin: np.ndarray
    vdiff: np.ndarray

    @classmethod
    def fit(cls, rows: np.ndarray) -> ScalarQuantiser:
        """The grid from the smallest to the largest value of every column of ``rows`` (N >= 1, D)."""
        x = np.asarray(rows, np.float32)
        lo = x.min(axis=0)
        vdiff = np.maximum(x.max(axis=0) - lo, np.float32(_MIN_VDIFF)).astype(np.float32)
        return cls((lo - vdiff / np.float32(2 * _LEVELS)).astype(np.float32), vdiff)

    @property
    def dim(self) -> int:
        return int(self.vmin.shape[0])

    @property
    def max_error(self) -> np.ndarray:
        """The largest decoding error per dimension of a value inside the fitted range: half a step,
        ``vdiff / 510``."""
        return self.vdiff / (2 * _LEVELS)

    def encode(self, rows: np.ndarray) -> np.ndarray:
        """(N, D) uint8 codes of float rows (computed in float32, as faiss does)."""
        t = (np.asarray(rows, np.float32) - self.vmin) / self.vdiff
        return np.floor(np.clip(t, 0.0, 1.0) * np.float32(_LEVELS)).astype(np.uint8)

    def decode(self, codes: np.ndarray) -> np.ndarray:
        """(N, D) float32 rows of ``codes``."""
        return (
            self.vmin + (np.asarray(codes, np.float32) + np.float32(0.5)) / np.float32(_LEVELS) * self.vdiff
        )

    def trained(self) -> np.ndarray:
        """The parameters in faiss's layout (``ScalarQuantizer.trained`` of ``QT_8bit``): vmin then vdiff."""
        return np.concatenate([self.vmin, self.vdiff]).astype(np.float32)


@dataclass(frozen=True)
class FixedPointCloud:
    """An (M, 3) cloud as int16 ``codes`` around ``centre`` (3,) with step ``scale`` (module docstring)."""

    codes: np.ndarray
    centre: np.ndarray
    scale: float

    @classmethod
    def encode(cls, xyz: np.ndarray) -> FixedPointCloud:
        p = np.asarray(xyz, np.float64).reshape(-1, 3)
        if p.shape[0] == 0:
            return cls(np.zeros((0, 3), np.int16), np.zeros(3), 1.0)
        centre = 0.5 * (p.min(axis=0) + p.max(axis=0))
        reach = float(np.abs(p - centre).max())
        scale = reach / _INT16_MAX if reach > 0 else 1.0
        codes = np.clip(np.rint((p - centre) / scale), -_INT16_MAX, _INT16_MAX).astype(np.int16)
        return cls(codes, centre, scale)

    def decode(self) -> np.ndarray:
        """(M, 3) float32 points."""
        return (self.codes.astype(np.float64) * self.scale + self.centre).astype(np.float32)

    @property
    def nbytes(self) -> int:
        return int(self.codes.nbytes + self.centre.nbytes + 8)

    def __len__(self) -> int:
        return int(self.codes.shape[0])


@dataclass(frozen=True)
class PackedCloud:
    """A `FixedPointCloud` of ``n`` points as zlib-compressed delta-coded byte planes ``data`` (module docstring),
    with its ``centre`` and ``scale``; in memory only (the byte planes are in this machine's byte order)."""

    data: bytes
    n: int
    centre: np.ndarray
    scale: float

    @classmethod
    def pack(cls, cloud: FixedPointCloud, level: int = 1) -> PackedCloud:
        cols = np.ascontiguousarray(cloud.codes.T)  # (3, n): one coordinate a row
        deltas = cols.copy()
        deltas[:, 1:] -= cols[:, :-1]  # int16 arithmetic wraps, and `unpack`'s cumulative sum wraps back
        planes = np.ascontiguousarray(deltas.view(np.uint8).reshape(3, -1, 2).transpose(2, 0, 1))
        return cls(zlib.compress(planes.tobytes(), level), len(cloud), cloud.centre, cloud.scale)

    @classmethod
    def encode(cls, xyz: np.ndarray, level: int = 1) -> PackedCloud:
        return cls.pack(FixedPointCloud.encode(xyz), level)

    def unpack(self) -> FixedPointCloud:
        planes = np.frombuffer(zlib.decompress(self.data), np.uint8).reshape(2, 3, self.n)
        deltas = np.ascontiguousarray(planes.transpose(1, 2, 0)).view(np.int16).reshape(3, self.n)
        return FixedPointCloud(np.cumsum(deltas, axis=1, dtype=np.int16).T.copy(), self.centre, self.scale)

    def decode(self) -> np.ndarray:
        """(M, 3) float32 points (those of the `FixedPointCloud` packed)."""
        return self.unpack().decode()

    @property
    def nbytes(self) -> int:
        return int(len(self.data) + self.centre.nbytes + 16)

    def __len__(self) -> int:
        return self.n


def encode_unit(values: np.ndarray) -> np.ndarray:
    """uint8 codes of values in [0, 1] (e.g. normalised intensity): ``round(255 v)``, error at most 1/510."""
    return np.rint(np.clip(np.asarray(values, np.float32), 0.0, 1.0) * _LEVELS).astype(np.uint8)


def decode_unit(codes: np.ndarray) -> np.ndarray:
    """float32 values of `encode_unit` codes."""
    return np.asarray(codes, np.float32) / np.float32(_LEVELS)
