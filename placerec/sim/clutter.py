"""Per-scan dynamic clutter: moving cars, pedestrians, cars in otherwise free parking slots, near-sensor occluders.

Clutter is not part of the static scene. For every scan a small mesh of the clutter near the sensor is built and
ray-cast in its own (tiny) scene; the nearer of the two hits wins. Moving agents follow the world's lanes and
walkways at constant speed as a function of the scan's timestamp, so consecutive scans see consistent motion and a
revisit minutes later sees other traffic. Free kerbside slots are occupied or not per 10-minute epoch.
Near-sensor occluders (the ISHOT paper's **occlusion** condition: pillars, walls, a van alongside, a roof above)
are drawn per scan from (seed, index).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from placerec.sim.geometry import MeshArrays, MeshBuilder
from placerec.sim.materials import M
from placerec.sim.noise import hash_unit
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


def _agents(world: World, cfg: ClutterConfig) -> dict[str, np.ndarray]:
    key = ("agents", cfg)
    if key in world.cache:
        return world.cache[key]
    rng = np.random.default_rng([world.seed, 0xA6E7])
    out: dict[str, np.ndarray] = {}
    for name, seg, density, vlo, vhi in (
        ("car", world.lanes, cfg.moving_cars_per_km, 5.0, 12.0),
        ("ped", world.walkways, cfg.pedestrians_per_km, 0.9, 1.7),
    ):
        if len(seg) == 0:
            out[name] = np.zeros((0, 3))
            out[name + "_u"] = np.zeros((0, 7))
            continue
        _, _, length = _segments(seg)
        n = rng.poisson(density * length / 1000.0)
        lane = np.repeat(np.arange(len(seg)), n)
        out[name] = np.c_[lane, rng.random(len(lane)) * length[lane], rng.uniform(vlo, vhi, len(lane))]
        out[name + "_u"] = rng.random((len(lane), 7))
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
            b.add_boxes(np.r_[xy, z], [rng.uniform(0.3, 0.8), rng.uniform(0.3, 0.8), rng.uniform(2.5, 4.0)], yaw + ang, M.CONCRETE, seed=int(rng.integers(2**31)))
        elif kind == "wall":
            dist = rng.uniform(2.0, 4.0)
            xy = to_world(dist * np.cos(ang), dist * np.sin(ang))
            z = world.ground_height(xy[0], xy[1])
            b.add_boxes(np.r_[xy, z], [0.25, rng.uniform(3.0, 7.0), rng.uniform(1.8, 3.0)], yaw + ang, M.STONE, seed=int(rng.integers(2**31)))
        elif kind == "van":
            side = rng.choice([-1.0, 1.0])
            xy = to_world(rng.uniform(-2.0, 2.0), side * rng.uniform(2.4, 3.2))
            z = world.ground_height(xy[0], xy[1])
            attrs = car_attributes(np.c_[np.zeros((1, 1)), rng.random((1, 6))], van_fraction=1.0)
            add_cars(b, xy[None], z, np.array([yaw]), attrs=attrs)
        else:  # a carport roof above the sensor on two posts
            h = o[2] + rng.uniform(0.6, 1.5)
            b.add_boxes(np.r_[o[:2], h], [6.0, 5.0, 0.25], yaw + ang, M.CORRUGATED, params=[[0.25, 0.12]], seed=int(rng.integers(2**31)))
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
        for name, seg in (("car", world.lanes), ("ped", world.walkways)):
            if len(ag[name]) == 0:
                continue
            xy, yaw = _positions(seg, ag[name], float(timestamp))
            dist = np.linalg.norm(xy - p, axis=1)
            near = (dist > config.min_distance) & (dist < config.radius)
            if not near.any():
                continue
            z = world.ground_height(xy[near, 0], xy[near, 1])
            if name == "car":
                add_cars(b, xy[near], z, yaw[near], attrs=car_attributes(ag["car_u"][near]))
            else:
                add_people(b, xy[near], z + float(world.info.get("walkway_z", 0.0)), ag["ped_u"][near][:, :4])
        slots = world.parking_slots
        if len(slots):
            epoch = int(np.floor(timestamp / config.epoch_seconds))
            k = np.arange(len(slots))
            occupied = hash_unit(k, epoch, world.seed, 0x51) < config.transient_parking
            dist = np.linalg.norm(slots[:, :2] - p, axis=1)
            sel = occupied & (dist > 3.5) & (dist < config.radius)
            if sel.any():
                u = np.stack([hash_unit(k[sel], epoch, c, 0x52) for c in range(7)], axis=1)
                z = world.ground_height(slots[sel, 0], slots[sel, 1])
                add_cars(b, slots[sel, :2], z, slots[sel, 2] + np.pi * (u[:, 0] < 0.5), attrs=car_attributes(u))
    if occluders:
        _occluders(b, world, pose, np.random.default_rng([int(seed), int(index), 0x0CC]))
    mesh = b.build()
    return mesh if len(mesh.triangles) else None
