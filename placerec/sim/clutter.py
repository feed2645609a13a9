"""Per-scan dynamic clutter: moving cars, pedestrians, cars in otherwise free parking slots, near-sensor occluders.

Clutter is not part of the static scene. For every scan a small mesh of the clutter near the sensor is built and
ray-cast in its own (tiny) scene; the nearer of the two hits wins. Moving agents follow the world's lanes and
walkways at constant speed as a function of the scan's timestamp, so consecutive scans see consistent motion and a
revisit minutes later sees other traffic. Free kerbside slots are occupied or not per 10-minute epoch.
Near-sensor occluders (the ISHOT paper's **occlusion** condition: pillars, walls, a van alongside, a roof above)
are drawn per scan from (seed, index).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from placerec.sim.geometry import MeshArrays, MeshBuilder
from placerec.sim.materials import M
from placerec.sim.noise import hash_u32, hash_unit
from placerec.sim.props import add_cars, add_people, car_attributes
from placerec.sim.world import World

__all__ = ["ClutterConfig", "build_clutter"]


@dataclass(frozen=True)
class ClutterConfig:
    """Densities of dynamic clutter. ``radius``: only clutter within this distance of the sensor is built."""

    moving_cars_per_km: float = 10.0
    pedestrians_per_km: float = 14.0
    transient_parking: float = 0.5
    epoch_seconds: float = 600.0
    radius: float = 70.0
    min_distance: float = 7.0


def _segments(seg: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    d = seg[:, 1] - seg[:, 0]
    length = np.linalg.norm(d, axis=1)
    return seg[:, 0], d / np.maximum(length, 1e-9)[:, None], length


@dataclass
class _Templates:
    """Meshes of K agents built once in their local frame (one object each), placed per scan by a rigid motion."""

    verts: np.ndarray  # (K, V, 3)
    tris: np.ndarray  # (K, T, 3) indices into the agent's own V vertices
    mats: np.ndarray  # (K, T)
    origin: np.ndarray  # (K, 3) object origin in the local frame
    params: np.ndarray  # (K, PARAM_COUNT)
    seeds: np.ndarray  # (K,)

    @classmethod
    def build(cls, add: Callable[..., object], k: int) -> _Templates:
        b = MeshBuilder()
        add(b, k)
        m = b.build()
        order = np.argsort(m.tri_object, kind="stable")
        tris = m.triangles[order].astype(np.int64).reshape(k, -1, 3)
        mats = m.tri_material[order].reshape(k, -1)
        verts, local = [], []
        for i in range(k):
            used, inv = np.unique(tris[i], return_inverse=True)
            verts.append(m.vertices[used])
            local.append(inv.reshape(-1, 3))
        return cls(
            np.stack(verts).astype(np.float64), np.stack(local), mats, m.obj_origin, m.obj_params, m.obj_seed
        )

    def place(self, b: MeshBuilder, idx: np.ndarray, xy: np.ndarray, z: np.ndarray, yaw: np.ndarray) -> None:
        k = len(idx)
        if k == 0:
            return
        c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
        v = self.verts[idx]
        out = np.empty_like(v)
        out[..., 0] = c * v[..., 0] - s * v[..., 1] + xy[:, 0:1]
        out[..., 1] = s * v[..., 0] + c * v[..., 1] + xy[:, 1:2]
        out[..., 2] = v[..., 2] + z[:, None]
        o = self.origin[idx]
        origin = np.c_[
            c[:, 0] * o[:, 0] - s[:, 0] * o[:, 1] + xy[:, 0],
            s[:, 0] * o[:, 0] + c[:, 0] * o[:, 1] + xy[:, 1],
            o[:, 2] + z,
        ]
        ids = b.add_objects(origin, yaw, self.params[idx], self.seeds[idx])
        nv = v.shape[1]
        tris = self.tris[idx] + (nv * np.arange(k))[:, None, None]
        b.add_mesh(
            out.reshape(-1, 3),
            tris.reshape(-1, 3),
            self.mats[idx].reshape(-1),
            np.repeat(ids, self.tris.shape[1]),
        )


_VARIANTS = 32  # looks of the cars that park in free slots


def _agents(world: World, cfg: ClutterConfig) -> dict:
    key = ("agents", cfg)
    if key in world.cache:
        return world.cache[key]
    rng = np.random.default_rng([world.seed, 0xA6E7])
    out: dict = {}
    for name, seg, density, vlo, vhi in (
        ("car", world.lanes, cfg.moving_cars_per_km, 5.0, 12.0),
        ("ped", world.walkways, cfg.pedestrians_per_km, 0.9, 1.7),
    ):
        n = np.zeros(0, int)
        if len(seg):
            _, _, length = _segments(seg)
            n = rng.poisson(density * length / 1000.0)
        lane = np.repeat(np.arange(len(n)), n)
        out[name] = np.c_[
            lane,
            rng.random(len(lane)) * (length[lane] if len(lane) else 0.0),
            rng.uniform(vlo, vhi, len(lane)),
        ]
        u = rng.random((len(lane), 7))
        if len(lane) == 0:
            out[name + "_tmpl"] = None
        elif name == "car":
            out[name + "_tmpl"] = _Templates.build(
                lambda b, k, u=u: add_cars(b, np.zeros((k, 2)), 0.0, np.zeros(k), attrs=car_attributes(u)),
                len(lane),
            )
        else:
            out[name + "_tmpl"] = _Templates.build(
                lambda b, k, u=u: add_people(b, np.zeros((k, 2)), 0.0, u[:, :4]), len(lane)
            )
    uv = np.stack([hash_unit(np.arange(_VARIANTS), c, world.seed, 0x52) for c in range(7)], axis=1)
    out["parked_tmpl"] = _Templates.build(
        lambda b, k: add_cars(b, np.zeros((k, 2)), 0.0, np.zeros(k), attrs=car_attributes(uv)), _VARIANTS
    )
    world.cache[key] = out
    return out


def _positions(seg: np.ndarray, agents: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
    a, d, length = _segments(seg)
    lane = agents[:, 0].astype(int)
    s = (agents[:, 1] + agents[:, 2] * t) % length[lane]
    return a[lane] + d[lane] * s[:, None], np.arctan2(d[lane, 1], d[lane, 0])


def _occluders(b: MeshBuilder, world: World, pose: np.ndarray, rng: np.random.Generator) -> None:
    yaw = np.arctan2(pose[1, 0], pose[0, 0])
    c, s = np.cos(yaw), np.sin(yaw)
    o = pose[:3, 3]

    def to_world(lx: float, ly: float) -> np.ndarray:
        return np.array([o[0] + c * lx - s * ly, o[1] + s * lx + c * ly])

    kinds = rng.choice(["pillar", "wall", "van", "roof"], size=int(rng.integers(2, 4)), replace=False)
    for kind in kinds:
        ang = rng.uniform(-np.pi, np.pi)
        if kind == "pillar":
            dist = rng.uniform(1.0, 2.5)
            xy = to_world(dist * np.cos(ang), dist * np.sin(ang))
            z = world.ground_height(xy[0], xy[1])
            b.add_boxes(
                np.r_[xy, z],
                [rng.uniform(0.3, 0.8), rng.uniform(0.3, 0.8), rng.uniform(2.5, 4.0)],
                yaw + ang,
                M.CONCRETE,
                seed=int(rng.integers(2**31)),
            )
        elif kind == "wall":
            dist = rng.uniform(2.0, 4.0)
            xy = to_world(dist * np.cos(ang), dist * np.sin(ang))
            z = world.ground_height(xy[0], xy[1])
            b.add_boxes(
                np.r_[xy, z],
                [0.25, rng.uniform(3.0, 7.0), rng.uniform(1.8, 3.0)],
                yaw + ang,
                M.STONE,
                seed=int(rng.integers(2**31)),
            )
        elif kind == "van":
            side = rng.choice([-1.0, 1.0])
            xy = to_world(rng.uniform(-2.0, 2.0), side * rng.uniform(2.4, 3.2))
            z = world.ground_height(xy[0], xy[1])
            attrs = car_attributes(np.c_[np.zeros((1, 1)), rng.random((1, 6))], van_fraction=1.0)
            add_cars(b, xy[None], z, np.array([yaw]), attrs=attrs)
        else:  # a carport roof above the sensor on two posts
            h = o[2] + rng.uniform(0.6, 1.5)
            b.add_boxes(
                np.r_[o[:2], h],
                [6.0, 5.0, 0.25],
                yaw + ang,
                M.CORRUGATED,
                params=[[0.25, 0.12]],
                seed=int(rng.integers(2**31)),
            )
            for lx in (-2.8, 2.8):
                xy = to_world(lx * np.cos(ang) - 2.3 * np.sin(ang), lx * np.sin(ang) + 2.3 * np.cos(ang))
                z = world.ground_height(xy[0], xy[1])
                b.add_boxes(np.r_[xy, z], [0.15, 0.15, h - z], yaw + ang, M.METAL, seed=1)


def build_clutter(
    world: World,
    pose: np.ndarray,
    timestamp: float,
    config: ClutterConfig | None,
    seed: int,
    index: int,
    occluders: bool = False,
) -> MeshArrays | None:
    """The clutter mesh around the sensor at ``pose`` (object ids continue after the world's), or None."""
    if config is None and not occluders:
        return None
    b = MeshBuilder(object_offset=world.n_objects)
    p = pose[:2, 3]
    if config is not None:
        ag = _agents(world, config)
        for name, seg, dz in (
            ("car", world.lanes, 0.0),
            ("ped", world.walkways, float(world.info.get("walkway_z", 0.0))),
        ):
            if ag[name + "_tmpl"] is None:
                continue
            xy, yaw = _positions(seg, ag[name], float(timestamp))
            dist = np.linalg.norm(xy - p, axis=1)
            near = np.flatnonzero((dist > config.min_distance) & (dist < config.radius))
            if len(near):
                z = world.ground_height(xy[near, 0], xy[near, 1]) + dz
                ag[name + "_tmpl"].place(b, near, xy[near], z, yaw[near])
        slots = world.parking_slots
        if len(slots):
            epoch = int(np.floor(timestamp / config.epoch_seconds))
            k = np.arange(len(slots))
            occupied = hash_unit(k, epoch, world.seed, 0x51) < config.transient_parking
            dist = np.linalg.norm(slots[:, :2] - p, axis=1)
            sel = np.flatnonzero(occupied & (dist > 3.5) & (dist < config.radius))
            if len(sel):
                variant = hash_u32(sel, epoch, world.seed, 0x53) % np.uint32(_VARIANTS)
                flip = hash_unit(sel, epoch, world.seed, 0x54) < 0.5
                z = world.ground_height(slots[sel, 0], slots[sel, 1])
                ag["parked_tmpl"].place(
                    b, variant.astype(np.int64), slots[sel, :2], z, slots[sel, 2] + np.pi * flip
                )
    if occluders:
        _occluders(b, world, pose, np.random.default_rng([int(seed), int(index), 0x0CC]))
    mesh = b.build()
    return mesh if len(mesh.triangles) else None
