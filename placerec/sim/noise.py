"""Procedural noise for the simulator's textures: lattice hashes, value noise, fBm and box-filtered pulse trains.

Each function comes twice: a scalar kernel (``*_1``, compiled with Numba and inlined into the per-hit kernels)
and a NumPy-style array function that broadcasts its arguments and runs the kernel over them in one pass. All are
pure functions of their inputs, so textures are deterministic from the world seed. Integer lattice hashing uses
32-bit arithmetic that wraps (computed in uint64 and masked); value noise hashes its lattice corners (about ten
integer operations each in compiled code, and no lookup tables to pass around).
"""

from __future__ import annotations

import numpy as np

from placerec.sim.jit import elementwise, inline, njit

__all__ = [
    "hash_u32",
    "hash_unit",
    "value_noise2",
    "value_noise3",
    "fbm2",
    "filtered_pulse",
]

_MASK = np.uint64(0xFFFFFFFF)
_P1 = np.uint64(0x8DA6B343)
_P2 = np.uint64(0xD8163841)
_P3 = np.uint64(0xCB1AB31F)
_P4 = np.uint64(0x165667B1)
_M1 = np.uint64(0x85EBCA6B)
_M2 = np.uint64(0xC2B2AE35)
_GOLD = np.uint64(0x9E3779B9)
_S8 = np.uint64(8)
_S13 = np.uint64(13)
_S16 = np.uint64(16)
_S20 = np.uint64(20)
_INV24 = np.float32(1.0 / 16777216.0)
_F2 = np.float32(2.0)
_F3 = np.float32(3.0)
_HALF = np.float32(0.5)

_LATTICE_SEED = 0x7AB1E  # mixed into the seed of lattice values, so value noise and plain hashes differ


# -- scalar kernels -------------------------------------------------------------------------------------------------
@inline
def hash_u32_1(a: int, b: int, c: int, seed: int) -> np.uint64:
    """Well-mixed 32-bit hash of three int64 lattice coordinates and a seed (each taken modulo 2**32)."""
    h = (np.uint64(a) & _MASK) * _P1 & _MASK
    h ^= (np.uint64(b) & _MASK) * _P2 & _MASK
    h ^= (np.uint64(c) & _MASK) * _P3 & _MASK
    h = ((h ^ ((np.uint64(seed) & _MASK) * _P4 & _MASK)) + _GOLD) & _MASK
    h ^= h >> _S16
    h = h * _M1 & _MASK
    h ^= h >> _S13
    h = h * _M2 & _MASK
    h ^= h >> _S16
    return h


@inline
def hash_unit_1(a: int, b: int, c: int, seed: int) -> np.float32:
    """Uniform float32 in [0, 1) from `hash_u32_1`."""
    return np.float32(hash_u32_1(a, b, c, seed) >> _S8) * _INV24


@inline
def _smooth(t):
    return t * t * (_F3 - _F2 * t)


@inline
def _lerp(a, b, t):
    return a + (b - a) * t


@njit
def value_noise2_1(x: float, y: float, seed: int) -> float:
    """Smooth 2D value noise in [0, 1) with unit lattice spacing: hashed lattice values, smoothstep blending."""
    xf = np.floor(x)
    yf = np.floor(y)
    ix = np.int64(xf)
    iy = np.int64(yf)
    s = seed ^ _LATTICE_SEED
    sx = _smooth(np.float32(x - xf))
    sy = _smooth(np.float32(y - yf))
    a = _lerp(hash_unit_1(ix, iy, 0, s), hash_unit_1(ix + 1, iy, 0, s), sx)
    b = _lerp(hash_unit_1(ix, iy + 1, 0, s), hash_unit_1(ix + 1, iy + 1, 0, s), sx)
    return _lerp(a, b, sy)


@njit
def value_noise3_1(x: float, y: float, z: float, seed: int) -> float:
    """Smooth 3D value noise in [0, 1) with unit lattice spacing (see `value_noise2_1`)."""
    xf = np.floor(x)
    yf = np.floor(y)
    zf = np.floor(z)
    ix = np.int64(xf)
    iy = np.int64(yf)
    iz = np.int64(zf)
    s = seed ^ _LATTICE_SEED
    sx = _smooth(np.float32(x - xf))
    sy = _smooth(np.float32(y - yf))
    sz = _smooth(np.float32(z - zf))
    lo_a = _lerp(hash_unit_1(ix, iy, iz, s), hash_unit_1(ix + 1, iy, iz, s), sx)
    lo_b = _lerp(hash_unit_1(ix, iy + 1, iz, s), hash_unit_1(ix + 1, iy + 1, iz, s), sx)
    hi_a = _lerp(hash_unit_1(ix, iy, iz + 1, s), hash_unit_1(ix + 1, iy, iz + 1, s), sx)
    hi_b = _lerp(hash_unit_1(ix, iy + 1, iz + 1, s), hash_unit_1(ix + 1, iy + 1, iz + 1, s), sx)
    return _lerp(_lerp(lo_a, lo_b, sy), _lerp(hi_a, hi_b, sy), sz)


@njit
def fbm2_1(x: float, y: float, seed: int, octaves: int) -> np.float32:
    """Fractal sum of `value_noise2_1` octaves (frequency x2.03, amplitude x0.5), centred: roughly in [-1, 1]."""
    total = np.float32(0.0)
    amp = np.float32(1.0)
    norm = np.float32(0.0)
    f = np.float32(1.0)
    for o in range(octaves):
        s = (np.uint64(seed) + np.uint64(977 * (o + 1))) & _MASK
        total += amp * (value_noise2_1(x * f, y * f, np.int64(s)) - _HALF)
        norm += amp
        amp *= _HALF
        f *= np.float32(2.03)
    return total * (_F2 / norm)


@inline
def _pulse_integral(t, duty):
    ft = np.floor(t)
    return ft * duty + min(t - ft, duty)


@njit
def filtered_pulse_1(x: float, period: float, duty: float, width: float) -> float:
    """Fraction of a box filter of ``width`` centred at ``x`` covering the "on" part of a pulse train (on where
    ``frac(x / period) < duty``); see `filtered_pulse`."""
    w = max(np.float32(width), np.float32(2e-3))
    inv = np.float32(1.0) / np.float32(period)
    t0 = (np.float32(x) - _HALF * w) * inv
    t1 = (np.float32(x) + _HALF * w) * inv
    d = np.float32(duty)
    return (_pulse_integral(t1, d) - _pulse_integral(t0, d)) / (t1 - t0)


# -- array kernels --------------------------------------------------------------------------------------------------
@njit
def _hash_u32_n(a, b, c, seed, out):
    for i in range(out.shape[0]):
        out[i] = hash_u32_1(a[i], b[i], c[i], seed[i])


@njit
def _hash_unit_n(a, b, c, seed, out):
    for i in range(out.shape[0]):
        out[i] = hash_unit_1(a[i], b[i], c[i], seed[i])


@njit
def _value_noise2_n(x, y, seed, out):
    for i in range(out.shape[0]):
        out[i] = value_noise2_1(x[i], y[i], seed[i])


@njit
def _value_noise3_n(x, y, z, seed, out):
    for i in range(out.shape[0]):
        out[i] = value_noise3_1(x[i], y[i], z[i], seed[i])


@njit
def _fbm2_n(x, y, seed, octaves, out):
    for i in range(out.shape[0]):
        out[i] = fbm2_1(x[i], y[i], seed[i], octaves)


@njit
def _filtered_pulse_n(x, period, duty, width, out):
    for i in range(out.shape[0]):
        out[i] = filtered_pulse_1(x[i], period[i], duty[i], width[i])


_I8 = np.int64
_F4 = np.float32


def hash_u32(a: np.ndarray | int, b: np.ndarray | int | None = None, c: np.ndarray | int | None = None,
             seed: np.ndarray | int = 0) -> np.ndarray:  # fmt: skip
    """A well-mixed uint32 hash of up to three integer lattice coordinates and a seed (arrays broadcast; floats
    are truncated to integers; a missing coordinate counts as 0)."""
    return elementwise(
        _hash_u32_n, (a, 0 if b is None else b, 0 if c is None else c, seed), (_I8,) * 4, np.uint32
    )


def hash_unit(a: np.ndarray | int, b: np.ndarray | int | None = None, c: np.ndarray | int | None = None,
              seed: np.ndarray | int = 0) -> np.ndarray:  # fmt: skip
    """Uniform float32 in [0, 1) from integer coordinates (see `hash_u32`)."""
    return elementwise(
        _hash_unit_n, (a, 0 if b is None else b, 0 if c is None else c, seed), (_I8,) * 4, np.float32
    )


def value_noise2(x: np.ndarray, y: np.ndarray, seed: np.ndarray | int = 0) -> np.ndarray:
    """Smooth 2D value noise in [0, 1) with unit lattice spacing."""
    return elementwise(_value_noise2_n, (x, y, seed), (_F4, _F4, _I8), np.float32)


def value_noise3(x: np.ndarray, y: np.ndarray, z: np.ndarray, seed: np.ndarray | int = 0) -> np.ndarray:
    """Smooth 3D value noise in [0, 1) with unit lattice spacing."""
    return elementwise(_value_noise3_n, (x, y, z, seed), (_F4, _F4, _F4, _I8), np.float32)


def fbm2(x: np.ndarray, y: np.ndarray, seed: np.ndarray | int = 0, octaves: int = 3) -> np.ndarray:
    """Fractal sum of `value_noise2` octaves, centred: roughly in [-1, 1]."""
    return elementwise(_fbm2_n, (x, y, seed), (_F4, _F4, _I8), np.float32, int(octaves))


def filtered_pulse(
    x: np.ndarray, period: float | np.ndarray, duty: float | np.ndarray, width: np.ndarray | float
) -> np.ndarray:
    """Fraction of a box filter of ``width`` centred at ``x`` that covers the "on" part of a pulse train.

    The train is on where ``frac(x / period) < duty``. Box-filtering by the beam footprint turns thin lines (mortar
    joints, tile gaps) into the partial contrast a real beam sees, and makes them fade with range.
    """
    return elementwise(_filtered_pulse_n, (x, period, duty, width), (_F4,) * 4, np.float32)
