"""Bit helpers for packed binary descriptors (ORB, BRISK, ...), shared by the binary retrieval back ends.

Layout: an OpenCV binary descriptor is a row of ``uint8``; bit ``8 * i + v`` of the descriptor is bit ``v`` (LSB
first) of byte ``i`` (the convention of srrg_hbst). Rows are padded with zero bytes to whole 64-bit words for the
popcount, which leaves Hamming distances unchanged.
"""

from __future__ import annotations

import numpy as np

__all__ = ["popcount", "to_words", "unpack_bits", "hamming"]

_HAS_BITWISE_COUNT = hasattr(np, "bitwise_count")
_POPCOUNT_U8 = np.array([bin(v).count("1") for v in range(256)], dtype=np.uint8)


def popcount(words: np.ndarray) -> np.ndarray:
    """Number of set bits of every element of an unsigned integer array (uint8 result per element)."""
    if _HAS_BITWISE_COUNT:
        return np.bitwise_count(words)
    # numpy < 2: per-byte lookup table, summed over the bytes of each element
    as_bytes = np.ascontiguousarray(words).view(np.uint8).reshape(*words.shape, words.dtype.itemsize)
    return _POPCOUNT_U8[as_bytes].sum(axis=-1, dtype=np.uint8)


def to_words(descriptors: np.ndarray) -> np.ndarray:
    """(N, B) uint8 -> (N, ceil(B / 8)) uint64, zero-padded; a copy-free view when B is a multiple of 8."""
    d = np.ascontiguousarray(descriptors, dtype=np.uint8)
    n, n_bytes = d.shape
    pad = -n_bytes % 8
    if pad:
        d = np.concatenate([d, np.zeros((n, pad), dtype=np.uint8)], axis=1)
    return d.view(np.uint64)


def unpack_bits(descriptors: np.ndarray) -> np.ndarray:
    """(N, B) uint8 -> (N, 8 B) uint8 of 0/1, bit ``8 * i + v`` = bit ``v`` of byte ``i``."""
    return np.unpackbits(descriptors, axis=1, bitorder="little")


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamming distances between rows of two word arrays from `to_words`, broadcast like ``a ^ b``: (...,) int32."""
    counts = popcount(np.bitwise_xor(a, b))
    # summing the few words column by column is several times faster than .sum(axis=-1) on (n, 4) arrays
    out = counts[..., 0].astype(np.int32)
    for k in range(1, counts.shape[-1]):
        out += counts[..., k]
    return out
