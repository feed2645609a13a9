"""Shared building blocks of the world presets: raster canvases and street furniture, vegetation, vehicles.

All prop functions are vectorised over K items and add triangles to a `MeshBuilder`; the ones that occupy ground
also stamp their footprint into the free-space canvas so query poses and clutter avoid them.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import ArrayLike

from placerec.sim.geometry import MeshBuilder
from placerec.sim.materials import M

__all__ = [
    "Canvas",
    "add_trees",
    "add_bushes",
    "add_lamps",
    "add_signs",
    "add_cars",
    "add_people",
    "add_fence",
    "add_benches",
    "car_paint",
    "car_attributes",
]

_SHIFT = 2  # cv2 sub-pixel bits


class Canvas:
    """A uint8 raster over the world's (x, y) extent, with polygon drawing in world coordinates."""

    def __init__(self, x0: float, y0: float, x1: float, y1: float, resolution: float, fill: int) -> None:
        self.x0, self.y0, self.res = float(x0), float(y0), float(resolution)
        w = int(np.ceil((x1 - x0) / resolution))
        h = int(np.ceil((y1 - y0) / resolution))
        self.img = np.full((h, w), fill, dtype=np.uint8)

    def _px(self, pts: np.ndarray) -> np.ndarray:
        p = (np.asarray(pts, dtype=np.float64) - [self.x0, self.y0]) / self.res
        return np.round(p * (1 << _SHIFT)).astype(np.int32).reshape(-1, 1, 2)

    def polygon(self, pts: np.ndarray, value: int) -> None:
        cv2.fillPoly(self.img, [self._px(pts)], int(value), lineType=cv2.LINE_8, shift=_SHIFT)

    def polygons(self, polys: np.ndarray, value: int) -> None:
        """Fill K polygons given as (K, n, 2)."""
        if len(polys):
            cv2.fillPoly(
                self.img, [self._px(p) for p in polys], int(value), lineType=cv2.LINE_8, shift=_SHIFT
            )

    def rect(self, x0: float, y0: float, x1: float, y1: float, value: int) -> None:
        self.polygon(np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]]), value)

    def strip(self, p0: np.ndarray, p1: np.ndarray, width: float, value: int) -> None:
        """A line of ``width`` metres from p0 to p1."""
        self.polygons(strip_polys(np.atleast_2d(p0), np.atleast_2d(p1), width), value)

    def dashed(
        self,
        p0: np.ndarray,
        p1: np.ndarray,
        width: float,
        dash: float,
        gap: float,
        value: int,
        phase: float = 0.0,
    ) -> None:
        p0 = np.asarray(p0, float)
        p1 = np.asarray(p1, float)
        length = float(np.linalg.norm(p1 - p0))
        if length < 1e-6:
            return
        d = (p1 - p0) / length
        starts = np.arange(phase % (dash + gap), length, dash + gap)
        ends = np.minimum(starts + dash, length)
        self.polygons(strip_polys(p0 + starts[:, None] * d, p0 + ends[:, None] * d, width), value)

    def circles(self, centers: np.ndarray, radius: float | np.ndarray, value: int) -> None:
        centers = np.atleast_2d(centers)
        radius = np.broadcast_to(np.asarray(radius, dtype=np.float64), (len(centers),))
        for c, r in zip(self._px(centers).reshape(-1, 2), radius, strict=True):
            cv2.circle(
                self.img,
                (int(c[0]), int(c[1])),
                int(round(r / self.res * (1 << _SHIFT))),
                int(value),
                -1,
                cv2.LINE_8,
                _SHIFT,
            )

    def boxes(
        self,
        center: ArrayLike,
        length: ArrayLike,
        width: ArrayLike,
        yaw: ArrayLike,
        value: int,
        margin: float = 0.0,
    ) -> None:
        """Fill K oriented rectangles (footprints)."""
        center = np.atleast_2d(center)
        k = len(center)
        hl = np.broadcast_to(np.asarray(length, float), (k,)) / 2 + margin
        hw = np.broadcast_to(np.asarray(width, float), (k,)) / 2 + margin
        yaw = np.broadcast_to(np.asarray(yaw, float), (k,))
        c, s = np.cos(yaw), np.sin(yaw)
        corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float)
        lx = corners[None, :, 0] * hl[:, None]
        ly = corners[None, :, 1] * hw[:, None]
        pts = (
            np.stack([c[:, None] * lx - s[:, None] * ly, s[:, None] * lx + c[:, None] * ly], -1)
            + center[:, None, :2]
        )
        self.polygons(pts, value)


def strip_polys(p0: np.ndarray, p1: np.ndarray, width: float) -> np.ndarray:
    d = p1 - p0
    n = np.linalg.norm(d, axis=1, keepdims=True)
    d = d / np.maximum(n, 1e-9)
    perp = np.stack([-d[:, 1], d[:, 0]], 1) * (width / 2)
    return np.stack([p0 - perp, p1 - perp, p1 + perp, p0 + perp], 1)


def _z(z: np.ndarray | float, k: int) -> np.ndarray:
    return np.broadcast_to(np.asarray(z, dtype=np.float64), (k,))


def add_trees(
    b: MeshBuilder,
    xy: np.ndarray,
    z: np.ndarray | float,
    rng: np.random.Generator,
    conifer: np.ndarray | None = None,
    scale: float = 1.0,
    free: Canvas | None = None,
) -> None:
    """Deciduous trees (trunk + jittered crown) or conifers (trunk + cone), vectorised."""
    xy = np.atleast_2d(xy)
    k = len(xy)
    if k == 0:
        return
    z = _z(z, k)
    conifer = np.zeros(k, bool) if conifer is None else conifer
    trunk_h = rng.uniform(1.8, 3.2, k) * scale
    trunk_r = rng.uniform(0.12, 0.25, k) * scale
    ids = b.add_objects(np.c_[xy, z], 0.0, None, rng.integers(0, 2**31, k))
    b.add_prisms(np.c_[xy, z], trunk_r, trunk_h + 1.0, M.BARK, ids, sides=6)
    dec = ~conifer
    if dec.any():
        r = rng.uniform(1.8, 3.6, dec.sum()) * scale
        rz = r * rng.uniform(0.7, 1.1, dec.sum())
        centre = np.c_[xy[dec], z[dec] + trunk_h[dec] + rz * 0.8]
        radii = np.c_[r * rng.uniform(0.85, 1.15, len(r)), r * rng.uniform(0.85, 1.15, len(r)), rz]
        b.add_blobs(centre, radii, M.FOLIAGE, ids[dec], rng, jitter=0.3, subdiv=1)
    if conifer.any():
        n = conifer.sum()
        h = rng.uniform(6.0, 14.0, n) * scale
        r = h * rng.uniform(0.22, 0.32, n)
        b.add_prisms(
            np.c_[xy[conifer], z[conifer] + trunk_h[conifer] * 0.5],
            r,
            h,
            M.FOLIAGE,
            ids[conifer],
            sides=10,
            top_radius=0.0,
        )
    if free is not None:
        free.circles(xy, trunk_r + 0.6, 0)


def add_bushes(
    b: MeshBuilder,
    xy: np.ndarray,
    z: np.ndarray | float,
    rng: np.random.Generator,
    free: Canvas | None = None,
) -> None:
    xy = np.atleast_2d(xy)
    k = len(xy)
    if k == 0:
        return
    z = _z(z, k)
    r = rng.uniform(0.5, 1.4, k)
    ids = b.add_objects(
        np.c_[xy, z], 0.0, np.c_[np.zeros((k, 3)), rng.uniform(0.35, 0.5, k)], rng.integers(0, 2**31, k)
    )
    b.add_blobs(
        np.c_[xy, z + r * 0.5],
        np.c_[r, r * rng.uniform(0.8, 1.2, k), r * 0.8],
        M.FOLIAGE,
        ids,
        rng,
        jitter=0.35,
    )
    if free is not None:
        free.circles(xy, r + 0.4, 0)


def add_lamps(
    b: MeshBuilder,
    xy: np.ndarray,
    z: np.ndarray | float,
    arm_yaw: np.ndarray,
    rng: np.random.Generator,
    free: Canvas | None = None,
) -> None:
    """Street lamps: a metal pole with an arm towards ``arm_yaw`` and a lamp head."""
    xy = np.atleast_2d(xy)
    k = len(xy)
    if k == 0:
        return
    z = _z(z, k)
    h = rng.uniform(5.5, 8.0, k)
    ids = b.add_objects(
        np.c_[xy, z], arm_yaw, np.c_[np.zeros((k, 3)), np.full(k, 0.3)], rng.integers(0, 2**31, k)
    )
    b.add_prisms(np.c_[xy, z], 0.09, h, M.METAL, ids, sides=6)
    d = np.c_[np.cos(arm_yaw), np.sin(arm_yaw)]
    b.add_boxes(
        np.c_[xy + d * 0.8, z + h - 0.1],
        np.c_[np.full(k, 1.6), np.full(k, 0.08), np.full(k, 0.1)],
        arm_yaw,
        M.METAL,
        obj=ids,
    )
    b.add_boxes(
        np.c_[xy + d * 1.5, z + h - 0.35],
        np.c_[np.full(k, 0.7), np.full(k, 0.3), np.full(k, 0.25)],
        arm_yaw,
        M.METAL,
        obj=ids,
    )
    if free is not None:
        free.circles(xy, 0.5, 0)


def add_signs(
    b: MeshBuilder,
    xy: np.ndarray,
    z: np.ndarray | float,
    facing_yaw: np.ndarray,
    rng: np.random.Generator,
    free: Canvas | None = None,
) -> None:
    """Traffic signs on poles; the retro-reflective face looks along ``facing_yaw``."""
    xy = np.atleast_2d(xy)
    k = len(xy)
    if k == 0:
        return
    z = _z(z, k)
    pid = b.add_objects(
        np.c_[xy, z], 0.0, np.c_[np.zeros((k, 3)), np.full(k, 0.3)], rng.integers(0, 2**31, k)
    )
    pole_h = rng.uniform(2.6, 3.2, k)
    b.add_prisms(np.c_[xy, z], 0.04, pole_h, M.METAL, pid, sides=6)
    style = rng.choice([0, 0, 1, 2, 3], k)
    width = np.where(style == 2, rng.uniform(1.0, 1.6, k), rng.uniform(0.6, 0.9, k))
    height = np.where(style == 2, width * 0.6, width)
    d = np.c_[np.cos(facing_yaw), np.sin(facing_yaw)]
    retro = rng.uniform(100.0, 400.0, k)  # retro sheeting: 100-1000x a white Lambertian surface
    params = np.c_[retro, np.zeros((k, 4)), style]
    b.add_boxes(
        np.c_[xy + d * 0.06, z + pole_h - height],
        np.c_[np.full(k, 0.04), width, height],
        facing_yaw,
        M.SIGN,
        params=params,
        seed=rng.integers(0, 2**31, k),
    )
    if free is not None:
        free.circles(xy, 0.4, 0)


_PAINTS = np.array([0.70, 0.06, 0.45, 0.35, 0.18, 0.28])
_PAINT_CDF = np.cumsum([0.25, 0.2, 0.28, 0.1, 0.1, 0.07])


def car_paint(u: np.ndarray) -> np.ndarray:
    """NIR reflectance of car paints from uniforms: white, black, silver/grey, red, blue, others."""
    return _PAINTS[np.minimum(np.searchsorted(_PAINT_CDF, u), len(_PAINTS) - 1)]


def car_attributes(u: np.ndarray, van_fraction: float = 0.15) -> np.ndarray:
    """Car shapes from uniforms ``u`` (K, 7): columns length, width, body height, paint, cabin length fraction,
    cabin height, seed. The mapping is deterministic, so an agent keeps its look from scan to scan."""
    u = np.atleast_2d(u)
    van = u[:, 0] < van_fraction
    w = u[:, 1]
    length = np.where(van, 4.8 + 0.8 * w, 3.9 + 1.0 * w)
    width = np.where(van, 1.9 + 0.15 * u[:, 2], 1.7 + 0.2 * u[:, 2])
    body_h = np.where(van, 1.6 + 0.3 * u[:, 3], 0.7 + 0.1 * u[:, 3])
    paint = car_paint(u[:, 4]) * (0.9 + 0.2 * u[:, 5])
    cabin_f = 0.48 + 0.1 * u[:, 5]
    cabin_h = np.where(van, 0.0, 0.42 + 0.13 * u[:, 6])
    seed = np.floor(u[:, 6] * 2**31)
    return np.c_[length, width, body_h, paint, cabin_f, cabin_h, seed]


def add_cars(
    b: MeshBuilder,
    xy: np.ndarray,
    z: np.ndarray | float,
    yaw: np.ndarray,
    rng: np.random.Generator | None = None,
    free: Canvas | None = None,
    attrs: np.ndarray | None = None,
) -> np.ndarray:
    """Cars and vans: painted body with licence plates and rear reflectors, glass cabin, wheels.

    Shapes come from ``attrs`` (see `car_attributes`) or are drawn from ``rng``.
    """
    xy = np.atleast_2d(xy)
    k = len(xy)
    if k == 0:
        return np.zeros(0, np.int32)
    z = _z(z, k)
    yaw = np.broadcast_to(np.asarray(yaw, float), (k,))
    if attrs is None:
        assert rng is not None
        attrs = car_attributes(rng.random((k, 7)))
    length, width, body_h, paint, cabin_f, cabin_h, seed = attrs.T
    base = np.c_[xy, z + 0.3]
    ids = b.add_boxes(
        base, np.c_[length, width, body_h], yaw, M.CAR, params=paint[:, None], seed=seed.astype(np.int64)
    )
    c, s = np.cos(yaw), np.sin(yaw)
    car = (
        cabin_h > 0
    )  # vans get a zero-size cabin, so every vehicle has the same mesh layout (see clutter.py)
    cl = np.where(car, length * cabin_f, 0.0)
    back = -0.08 * length
    cab_base = np.c_[xy + np.c_[c, s] * back[:, None], z + 0.3 + body_h]
    b.add_boxes(
        cab_base,
        np.c_[cl, np.where(car, width - 0.16, 0.0), cabin_h],
        yaw,
        M.CAR_GLASS,
        top_mat=M.CAR,
        obj=ids,
    )
    off = np.array([[1, 1], [1, -1], [-1, 1], [-1, -1]], float)
    wl = (length / 2 - 0.75)[:, None] * off[None, :, 0]
    ww = (width / 2 - 0.2)[:, None] * off[None, :, 1]
    wxy = (
        np.stack([c[:, None] * wl - s[:, None] * ww, s[:, None] * wl + c[:, None] * ww], -1) + xy[:, None, :]
    )
    b.add_boxes(
        np.c_[wxy.reshape(-1, 2), np.repeat(z, 4)],
        np.array([0.62, 0.22, 0.6]),
        np.repeat(yaw, 4),
        M.RUBBER,
        obj=np.repeat(ids, 4),
    )
    if free is not None:
        free.boxes(xy, length, width, yaw, 0, margin=0.4)
    return ids


def add_people(b: MeshBuilder, xy: np.ndarray, z: np.ndarray | float, u: np.ndarray) -> None:
    """Pedestrians (8-sided prisms, clothing reflectance from uniforms ``u`` (K, 4))."""
    xy = np.atleast_2d(xy)
    k = len(xy)
    if k == 0:
        return
    z = _z(z, k)
    u = np.atleast_2d(u)
    tops = 0.1 + 0.5 * u[:, 0]
    legs = 0.08 + 0.32 * u[:, 1]
    ids = b.add_objects(
        np.c_[xy, z], 0.0, np.c_[np.zeros((k, 3)), tops, legs], np.floor(u[:, 3] * 2**31).astype(np.int64)
    )
    b.add_prisms(np.c_[xy, z], 0.2 + 0.08 * u[:, 2], 1.55 + 0.35 * u[:, 3], M.PERSON, ids, sides=8)


def add_fence(
    b: MeshBuilder,
    p0: np.ndarray,
    p1: np.ndarray,
    z: np.ndarray | float,
    height: float,
    style: int,
    rng: np.random.Generator,
    free: Canvas | None = None,
    tone: float = 0.0,
) -> None:
    """Straight fence panels from p0 to p1 (K each): 0 chain-link, 1 wooden planks, 2 metal palisade."""
    p0 = np.atleast_2d(p0)
    p1 = np.atleast_2d(p1)
    k = len(p0)
    if k == 0:
        return
    z = _z(z, k)
    d = p1 - p0
    length = np.linalg.norm(d, axis=1)
    yaw = np.arctan2(d[:, 1], d[:, 0])
    mid = (p0 + p1) / 2
    params = np.c_[np.full(k, tone), np.zeros((k, 4)), np.full(k, style)]
    b.add_boxes(
        np.c_[mid, z],
        np.c_[length, np.full(k, 0.05), np.full(k, height)],
        yaw,
        M.FENCE,
        params=params,
        seed=rng.integers(0, 2**31, k),
    )
    # posts every ~3 m
    n = np.maximum(np.ceil(length / 3.0).astype(int), 1)
    t = np.concatenate([np.linspace(0, 1, m + 1) for m in n])
    base = np.repeat(p0, n + 1, axis=0) + t[:, None] * np.repeat(d, n + 1, axis=0)
    pid = b.add_objects(np.c_[base[:1], [0.0]], 0.0, np.array([[0, 0, 0, 0.3]]), 0)
    b.add_prisms(np.c_[base, np.repeat(z, n + 1)], 0.05, height + 0.1, M.METAL, pid[0], sides=4)
    if free is not None:
        free.polygons(strip_polys(p0, p1, 0.8), 0)


def add_benches(
    b: MeshBuilder,
    xy: np.ndarray,
    z: np.ndarray | float,
    yaw: np.ndarray,
    rng: np.random.Generator,
    free: Canvas | None = None,
) -> None:
    xy = np.atleast_2d(xy)
    k = len(xy)
    if k == 0:
        return
    z = _z(z, k)
    b.add_boxes(np.c_[xy, z + 0.4], np.array([1.8, 0.5, 0.08]), yaw, M.WOOD, seed=rng.integers(0, 2**31, k))
    c, s = np.cos(yaw), np.sin(yaw)
    back = xy - 0.22 * np.c_[-s, c]
    b.add_boxes(
        np.c_[back, z + 0.5], np.array([1.8, 0.06, 0.45]), yaw, M.WOOD, seed=rng.integers(0, 2**31, k)
    )
    b.add_boxes(np.c_[xy, z], np.array([1.5, 0.4, 0.4]), yaw, M.METAL, seed=rng.integers(0, 2**31, k))
    if free is not None:
        free.circles(xy, 1.0, 0)
