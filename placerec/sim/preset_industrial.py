"""The ``industrial`` preset: an estate of fenced plots along a grid of service roads.

Plots (45-55 m around the anchor, 60-95 m elsewhere) hold one of: large corrugated-metal sheds with roller doors
and translucent window strips, stacks of shipping containers (painted, corrugated, logo bands, door ends), open
concrete or gravel yards with heaps, pallet stacks, trucks and trailers, or storage tanks. Chain-link or palisade
fences with gates surround the plots; light masts, signs and a few trees line the roads, which have dashed centre
lines and solid edge lines on dark asphalt; the road through the route anchor has two lanes per direction. Large flat surfaces and repeated containers make it geometrically
repetitive: intensity (paint, logos, doors) carries much of what distinguishes places.
"""

from __future__ import annotations

import numpy as np

from placerec.sim.geometry import MeshBuilder
from placerec.sim.materials import M
from placerec.sim.props import Canvas, add_cars, add_fence, add_lamps, add_signs, add_trees, strip_polys
from placerec.sim.site import FreeSpace, GroundMap, PresetResult, RoadGraph, Terrain

__all__ = ["build_industrial"]

_N = 5
_ANCHOR = (1, 1)
LANE_W = 3.75
KERB_H = 0.12


def _trucks(b: MeshBuilder, xy: np.ndarray, yaw: np.ndarray, rng: np.random.Generator, free: Canvas) -> None:
    k = len(xy)
    if k == 0:
        return
    c, s = np.cos(yaw), np.sin(yaw)
    fwd = np.c_[c, s]
    cab = xy + fwd * 6.8
    b.add_boxes(
        np.c_[cab, np.full(k, 0.5)],
        [2.3, 2.45, 2.6],
        yaw,
        M.CAR,
        params=rng.uniform(0.3, 0.7, (k, 1)),
        seed=rng.integers(0, 2**31, k),
    )
    b.add_boxes(
        np.c_[xy, np.full(k, 1.1)],
        [12.5, 2.5, 2.7],
        yaw,
        M.CORRUGATED,
        params=np.c_[rng.uniform(0.2, 0.7, k), np.full(k, 0.3), np.zeros((k, 3)), np.ones(k)],
        seed=rng.integers(0, 2**31, k),
    )
    for off in (-4.5, -3.3, 5.8, 7.0):
        w = xy + fwd * off
        b.add_boxes(np.c_[w, np.zeros(k)], [1.0, 2.4, 1.0], yaw, M.RUBBER, seed=1)
    free.boxes(xy + fwd * 1.0, 16.0, 2.6, yaw, 0, margin=0.5)


def _plot(
    b: MeshBuilder,
    ground: Canvas,
    free: Canvas,
    rng: np.random.Generator,
    x0: float,
    y0: float,
    x1: float,
    y1: float,
    gate_side: int,
) -> np.ndarray:
    """Fill one fenced plot; returns free parking slots (x, y, yaw)."""
    kind = rng.choice(["shed", "containers", "yard", "tanks"], p=[0.4, 0.25, 0.2, 0.15])
    ground.rect(x0, y0, x1, y1, M.GRAVEL if (kind == "yard" and rng.random() < 0.5) else M.CONCRETE)
    w, h = x1 - x0, y1 - y0
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    # fence with a gate gap
    corners = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
    style = int(rng.choice([0, 0, 2]))
    for k in range(4):
        p, q = corners[k], corners[(k + 1) % 4]
        if k == gate_side:
            m = (p + q) / 2
            d = (q - p) / np.linalg.norm(q - p)
            gate = rng.uniform(8.0, 12.0) / 2
            add_fence(
                b, np.stack([p, m + d * gate]), np.stack([m - d * gate, q]), KERB_H, 2.2, style, rng, free
            )
        else:
            add_fence(b, p[None], q[None], KERB_H, 2.2, style, rng, free)
    slots = np.zeros((0, 3))
    inner = 6.0
    if kind == "shed":
        n = 1 if rng.random() < 0.6 else 2
        for k in range(n):
            L = rng.uniform(0.5, 0.8) * (w - 2 * inner) / (1 if n == 1 else 1.6)
            W = rng.uniform(0.45, 0.7) * (h - 2 * inner)
            H = rng.uniform(6.0, 12.0)
            px = cx + (0 if n == 1 else (k - 0.5) * (w - 2 * inner) * 0.5)
            params = [[rng.uniform(0.2, 0.5), rng.uniform(0.15, 0.25), 0, 0, 0, 0, float(rng.random() < 0.5)]]
            b.add_boxes(
                [px, cy, KERB_H],
                [L, W, H],
                0.0,
                M.CORRUGATED,
                top_mat=M.ROOF,
                params=params,
                seed=int(rng.integers(2**31)),
            )
            free.boxes(np.array([px, cy]), L, W, 0.0, 0, margin=0.5)
        if rng.random() < 0.6:
            _trucks(b, np.array([[cx, y0 + 4.0]]), np.array([0.0]), rng, free)
        ground.dashed(np.array([x0 + 3, y1 - 3]), np.array([x1 - 3, y1 - 3]), 0.15, 4.0, 2.0, M.MARKING)
    elif kind == "containers":
        length = np.where(rng.random(64) < 0.6, 12.19, 6.06)
        xs = x0 + inner
        rows = np.arange(y0 + inner + 1.3, y1 - inner - 1.3, rng.uniform(4.0, 9.0))
        for ry in rows:
            xs = x0 + inner
            k = 0
            while xs + length[k % 64] < x1 - inner:
                Lc = length[k % 64]
                levels = int(rng.integers(1, 4))
                if rng.random() < 0.85:
                    base = np.c_[
                        np.full(levels, xs + Lc / 2), np.full(levels, ry), KERB_H + 2.59 * np.arange(levels)
                    ]
                    tone = rng.choice([0.1, 0.2, 0.35, 0.5, 0.6], levels) * rng.uniform(0.9, 1.1, levels)
                    prm = np.c_[tone, np.full(levels, 0.28), np.zeros((levels, 3)), np.ones(levels)]
                    yaw = 0.0 if rng.random() < 0.5 else np.pi
                    b.add_boxes(
                        base,
                        [Lc, 2.44, 2.59],
                        yaw,
                        M.CORRUGATED,
                        params=prm,
                        seed=rng.integers(0, 2**31, levels),
                    )
                    free.boxes(np.array([xs + Lc / 2, ry]), Lc, 2.44, 0.0, 0, margin=0.4)
                xs += Lc + rng.uniform(0.3, 1.5)
                k += 1
    elif kind == "yard":
        nh = int(rng.integers(1, 4))
        hc = np.c_[rng.uniform(x0 + 12, x1 - 12, nh), rng.uniform(y0 + 12, y1 - 12, nh)]
        r = rng.uniform(3.0, 6.0, nh)
        obj = b.add_objects(
            np.c_[hc, np.zeros(nh)],
            0.0,
            np.c_[np.zeros((nh, 3)), rng.uniform(0.15, 0.35, nh)],
            rng.integers(0, 2**31, nh),
        )
        b.add_blobs(
            np.c_[hc, np.zeros(nh)],
            np.c_[r, r * rng.uniform(0.7, 1.3, nh), r * rng.uniform(0.35, 0.6, nh)],
            M.DIRT,
            obj,
            rng,
            jitter=0.2,
            subdiv=1,
        )
        free.circles(hc, r + 1.0, 0)
        npal = int(rng.integers(6, 20))
        pxy = np.c_[rng.uniform(x0 + 5, x1 - 5, npal), rng.uniform(y0 + 5, y1 - 5, npal)]
        b.add_boxes(
            np.c_[pxy, np.full(npal, KERB_H)],
            np.c_[np.full(npal, 1.2), np.full(npal, 1.0), rng.uniform(0.2, 1.6, npal)],
            rng.uniform(0, np.pi, npal),
            M.WOOD,
            seed=rng.integers(0, 2**31, npal),
        )
        free.circles(pxy, 1.2, 0)
        _trucks(b, np.array([[cx, y1 - 6.0]]), np.array([np.pi]), rng, free)
        sxy = np.c_[np.linspace(x0 + 5, x1 - 5, 8), np.full(8, y0 + 4.0)]
        occ = rng.random(8) < 0.5
        add_cars(b, sxy[occ], KERB_H, np.full(occ.sum(), np.pi / 2), rng, free)
        slots = np.c_[sxy[~occ], np.full((~occ).sum(), np.pi / 2)]
        ground.polygons(strip_polys(sxy - [1.3, 2.5], sxy - [1.3, -2.5], 0.12), M.MARKING)
    else:
        nt = int(rng.integers(2, 5))
        r = rng.uniform(3.0, 7.0, nt)
        tc = np.c_[
            np.linspace(x0 + inner + r[0], x1 - inner - r[-1], nt), np.full(nt, cy) + rng.uniform(-5, 5, nt)
        ]
        obj = b.add_objects(
            np.c_[tc, np.zeros(nt)],
            0.0,
            np.c_[np.zeros((nt, 3)), rng.uniform(0.4, 0.65, nt)],
            rng.integers(0, 2**31, nt),
        )
        b.add_prisms(np.c_[tc, np.full(nt, KERB_H)], r, rng.uniform(6.0, 15.0, nt), M.METAL, obj, sides=20)
        free.circles(tc, r + 1.0, 0)
    return slots


def build_industrial(seed: int) -> PresetResult:
    """Build the industrial preset for ``seed`` (see the module docstring)."""
    rng = np.random.default_rng([int(seed), 0x1D5])
    ai, aj = _ANCHOR
    bx = rng.uniform(60.0, 95.0, _N)
    by = rng.uniform(60.0, 95.0, _N)
    bx[ai] = rng.uniform(45.0, 55.0)
    bx[ai + 1] = rng.uniform(45.0, 55.0)
    by[aj] = rng.uniform(45.0, 55.0)
    X = np.concatenate([[0.0], np.cumsum(bx)])
    Y = np.concatenate([[0.0], np.cumsum(by)])
    X -= X[ai]
    Y -= Y[aj]
    n_h = np.ones(len(Y), int)
    n_h[aj] = 2  # the main road through the anchor has two lanes per direction
    n_v = np.ones(len(X), int)
    half_h = n_h * LANE_W + 0.5
    half_v = n_v * LANE_W + 0.5
    margin = 30.0
    x0, x1, y0, y1 = X[0] - margin, X[-1] + margin, Y[0] - margin, Y[-1] + margin
    ground = Canvas(x0, y0, x1, y1, 0.1, int(M.DIRT))
    free = Canvas(x0, y0, x1, y1, 0.5, 1)
    b = MeshBuilder()
    b.add_ground_plane(x0, y0, x1, y1, M.GROUND)
    for xi, hv in zip(X, half_v, strict=True):
        ground.rect(xi - hv, Y[0] - half_h[0], xi + hv, Y[-1] + half_h[-1], M.ASPHALT)
    for yj, hh in zip(Y, half_h, strict=True):
        ground.rect(X[0] - half_v[0], yj - hh, X[-1] + half_v[-1], yj + hh, M.ASPHALT)
    edges: dict = {}
    lane_count: dict = {}
    lanes, walk, slots = [], [], []
    sign_xy, sign_yaw, lamp_xy, lamp_yaw, tree_xy = [], [], [], [], []
    segs = []  # (a node, e node, p0, p1, lanes, half, half of the crossing street at p0, at p1)
    for j, yj in enumerate(Y):
        for i in range(len(X) - 1):
            segs.append(
                (
                    (i, j),
                    (i + 1, j),
                    np.array([X[i], yj]),
                    np.array([X[i + 1], yj]),
                    n_h[j],
                    half_h[j],
                    half_v[i],
                    half_v[i + 1],
                )
            )
    for i, xi in enumerate(X):
        for j in range(len(Y) - 1):
            segs.append(
                (
                    (i, j),
                    (i, j + 1),
                    np.array([xi, Y[j]]),
                    np.array([xi, Y[j + 1]]),
                    n_v[i],
                    half_v[i],
                    half_h[j],
                    half_h[j + 1],
                )
            )
    for na, ne, p0, p1, nl, half, c0, c1 in segs:
        edges[(na, ne)] = np.stack([p0, p1])
        lane_count[(na, ne)] = int(nl)
        d = (p1 - p0) / np.linalg.norm(p1 - p0)
        n = np.array([-d[1], d[0]])
        a, e = p0 + d * (c0 + 1.0), p1 - d * (c1 + 1.0)
        if nl == 1:
            ground.dashed(a, e, 0.15, 3.0, 9.0, M.MARKING, phase=rng.uniform(0, 12))
        else:
            for s_ in (-0.12, 0.12):
                ground.strip(a + n * s_, e + n * s_, 0.12, M.MARKING)
            for s_ in (-LANE_W, LANE_W):
                ground.dashed(a + n * s_, e + n * s_, 0.15, 3.0, 9.0, M.MARKING)
        for s_ in (-half + 0.35, half - 0.35):
            ground.strip(a + n * s_, e + n * s_, 0.15, M.MARKING)
        for k in range(nl):
            off = (k + 0.5) * LANE_W
            lanes += [np.array([p0 - n * off, p1 - n * off]), np.array([p1 + n * off, p0 + n * off])]
        walk.append(np.array([a + n * (half + 1.0), e + n * (half + 1.0)]))
        length = float(np.linalg.norm(e - a))
        for side in (-1.0, 1.0):
            pos = np.arange(rng.uniform(5, 20), length - 5, rng.uniform(35, 50))
            lamp_xy.append(a + d * pos[:, None] + n * side * (half + 0.8))
            lamp_yaw.append(np.full(len(pos), np.arctan2(-n[1] * side, -n[0] * side)))
            if rng.random() < 0.25:
                tp = np.arange(rng.uniform(3, 10), length - 3, rng.uniform(10, 16))
                tree_xy.append(a + d * tp[:, None] + n * side * (half + 2.0))
        if rng.random() < 0.6:
            right = np.array([d[1], -d[0]])
            sign_xy.append(e - d * 6.0 + right * (half + 0.8))
            sign_yaw.append(np.arctan2(-d[1], -d[0]))
    for i in range(_N):
        for j in range(_N):
            kx0, kx1 = X[i] + half_v[i], X[i + 1] - half_v[i + 1]
            ky0, ky1 = Y[j] + half_h[j], Y[j + 1] - half_h[j + 1]
            b.add_boxes(
                [(kx0 + kx1) / 2, (ky0 + ky1) / 2, 0.0],
                [kx1 - kx0, ky1 - ky0, KERB_H],
                0.0,
                M.CURB,
                top_mat=M.GROUND,
                seed=int(rng.integers(2**31)),
            )
            slots.append(
                _plot(
                    b,
                    ground,
                    free,
                    np.random.default_rng(int(rng.integers(2**31))),
                    kx0 + 2.0,
                    ky0 + 2.0,
                    kx1 - 2.0,
                    ky1 - 2.0,
                    int(rng.integers(4)),
                )
            )
    add_lamps(b, np.concatenate(lamp_xy), KERB_H, np.concatenate(lamp_yaw), rng, free)
    if tree_xy:
        add_trees(b, np.concatenate(tree_xy), KERB_H, rng, free=free)
    add_signs(b, np.stack(sign_xy), KERB_H, np.array(sign_yaw), rng, free)
    masts = np.c_[X[:-1] + half_v[:-1] + 3.0, Y[:-1] + half_h[:-1] + 3.0]
    mobj = b.add_objects(
        np.c_[masts, np.zeros(len(masts))], 0.0, np.c_[np.zeros((len(masts), 3)), np.full(len(masts), 0.3)], 7
    )
    b.add_prisms(
        np.c_[masts, np.full(len(masts), KERB_H)], 0.25, 16.0, M.METAL, mobj, sides=8, top_radius=0.12
    )
    b.add_boxes(np.c_[masts, np.full(len(masts), 16.0)], [1.6, 1.6, 0.6], 0.0, M.METAL, obj=mobj)
    per = np.c_[rng.uniform(x0 + 5, x1 - 5, 120), rng.choice([y0 + 10, y1 - 10], 120)] + rng.normal(
        0, 2.5, (120, 2)
    )
    add_trees(b, per, 0.0, rng, conifer=rng.random(120) < 0.5, free=free)
    nodes = np.stack(np.meshgrid(X, Y, indexing="ij"), -1)
    return PresetResult(
        mesh=b.build(),
        ground=GroundMap(ground.img, ground.x0, ground.y0, ground.res),
        terrain=Terrain(),
        roads=RoadGraph(nodes=nodes, edges=edges, lane_width=LANE_W, anchor=_ANCHOR, lanes=lane_count),
        free=FreeSpace(free.img.astype(bool), free.x0, free.y0, free.res),
        lanes=np.stack(lanes),
        walkways=np.concatenate([np.stack(walk), np.stack(walk)[:, ::-1]]),
        parking_slots=np.concatenate(slots) if slots else np.zeros((0, 3)),
        bounds=(x0, y0, x1, y1),
        info={"walkway_z": KERB_H},
    )
