"""The ``campus`` preset (alias ``park``): an unstructured, mostly vegetated place, as in the ISHOT paper.

Rolling terrain (sum of sinusoids, ~1-2 m relief) covered with grass; a jittered grid of curved paths (asphalt main
paths through the anchor, gravel elsewhere); tree groups and forest patches (deciduous crowns and conifers) whose
density follows a smooth noise field, bushes and hedges near the paths; a few large rotated buildings with paved
forecourts; parking lots; lamps, benches, sign posts and low walls. Paths keep a 6.5 m corridor free of trees so
routes can drive beside them (lateral-offset revisits).
"""

from __future__ import annotations

import numpy as np

from placerec.sim.geometry import MeshBuilder
from placerec.sim.materials import M
from placerec.sim.noise import fbm2
from placerec.sim.props import (
    Canvas,
    add_benches,
    add_bushes,
    add_cars,
    add_lamps,
    add_signs,
    add_trees,
    strip_polys,
)
from placerec.sim.site import FreeSpace, GroundMap, PresetResult, RoadGraph, Terrain

__all__ = ["build_campus"]

_N = 6
_ANCHOR = (2, 2)
_CORRIDOR = 6.5


def _bezier(p0: np.ndarray, p1: np.ndarray, bend: float, step: float = 2.0) -> np.ndarray:
    d = p1 - p0
    length = float(np.linalg.norm(d))
    n = np.array([-d[1], d[0]]) / max(length, 1e-9)
    c = (p0 + p1) / 2 + n * bend
    t = np.linspace(0.0, 1.0, max(int(length / step), 2) + 1)[:, None]
    return (1 - t) ** 2 * p0 + 2 * (1 - t) * t * c + t**2 * p1


def build_campus(seed: int) -> PresetResult:
    """Build the campus preset for ``seed`` (see the module docstring)."""
    rng = np.random.default_rng([int(seed), 0xCA3])
    ai, aj = _ANCHOR
    gx = rng.uniform(50.0, 70.0, _N - 1)
    gy = rng.uniform(50.0, 70.0, _N - 1)
    gx[ai] = gx[ai + 1] = rng.uniform(38.0, 44.0)
    gy[aj] = rng.uniform(38.0, 44.0)
    X = np.concatenate([[0.0], np.cumsum(gx)])
    Y = np.concatenate([[0.0], np.cumsum(gy)])
    X -= X[ai]
    Y -= Y[aj]
    nodes = np.stack(np.meshgrid(X, Y, indexing="ij"), -1) + rng.uniform(-7.0, 7.0, (_N, _N, 2))
    core = [(ai + i, aj + j) for i in range(3) for j in range(2)]
    for n in core:
        nodes[n] = np.array([X[n[0]], Y[n[1]]]) + rng.uniform(-3.0, 3.0, 2)
    nodes[ai, aj] = 0.0

    terrain = Terrain(
        amplitude=rng.uniform(0.4, 1.1, 4), kx=rng.uniform(-1, 1, 4) * 2 * np.pi / rng.uniform(60, 200, 4),
        ky=rng.uniform(-1, 1, 4) * 2 * np.pi / rng.uniform(60, 200, 4), phase=rng.uniform(0, 2 * np.pi, 4),
    )  # fmt: skip
    margin = 45.0
    x0, x1 = nodes[..., 0].min() - margin, nodes[..., 0].max() + margin
    y0, y1 = nodes[..., 1].min() - margin, nodes[..., 1].max() + margin
    ground = Canvas(x0, y0, x1, y1, 0.1, int(M.GRASS))
    free = Canvas(x0, y0, x1, y1, 0.5, 1)
    corridor = Canvas(x0, y0, x1, y1, 0.5, 0)
    b = MeshBuilder()
    gobj = b.add_objects(np.zeros((1, 3)))[0]
    xs = np.arange(x0 - 60, x1 + 62, 2.0)
    ys = np.arange(y0 - 60, y1 + 62, 2.0)
    XX, YY = np.meshgrid(xs, ys)
    b.add_heightfield(xs, ys, terrain.height(XX, YY), M.GROUND, gobj)
    h = terrain.height

    # paths
    edges: dict = {}
    walk: list[np.ndarray] = []
    lamp_xy, lamp_yaw, bench_xy, bench_yaw = [], [], [], []
    for i in range(_N):
        for j in range(_N):
            for di, dj in ((1, 0), (0, 1)):
                a, e = (i, j), (i + di, j + dj)
                if e[0] >= _N or e[1] >= _N:
                    continue
                needed = a in core and e in core
                if not needed and rng.random() < 0.15:
                    continue
                bend = rng.uniform(-3.0, 3.0) if needed else rng.uniform(-9.0, 9.0)
                poly = _bezier(nodes[a], nodes[e], bend)
                edges[(a, e)] = poly
                main = (j == aj and di == 1) or (i == ai + 1 and dj == 1)
                ground.polygons(
                    strip_polys(poly[:-1], poly[1:], 3.6 if main else 2.6), M.ASPHALT if main else M.GRAVEL
                )
                corridor.polygons(strip_polys(poly[:-1], poly[1:], 2 * _CORRIDOR), 1)
                walk.append(np.stack([poly[:-1], poly[1:]], 1))
                walk.append(np.stack([poly[1:], poly[:-1]], 1))
                s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poly, axis=0), axis=1))])
                if main or rng.random() < 0.4:
                    for sp in np.arange(rng.uniform(10, 20), s[-1] - 10, 30.0):  # away from junctions
                        k = int(np.searchsorted(s, sp))
                        d = poly[min(k + 1, len(poly) - 1)] - poly[max(k - 1, 0)]
                        nrm = np.array([-d[1], d[0]]) / np.linalg.norm(d)
                        side = 1.0 if rng.random() < 0.5 else -1.0
                        lamp_xy.append(poly[k] + nrm * side * 3.0)
                        lamp_yaw.append(np.arctan2(-nrm[1] * side, -nrm[0] * side))
                if rng.random() < 0.5 and len(poly) > 12:
                    k = int(rng.integers(6, len(poly) - 6))
                    d = poly[k + 1] - poly[k - 1]
                    nrm = np.array([-d[1], d[0]]) / np.linalg.norm(d)
                    bench_xy.append(poly[k] + nrm * 3.6)
                    bench_yaw.append(np.arctan2(d[1], d[0]))

    # buildings with forecourts, parking lots
    bldg_tree_block = Canvas(x0, y0, x1, y1, 0.5, 0)
    slots = []
    car_xy, car_yaw = [], []
    for i in range(_N - 1):
        for j in range(_N - 1):
            cell = nodes[i : i + 2, j : j + 2].reshape(-1, 2)
            c = cell.mean(axis=0)
            half = (cell.max(axis=0) - cell.min(axis=0)) / 2 - 14.0
            if np.any(half < 6.0):
                continue
            r = rng.random()
            yaw = rng.uniform(-0.5, 0.5)
            if r < 0.3:
                L = min(rng.uniform(20, 45), 2 * half.min() * 1.2)
                W = min(rng.uniform(12, 25), 2 * half.min() * 0.9)
                H = rng.uniform(8, 16)
                style = rng.choice([0, 1, 2], p=[0.3, 0.4, 0.3])
                floor_h = rng.uniform(3.4, 4.0)
                pitch = 1.8 if style == 2 else rng.uniform(2.6, 3.6)
                prm = [rng.uniform(0.25, 0.55), floor_h, pitch - 0.2 if style == 2 else rng.uniform(1.0, 1.6),
                       floor_h - 1.0 if style == 2 else rng.uniform(1.4, 2.0), pitch, style, 2 * (rng.random() < 0.3)]  # fmt: skip
                corners = c + np.array([[L, W], [-L, W], [L, -W], [-L, -W]]) / 2 @ np.array(
                    [[np.cos(yaw), np.sin(yaw)], [-np.sin(yaw), np.cos(yaw)]]
                )
                zb = float(h(corners[:, 0], corners[:, 1]).min()) - 0.3
                H += float(h(c[0], c[1])) - zb
                b.add_boxes(
                    np.r_[c, zb],
                    [L, W, H + 0.3],
                    yaw,
                    M.FACADE,
                    top_mat=M.ROOF,
                    params=[prm],
                    seed=int(rng.integers(2**31)),
                )
                ground.boxes(c, L + 8, W + 8, yaw, M.PAVING)
                free.boxes(c, L, W, yaw, 0, margin=0.5)
                bldg_tree_block.boxes(c, L + 8, W + 8, yaw, 1)
            elif r < 0.42:
                L, W = 2 * half.min() * 0.9, 2 * half.min() * 0.7
                ground.boxes(c, L, W, yaw, M.ASPHALT)
                bldg_tree_block.boxes(c, L + 4, W + 4, yaw, 1)
                cy, sy = np.cos(yaw), np.sin(yaw)
                for row in (-1, 1):
                    off = np.arange(-L / 2 + 2, L / 2 - 2, 2.6)
                    pts = c + np.outer(off, [cy, sy]) + row * (W / 4) * np.array([-sy, cy])
                    occ = rng.random(len(pts)) < 0.6
                    car_xy.append(pts[occ])
                    car_yaw.append(np.full(occ.sum(), yaw + np.pi / 2 * row))
                    slots.append(np.c_[pts[~occ], np.full((~occ).sum(), yaw + np.pi / 2 * row)])
                    tick = pts - np.array([cy, sy]) * 1.3
                    perp = np.array([-sy, cy]) * 2.5
                    ground.polygons(strip_polys(tick - perp, tick + perp, 0.12), M.MARKING)

    # vegetation: density from smooth noise; keep path corridors, buildings and lots clear
    area = (x1 - x0) * (y1 - y0)
    cand = np.c_[rng.uniform(x0 + 3, x1 - 3, int(area / 45)), rng.uniform(y0 + 3, y1 - 3, int(area / 45))]
    dens = fbm2(cand[:, 0] / 70.0, cand[:, 1] / 70.0, int(seed) + 5, octaves=3)
    keep = (dens > 0.15) | (rng.random(len(cand)) < 0.06)

    def clear(p: np.ndarray, canvas: Canvas) -> np.ndarray:
        ix = ((p[:, 0] - canvas.x0) / canvas.res).astype(int).clip(0, canvas.img.shape[1] - 1)
        iy = ((p[:, 1] - canvas.y0) / canvas.res).astype(int).clip(0, canvas.img.shape[0] - 1)
        return canvas.img[iy, ix] == 0

    trees = cand[keep & clear(cand, corridor) & clear(cand, bldg_tree_block)]
    add_trees(
        b, trees, h(trees[:, 0], trees[:, 1]) - 0.1, rng, conifer=rng.random(len(trees)) < 0.35, free=free
    )
    bush = np.c_[rng.uniform(x0, x1, 900), rng.uniform(y0, y1, 900)]
    near_path = ~clear(bush, corridor)
    bush = bush[clear(bush, bldg_tree_block) & (near_path | (rng.random(900) < 0.3))]
    # keep bushes at least 7.5 m from path centre lines (routes drive up to 4.5 m off them)
    inner = Canvas(x0, y0, x1, y1, 0.5, 0)
    for poly in edges.values():
        inner.polygons(strip_polys(poly[:-1], poly[1:], 15.0), 1)
    bush = bush[clear(bush, inner)]
    add_bushes(b, bush, h(bush[:, 0], bush[:, 1]) - 0.1, rng, free=free)
    # hedges along some straight-ish path stretches, clear of every path's 6 m band
    for poly in list(edges.values())[::3]:
        if rng.random() < 0.5 or len(poly) < 14:
            continue
        k0 = int(rng.integers(3, len(poly) - 10))
        seg = poly[k0 : k0 + 8]
        d = seg[-1] - seg[0]
        nrm = np.array([-d[1], d[0]]) / np.linalg.norm(d)
        mid = (seg[0] + seg[-1]) / 2 + nrm * 7.0 * (1 if rng.random() < 0.5 else -1)
        along = np.linspace(-0.5, 0.5, 7)[:, None] * d + mid
        if not clear(along, inner).all():
            continue
        yaw = np.arctan2(d[1], d[0])
        b.add_boxes(
            np.r_[mid, h(mid[0], mid[1]) - 0.1],
            [float(np.linalg.norm(d)), 1.0, rng.uniform(1.1, 1.8)],
            yaw,
            M.FOLIAGE,
            params=[[0.45]],
            seed=int(rng.integers(2**31)),
        )
        free.boxes(mid, np.linalg.norm(d), 1.0, yaw, 0, margin=0.5)

    if lamp_xy:
        lxy = np.stack(lamp_xy)
        add_lamps(b, lxy, h(lxy[:, 0], lxy[:, 1]), np.array(lamp_yaw), rng, free)
    if bench_xy:
        bxy = np.stack(bench_xy)
        add_benches(b, bxy, h(bxy[:, 0], bxy[:, 1]), np.array(bench_yaw), rng, free)
    pick = rng.random(_N * _N) < 0.35
    diag = rng.choice([-1.0, 1.0], (int(pick.sum()), 2)) * 5.0  # between the paths, clear of the lanes
    junctions = nodes.reshape(-1, 2)[pick] + diag
    add_signs(
        b,
        junctions,
        h(junctions[:, 0], junctions[:, 1]),
        rng.uniform(-np.pi, np.pi, len(junctions)),
        rng,
        free,
    )
    if car_xy:
        cxy = np.concatenate(car_xy)
        add_cars(b, cxy, h(cxy[:, 0], cxy[:, 1]), np.concatenate(car_yaw), rng, free)
    # a few low stone walls
    for _ in range(6):
        p = np.array([rng.uniform(x0 + 20, x1 - 20), rng.uniform(y0 + 20, y1 - 20)])
        if not clear(p[None], corridor)[0]:
            continue
        L, yaw = rng.uniform(6, 20), rng.uniform(-np.pi, np.pi)
        b.add_boxes(
            np.r_[p, h(p[0], p[1]) - 0.2],
            [L, 0.5, rng.uniform(0.8, 1.4)],
            yaw,
            M.STONE,
            seed=int(rng.integers(2**31)),
        )
        free.boxes(p, L, 0.5, yaw, 0, margin=0.5)

    roads = RoadGraph(nodes=nodes, edges=edges, lane_width=3.0, anchor=_ANCHOR)
    walkways = np.concatenate(walk) if walk else np.zeros((0, 2, 2))
    return PresetResult(
        mesh=b.build(),
        ground=GroundMap(ground.img, ground.x0, ground.y0, ground.res),
        terrain=terrain,
        roads=roads,
        free=FreeSpace(free.img.astype(bool), free.x0, free.y0, free.res),
        lanes=np.zeros((0, 2, 2)),
        walkways=walkways[::4],
        parking_slots=np.concatenate(slots) if slots else np.zeros((0, 3)),
        bounds=(x0, y0, x1, y1),
        info={"n_trees": int(len(trees)), "n_bushes": int(len(bush))},
    )
