"""Vectorised triangle-mesh builders for the procedural worlds (boxes, prisms, cones, blobs, height fields).

Every triangle carries a material id and an object id. Objects carry a local frame (origin at the centre of the
base, rotated by a yaw about z), a parameter row (see `placerec.sim.materials`) and a seed, so textures can be
evaluated in object coordinates. Closed shapes are wound counter-clockwise seen from outside, so ray-cast normals
point outwards.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from placerec.sim.materials import PARAM_COUNT

__all__ = ["MeshBuilder", "MeshArrays", "yaw_matrices", "euler_rotation"]


@dataclass
class MeshArrays:
    vertices: np.ndarray  # (V, 3) float32
    triangles: np.ndarray  # (T, 3) uint32
    tri_material: np.ndarray  # (T,) uint8
    tri_object: np.ndarray  # (T,) int32
    obj_rot: np.ndarray  # (M, 3, 3) float32, world -> local rotation
    obj_origin: np.ndarray  # (M, 3) float64
    obj_params: np.ndarray  # (M, PARAM_COUNT) float32
    obj_seed: np.ndarray  # (M,) uint32


def yaw_matrices(yaw: np.ndarray) -> np.ndarray:
    """(K, 3, 3) rotations about z (local -> world)."""
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.zeros((len(yaw), 3, 3))
    R[:, 0, 0] = c
    R[:, 0, 1] = -s
    R[:, 1, 0] = s
    R[:, 1, 1] = c
    R[:, 2, 2] = 1.0
    return R


_BOX_CORNERS = np.array([[x, y, z] for z in (0, 1) for y in (-1, 1) for x in (-1, 1)], dtype=np.float64)
# faces as quads (outward CCW): bottom, top, -y, +y, -x, +x
_BOX_QUADS = np.array([[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]])
_BOX_TRIS = np.concatenate([_BOX_QUADS[:, [0, 1, 2]], _BOX_QUADS[:, [0, 2, 3]]], axis=0)
_BOX_TRI_FACE = np.concatenate([np.arange(6), np.arange(6)])  # face index of each triangle


@functools.lru_cache(maxsize=4)
def _icosphere(subdiv: int) -> tuple[np.ndarray, np.ndarray]:
    t = (1.0 + 5**0.5) / 2.0
    v = [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
         [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]]  # fmt: skip
    f = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
         [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11],
         [6, 2, 10], [8, 6, 7], [9, 8, 1]]  # fmt: skip
    verts = [np.array(p, float) / np.linalg.norm(p) for p in v]
    faces = f
    for _ in range(subdiv):
        cache: dict[tuple[int, int], int] = {}
        new = []
        for a, b, c in faces:
            mids = []
            for p, q in ((a, b), (b, c), (c, a)):
                key = (min(p, q), max(p, q))
                if key not in cache:
                    m = verts[p] + verts[q]
                    verts.append(m / np.linalg.norm(m))
                    cache[key] = len(verts) - 1
                mids.append(cache[key])
            ab, bc, ca = mids
            new += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        faces = new
    return np.array(verts), np.array(faces)


def euler_rotation(
    yaw: np.ndarray | float, pitch: np.ndarray | float, roll: np.ndarray | float
) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from Z-Y-X Euler angles in radians (yaw about z, then pitch about y, roll
    about x); the angles broadcast against each other."""
    yaw, pitch, roll = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (yaw, pitch, roll)))
    cy, sy, cp, sp, cr, sr = (
        np.cos(yaw),
        np.sin(yaw),
        np.cos(pitch),
        np.sin(pitch),
        np.cos(roll),
        np.sin(roll),
    )
    R = np.empty(yaw.shape + (3, 3))
    R[..., 0, :] = np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1)
    R[..., 1, :] = np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1)
    R[..., 2, :] = np.stack([-sp, cp * sr, cp * cr], -1)
    return R


class MeshBuilder:
    """Accumulates triangles, per-triangle material/object ids and object frames; `build` concatenates them."""

    def __init__(self, object_offset: int = 0) -> None:
        self._verts: list[np.ndarray] = []
        self._tris: list[np.ndarray] = []
        self._mat: list[np.ndarray] = []
        self._obj: list[np.ndarray] = []
        self._nv = 0
        self._origins: list[np.ndarray] = []
        self._yaws: list[np.ndarray] = []
        self._params: list[np.ndarray] = []
        self._seeds: list[np.ndarray] = []
        self._nobj = 0
        self.object_offset = object_offset

    @property
    def n_objects(self) -> int:
        return self._nobj

    def add_objects(
        self,
        origin: ArrayLike,
        yaw: ArrayLike = 0.0,
        params: ArrayLike | None = None,
        seed: ArrayLike = 0,
    ) -> np.ndarray:
        """Register K objects; returns their ids (with ``object_offset`` added)."""
        origin = np.atleast_2d(np.asarray(origin, dtype=np.float64))
        k = origin.shape[0]
        yaw = np.broadcast_to(np.asarray(yaw, dtype=np.float64), (k,)).copy()
        prm = np.zeros((k, PARAM_COUNT), np.float32)
        if params is not None:
            p = np.atleast_2d(np.asarray(params, dtype=np.float32))
            prm[:, : p.shape[1]] = p
        seeds = np.broadcast_to(np.asarray(seed).astype(np.int64).astype(np.uint32), (k,)).copy()
        self._origins.append(origin)
        self._yaws.append(yaw)
        self._params.append(prm)
        self._seeds.append(seeds)
        ids = np.arange(self._nobj, self._nobj + k) + self.object_offset
        self._nobj += k
        return ids

    def add_ground_plane(
        self, x0: float, y0: float, x1: float, y1: float, material: int, margin: float = 400.0
    ) -> int:
        """A flat ground quad at z = 0 over the site's box grown by ``margin`` m (so the horizon is ground, not
        sky), as one object at the origin; returns its id."""
        obj = int(self.add_objects(np.zeros((1, 3)))[0])
        corners = [[x0 - margin, y0 - margin], [x1 + margin, y0 - margin], [x1 + margin, y1 + margin]]
        corners.append([x0 - margin, y1 + margin])
        verts = np.c_[np.asarray(corners, dtype=np.float64), np.zeros(4)]
        self.add_mesh(verts, np.array([[0, 1, 2], [0, 2, 3]]), material, obj)
        return obj

    def add_mesh(
        self, verts: np.ndarray, tris: np.ndarray, material: np.ndarray | int, obj: np.ndarray | int
    ) -> None:
        """Add raw triangles (``tris`` index into ``verts``)."""
        tris = np.asarray(tris, dtype=np.int64).reshape(-1, 3)
        n = tris.shape[0]
        self._verts.append(np.asarray(verts, dtype=np.float64).reshape(-1, 3))
        self._tris.append(tris + self._nv)
        self._mat.append(np.broadcast_to(np.asarray(material, dtype=np.uint8), (n,)).copy())
        self._obj.append(np.broadcast_to(np.asarray(obj, dtype=np.int32), (n,)).copy())
        self._nv += self._verts[-1].shape[0]

    def add_boxes(
        self,
        base: ArrayLike,
        size: ArrayLike,
        yaw: ArrayLike,
        side_mat: ArrayLike,
        top_mat: ArrayLike | None = None,
        obj: ArrayLike | None = None,
        params: ArrayLike | None = None,
        seed: ArrayLike = 0,
        bottom: bool = False,
    ) -> np.ndarray:
        """K oriented boxes: ``base`` = centre of the bottom face, ``size`` = (length x, width y, height z).

        Without ``obj`` each box becomes its own object whose parameter row starts with (hx, hy, h) followed by
        ``params``. Returns the object id of every box.
        """
        base = np.atleast_2d(np.asarray(base, dtype=np.float64))
        size = np.atleast_2d(np.asarray(size, dtype=np.float64))
        k = base.shape[0]
        size = np.broadcast_to(size, (k, 3))
        yaw = np.broadcast_to(np.asarray(yaw, dtype=np.float64), (k,))
        if obj is None:
            prm = np.zeros((k, PARAM_COUNT), np.float32)
            prm[:, 0] = size[:, 0] / 2
            prm[:, 1] = size[:, 1] / 2
            prm[:, 2] = size[:, 2]
            if params is not None:
                p = np.atleast_2d(np.asarray(params, dtype=np.float32))
                prm[:, 3 : 3 + p.shape[1]] = p
            obj = self.add_objects(base, yaw, prm, seed)
        obj = np.broadcast_to(np.asarray(obj, dtype=np.int32), (k,))
        local = (
            _BOX_CORNERS[None, :, :]
            * np.stack([size[:, 0] / 2, size[:, 1] / 2, size[:, 2]], axis=1)[:, None, :]
        )
        R = yaw_matrices(yaw)
        verts = np.einsum("kij,kvj->kvi", R, local) + base[:, None, :]
        faces = _BOX_TRIS if bottom else _BOX_TRIS[_BOX_TRI_FACE != 0]
        tri_face = _BOX_TRI_FACE if bottom else _BOX_TRI_FACE[_BOX_TRI_FACE != 0]
        tris = faces[None, :, :] + 8 * np.arange(k)[:, None, None]
        side = np.broadcast_to(np.asarray(side_mat, dtype=np.uint8), (k,))
        top = side if top_mat is None else np.broadcast_to(np.asarray(top_mat, dtype=np.uint8), (k,))
        mats = np.where((tri_face == 1)[None, :], top[:, None], side[:, None])
        objs = np.repeat(obj[:, None], len(faces), axis=1)
        self.add_mesh(verts.reshape(-1, 3), tris.reshape(-1, 3), mats.reshape(-1), objs.reshape(-1))
        return obj

    def add_prisms(
        self,
        base: np.ndarray,
        radius: np.ndarray | float,
        height: np.ndarray | float,
        material: np.ndarray | int,
        obj: np.ndarray | int,
        sides: int = 8,
        top_radius: np.ndarray | float | None = None,
        cap_material: np.ndarray | int | None = None,
    ) -> None:
        """K vertical prisms (cylinders) or, with ``top_radius`` < radius, frusta/cones."""
        base = np.atleast_2d(np.asarray(base, dtype=np.float64))
        k = base.shape[0]
        r0 = np.broadcast_to(np.asarray(radius, dtype=np.float64), (k,))
        r1 = r0 if top_radius is None else np.broadcast_to(np.asarray(top_radius, dtype=np.float64), (k,))
        h = np.broadcast_to(np.asarray(height, dtype=np.float64), (k,))
        a = 2 * np.pi * np.arange(sides) / sides
        ca, sa = np.cos(a), np.sin(a)
        ring0 = np.stack([ca[None] * r0[:, None], sa[None] * r0[:, None], np.zeros((k, sides))], -1)
        ring1 = np.stack(
            [ca[None] * r1[:, None], sa[None] * r1[:, None], np.repeat(h[:, None], sides, 1)], -1
        )
        top_c = np.stack([np.zeros(k), np.zeros(k), h], -1)[:, None, :]
        verts = np.concatenate([ring0, ring1, top_c], axis=1) + base[:, None, :]
        i = np.arange(sides)
        j = (i + 1) % sides
        side_tris = np.concatenate([np.stack([i, j, sides + j], 1), np.stack([i, sides + j, sides + i], 1)])
        cap = np.stack([np.full(sides, 2 * sides), sides + i, sides + j], 1)
        nv = 2 * sides + 1
        tris = np.concatenate([side_tris, cap])[None] + nv * np.arange(k)[:, None, None]
        mat = np.broadcast_to(np.asarray(material, dtype=np.uint8), (k,))
        capm = (
            mat if cap_material is None else np.broadcast_to(np.asarray(cap_material, dtype=np.uint8), (k,))
        )
        mats = np.concatenate(
            [np.repeat(mat[:, None], 2 * sides, 1), np.repeat(capm[:, None], sides, 1)], axis=1
        )
        objs = np.repeat(np.broadcast_to(np.asarray(obj, dtype=np.int32), (k,))[:, None], 3 * sides, 1)
        self.add_mesh(verts.reshape(-1, 3), tris.reshape(-1, 3), mats.reshape(-1), objs.reshape(-1))

    def add_blobs(
        self,
        center: np.ndarray,
        radii: np.ndarray,
        material: np.ndarray | int,
        obj: np.ndarray | int,
        rng: np.random.Generator,
        jitter: float = 0.25,
        subdiv: int = 1,
    ) -> None:
        """K irregular ellipsoids (tree crowns, bushes, heaps): icospheres with radially jittered vertices."""
        center = np.atleast_2d(np.asarray(center, dtype=np.float64))
        k = center.shape[0]
        radii = np.broadcast_to(
            np.asarray(radii, dtype=np.float64).reshape(-1, 3)
            if np.ndim(radii) > 1
            else np.asarray(radii, dtype=np.float64),
            (k, 3),
        )
        uv, uf = _icosphere(subdiv)
        scale = 1.0 + jitter * (rng.random((k, uv.shape[0])) - 0.5) * 2.0
        verts = uv[None] * scale[:, :, None] * radii[:, None, :] + center[:, None, :]
        tris = uf[None] + uv.shape[0] * np.arange(k)[:, None, None]
        n = uf.shape[0]
        mats = np.repeat(np.broadcast_to(np.asarray(material, dtype=np.uint8), (k,))[:, None], n, 1)
        objs = np.repeat(np.broadcast_to(np.asarray(obj, dtype=np.int32), (k,))[:, None], n, 1)
        self.add_mesh(verts.reshape(-1, 3), tris.reshape(-1, 3), mats.reshape(-1), objs.reshape(-1))

    def add_heightfield(self, xs: np.ndarray, ys: np.ndarray, z: np.ndarray, material: int, obj: int) -> None:
        """A terrain grid: ``z[j, i]`` is the height at (xs[i], ys[j]); triangles face up."""
        X, Y = np.meshgrid(xs, ys)
        verts = np.stack([X, Y, z], -1).reshape(-1, 3)
        nx = len(xs)
        jj, ii = np.meshgrid(np.arange(len(ys) - 1), np.arange(nx - 1), indexing="ij")
        a = (jj * nx + ii).reshape(-1)
        b, c, d = a + 1, a + nx + 1, a + nx
        tris = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
        self.add_mesh(verts, tris, material, obj)

    def build(self) -> MeshArrays:
        """Concatenate everything added so far."""
        if self._verts:
            verts = np.concatenate(self._verts).astype(np.float32)
            tris = np.concatenate(self._tris).astype(np.uint32)
            mat = np.concatenate(self._mat)
            obj = np.concatenate(self._obj)
        else:
            verts = np.zeros((0, 3), np.float32)
            tris = np.zeros((0, 3), np.uint32)
            mat = np.zeros(0, np.uint8)
            obj = np.zeros(0, np.int32)
        if self._origins:
            origin = np.concatenate(self._origins)
            yaw = np.concatenate(self._yaws)
            rot = np.transpose(yaw_matrices(yaw), (0, 2, 1)).astype(np.float32)
            params = np.concatenate(self._params)
            seeds = np.concatenate(self._seeds)
        else:
            origin = np.zeros((0, 3))
            rot = np.zeros((0, 3, 3), np.float32)
            params = np.zeros((0, PARAM_COUNT), np.float32)
            seeds = np.zeros(0, np.uint32)
        return MeshArrays(verts, tris, mat, obj, rot, origin, params, seeds)
