"""Map/query splits for global localisation experiments, after the ISHOT paper's evaluation.

A **map** sequence drives a route through the world; each **query** set holds static scans taken within
``max_offset`` (10 m) of that route, at a free spot, with a random heading, at a later time (so parked and moving
clutter differs), with the same physical sensor unit (same per-beam response). Conditions:

* ``gator`` — the mapping vehicle's sensor height, no occlusion (the paper's easy set);
* ``pole`` — the sensor held on a pole at heights between 0.8 m and 2.5 m, gravity aligned (viewpoint change);
* ``occlusion`` — the vehicle's sensor height with near-sensor occluders: pillars, walls, a van alongside, a roof.

Ground truth: every query's pose (``queries[c].poses``) and its nearest map scan (`LocalizationSplit.nearest_map`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from placerec.errors import ConfigError
from placerec.sim.routes import Route, poses_from_xy_yaw
from placerec.sim.sensors import SensorModel
from placerec.sim.sequence import SimulatedSequence

__all__ = ["CONDITIONS", "LocalizationSplit", "make_localization_split"]

CONDITIONS = ("gator", "pole", "occlusion")


@dataclass
class LocalizationSplit:
    """A mapping sequence and one query sequence per condition."""

    map: SimulatedSequence
    queries: dict[str, SimulatedSequence]

    def nearest_map(self, condition: str) -> tuple[np.ndarray, np.ndarray]:
        """(index of the nearest map scan, its horizontal distance in m) for every query of ``condition``."""
        q = self.queries[condition].poses[:, :2, 3]
        m = self.map.poses[:, :2, 3]
        d = np.linalg.norm(q[:, None, :] - m[None, :, :], axis=2)
        idx = np.argmin(d, axis=1)
        return idx, d[np.arange(len(q)), idx]


def make_localization_split(
    preset: str = "town",
    sensor: str | SensorModel = "vlp16",
    seed: int = 0,
    n_queries: int = 20,
    max_offset: float = 10.0,
    map_route: str = "default",
    n_map: int | None = None,
    conditions: tuple[str, ...] = CONDITIONS,
    draw: int = 0,
) -> LocalizationSplit:
    """Build the map sequence and ``n_queries`` query scans per condition (see the module docstring).

    ``draw`` > 0 draws another set of query spots, headings and clutter in the same world (e.g. training scans
    for the vote model, `placerec.artifacts.votes`); 0 is the evaluation set."""
    unknown = set(conditions) - set(CONDITIONS)
    if unknown:
        raise ConfigError(
            f"sim.localization.conditions: unknown {sorted(unknown)}; allowed: {list(CONDITIONS)}"
        )
    mapping = SimulatedSequence(world=preset, sensor=sensor, n_scans=n_map, seed=seed, route=map_route)
    world = mapping.world
    mxy = mapping.poses[:, :2, 3]
    queries: dict[str, SimulatedSequence] = {}
    for c_idx, cond in enumerate(CONDITIONS):
        if cond not in conditions:
            continue
        rng = np.random.default_rng([int(seed), c_idx, 0x10C] + ([int(draw)] if draw else []))
        xy: list[np.ndarray] = []
        for _ in range(200 * n_queries):
            if len(xy) == n_queries:
                break
            base = mxy[int(rng.integers(len(mxy)))]
            r = max_offset * np.sqrt(rng.random())
            a = rng.uniform(-np.pi, np.pi)
            p = base + r * np.array([np.cos(a), np.sin(a)])
            near = np.min(np.linalg.norm(mxy - p, axis=1))
            if near <= max_offset and bool(world.free.is_free(p[0], p[1])):
                xy.append(p)
        if len(xy) < n_queries:
            raise ConfigError(f"sim.localization: found only {len(xy)} free query spots for {cond}")
        pts = np.stack(xy)
        yaw = rng.uniform(-np.pi, np.pi, n_queries)
        height = (
            rng.uniform(0.8, 2.5, n_queries)
            if cond == "pole"
            else np.full(n_queries, mapping.sensor.mount_height)
        )
        poses = poses_from_xy_yaw(pts, world.ground_height(pts[:, 0], pts[:, 1]) + height, yaw)
        times = 86400.0 * (c_idx + 1) + 601.0 * np.arange(n_queries)
        route = Route(poses=poses, timestamps=times, name=cond)
        suffix = f"-draw{draw}" if draw else ""
        queries[cond] = SimulatedSequence(
            world=world, sensor=mapping.sensor, seed=int(seed) * 1000 + c_idx + 1 + 100 * int(draw), route=route,
            occluders=cond == "occlusion", unit_seed=mapping.spec.unit_seed, name=f"{mapping.name}-query-{cond}{suffix}",
        )  # fmt: skip
    return LocalizationSplit(map=mapping, queries=queries)
