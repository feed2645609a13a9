"""Procedural textures of the simulator's materials, evaluated per hit by compiled kernels.

A texture maps one hit to ``(reflectance, extra dropout probability, extra range)``. It sees the hit point in world
coordinates ``pw``, the point and normal in the hit object's local frame ``pl``/``nl`` (for ground-like materials
below `M.FACADE` these are the world point and normal), the object's parameter row ``prm`` and seed, the beam
footprint diameter ``fp`` (m) and the base reflectance ``tone``. Each texture is a pure function of these, so scans
are deterministic. Thin features (mortar joints, tile gaps, ribs) are box-filtered by the footprint, so their
contrast fades with range as on a real sensor.

`TEXTURES` names the textures; materials refer to them by name (`placerec.sim.materials`) and the renderer by id.
`shade` evaluates materials on arrays of hits (for tests and tools; the renderer calls `shade_hit` per hit).
"""

from __future__ import annotations

import numpy as np

from placerec.sim.jit import inline, njit
from placerec.sim.materials import MATERIALS, P_A, P_B, P_C, P_D, P_FLAGS, P_H, P_HX, P_HY, P_STYLE, P_TONE, M
from placerec.sim.noise import (
    fbm2_1,
    filtered_pulse_1,
    hash_u32_1,
    hash_unit_1,
    value_noise2_1,
    value_noise3_1,
)

__all__ = ["TEXTURES", "TEXTURE_ID", "MATERIAL_TABLE", "shade", "shade_hit", "param_row"]

#: texture names in id order (the id is what the compiled dispatcher `_texture` switches on)
TEXTURES: tuple[str, ...] = ("plain", "rough", "asphalt", "marking", "grass", "paving", "concrete", "manhole", "foliage",
                             "wood", "person", "corrugated", "fence", "sign", "car", "facade")  # fmt: skip
TEXTURE_ID: dict[str, int] = {name: i for i, name in enumerate(TEXTURES)}

_N_MAT = len(M)
#: per material: texture id, base reflectance, material dropout, specular, Lambert exponent (rows in that order)
MATERIAL_TABLE = np.array(
    [
        [TEXTURE_ID[MATERIALS[M(i)].texture] for i in range(_N_MAT)],
        [MATERIALS[M(i)].reflectance for i in range(_N_MAT)],
        [MATERIALS[M(i)].dropout for i in range(_N_MAT)],
        [MATERIALS[M(i)].specular for i in range(_N_MAT)],
        [MATERIALS[M(i)].lambert for i in range(_N_MAT)],
    ],
    dtype=np.float32,
)

_F0 = np.float32(0.0)
_F1 = np.float32(1.0)


@inline
def _att(fp, size):
    """Contrast left of a detail of ``size`` metres after averaging over the footprint."""
    q = fp / size
    return _F1 / (_F1 + q * q)


@inline
def _hu(a, b, c, seed) -> float:
    """`hash_unit_1` of float lattice coordinates (truncated to integers, as array hashing does)."""
    return hash_unit_1(np.int64(a), np.int64(b), np.int64(c), np.int64(seed))


@njit
def _rough(pw, seed, fp, tone):
    n = value_noise3_1(pw[0] * 3.0, pw[1] * 3.0, pw[2] * 3.0, seed) - 0.5
    big = value_noise2_1(pw[0] * 0.3 + pw[2], pw[1] * 0.3, 7) - 0.5
    return tone * (1.0 + 0.35 * n * _att(fp, 0.3) + 0.3 * big)


@njit
def _asphalt(x, y, fp, tone):
    big = fbm2_1(x * 0.07, y * 0.07, 11, 2)
    grain = value_noise2_1(x * 6.0, y * 6.0, 12) - 0.5
    return tone * (1.0 + 0.3 * big + 0.6 * grain * _att(fp, 0.15))


@njit
def _grass(x, y, fp, tone):
    patches = fbm2_1(x * 0.12, y * 0.12, 31, 3)
    tufts = value_noise2_1(x * 4.0, y * 4.0, 32) - 0.5
    return tone * (1.0 + 0.35 * patches + 0.7 * tufts * _att(fp, 0.25))


@njit
def _paving(x, y, fp, tone):
    tile = 0.4
    joint = max(1.0 - filtered_pulse_1(x, tile, 0.97, fp), 1.0 - filtered_pulse_1(y, tile, 0.97, fp))
    var = _hu(np.floor(x / tile), np.floor(y / tile), 0, 41) - 0.5
    stain = fbm2_1(x * 0.2, y * 0.2, 42, 2)
    return tone * (1.0 + 0.3 * var * _att(fp, 0.4) + 0.2 * stain) * (1.0 - 0.5 * joint)


@njit
def _concrete(x, y, fp, tone):
    joint = max(1.0 - filtered_pulse_1(x, 6.0, 0.995, fp), 1.0 - filtered_pulse_1(y, 6.0, 0.995, fp))
    stain = fbm2_1(x * 0.15, y * 0.15, 51, 3)
    oil = min(max(value_noise2_1(x * 0.4, y * 0.4, 52) - 0.75, 0.0), 1.0) * 2.5
    return tone * (1.0 + 0.3 * stain) * (1.0 - 0.6 * oil) * (1.0 - 0.6 * joint)


@njit
def _foliage(pw, seed, tone):
    """Leaves: bright clumps with gaps the beam passes through, and returns from inside the crown."""
    clumps = value_noise3_1(pw[0] / 0.45, pw[1] / 0.45, pw[2] / 0.45, seed)
    fine = value_noise3_1(pw[0] / 0.12, pw[1] / 0.12, pw[2] / 0.12, seed + 5)
    rho = max(tone * (0.45 + 0.8 * clumps + 0.5 * (fine - 0.5)), 0.02)
    gaps = min(max(0.6 - 1.4 * clumps, 0.0), 0.9)
    return rho, gaps, 0.6 * (1.0 - fine) ** 2


@inline
def _face_coords(pl, nl, prm):
    """(u along the face, face length, face index 0..3, horizontal face?) for box objects."""
    along_y = abs(nl[0]) >= abs(nl[1])
    pos = (nl[0] if along_y else nl[1]) > 0
    half = prm[P_HY] if along_y else prm[P_HX]
    coord = pl[1] if along_y else pl[0]
    # walking around the box counter-clockwise seen from above, u grows along each face
    u = half + (-coord if pos == along_y else coord)
    return u, 2.0 * half, np.int64(along_y) * 2 + np.int64(pos), abs(nl[2]) > 0.7


@njit
def _corrugated(pl, nl, prm, seed, fp, tone):
    """Sheds (roller doors, window strip under the eaves) and containers (logo bands, lock bars)."""
    u, length, face, horiz = _face_coords(pl, nl, prm)
    v = pl[2]
    period = prm[P_A] if prm[P_A] > 0 else 0.15
    ribs = np.cos(2 * np.pi * u / period) * np.exp(-2.0 * (np.pi * fp / period) ** 2)
    rust = fbm2_1(u * 0.3, v * 0.3, seed, 3)
    rho = tone * (1.0 + 0.3 * ribs) * (1.0 + 0.25 * rust)
    style = np.int64(prm[P_STYLE])
    height = prm[P_H]
    long_face = length > 12.0
    if style == 0:  # shed
        dc = np.floor(u / 14.0)
        du = u - dc * 14.0
        if long_face and _hu(dc, face, 0, seed) < 0.5 and 5.0 < du < 10.0 and v < min(4.8, height - 1.0):
            slats = filtered_pulse_1(v, 0.09, 0.8, fp)
            rho = (0.2 + 0.5 * _hu(dc, face, 3, seed)) * (0.8 + 0.25 * slats)
        if prm[P_FLAGS] > 0 and height - 2.2 < v < height - 1.3:
            rho = 0.55
    elif style == 1:  # container
        if long_face and _hu(face, 0, 0, seed) < 0.45 and 1.0 < v < 1.75 and 1.5 < u < length - 1.5:
            if _hu(np.floor(u / 0.7), face, 0, seed) < 0.6:
                rho = 0.75
        if not long_face and nl[0] > 0.5:
            bars = filtered_pulse_1(u + 0.3, 0.6, 0.12, fp)
            rho = rho * (1.0 - 0.5 * bars) + 0.3 * bars
    if horiz:
        rho = tone * (1.0 + 0.2 * rust)
    return max(rho, 0.01)


@njit
def _fence(pl, nl, prm, seed, fp, tone):
    """Chain-link (mostly see-through), wooden planks with gaps, palisade bars."""
    u = _face_coords(pl, nl, prm)[0]
    style = np.int64(prm[P_STYLE])
    if style == 1:
        var = _hu(np.floor(u / 0.15), 0, 0, seed) - 0.5
        return tone * (1.0 + 0.35 * var), 1.0 - filtered_pulse_1(u, 0.15, 0.8, fp)
    if style == 2:
        return tone, 1.0 - filtered_pulse_1(u, 0.13, 0.25, fp)
    return tone, 0.6


@njit
def _sign(pl, nl, prm, seed, tone):
    """Retro-reflective sheeting on the front: round signs (ring, symbol, empty corners), guide signs (letters)."""
    if nl[0] <= 0.5:
        return 0.28, 0.0  # the painted back
    s = pl[1] / max(prm[P_HY], 1e-3)
    t = 2.0 * pl[2] / max(prm[P_H], 1e-3) - 1.0
    style = np.int64(prm[P_STYLE])
    r = np.sqrt(s * s + t * t)
    rho = tone
    drop = 0.0
    if style == 0:
        if r > 0.72:
            rho = 0.55 * tone
        if r < 0.6 and abs(t) < 0.25 and _hu(np.floor((s + 1) * 4), 0, 0, seed) < 0.6:
            rho = 0.05
        if r > 1.0:
            drop = 1.0
    elif style == 2:
        cell = _hu(np.floor((s + 1) * 6), np.floor((t + 1) * 2.5), 0, seed) < 0.5
        rho = tone if (cell and abs(t) < 0.8 and abs(s) < 0.9) else 0.25 * tone
    return rho, drop


@njit
def _car(pl, nl, seed, tone):
    """Paint with grime, a retro-reflective licence plate and rear reflectors on the ends."""
    ends = abs(nl[0]) > 0.6
    y = abs(pl[1])
    z = pl[2]
    if ends and y < 0.26 and 0.12 < z < 0.25:
        return 150.0
    if ends and 0.5 < y < 0.8 and 0.32 < z < 0.48:
        return 20.0
    return tone * (1.0 + 0.15 * fbm2_1(pl[0] * 0.8 + pl[2], pl[1] * 0.8, seed, 2))


@njit
def _facade(pl, nl, prm, seed, fp, tone):
    """Building facades: brick/plaster/office walls, a grid of windows, shop fronts, doors, plinths, posters."""
    u, length, face, horiz = _face_coords(pl, nl, prm)
    if horiz:
        return max(tone * (0.9 + 0.2 * value_noise2_1(u * 0.5, pl[2] * 0.5, seed)), 0.01), 0.0
    v = pl[2]
    floor_h = max(prm[P_A], 2.5)
    win_w = prm[P_B]
    win_h = prm[P_C]
    pitch = max(prm[P_D], win_w + 0.3)
    style = prm[P_STYLE]
    flags = np.int64(prm[P_FLAGS])
    fseed = hash_u32_1(face, 0, 0, seed)

    # wall, per style
    wall = tone
    if style == 0:  # brick: 21.5 x 6.5 cm bricks, 1 cm mortar, per-brick tone
        row = np.floor(v / 0.075)
        us = u + 0.1125 * (row % 2)
        solid = filtered_pulse_1(v, 0.075, 0.87, fp) * filtered_pulse_1(us, 0.225, 0.955, fp)
        bid = _hu(np.floor(us / 0.225), row, 0, seed) - 0.5
        wall = tone * (1.0 + 0.35 * bid * _att(fp, 0.15)) * solid + 0.55 * (1.0 - solid)
    elif style == 1:  # plaster
        wall = tone * (0.85 + 0.3 * value_noise2_1(u * 0.33, v * 0.33, seed + 7))
    elif style == 2:  # office cladding panels
        wall = tone * (1.0 - 0.5 * (1.0 - filtered_pulse_1(u, 1.5, 0.98, fp)))
    if v < 1.5:
        wall *= 0.85 + 0.1 * v
    if (flags & 4) > 0 and abs(v - np.rint(v / floor_h) * floor_h) < 0.12 and v > 1.0:
        wall = 0.65  # cornice
    if v < 0.4 + 0.5 * hash_unit_1(seed, 0, 0, 3):
        wall = 0.2  # plinth

    # windows on the upper floors (and on the ground floor unless it is a shop)
    shop = (flags & 1) > 0
    ncols = np.floor((length - 1.0) / pitch)
    uc = u - 0.5 * (length - ncols * pitch)
    col = np.floor(uc / pitch)
    du = uc - col * pitch - 0.5 * (pitch - win_w)
    flr = np.floor(v / floor_h)
    dv = v - flr * floor_h - (0.6 if style == 2 else 0.9)
    win = (
        0 <= col < ncols
        and 0 <= du <= win_w
        and 0 <= dv <= win_h
        and v < prm[P_H] - 0.7
        and (flr >= 1 or not shop)
    )
    rho = wall
    drop = 0.0
    if win:
        edge = min(min(du, win_w - du), min(dv, win_h - dv))
        state = _hu(col, flr, face, seed)
        if edge < 0.09:  # frame
            rho = 0.1 if (flags & 2) > 0 else 0.65
        else:
            rho = (
                0.04
                if state < 0.62
                else (0.45 + 0.15 * filtered_pulse_1(dv, 0.05, 0.7, fp) if state < 0.82 else 0.28)
            )
            drop = 0.0 if state >= 0.62 else 0.85

    # shop fronts: big windows between pillars, a fascia with lettering (sometimes retro-reflective)
    if shop and v < 3.7:
        su = u - np.floor(u / 5.0) * 5.0
        if 0.35 < v < 2.8 and 0.6 < su < 4.4 and 1.0 < u < length - 1.0:
            rho = 0.05
            drop = 0.7
        if v >= 3.0 and 0.5 < u < length - 0.5:
            bg = 0.1 if hash_unit_1(fseed, 0, 0, 5) < 0.5 else 0.6
            letter = _hu(np.floor(u / 0.45), fseed, 0, 6) < 0.55 and 3.12 < v < 3.58
            if letter:
                rho = 30.0 if hash_unit_1(fseed, 0, 0, 7) < 0.06 else (0.1 if bg > 0.3 else 0.8)
            else:
                rho = bg

    # one door per face, posters on the ground floor walls
    if v < 2.2:
        door = abs(u - (1.5 + (length - 3.0) * hash_unit_1(fseed, 0, 0, 8))) < 0.6
        pc = np.floor(u / 1.6)
        if door:
            rho = 0.12
            drop = 0.0
        elif v > 0.9 and not win and drop == 0 and _hu(pc, fseed, 0, 9) < 0.08:
            rho = 0.1 + 0.7 * _hu(pc, fseed, 0, 10)
    rho *= 0.9 + 0.2 * value_noise2_1(u * 0.5, v * 0.5, seed)
    return max(rho, 0.01), drop


@njit
def _texture(tex, pw, pl, nl, prm, seed, fp, tone):
    """Dispatch on the texture id: (reflectance, extra dropout, extra range) of one hit."""
    x, y = pw[0], pw[1]
    if tex == 15:  # facade (most hits first)
        rho, drop = _facade(pl, nl, prm, seed, fp, tone)
        return rho, drop, 0.0
    if tex == 2:  # asphalt
        return _asphalt(x, y, fp, tone), 0.0, 0.0
    if tex == 1:  # rough
        return _rough(pw, seed, fp, tone), 0.0, 0.0
    if tex == 8:  # foliage
        return _foliage(pw, seed, tone)
    if tex == 0:  # plain
        return tone, 0.0, 0.0
    if tex == 3:  # marking
        return tone * (0.65 + 0.45 * value_noise2_1(x * 1.5, y * 1.5, 21)), 0.0, 0.0
    if tex == 4:  # grass
        return _grass(x, y, fp, tone), 0.0, 0.0
    if tex == 5:  # paving
        return _paving(x, y, fp, tone), 0.0, 0.0
    if tex == 6:  # concrete
        return _concrete(x, y, fp, tone), 0.0, 0.0
    if tex == 7:  # manhole
        return (
            tone * (0.7 + 0.6 * filtered_pulse_1(x, 0.06, 0.5, fp) * filtered_pulse_1(y, 0.06, 0.5, fp)),
            0.0,
            0.0,
        )
    if tex == 9:  # wood
        planks = _hu(np.floor(pl[2] / 0.15), np.floor((pl[0] + pl[1]) / 1.2), 0, seed) - 0.5
        return tone * (1.0 + 0.4 * planks), 0.0, 0.0
    if tex == 10:  # person: trousers (parameter A), jacket (tone), head
        return (prm[P_A] if pl[2] < 0.85 else (tone if pl[2] < 1.5 else 0.35)), 0.0, 0.0
    if tex == 11:  # corrugated
        return _corrugated(pl, nl, prm, seed, fp, tone), 0.0, 0.0
    if tex == 12:  # fence
        rho, drop = _fence(pl, nl, prm, seed, fp, tone)
        return rho, drop, 0.0
    if tex == 13:  # sign
        rho, drop = _sign(pl, nl, prm, seed, tone)
        return rho, drop, 0.0
    if tex == 14:  # car
        return _car(pl, nl, seed, tone), 0.0, 0.0
    return tone, 0.0, 0.0


@inline
def shade_hit(texture, base, dropout, pw, pl, nl, prm, seed, fp):
    """Reflectance, dropout probability (texture and material combined) and extra range of one hit on a material
    with ``texture`` id, base reflectance ``base`` and own ``dropout`` (a `MATERIAL_TABLE` column)."""
    tone = prm[P_TONE] if prm[P_TONE] > 0 else base
    rho, drop, depth = _texture(np.int64(texture), pw, pl, nl, prm, seed, fp, tone)
    return np.float32(rho), np.float32(1.0 - (1.0 - drop) * (1.0 - dropout)), np.float32(depth)


@inline
def param_row(table: np.ndarray, i: int, first: int) -> tuple:
    """Row ``i`` of an object parameter table (columns ``first``..``first + PARAM_COUNT - 1``) as a tuple: hits
    pass parameters by value, as an array view per hit would cost a reference-count update."""
    return (table[i, first], table[i, first + 1], table[i, first + 2], table[i, first + 3], table[i, first + 4],
            table[i, first + 5], table[i, first + 6], table[i, first + 7], table[i, first + 8], table[i, first + 9])  # fmt: skip


@njit
def _shade_n(material, pw, pl, nl, params, seed, footprint, mtab, rho, drop, depth):
    for i in range(material.shape[0]):
        m = material[i]
        rho[i], drop[i], depth[i] = shade_hit(mtab[0, m], mtab[1, m], mtab[2, m], (pw[i, 0], pw[i, 1], pw[i, 2]),
                                              (pl[i, 0], pl[i, 1], pl[i, 2]), (nl[i, 0], nl[i, 1], nl[i, 2]),
                                              param_row(params, i, 0), np.int64(seed[i]), footprint[i])  # fmt: skip


def shade(
    material: np.ndarray | int,
    pw: np.ndarray,
    pl: np.ndarray | None = None,
    nl: np.ndarray | None = None,
    params: np.ndarray | None = None,
    seed: np.ndarray | int = 0,
    footprint: np.ndarray | float = 0.01,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Evaluate materials on n hits: (reflectance, dropout probability, extra range), float32 arrays.

    ``pw`` (n, 3) world points; ``pl``/``nl`` (n, 3) point and normal in the object frame (default: ``pw`` and
    +z); ``params`` (n, PARAM_COUNT) object parameter rows (default zeros: the material's base tone).
    """
    pw = np.ascontiguousarray(pw, dtype=np.float32).reshape(-1, 3)
    n = pw.shape[0]
    pl = pw if pl is None else np.ascontiguousarray(pl, dtype=np.float32).reshape(n, 3)
    nl = (
        np.tile(np.array([0, 0, 1], np.float32), (n, 1))
        if nl is None
        else np.ascontiguousarray(nl, dtype=np.float32).reshape(n, 3)
    )
    prm = (
        np.zeros((n, P_FLAGS + 1), np.float32)
        if params is None
        else np.ascontiguousarray(params, dtype=np.float32).reshape(n, -1)
    )
    mat = np.ascontiguousarray(np.broadcast_to(np.asarray(material, dtype=np.int64), (n,)))
    sd = np.ascontiguousarray(np.broadcast_to(np.asarray(seed).astype(np.int64), (n,)))
    fp = np.ascontiguousarray(np.broadcast_to(np.asarray(footprint, dtype=np.float32), (n,)))
    rho, drop, depth = (np.empty(n, np.float32) for _ in range(3))
    _shade_n(mat, pw, pl, nl, prm, sd, fp, MATERIAL_TABLE, rho, drop, depth)
    return rho, drop, depth
