"""The simulator's compiled kernels: noise and hashing against independent references, textures and shading on
hand-made hits, and the disk cache keyed on every kernel source."""

from __future__ import annotations

import numpy as np
import pytest

from placerec.sim import jit, noise, render
from placerec.sim.materials import P_A, P_H, P_HX, P_HY, P_STYLE, P_TONE, PARAM_COUNT, M
from placerec.sim.textures import MATERIAL_TABLE, TEXTURE_ID, TEXTURES, shade


def _murmur_reference(a, b, c, seed) -> np.ndarray:
    """The documented hash, written independently with NumPy's wrapping uint32 arithmetic."""
    u = [np.asarray(v).astype(np.int64).astype(np.uint32) for v in (a, b, c, seed)]
    with np.errstate(over="ignore"):
        h = (u[0] * np.uint32(0x8DA6B343)) ^ (u[1] * np.uint32(0xD8163841)) ^ (u[2] * np.uint32(0xCB1AB31F))
        h = (h ^ (u[3] * np.uint32(0x165667B1))) + np.uint32(0x9E3779B9)
        h ^= h >> np.uint32(16)
        h *= np.uint32(0x85EBCA6B)
        h ^= h >> np.uint32(13)
        h *= np.uint32(0xC2B2AE35)
        h ^= h >> np.uint32(16)
    return h


def test_hash_matches_reference_and_broadcasts() -> None:
    rng = np.random.default_rng(0)
    a = rng.integers(-(2**40), 2**40, 5000)
    b = rng.normal(0, 1e4, 5000)  # floats are truncated toward zero
    seed = rng.integers(0, 2**32, 5000).astype(np.uint32)
    assert np.array_equal(noise.hash_u32(a, b, 7, seed), _murmur_reference(a, b, 7, seed))
    assert np.array_equal(noise.hash_u32(a, None, None, 3), _murmur_reference(a, 0, 0, 3))  # missing = 0
    grid = noise.hash_u32(np.arange(4)[:, None], np.arange(3)[None, :], None, 1)
    assert grid.shape == (4, 3) and grid.dtype == np.uint32 and len(np.unique(grid)) == 12
    u = noise.hash_unit(np.arange(200_000), None, None, 5)
    assert u.dtype == np.float32 and u.min() >= 0.0 and u.max() < 1.0
    assert np.histogram(u, bins=10, range=(0, 1))[0].min() > 19_000  # uniform within 5 %


def test_value_noise_interpolates_hashed_lattice_values() -> None:
    ix, iy, iz = np.meshgrid(np.arange(-3, 4), np.arange(-3, 4), np.arange(2), indexing="ij")
    ix, iy, iz = (v.ravel().astype(np.float32) for v in (ix, iy, iz))
    lattice_seed = 9 ^ noise._LATTICE_SEED
    assert np.allclose(noise.value_noise2(ix, iy, 9), noise.hash_unit(ix, iy, 0, lattice_seed))
    assert np.allclose(noise.value_noise3(ix, iy, iz, 9), noise.hash_unit(ix, iy, iz, lattice_seed))
    # halfway between two lattice points on a lattice line: the smoothstep weight is exactly 1/2
    mid = noise.value_noise2(np.float32(2.5), np.float32(-1.0), 9)
    ends = noise.hash_unit(np.array([2, 3]), -1, 0, lattice_seed)
    assert mid == pytest.approx(ends.mean(), abs=1e-6)
    # continuous (C1): tiny steps give tiny changes, also across cell borders
    x = np.linspace(-5, 5, 20001, dtype=np.float32)
    v = noise.value_noise2(x, np.full_like(x, 0.3), 4)
    assert v.min() >= 0.0 and v.max() < 1.0 and np.abs(np.diff(v)).max() < 2e-3


def test_fbm_is_a_normalised_octave_sum() -> None:
    x = np.linspace(0, 20, 500, dtype=np.float32)
    y = np.full_like(x, 1.7)
    one = noise.fbm2(x, y, 11, octaves=1)
    assert np.allclose(one, 2.0 * (noise.value_noise2(x, y, 11 + 977) - 0.5), atol=1e-6)
    three = noise.fbm2(x, y, 11, octaves=3)
    expected = (
        (noise.value_noise2(x, y, 11 + 977) - 0.5)
        + 0.5 * (noise.value_noise2(x * np.float32(2.03), y * np.float32(2.03), 11 + 2 * 977) - 0.5)
        + 0.25
        * (noise.value_noise2(x * np.float32(2.03 * 2.03), y * np.float32(2.03 * 2.03), 11 + 3 * 977) - 0.5)
    ) * (2.0 / 1.75)
    assert np.allclose(three, expected, atol=1e-5)


def test_filtered_pulse_hand_computed() -> None:
    # train with period 1, on for the first 0.25: a thin beam sees 1 on the line and 0 off it
    assert noise.filtered_pulse(np.float32(0.1), 1.0, 0.25, 1e-4) == pytest.approx(1.0)
    assert noise.filtered_pulse(np.float32(0.6), 1.0, 0.25, 1e-4) == pytest.approx(0.0)
    # a box of width 0.5 centred at 0.25 covers [0, 0.5]: half of it is on
    assert noise.filtered_pulse(np.float32(0.25), 1.0, 0.25, 0.5) == pytest.approx(0.5, abs=1e-6)
    # a box of whole periods sees the duty cycle wherever it sits
    x = np.random.default_rng(1).uniform(-10, 10, 100).astype(np.float32)
    assert np.allclose(noise.filtered_pulse(x, 0.4, 0.3, 4.0), 0.3, atol=1e-4)


def _hits(n: int, material: M, **params: float) -> dict:
    prm = np.zeros((n, PARAM_COUNT), np.float32)
    for key, value in params.items():
        prm[:, {"hx": P_HX, "hy": P_HY, "h": P_H, "tone": P_TONE, "style": P_STYLE, "a": P_A}[key]] = value
    return {"material": int(material), "params": prm}


def test_retro_sign_front_is_bright_back_is_paint() -> None:
    # a rectangular guide-less sign (style 1) facing +x: 1 m wide, 1 m tall
    pl = np.array([[0.0, 0.1, 0.5], [0.0, 0.1, 0.5]], np.float32)
    nl = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]], np.float32)
    rho, drop, _ = shade(pw=pl, pl=pl, nl=nl, seed=3, **_hits(2, M.SIGN, hy=0.5, h=1.0, style=1))
    assert rho[0] == pytest.approx(MATERIAL_TABLE[1, M.SIGN]) and rho[0] > 100  # retro-reflective sheeting
    assert rho[1] == pytest.approx(0.28) and drop.max() == 0.0
    # a round sign (style 0) has no sheeting outside its disc: those rays pass
    corner = np.array([[0.0, 0.49, 0.98]], np.float32)
    _, drop, _ = shade(pw=corner, pl=corner, nl=nl[:1], **_hits(1, M.SIGN, hy=0.5, h=1.0, style=0))
    assert drop[0] == 1.0


def test_material_dropout_and_tone_and_foliage_depth() -> None:
    pw = np.random.default_rng(2).uniform(-50, 50, (2000, 3)).astype(np.float32)
    rho, drop, depth = shade(int(M.GLASS), pw)
    assert np.all(drop == pytest.approx(MATERIAL_TABLE[2, M.GLASS])) and np.all(depth == 0)
    base, _, _ = shade(int(M.ASPHALT), pw)
    toned, _, _ = shade(int(M.ASPHALT), pw, params=_hits(len(pw), M.ASPHALT, tone=0.2)["params"])
    assert np.allclose(
        toned / base, 0.2 / MATERIAL_TABLE[1, M.ASPHALT], rtol=1e-5
    )  # the texture scales the tone
    assert 0.08 < base.mean() < 0.12  # asphalt is dark in the near infrared
    rho, drop, depth = shade(int(M.FOLIAGE), pw, seed=5)
    assert depth.min() >= 0 and depth.max() <= 0.6 and depth.std() > 0.02  # returns from inside the crown
    own = MATERIAL_TABLE[2, M.FOLIAGE]
    assert drop.min() >= own - 1e-6 and drop.max() > own + 0.1  # leaf gaps add to the material's dropout
    assert np.array_equal(shade(int(M.FOLIAGE), pw, seed=5)[0], rho)  # deterministic


def test_every_material_has_a_texture_in_the_registry() -> None:
    assert set(TEXTURE_ID) == set(TEXTURES) and len(TEXTURES) == len(set(TEXTURES))
    pw = np.random.default_rng(3).uniform(-20, 20, (300, 3)).astype(np.float32)
    pl = np.abs(pw) % 3
    nl = np.tile(np.float32([1, 0, 0]), (300, 1))
    for m in M:
        if m in (M.NONE, M.GROUND):
            continue
        rho, drop, depth = shade(int(m), pw, pl, nl, _hits(300, m, hx=3, hy=3, h=6, a=0.3)["params"], seed=1)
        assert np.all(np.isfinite(rho)) and rho.min() > 0, m.name
        assert np.all((drop >= 0) & (drop <= 1)), m.name


def test_kernel_cache_is_keyed_on_all_kernel_sources() -> None:
    stamp = jit._kernel_sources_stamp()
    for kernel in (render._shade_rays, noise._hash_u32_n):
        cache_file = kernel._cache._cache_file
        assert cache_file._source_stamp[1] == stamp, (
            "numba's cache layout changed: update placerec.sim.jit._stamped"
        )
