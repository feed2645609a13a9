"""Vectorised procedural noise for the simulator's textures.

Everything here works on whole NumPy arrays (no per-point Python loops) and is a pure function of its inputs, so
textures are deterministic from the world seed. Integer lattice hashing uses 32-bit arithmetic that wraps.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "hash_u32",
    "hash_unit",
    "value_noise2",
    "value_noise3",
    "fbm2",
    "filtered_pulse",
]

_P1 = np.uint32(0x8DA6B343)
_P2 = np.uint32(0xD8163841)
_P3 = np.uint32(0xCB1AB31F)
_P4 = np.uint32(0x165667B1)
_M1 = np.uint32(0x85EBCA6B)
_M2 = np.uint32(0xC2B2AE35)
_GOLD = np.uint32(0x9E3779B9)
_INV24 = np.float32(1.0 / 16777216.0)


def _u32(a: np.ndarray | int) -> np.ndarray:
    arr = np.asarray(a)
    if arr.dtype == np.uint32:
        return arr
    if arr.dtype.kind == "f":
        arr = arr.astype(np.int64)
    return arr.astype(np.int64).astype(np.uint32)


def hash_u32(
    a: np.ndarray | int,
    b: np.ndarray | int | None = None,
    c: np.ndarray | int | None = None,
    seed: np.ndarray | int = 0,
) -> np.ndarray:
    """A well-mixed uint32 hash of up to three integer lattice coordinates and a seed (arrays broadcast)."""
    h = _u32(a) * _P1
    if b is not None:
        h = h ^ (_u32(b) * _P2)
    if c is not None:
        h = h ^ (_u32(c) * _P3)
    h = (h ^ (_u32(seed) * _P4)) + _GOLD
    h = h ^ (h >> np.uint32(16))
    h = h * _M1
    h = h ^ (h >> np.uint32(13))
    h = h * _M2
    h = h ^ (h >> np.uint32(16))
    return h


def hash_unit(
    a: np.ndarray | int,
    b: np.ndarray | int | None = None,
    c: np.ndarray | int | None = None,
    seed: np.ndarray | int = 0,
) -> np.ndarray:
    """Uniform float32 in [0, 1) from integer coordinates (see `hash_u32`)."""
    return (hash_u32(a, b, c, seed) >> np.uint32(8)).astype(np.float32) * _INV24


def _smooth(t: np.ndarray) -> np.ndarray:
    return t * t * (3.0 - 2.0 * t)


# Lattice values of the value noise come from fixed random tables (periodic: 256 cells in 2D, 64 in 3D), padded by
# one row/column so the +1 neighbours need no wrapping; the seed shifts the lattice so different objects see
# different noise. Table lookups are several times cheaper than hashing every corner.
_T2 = np.random.default_rng(0x7AB1E).random((256, 256)).astype(np.float32)
_T2P = np.pad(_T2, ((0, 1), (0, 1)), mode="wrap").reshape(-1)
_T3 = np.random.default_rng(0x7AB1F).random((64, 64, 64)).astype(np.float32)
_T3P = np.pad(_T3, ((0, 1), (0, 1), (0, 1)), mode="wrap").reshape(-1)


def _seed_shift(seed: np.ndarray | int, mult: int) -> np.ndarray:
    return (_u32(seed) * np.uint32(mult) >> np.uint32(20)).astype(np.int64)


def value_noise2(x: np.ndarray, y: np.ndarray, seed: np.ndarray | int = 0) -> np.ndarray:
    """Smooth 2D value noise in [0, 1) with unit lattice spacing."""
    xf = np.floor(x)
    yf = np.floor(y)
    base = ((xf.astype(np.int64) + _seed_shift(seed, 0x9E3779B1)) & 255) * 257 + ((yf.astype(np.int64) + _seed_shift(seed, 0x85EBCA77)) & 255)
    sx = _smooth((x - xf).astype(np.float32, copy=False))
    sy = _smooth((y - yf).astype(np.float32, copy=False))
    v00 = np.take(_T2P, base)
    v01 = np.take(_T2P, base + 1)
    v10 = np.take(_T2P, base + 257)
    v11 = np.take(_T2P, base + 258)
    a = v00 + (v10 - v00) * sx
    b = v01 + (v11 - v01) * sx
    return a + (b - a) * sy


def value_noise3(x: np.ndarray, y: np.ndarray, z: np.ndarray, seed: np.ndarray | int = 0) -> np.ndarray:
    """Smooth 3D value noise in [0, 1) with unit lattice spacing."""
    xf, yf, zf = np.floor(x), np.floor(y), np.floor(z)
    base = (((xf.astype(np.int64) + _seed_shift(seed, 0x9E3779B1)) & 63) * 4225
            + ((yf.astype(np.int64) + _seed_shift(seed, 0x85EBCA77)) & 63) * 65 + (zf.astype(np.int64) & 63))  # fmt: skip
    sx = _smooth((x - xf).astype(np.float32, copy=False))
    sy = _smooth((y - yf).astype(np.float32, copy=False))
    sz = _smooth((z - zf).astype(np.float32, copy=False))
    out = None
    for dz, wz in ((0, 1.0 - sz), (1, sz)):
        b0 = base + dz
        v00 = np.take(_T3P, b0)
        v10 = np.take(_T3P, b0 + 4225)
        v01 = np.take(_T3P, b0 + 65)
        v11 = np.take(_T3P, b0 + 4290)
        a = v00 + (v10 - v00) * sx
        b = v01 + (v11 - v01) * sx
        layer = (a + (b - a) * sy) * wz
        out = layer if out is None else out + layer
    return out


def fbm2(x: np.ndarray, y: np.ndarray, seed: np.ndarray | int = 0, octaves: int = 3) -> np.ndarray:
    """Fractal sum of `value_noise2` octaves, centred: roughly in [-1, 1]."""
    total = np.zeros(np.shape(x), dtype=np.float32)
    amp, norm, f = 1.0, 0.0, 1.0
    seed = _u32(seed)
    for o in range(octaves):
        total += amp * (value_noise2(x * f, y * f, seed + np.uint32(977 * (o + 1))) - 0.5)
        norm += amp
        amp *= 0.5
        f *= 2.03
    return total * (2.0 / norm)


def _pulse_integral(t: np.ndarray, duty: float | np.ndarray) -> np.ndarray:
    ft = np.floor(t)
    return ft * duty + np.minimum(t - ft, duty)


def filtered_pulse(
    x: np.ndarray, period: float | np.ndarray, duty: float | np.ndarray, width: np.ndarray | float
) -> np.ndarray:
    """Fraction of a box filter of ``width`` centred at ``x`` that covers the "on" part of a pulse train.

    The train is on where ``frac(x / period) < duty``. Box-filtering by the beam footprint turns thin lines (mortar
    joints, tile gaps) into the partial contrast a real beam sees, and makes them fade with range.
    """
    x = np.asarray(x, dtype=np.float32)
    w = np.maximum(np.asarray(width, dtype=np.float32), np.float32(2e-3))
    inv = np.float32(1.0) / np.asarray(period, dtype=np.float32)
    t0 = (x - 0.5 * w) * inv
    t1 = (x + 0.5 * w) * inv
    duty = np.asarray(duty, dtype=np.float32)
    return (_pulse_integral(t1, duty) - _pulse_integral(t0, duty)) / (t1 - t0)
