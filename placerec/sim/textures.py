"""Procedural textures of the simulator's materials, evaluated on batches of hits (see `placerec.sim.materials`).

Every texture is vectorised over the hits of one material and a pure function of the hit's coordinates (world or
object frame), the object's parameter row and seed, and the beam footprint; so scans are deterministic.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from placerec.sim.materials import (
    MATERIALS,
    P_A,
    P_B,
    P_C,
    P_D,
    P_FLAGS,
    P_H,
    P_HX,
    P_HY,
    P_STYLE,
    Hits,
    M,
    Shade,
)
from placerec.sim.noise import fbm2, filtered_pulse, hash_u32, hash_unit, value_noise2, value_noise3

__all__ = ["shade", "TEXTURES"]


def _att(footprint: np.ndarray, size: float) -> np.ndarray:
    """Contrast left of a detail of ``size`` metres after averaging over the footprint."""
    return 1.0 / (1.0 + (footprint / size) ** 2)


def _tex_plain(h: Hits) -> Shade:
    return Shade(h.tone())


def _tex_rough(h: Hits) -> Shade:
    p = h.pw
    n = value_noise3(p[:, 0] * 3.0, p[:, 1] * 3.0, p[:, 2] * 3.0, h.seed) - 0.5
    big = value_noise2(p[:, 0] * 0.3 + p[:, 2], p[:, 1] * 0.3, 7) - 0.5
    return Shade(h.tone() * (1.0 + 0.35 * n * _att(h.footprint, 0.3) + 0.3 * big))


def _tex_asphalt(h: Hits) -> Shade:
    x, y = h.pw[:, 0], h.pw[:, 1]
    big = fbm2(x * 0.07, y * 0.07, 11, octaves=2)
    grain = value_noise2(x * 6.0, y * 6.0, 12) - 0.5
    return Shade(h.tone() * (1.0 + 0.3 * big + 0.6 * grain * _att(h.footprint, 0.15)))


def _tex_marking(h: Hits) -> Shade:
    x, y = h.pw[:, 0], h.pw[:, 1]
    wear = value_noise2(x * 1.5, y * 1.5, 21)
    return Shade(h.tone() * (0.65 + 0.45 * wear))


def _tex_grass(h: Hits) -> Shade:
    x, y = h.pw[:, 0], h.pw[:, 1]
    patches = fbm2(x * 0.12, y * 0.12, 31, octaves=3)
    tufts = value_noise2(x * 4.0, y * 4.0, 32) - 0.5
    return Shade(h.tone() * (1.0 + 0.35 * patches + 0.7 * tufts * _att(h.footprint, 0.25)))


def _tex_paving(h: Hits) -> Shade:
    x, y = h.pw[:, 0], h.pw[:, 1]
    tile = 0.4
    joint_x = 1.0 - filtered_pulse(x, tile, 0.97, h.footprint)
    joint_y = 1.0 - filtered_pulse(y, tile, 0.97, h.footprint)
    joint = np.maximum(joint_x, joint_y)
    var = hash_unit(np.floor(x / tile), np.floor(y / tile), None, 41) - 0.5
    stain = fbm2(x * 0.2, y * 0.2, 42, octaves=2)
    rho = h.tone() * (1.0 + 0.3 * var * _att(h.footprint, 0.4) + 0.2 * stain)
    return Shade(rho * (1.0 - 0.5 * joint))


def _tex_concrete(h: Hits) -> Shade:
    x, y = h.pw[:, 0], h.pw[:, 1]
    joint = np.maximum(1.0 - filtered_pulse(x, 6.0, 0.995, h.footprint), 1.0 - filtered_pulse(y, 6.0, 0.995, h.footprint))
    stain = fbm2(x * 0.15, y * 0.15, 51, octaves=3)
    oil = np.clip(value_noise2(x * 0.4, y * 0.4, 52) - 0.75, 0.0, 1.0) * 2.5
    return Shade(h.tone() * (1.0 + 0.3 * stain) * (1.0 - 0.6 * oil) * (1.0 - 0.6 * joint))


def _tex_manhole(h: Hits) -> Shade:
    x, y = h.pw[:, 0], h.pw[:, 1]
    grid = filtered_pulse(x, 0.06, 0.5, h.footprint) * filtered_pulse(y, 0.06, 0.5, h.footprint)
    return Shade(h.tone() * (0.7 + 0.6 * grid))


def _tex_foliage(h: Hits, rng_depth: bool = True) -> Shade:
    p = h.pw
    clumps = value_noise3(p[:, 0] / 0.45, p[:, 1] / 0.45, p[:, 2] / 0.45, h.seed)
    fine = value_noise3(p[:, 0] / 0.12, p[:, 1] / 0.12, p[:, 2] / 0.12, h.seed + np.uint32(5))
    rho = h.tone() * (0.45 + 0.8 * clumps + 0.5 * (fine - 0.5))
    gaps = np.clip(0.6 - 1.4 * clumps, 0.0, 0.9)
    depth = 0.6 * (1.0 - fine) ** 2
    return Shade(np.maximum(rho, 0.02), dropout=gaps, depth=depth.astype(np.float32))


def _tex_wood(h: Hits) -> Shade:
    u = h.pl[:, 0] + h.pl[:, 1]
    planks = hash_unit(np.floor(h.pl[:, 2] / 0.15), np.floor(u / 1.2), None, h.seed) - 0.5
    return Shade(h.tone() * (1.0 + 0.4 * planks))


def _tex_person(h: Hits) -> Shade:
    z = h.pl[:, 2]
    legs = h.params[:, P_A]
    rho = np.where(z < 0.85, legs, np.where(z < 1.5, h.tone(), 0.35))
    return Shade(rho.astype(np.float32))


def _face_coords(h: Hits) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(u along the face, face length, face index 0..3, horizontal-face mask) for box objects."""
    nx = h.nl[:, 0]
    ny = h.nl[:, 1]
    along_y = np.abs(nx) >= np.abs(ny)
    hx = h.params[:, P_HX]
    hy = h.params[:, P_HY]
    pos = np.where(along_y, nx, ny) > 0
    half = np.where(along_y, hy, hx)
    coord = np.where(along_y, h.pl[:, 1], h.pl[:, 0])
    # walking around the box counter-clockwise seen from above, u grows along each face
    u = half + np.where(pos == along_y, -coord, coord)
    face = along_y * 2 + pos  # 0..3
    horizontal = np.abs(h.nl[:, 2]) > 0.7
    return u, 2.0 * half, face.astype(np.int64), horizontal


def _tex_corrugated(h: Hits) -> Shade:
    u, length, face, horiz = _face_coords(h)
    v = h.pl[:, 2]
    period = np.where(h.params[:, P_A] > 0, h.params[:, P_A], 0.15)
    ribs = np.cos(2 * np.pi * u / period) * np.exp(-2.0 * (np.pi * h.footprint / period) ** 2)
    rho = h.tone() * (1.0 + 0.3 * ribs)
    rust = fbm2(u * 0.3, v * 0.3, h.seed, octaves=3)
    rho = rho * (1.0 + 0.25 * rust)
    style = h.params[:, P_STYLE].astype(np.int64)
    height = h.params[:, P_H]
    # sheds: roller doors on the long faces and a translucent window strip under the eaves
    is_shed = style == 0
    long_face = length > 12.0
    door_pitch = 14.0
    dc = np.floor(u / door_pitch)
    du = u - dc * door_pitch
    has_door = hash_unit(dc, face, None, h.seed) < 0.5
    door = is_shed & long_face & has_door & (du > 5.0) & (du < 10.0) & (v < np.minimum(4.8, height - 1.0))
    slats = filtered_pulse(v, 0.09, 0.8, h.footprint)
    door_tone = 0.2 + 0.5 * hash_unit(dc, face, 3, h.seed)
    rho = np.where(door, door_tone * (0.8 + 0.25 * slats), rho)
    strip = is_shed & (h.params[:, P_FLAGS] > 0) & (v > height - 2.2) & (v < height - 1.3)
    rho = np.where(strip, 0.55, rho)
    # containers: a painted logo band on some long sides, lock bars on the door end
    is_box = style == 1
    logo_side = is_box & long_face & (hash_unit(face, None, None, h.seed) < 0.45)
    cell = np.floor(u / 0.7)
    letters = logo_side & (v > 1.0) & (v < 1.75) & (u > 1.5) & (u < length - 1.5) & (hash_unit(cell, face, None, h.seed) < 0.6)
    rho = np.where(letters, 0.75, rho)
    door_end = is_box & ~long_face & (h.nl[:, 0] > 0.5)
    bars = filtered_pulse(u + 0.3, 0.6, 0.12, h.footprint)
    rho = np.where(door_end, rho * (1.0 - 0.5 * bars) + 0.3 * bars, rho)
    rho = np.where(horiz, h.tone() * (1.0 + 0.2 * rust), rho)
    return Shade(np.maximum(rho, 0.01).astype(np.float32))


def _tex_fence(h: Hits) -> Shade:
    u, _, _, _ = _face_coords(h)
    style = h.params[:, P_STYLE].astype(np.int64)
    tone = h.tone()
    drop = np.full(len(h), 0.6, dtype=np.float32)  # chain-link: mostly see-through
    planks = filtered_pulse(u, 0.15, 0.8, h.footprint)  # wooden: gaps between planks
    bars = filtered_pulse(u, 0.13, 0.25, h.footprint)  # palisade: thin bars
    drop = np.where(style == 1, 1.0 - planks, np.where(style == 2, 1.0 - bars, drop))
    var = hash_unit(np.floor(u / 0.15), None, None, h.seed) - 0.5
    rho = tone * np.where(style == 1, 1.0 + 0.35 * var, 1.0)
    return Shade(rho.astype(np.float32), dropout=drop.astype(np.float32))


def _tex_sign(h: Hits) -> Shade:
    front = h.nl[:, 0] > 0.5
    s = h.pl[:, 1] / np.maximum(h.params[:, P_HY], 1e-3)
    height = np.maximum(h.params[:, P_H], 1e-3)
    t = 2.0 * h.pl[:, 2] / height - 1.0
    retro = h.tone()
    style = h.params[:, P_STYLE].astype(np.int64)
    r = np.sqrt(s * s + t * t)
    rho = retro.copy()
    drop = np.zeros(len(h), dtype=np.float32)
    # round sign: red ring, white field, dark symbol; corners outside the disc are empty
    round_ = style == 0
    rho = np.where(round_ & (r > 0.72), 0.55 * retro, rho)
    sym = round_ & (r < 0.6) & (np.abs(t) < 0.25) & (hash_unit(np.floor((s + 1) * 4), None, None, h.seed) < 0.6)
    rho = np.where(sym, 0.05, rho)
    drop = np.where(round_ & (r > 1.0), 1.0, drop)
    # guide sign: darker sheeting with bright letters
    guide = style == 2
    cells = hash_unit(np.floor((s + 1) * 6), np.floor((t + 1) * 2.5), None, h.seed) < 0.5
    rho = np.where(guide, np.where(cells & (np.abs(t) < 0.8) & (np.abs(s) < 0.9), retro, 0.25 * retro), rho)
    rho = np.where(front, rho, 0.28)
    drop = np.where(front, drop, 0.0)
    return Shade(rho.astype(np.float32), dropout=drop.astype(np.float32))


def _tex_car(h: Hits) -> Shade:
    paint = h.tone()
    ends = np.abs(h.nl[:, 0]) > 0.6
    y = np.abs(h.pl[:, 1])
    z = h.pl[:, 2]
    plate = ends & (y < 0.26) & (z > 0.12) & (z < 0.25)
    lights = ends & (y > 0.5) & (y < 0.8) & (z > 0.32) & (z < 0.48)
    grime = fbm2(h.pl[:, 0] * 0.8 + h.pl[:, 2], h.pl[:, 1] * 0.8, h.seed, octaves=2)
    rho = paint * (1.0 + 0.15 * grime)
    rho = np.where(lights, 20.0, rho)  # rear reflectors
    rho = np.where(plate, 150.0, rho)
    return Shade(rho.astype(np.float32))


def _tex_facade(h: Hits) -> Shade:
    """Building facades: brick/plaster/office walls, a grid of windows, shop fronts, doors, plinths, posters."""
    u, length, face, horiz = _face_coords(h)
    v = h.pl[:, 2]
    p = h.params
    n = len(h)
    tone = h.tone()
    floor_h = np.maximum(p[:, P_A], 2.5)
    win_w = p[:, P_B]
    win_h = p[:, P_C]
    pitch = np.maximum(p[:, P_D], win_w + 0.3)
    style = p[:, P_STYLE]
    flags = p[:, P_FLAGS].astype(np.int32)
    height = p[:, P_H]
    fp = h.footprint
    seed = h.seed
    fseed = hash_u32(face, None, None, seed)

    # wall, per style
    wall = tone.copy()
    i = np.flatnonzero(style == 0)  # brick: 21.5 x 6.5 cm bricks, 1 cm mortar, per-brick tone
    if len(i):
        vi, ui = v[i], u[i]
        row = np.floor(vi / 0.075)
        us = ui + np.float32(0.1125) * (row % 2)
        solid = filtered_pulse(vi, 0.075, 0.87, fp[i]) * filtered_pulse(us, 0.225, 0.955, fp[i])
        bid = hash_unit(np.floor(us / 0.225), row, None, seed[i]) - 0.5
        wall[i] = tone[i] * (1.0 + 0.35 * bid * _att(fp[i], 0.15)) * solid + 0.55 * (1.0 - solid)
    i = np.flatnonzero(style == 1)  # plaster
    if len(i):
        wall[i] = tone[i] * (0.85 + 0.3 * value_noise2(u[i] * 0.33, v[i] * 0.33, seed[i] + np.uint32(7)))
    i = np.flatnonzero(style == 2)  # office cladding panels
    if len(i):
        wall[i] = tone[i] * (1.0 - 0.5 * (1.0 - filtered_pulse(u[i], 1.5, 0.98, fp[i])))
    wall *= np.where(v < 1.5, 0.85 + 0.1 * v, 1.0)
    cornice = ((flags & 4) > 0) & (np.abs(v - np.rint(v / floor_h) * floor_h) < 0.12) & (v > 1.0)
    wall[cornice] = 0.65
    plinth = v < 0.4 + 0.5 * hash_unit(seed, None, None, 3)
    wall[plinth] = 0.2

    # windows on the upper floors (and on the ground floor unless it is a shop)
    shop = (flags & 1) > 0
    ncols = np.floor((length - 1.0) / pitch)
    uc = u - 0.5 * (length - ncols * pitch)
    col = np.floor(uc / pitch)
    du = uc - col * pitch - 0.5 * (pitch - win_w)
    flr = np.floor(v / floor_h)
    dv = v - flr * floor_h - np.where(style == 2, np.float32(0.6), np.float32(0.9))
    win = (col >= 0) & (col < ncols) & (du >= 0) & (du <= win_w) & (dv >= 0) & (dv <= win_h) & (v < height - 0.7) & ((flr >= 1) | ~shop)
    rho = wall
    drop = np.zeros(n, np.float32)
    i = np.flatnonzero(win)
    if len(i):
        edge = np.minimum(np.minimum(du[i], win_w[i] - du[i]), np.minimum(dv[i], win_h[i] - dv[i]))
        state = hash_unit(col[i], flr[i], face[i], seed[i])
        slats = filtered_pulse(dv[i], 0.05, 0.7, fp[i])
        pane_rho = np.where(state < 0.62, 0.04, np.where(state < 0.82, 0.45 + 0.15 * slats, 0.28))
        frame = edge < 0.09
        rho[i] = np.where(frame, np.where((flags[i] & 2) > 0, 0.1, 0.65), pane_rho)
        drop[i] = np.where(frame | (state >= 0.62), 0.0, 0.85)

    # shop fronts: big windows between pillars, a fascia with lettering (sometimes retro-reflective)
    i = np.flatnonzero(shop & (v < 3.7))
    if len(i):
        ui, vi, li, fs = u[i], v[i], length[i], fseed[i]
        su = ui - np.floor(ui / 5.0) * 5.0
        shop_win = (vi > 0.35) & (vi < 2.8) & (su > 0.6) & (su < 4.4) & (ui > 1.0) & (ui < li - 1.0)
        fascia = (vi >= 3.0) & (ui > 0.5) & (ui < li - 0.5)
        bg = np.where(hash_unit(fs, None, None, 5) < 0.5, 0.1, 0.6)
        letter = (hash_unit(np.floor(ui / 0.45), fs, None, 6) < 0.55) & (vi > 3.12) & (vi < 3.58)
        letter_rho = np.where(hash_unit(fs, None, None, 7) < 0.06, 30.0, np.where(bg > 0.3, 0.1, 0.8))
        r = np.where(shop_win, 0.05, rho[i])
        rho[i] = np.where(fascia, np.where(letter, letter_rho, bg), r)
        drop[i] = np.where(shop_win, 0.7, drop[i])

    # one door per face, posters on the ground floor walls
    i = np.flatnonzero(v < 2.2)
    if len(i):
        ui, vi, fs = u[i], v[i], fseed[i]
        door = np.abs(ui - (1.5 + (length[i] - 3.0) * hash_unit(fs, None, None, 8))) < 0.6
        pc = np.floor(ui / 1.6)
        poster = (vi > 0.9) & ~win[i] & ~door & (drop[i] == 0) & (hash_unit(pc, fs, None, 9) < 0.08)
        r = np.where(door, 0.12, rho[i])
        rho[i] = np.where(poster, 0.1 + 0.7 * hash_unit(pc, fs, None, 10), r)
        drop[i] = np.where(door, 0.0, drop[i])

    rho = np.where(horiz, tone, rho)
    drop[horiz] = 0.0
    rho *= 0.9 + 0.2 * value_noise2(u * 0.5, v * 0.5, seed)
    return Shade(np.maximum(rho, 0.01).astype(np.float32), dropout=drop)


TEXTURES: dict[str, Callable[[Hits], Shade]] = {
    "plain": _tex_plain,
    "rough": _tex_rough,
    "asphalt": _tex_asphalt,
    "marking": _tex_marking,
    "grass": _tex_grass,
    "paving": _tex_paving,
    "concrete": _tex_concrete,
    "manhole": _tex_manhole,
    "foliage": _tex_foliage,
    "wood": _tex_wood,
    "person": _tex_person,
    "corrugated": _tex_corrugated,
    "fence": _tex_fence,
    "sign": _tex_sign,
    "car": _tex_car,
    "facade": _tex_facade,
}


def shade(h: Hits) -> Shade:
    """Evaluate the material's texture on a batch of hits; adds the material's own dropout probability."""
    mat = MATERIALS[M(h.material)]
    out = TEXTURES[mat.texture](h)
    if mat.dropout > 0:
        base = np.float32(mat.dropout)
        out.dropout = np.full(len(h), base, np.float32) if out.dropout is None else 1.0 - (1.0 - out.dropout) * (1.0 - base)
    return out
