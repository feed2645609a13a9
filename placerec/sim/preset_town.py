"""The ``town`` preset: an irregular street grid with buildings, sidewalks, markings, street furniture and cars.

Layout (all random choices from the seed): 7 x 6 blocks between street centre lines 50-78 m apart; the blocks
around the route anchor (node (2, 2), at the origin) are small (38-44 m) so the default route is short. The street
through the anchor along x is an avenue with two lanes per direction, double centre line, lane separators, road
studs and trees; other streets have one lane per direction, a dashed centre line and often kerbside parking.
Blocks hold row houses (brick, plaster or office facades with window grids, shop fronts, balconies), small parks
or parking lots. About a quarter of the building blocks reuse the buildings (sizes and facade seeds) of an earlier
block of similar size, so similar-looking places exist in different parts of town (perceptual aliasing).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from placerec.sim.geometry import MeshBuilder
from placerec.sim.materials import M
from placerec.sim.props import (
    Canvas,
    add_benches,
    add_cars,
    add_fence,
    add_lamps,
    add_signs,
    add_trees,
    strip_polys,
)
from placerec.sim.site import FreeSpace, GroundMap, PresetResult, RoadGraph, Terrain

__all__ = ["build_town"]

LANE_W = 3.5
PARK_W = 2.3
KERB_H = 0.14
_NX, _NY = 7, 6
_ANCHOR = (2, 2)


class _Street:
    def __init__(self, lanes: int, parking: bool, sidewalk: float, trees: bool) -> None:
        self.lanes = lanes
        self.parking = parking
        self.sidewalk = sidewalk
        self.trees = trees

    @property
    def half(self) -> float:
        return self.lanes * LANE_W + (PARK_W if self.parking else 0.0)


def _facade_params(rng: np.random.Generator, n: int, shop_p: float) -> tuple[np.ndarray, np.ndarray]:
    """(params rows [tone, floor_h, win_w, win_h, pitch, style, flags], floors) for n buildings."""
    style = rng.choice([0, 1, 2], n, p=[0.4, 0.45, 0.15])
    floors = rng.integers(2, 7, n)
    floor_h = rng.uniform(3.0, 3.6, n)
    tone = np.where(
        style == 0,
        rng.uniform(0.26, 0.42, n),
        np.where(style == 1, rng.uniform(0.35, 0.62, n), rng.uniform(0.18, 0.45, n)),
    )
    pitch = np.where(style == 2, rng.uniform(1.5, 2.0, n), rng.uniform(2.3, 3.6, n))
    win_w = np.where(style == 2, pitch - 0.2, rng.uniform(0.9, 1.5, n))
    win_h = np.where(style == 2, floor_h - 1.0, rng.uniform(1.3, 1.8, n))
    flags = (rng.random(n) < shop_p) * 1 + (rng.random(n) < 0.3) * 2 + (rng.random(n) < 0.3) * 4
    return np.c_[tone, floor_h, win_w, win_h, pitch, style, flags], floors


def _row(rng: np.random.Generator, length: float, depth_max: float, shop_p: float) -> list[dict]:
    """Buildings along one side of a block lot, as specs relative to the side (offset along, width, depth)."""
    specs = []
    pos = 0.0
    while length - pos > 5.0:
        w = rng.uniform(7.0, 18.0)
        if length - pos - w < 6.0:
            w = length - pos
        if rng.random() < 0.1 and w < length - pos - 8:
            pos += rng.uniform(3.0, 6.0)  # a gap: driveway or alley
            continue
        prm, floors = _facade_params(rng, 1, shop_p)
        specs.append(
            dict(
                off=pos, w=w, d=min(rng.uniform(9.0, 15.0), depth_max), floors=int(floors[0]), params=prm[0],
                seed=int(rng.integers(0, 2**31)), balcony=bool(rng.random() < 0.25 and prm[0, 5] < 2),
            )
        )  # fmt: skip
        pos += w
    return specs


def _place_row(
    b: MeshBuilder,
    specs: list[dict],
    origin: np.ndarray,
    along: np.ndarray,
    inward: np.ndarray,
    limit: float,
    free: Canvas,
) -> None:
    """Instantiate row-house specs along a lot side (origin = lot corner, ``along`` unit, ``inward`` unit)."""
    yaw_row = np.arctan2(along[1], along[0])
    for s in specs:
        if s["off"] + 3.0 > limit:
            break
        w = min(s["w"], limit - s["off"])
        h = s["floors"] * s["params"][1] + 0.8
        centre = origin + along * (s["off"] + w / 2) + inward * (s["d"] / 2)
        prm = s["params"]
        b.add_boxes(
            np.r_[centre, KERB_H],
            np.array([w, s["d"], h]),
            yaw_row,
            M.FACADE,
            top_mat=M.ROOF,
            params=prm[None, :],
            seed=s["seed"],
        )
        free.boxes(centre, w, s["d"], yaw_row, 0, margin=0.3)
        if s["balcony"]:
            pitch, win_w = prm[4], prm[2]
            ncols = int(np.floor((w - 1.0) / pitch))
            margin = 0.5 * (w - ncols * pitch)
            cols = np.arange(0, ncols, 2)
            floors = np.arange(1, s["floors"])
            if len(cols) == 0 or len(floors) == 0:
                continue
            C, F = np.meshgrid(cols, floors)
            # the street face is the -inward face; its u runs along +along from the row origin side
            u = margin + (C.reshape(-1) + 0.5) * pitch
            z = KERB_H + F.reshape(-1) * prm[1]
            face0 = origin + along * s["off"]
            pos = face0[None, :] + along[None, :] * u[:, None] - inward[None, :] * 0.5
            bw = win_w + 0.8
            b.add_boxes(np.c_[pos, z], np.array([bw, 1.0, 0.15]), yaw_row, M.STONE, seed=s["seed"])
            rail = pos - inward[None, :] * 0.48
            b.add_boxes(
                np.c_[rail, z + 0.15], np.array([bw, 0.05, 1.0]), yaw_row, M.METAL, seed=s["seed"] + 1
            )


@dataclass
class _Town:
    """The town under construction: its street grid, mesh and canvases, and what the steps collect on the way
    (street furniture is placed in one go at the end, so it can avoid everything built before)."""

    rng: np.random.Generator
    bx: np.ndarray  # block sizes along x and y (m)
    by: np.ndarray
    X: np.ndarray  # street centre lines along x and y (m), the anchor node at the origin
    Y: np.ndarray
    vs: list[_Street]  # the streets along y at each X, and along x at each Y
    hs: list[_Street]
    bounds: tuple[float, float, float, float]
    b: MeshBuilder
    ground: Canvas
    free: Canvas
    lanes: list[np.ndarray] = field(default_factory=list)
    walk: list[np.ndarray] = field(default_factory=list)
    slots: list[np.ndarray] = field(default_factory=list)
    edges: dict = field(default_factory=dict)
    lane_count: dict = field(default_factory=dict)
    lamp_xy: list[np.ndarray] = field(default_factory=list)
    lamp_yaw: list[np.ndarray] = field(default_factory=list)
    tree_xy: list[np.ndarray] = field(default_factory=list)
    park_tree_xy: list[np.ndarray] = field(default_factory=list)
    sign_xy: list[np.ndarray] = field(default_factory=list)
    sign_yaw: list[np.ndarray] = field(default_factory=list)
    car_xy: list[np.ndarray] = field(default_factory=list)
    car_yaw: list[np.ndarray] = field(default_factory=list)
    templates: list[tuple[float, float, list]] = field(default_factory=list)
    n_reused: int = 0


def build_town(seed: int) -> PresetResult:
    """Build the town preset for ``seed`` (see the module docstring)."""
    town = _street_grid(np.random.default_rng([int(seed), 0x70A1]))
    _carriageways(town)
    _streets(town)
    _blocks(town)
    _street_furniture(town)
    _outskirts(town)
    return _result(town)


def _street_grid(rng: np.random.Generator) -> _Town:
    """Block sizes, street centre lines and street types; an empty ground plane and canvases around them."""
    ai, aj = _ANCHOR
    bx = rng.uniform(50.0, 78.0, _NX)
    by = rng.uniform(50.0, 78.0, _NY)
    bx[ai] = rng.uniform(38.0, 44.0)
    bx[ai + 1] = rng.uniform(38.0, 44.0)
    by[aj] = rng.uniform(38.0, 44.0)
    by[aj - 1] = rng.uniform(44.0, 52.0)
    X = np.concatenate([[0.0], np.cumsum(bx)])
    Y = np.concatenate([[0.0], np.cumsum(by)])
    X -= X[ai]
    Y -= Y[aj]
    vs = [_Street(1, bool(rng.random() < 0.6), rng.uniform(2.5, 4.5), bool(rng.random() < 0.35)) for _ in X]
    hs = [_Street(1, bool(rng.random() < 0.6), rng.uniform(2.5, 4.5), bool(rng.random() < 0.35)) for _ in Y]
    hs[aj] = _Street(2, False, 4.5, True)  # the avenue
    vs[ai + 1].parking = True
    margin = 35.0
    x0, x1, y0, y1 = X[0] - margin, X[-1] + margin, Y[0] - margin, Y[-1] + margin
    ground = Canvas(x0, y0, x1, y1, 0.1, int(M.GRASS))
    free = Canvas(x0, y0, x1, y1, 0.5, 1)
    b = MeshBuilder()
    b.add_ground_plane(x0, y0, x1, y1, M.GROUND)
    return _Town(rng, bx, by, X, Y, vs, hs, (x0, y0, x1, y1), b, ground, free)


def _carriageways(town: _Town) -> None:
    """The asphalt of every street, from end to end of the grid."""
    X, Y, vs, hs, ground = town.X, town.Y, town.vs, town.hs, town.ground
    for i, st in enumerate(vs):
        ground.rect(X[i] - st.half, Y[0] - hs[0].half, X[i] + st.half, Y[-1] + hs[-1].half, M.ASPHALT)
    for j, st in enumerate(hs):
        ground.rect(X[0] - vs[0].half, Y[j] - st.half, X[-1] + vs[-1].half, Y[j] + st.half, M.ASPHALT)


def _streets(town: _Town) -> None:
    """Every street segment between two junctions (those along x first), and the road graph's edges."""
    X, Y, vs, hs = town.X, town.Y, town.vs, town.hs
    for j in range(len(Y)):
        for i in range(len(X) - 1):
            p0, p1 = np.array([X[i], Y[j]]), np.array([X[i + 1], Y[j]])
            _street_segment(town, p0, p1, hs[j], vs[i], vs[i + 1])
            town.edges[((i, j), (i + 1, j))] = np.array([p0, p1])
            town.lane_count[((i, j), (i + 1, j))] = hs[j].lanes
    for i in range(len(X)):
        for j in range(len(Y) - 1):
            p0, p1 = np.array([X[i], Y[j]]), np.array([X[i], Y[j + 1]])
            _street_segment(town, p0, p1, vs[i], hs[j], hs[j + 1])
            town.edges[((i, j), (i, j + 1))] = np.array([p0, p1])
            town.lane_count[((i, j), (i, j + 1))] = vs[i].lanes


def _street_segment(town: _Town, p0: np.ndarray, p1: np.ndarray, st: _Street, cross0: _Street, cross1: _Street
                    ) -> None:  # fmt: skip
    """One street from junction ``p0`` to ``p1`` (crossing streets ``cross0`` and ``cross1`` there): its road
    surface and markings, lanes, both kerbsides, and the signs before its junctions."""
    d = (p1 - p0) / np.linalg.norm(p1 - p0)
    n = np.array([-d[1], d[0]])  # left of the direction p0 -> p1
    a = p0 + d * cross0.half
    e = p1 - d * cross1.half
    length = float(np.linalg.norm(e - a))
    _road_surface(town, a, e, d, n, length, st)
    # lanes (right-hand traffic) and edges of the road graph
    for k in range(st.lanes):
        off = (k + 0.5) * LANE_W
        town.lanes.append(np.array([p0 - n * off, p1 - n * off]))
        town.lanes.append(np.array([p1 + n * off, p0 + n * off]))
    for side in (1.0, -1.0):
        _kerbside(town, a, e, d, n, length, st, side)
    _junction_signs(town, a, e, d, st)


def _road_surface(town: _Town, a: np.ndarray, e: np.ndarray, d: np.ndarray, n: np.ndarray, length: float,
                  st: _Street) -> None:  # fmt: skip
    """Asphalt patches, manholes, then markings: centre and lane lines (road studs on an avenue), and at each end
    maybe a zebra crossing with a stop line."""
    rng, ground = town.rng, town.ground
    for _ in range(rng.poisson(1.0)):
        c = a + d * rng.uniform(3, length - 3) + n * rng.uniform(-st.half + 1, st.half - 1)
        ground.boxes(c, rng.uniform(2, 9), rng.uniform(1, 3), np.arctan2(d[1], d[0]), M.ASPHALT_PATCH)
    ground.circles(
        a + d[None] * rng.uniform(5, length - 5, 2)[:, None] + n * rng.uniform(-2, 2, (2, 1)),
        0.32,
        M.MANHOLE,
    )
    cw0 = rng.random() < 0.55
    cw1 = rng.random() < 0.55
    m0 = a + d * (6.5 if cw0 else 1.0)
    m1 = e - d * (6.5 if cw1 else 1.0)
    if st.lanes == 1:
        ground.dashed(m0, m1, 0.12, 3.0, 6.0, M.MARKING, phase=rng.uniform(0, 9))
    else:
        for s in (-0.12, 0.12):
            ground.strip(m0 + n * s, m1 + n * s, 0.12, M.MARKING)
        for s in (-LANE_W, LANE_W):
            ground.dashed(m0 + n * s, m1 + n * s, 0.12, 3.0, 9.0, M.MARKING)
        for s in (-2 * LANE_W + 0.2, 2 * LANE_W - 0.2):
            ground.strip(m0 + n * s, m1 + n * s, 0.15, M.MARKING)
        studs = m0 + d * np.arange(2.0, float(np.linalg.norm(m1 - m0)), 8.0)[:, None]
        ground.boxes(studs, 0.15, 0.15, np.arctan2(d[1], d[0]), M.ROAD_STUD)
    for flag, base, sgn in ((cw0, a, 1.0), (cw1, e, -1.0)):
        if not flag:
            continue
        offs = np.arange(-st.lanes * LANE_W + 0.5, st.lanes * LANE_W - 0.3, 1.0)
        ground.polygons(
            strip_polys(
                base + d * sgn * 1.0 + n * offs[:, None], base + d * sgn * 5.0 + n * offs[:, None], 0.5
            ),
            M.MARKING,
        )
        # stop line across the lanes that approach this end
        side = 1.0 if sgn > 0 else -1.0  # traffic approaching p0 drives on the left of d
        ground.strip(
            base + d * sgn * 5.8 + n * side * 0.2,
            base + d * sgn * 5.8 + n * side * st.lanes * LANE_W,
            0.4,
            M.MARKING,
        )


def _kerbside(town: _Town, a: np.ndarray, e: np.ndarray, d: np.ndarray, n: np.ndarray, length: float,
              st: _Street, side: float) -> None:  # fmt: skip
    """One side of a street (``side`` 1: left of ``d``): its walkway, lamps, trees and kerbside parking."""
    rng = town.rng
    kerb = st.half
    town.walk.append(
        np.array([a + n * side * (kerb + st.sidewalk / 2), e + n * side * (kerb + st.sidewalk / 2)])
    )
    # lamps, trees
    pitch = rng.uniform(24, 34)
    pos = np.arange(rng.uniform(4, 12) if side > 0 else pitch / 2, length - 3, pitch)
    town.lamp_xy.append(a + d * pos[:, None] + n * side * (kerb + 0.5))
    town.lamp_yaw.append(np.full(len(pos), np.arctan2(-n[1] * side, -n[0] * side)))
    if st.trees:
        tp = np.arange(rng.uniform(3, 8), length - 3, rng.uniform(8.5, 12))
        tp = tp[np.min(np.abs(tp[:, None] - pos[None, :]), axis=1, initial=99) > 2.5] if len(pos) else tp
        town.tree_xy.append(a + d * tp[:, None] + n * side * (kerb + min(1.3, st.sidewalk - 0.8)))
    if st.parking:
        sp = np.arange(rng.uniform(2, 6), length - 8, 6.0) + 3.0
        occ = rng.random(len(sp)) < 0.55
        c = a + d * sp[:, None] + n * side * (st.lanes * LANE_W + PARK_W / 2)
        yaw = np.arctan2(d[1], d[0]) + (0 if side < 0 else np.pi)
        town.car_xy.append(c[occ])
        town.car_yaw.append(np.full(occ.sum(), yaw))
        town.slots.append(np.c_[c[~occ], np.full((~occ).sum(), yaw)])
        ticks = a + d * (sp - 3.0)[:, None] + n * side * (st.lanes * LANE_W + 0.1)
        town.ground.polygons(strip_polys(ticks, ticks + n * side * 0.5, 0.12), M.MARKING)


def _junction_signs(town: _Town, a: np.ndarray, e: np.ndarray, d: np.ndarray, st: _Street) -> None:
    """Signs facing traffic approaching each end (on its right, a few metres before the junction)."""
    for end, direction in ((e, d), (a, -d)):
        if town.rng.random() < 0.55:
            right = np.array([direction[1], -direction[0]])
            town.sign_xy.append((end - direction * 7.0 + right * (st.half + 0.6))[None])
            town.sign_yaw.append(np.array([np.arctan2(-direction[1], -direction[0])]))


def _blocks(town: _Town) -> None:
    """Every block between the streets: row houses (always around the anchor), a park or a parking lot."""
    ai, aj = _ANCHOR
    X, Y, vs, hs = town.X, town.Y, town.vs, town.hs
    for i in range(_NX):
        for j in range(_NY):
            kerbs = X[i] + vs[i].half, X[i + 1] - vs[i + 1].half, Y[j] + hs[j].half, Y[j + 1] - hs[j + 1].half
            sw = max(vs[i].sidewalk, hs[j].sidewalk)
            core = abs(i - ai) <= 1 and abs(j - aj) <= 1
            probs = [0.86, 0.07, 0.07] if core else [0.72, 0.14, 0.14]
            kind = str(town.rng.choice(["buildings", "park", "parking"], p=probs))
            if (i, j) in ((ai, aj), (ai + 1, aj)):
                kind = "buildings"
            bseed = int(town.rng.integers(0, 2**31))
            if kind == "buildings":
                _building_block(town, kerbs, sw, 0.7 if j in (aj, aj - 1) else 0.3, bseed)
            else:
                _open_block(town, kind, kerbs, sw, bseed)


def _building_block(town: _Town, kerbs: tuple, sw: float, shop_p: float, bseed: int) -> None:
    """A paved block inside kerbs ``(x0, x1, y0, y1)`` with rows of houses along its four sides (those of an
    earlier block of similar size, about a third of the time) and maybe courtyard trees."""
    cx0, cx1, cy0, cy1 = kerbs
    b, brng = town.b, np.random.default_rng(bseed)
    b.add_boxes(
        [(cx0 + cx1) / 2, (cy0 + cy1) / 2, 0.0], [cx1 - cx0, cy1 - cy0, KERB_H], 0.0, M.CURB, top_mat=M.PAVING,
        seed=bseed,
    )  # fmt: skip
    lx0, lx1, ly0, ly1 = cx0 + sw, cx1 - sw, cy0 + sw, cy1 - sw
    W, H = lx1 - lx0, ly1 - ly0
    reuse = [t for t in town.templates if abs(t[0] - W) < 4 and abs(t[1] - H) < 4]
    if reuse and brng.random() < 0.35:
        rows = reuse[int(brng.integers(len(reuse)))][2]
        town.n_reused += 1
    else:
        rows = _block_rows(brng, W, H, shop_p)
        town.templates.append((W, H, rows))
    dn, dn2 = rows[4]
    # each row from a lot corner: (origin, along the side, inward); written out, as -x would be (-1, -0)
    east, west, north, south = (
        np.array([1.0, 0.0]),
        np.array([-1.0, 0.0]),
        np.array([0.0, 1.0]),
        np.array([0.0, -1.0]),
    )
    _place_row(b, rows[0], np.array([lx0, ly0]), east, north, W, town.free)
    _place_row(b, rows[1], np.array([lx1, ly1]), west, south, W, town.free)
    _place_row(b, rows[2], np.array([lx1, ly0 + dn]), north, west, H - dn - dn2, town.free)
    _place_row(b, rows[3], np.array([lx0, ly1 - dn2]), south, east, H - dn - dn2, town.free)
    n_ct = brng.integers(0, 3)
    town.park_tree_xy.append(
        np.c_[brng.uniform(lx0 + 15, lx1 - 15, n_ct), brng.uniform(ly0 + 15, ly1 - 15, n_ct)]
        if W > 32 and H > 32
        else np.zeros((0, 2))
    )


def _block_rows(brng: np.random.Generator, W: float, H: float, shop_p: float) -> list:
    """Row-house specs of a ``W`` x ``H`` lot: the rows along its two x sides, then its two y sides (between
    those, when there is room), then the depths of the first two ``[dn, dn2]``."""
    ds = min(14.0, H / 2 - 1)
    rows: list[list[Any]] = [_row(brng, W, ds, shop_p), _row(brng, W, ds, shop_p)]
    dn = max((s["d"] for s in rows[0]), default=10.0)
    dn2 = max((s["d"] for s in rows[1]), default=10.0)
    side_len = H - dn - dn2
    dw = min(12.0, W / 2 - 1)
    rows += [_row(brng, side_len, dw, 0.2), _row(brng, side_len, dw, 0.2)] if side_len > 8 else [[], []]
    rows.append([dn, dn2])
    return rows


def _open_block(town: _Town, kind: str, kerbs: tuple, sw: float, bseed: int) -> None:
    """A park or a parking lot inside kerbs ``(x0, x1, y0, y1)``: a paved ring, a fence on some sides, then the
    inside."""
    cx0, cx1, cy0, cy1 = kerbs
    b, brng = town.b, np.random.default_rng(bseed)
    ring = [((cx0 + cx1) / 2, cy0 + sw / 2, cx1 - cx0, sw), ((cx0 + cx1) / 2, cy1 - sw / 2, cx1 - cx0, sw),
            (cx0 + sw / 2, (cy0 + cy1) / 2, sw, cy1 - cy0 - 2 * sw), (cx1 - sw / 2, (cy0 + cy1) / 2, sw, cy1 - cy0 - 2 * sw)]  # fmt: skip
    for rx, ry, rw, rh in ring:
        b.add_boxes([rx, ry, 0.0], [rw, rh, KERB_H], 0.0, M.CURB, top_mat=M.PAVING, seed=bseed)
    inside = cx0 + sw, cx1 - sw, cy0 + sw, cy1 - sw
    ix0, ix1, iy0, iy1 = inside
    corners = np.array([[ix0, iy0], [ix1, iy0], [ix1, iy1], [ix0, iy1]]) + 0.3 * np.array(
        [[1, 1], [-1, 1], [-1, -1], [1, -1]]
    )
    fence_style = int(brng.choice([0, 2])) if kind == "parking" else int(brng.choice([1, 2]))
    sides = np.array([k for k in range(4) if brng.random() < 0.7], dtype=int)
    add_fence(b, corners[sides], corners[(sides + 1) % 4], 0.0, 1.5 if fence_style else 2.0, fence_style, brng,
              town.free)  # fmt: skip
    if kind == "park":
        _park(town, inside, brng)
    else:
        _parking_lot(town, inside, brng)


def _park(town: _Town, inside: tuple, brng: np.random.Generator) -> None:
    """Grass with two gravel paths, trees and a bench."""
    ix0, ix1, iy0, iy1 = inside
    town.ground.rect(ix0, iy0, ix1, iy1, M.GRASS)
    town.ground.strip(np.array([ix0, iy0]), np.array([ix1, iy1]), 2.5, M.GRAVEL)
    town.ground.strip(np.array([ix0, (iy0 + iy1) / 2]), np.array([ix1, (iy0 + iy1) / 2]), 2.5, M.GRAVEL)
    n_t = int((ix1 - ix0) * (iy1 - iy0) / 150)
    txy = np.c_[brng.uniform(ix0 + 2, ix1 - 2, n_t), brng.uniform(iy0 + 2, iy1 - 2, n_t)]
    town.park_tree_xy.append(txy)
    bench = np.array([[(ix0 + ix1) / 2 + 3, (iy0 + iy1) / 2 + 2.2]])
    add_benches(town.b, bench, 0.0, np.zeros(1), brng, town.free)


def _parking_lot(town: _Town, inside: tuple, brng: np.random.Generator) -> None:
    """Asphalt with rows of marked bays, cars in about 60 % of them, and a lamp in the middle."""
    ix0, ix1, iy0, iy1 = inside
    town.ground.rect(ix0, iy0, ix1, iy1, M.ASPHALT)
    rows_y = np.arange(iy0 + 3.0, iy1 - 5.5, 13.0)
    xs = np.arange(ix0 + 3.0, ix1 - 3.0, 2.6)
    for ry in rows_y:
        ticks = strip_polys(np.c_[xs, np.full(len(xs), ry)], np.c_[xs, np.full(len(xs), ry + 5.0)], 0.12)
        town.ground.polygons(ticks, M.MARKING)
        c = np.c_[xs[:-1] + 1.3, np.full(len(xs) - 1, ry + 2.5)]
        occ = brng.random(len(c)) < 0.6
        town.car_xy.append(c[occ])
        town.car_yaw.append(np.full(occ.sum(), np.pi / 2 + np.pi * (brng.random() < 0.5)))
        town.slots.append(np.c_[c[~occ], np.full((~occ).sum(), np.pi / 2)])
    town.lamp_xy.append(np.array([[(ix0 + ix1) / 2, (iy0 + iy1) / 2]]))
    town.lamp_yaw.append(np.zeros(1))


def _cat(parts: list[np.ndarray], width: int) -> np.ndarray:
    return np.concatenate(parts) if parts else np.zeros((0, width))


def _street_furniture(town: _Town) -> None:
    """The lamps, trees, signs and parked cars the streets and blocks collected, each kept clear of the rest."""
    b, rng, free = town.b, town.rng, town.free
    add_lamps(b, _cat(town.lamp_xy, 2), KERB_H, _cat(town.lamp_yaw, 1).reshape(-1), rng, free)
    all_trees = np.concatenate([_cat(town.tree_xy, 2), _cat(town.park_tree_xy, 2)])
    add_trees(b, all_trees, KERB_H, rng, free=free)
    add_signs(b, _cat(town.sign_xy, 2), KERB_H, _cat(town.sign_yaw, 1).reshape(-1), rng, free)
    cars = _cat(town.car_xy, 2)
    add_cars(b, cars, 0.0, _cat(town.car_yaw, 1).reshape(-1), rng, free)


def _outskirts(town: _Town) -> None:
    """A belt of trees around the town."""
    rng = town.rng
    x0, y0, x1, y1 = town.bounds
    per = np.concatenate([
        np.c_[rng.uniform(x0 + 5, x1 - 5, 60), np.full(60, y0 + 12)], np.c_[rng.uniform(x0 + 5, x1 - 5, 60), np.full(60, y1 - 12)],
        np.c_[np.full(50, x0 + 12), rng.uniform(y0 + 5, y1 - 5, 50)], np.c_[np.full(50, x1 - 12), rng.uniform(y0 + 5, y1 - 5, 50)],
    ]) + rng.normal(0, 3.0, (220, 2))  # fmt: skip
    add_trees(town.b, per, 0.0, rng, conifer=rng.random(len(per)) < 0.3, free=town.free)


def _result(town: _Town) -> PresetResult:
    """The built mesh, ground, road graph, free space, lanes, walkways and parking slots as a `PresetResult`."""
    nodes = np.stack(np.meshgrid(town.X, town.Y, indexing="ij"), -1)
    roads = RoadGraph(nodes=nodes, edges=town.edges, lane_width=LANE_W, anchor=_ANCHOR, lanes=town.lane_count)
    walk_arr = np.concatenate([np.stack(town.walk), np.stack(town.walk)[:, ::-1]])
    ground, free = town.ground, town.free
    return PresetResult(
        mesh=town.b.build(),
        ground=GroundMap(ground.img, ground.x0, ground.y0, ground.res),
        terrain=Terrain(),
        roads=roads,
        free=FreeSpace(free.img.astype(bool), free.x0, free.y0, free.res),
        lanes=np.stack(town.lanes),
        walkways=walk_arr,
        parking_slots=_cat(town.slots, 3),
        bounds=town.bounds,
        info={
            "walkway_z": KERB_H,
            "block_x": town.bx.tolist(),
            "block_y": town.by.tolist(),
            "n_building_blocks": len(town.templates) + town.n_reused,
            "n_reused_blocks": town.n_reused,
        },
    )
