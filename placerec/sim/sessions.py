"""Two sessions over one world, for maps that outlive a session: a mapping drive and a later drive to localise or
join against it, with the ground truth of where the second session overlaps the first.

Both sessions see the **same static world** (one world seed: the same `World`, triangle for triangle) with the
**same physical sensor unit** (one ``unit_seed``), and their ground-truth poses are in that world's frame. The
second session is driven a day later (timestamps from ``query_t0`` = 86 400 s) with its own ``query_seed``: moving
cars and pedestrians are elsewhere, the kerbside and lot slots are re-drawn (other parked cars), and every scan's
noise differs. The routes are planned on the road graph like the other routes (`placerec.sim.routes`: smoothed,
sampled every ``spacing`` metres, default 1 m); the second drive's samples are shifted by half a step
(``phase=0.5``), so its scans never sit exactly on the map's.

Kinds (anchor-relative road-graph nodes, `LAYOUTS`; ``M`` is the map's plan, the loop around the 2 x 2 blocks next
to the anchor, counter-clockwise, (0,0) (1,0) (2,0) (2,1) (2,2) (1,2) (0,2) (0,1) (0,0): 350 scans in the town
preset, seed 0):

* ``revisit`` — ``M`` again, same streets, same direction, same lane: every query scan overlaps.
* ``partial`` — ``M`` up to (2,2), then (3,2) (3,3) (2,3) (1,3) (0,3), streets the map never saw (through none of
  its nodes): **41 % of the query scans overlap in the town preset** (seed 0; 41-42 % for seeds 4601-4602),
  26-46 % in the campus and industrial presets.
* ``opposite`` — ``M`` backwards: every street in the opposite direction, on the other side of the road (one lane
  width, 3-3.75 m, from the map's lane); all of it overlaps, and the nearest map scan is turned more than 135 deg
  at 98-99 % of the scans (less only in corners).
* ``disjoint`` — (3,-1) (3,0) (3,1) (3,2) (3,3) (2,3) (1,3) (0,3) (-1,3): streets at least a block away from the
  map, touching none of its nodes; no scan overlaps ("sessions that never overlap stay separate").
* ``sensor`` — ``M`` again with another sensor (``query_sensor``, default ``os1-64``, or ``vlp16`` when the map
  is an OS1-64), mounted at that sensor's own height.

A world uses the first layout whose map loop has all its streets: the campus drops paths outside its core
(15 % of them, by seed) and then falls back to the loop around the core's 2 x 1 blocks. A missing street of the
query's new part is driven by a detour of at most 3 streets through nodes the map never visited, or skipped. When
the planned new streets cannot be driven at all, ``partial`` leaves the map from the node nearest (in the plan) to
the planned one and ``disjoint`` takes the longest walk through unvisited nodes, straight on where possible
(campus seeds 19 and 23). ``partial``'s new part is at most twice as many streets as its shared part.

Ground truth (`SessionPair`): ``map.poses`` and ``query.poses`` (``T_world_sensor``, one frame);
``nearest_map = (idx, dist)``: for every query scan the nearest map scan and its horizontal distance (m);
``overlap``: ``dist <= overlap_m`` (default 5 m), the "overlapping part of a second session";
``heading_diff``: the absolute heading difference to that nearest map scan (deg). `kidnap_trials` draws
relocalisation trials with a teleport inside the overlap.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from placerec.errors import ConfigError
from placerec.sim.clutter import ClutterConfig
from placerec.sim.odometry import OdometryDrift
from placerec.sim.routes import Node, Route, connect_waypoints, route_from_plan
from placerec.sim.sensors import SensorModel, get_sensor
from placerec.sim.sequence import SimulatedSequence
from placerec.sim.site import RoadGraph
from placerec.sim.world import World, build_world

__all__ = ["KINDS", "LAYOUTS", "Layout", "SessionPair", "KidnapTrial", "make_session_pair", "kidnap_trials"]

KINDS: tuple[str, ...] = ("revisit", "partial", "opposite", "disjoint", "sensor")


@dataclass(frozen=True)
class Layout:
    """Anchor-relative waypoints of a pair's routes: the map's loop (lane 0 on every leg), ``partial``'s share of
    it (the map's plan up to ``partial_until``) and its new streets, and ``disjoint``'s streets."""

    map: tuple[Node, ...]
    partial_until: Node
    partial_new: tuple[Node, ...]
    disjoint: tuple[Node, ...]


_FAR = ((3, -1), (3, 0), (3, 1), (3, 2), (3, 3), (2, 3), (1, 3), (0, 3), (-1, 3))
#: The layouts in order of preference; a world uses the first whose map loop has all its streets (the 2 x 2
#: blocks next to the anchor; the campus, which may drop paths outside its core, falls back to the core's 2 x 1).
LAYOUTS: tuple[Layout, ...] = (
    Layout(((0, 0), (1, 0), (2, 0), (2, 1), (2, 2), (1, 2), (0, 2), (0, 1), (0, 0)), (2, 2),
           ((3, 2), (3, 3), (2, 3), (1, 3), (0, 3)), _FAR),
    Layout(((0, 0), (1, 0), (2, 0), (2, 1), (1, 1), (0, 1), (0, 0)), (2, 0),
           ((3, 0), (3, 1), (3, 2), (2, 2), (1, 2), (0, 2)), _FAR),
)  # fmt: skip

#: The query session's seed is ``seed + QUERY_SEED_OFFSET`` unless given.
QUERY_SEED_OFFSET = 100_000


@dataclass
class SessionPair:
    """A mapping session, a second session over the same world, and where the second overlaps the first.

    ``nearest_map`` is ``(idx, dist)``: per query scan, the index of the nearest map scan and its horizontal
    distance (m); ``overlap`` is ``dist <= overlap_m``; ``heading_diff`` the absolute heading difference (deg) to
    that map scan. Poses of both sessions are ground truth in the world frame."""

    kind: str
    map: SimulatedSequence
    query: SimulatedSequence
    overlap_m: float
    overlap: np.ndarray
    nearest_map: tuple[np.ndarray, np.ndarray]
    heading_diff: np.ndarray

    @property
    def overlap_fraction(self) -> float:
        """The fraction of query scans in the overlap."""
        return float(self.overlap.mean()) if len(self.overlap) else 0.0

    def describe(self) -> dict:
        """A plain description (for logs and reports)."""
        return {"kind": self.kind, "world": self.map.world.preset, "world_seed": self.map.world.seed,
                "map": self.map.name, "query": self.query.name, "n_map": len(self.map), "n_query": len(self.query),
                "overlap_m": self.overlap_m, "overlap_fraction": round(self.overlap_fraction, 4)}  # fmt: skip


@dataclass(frozen=True)
class KidnapTrial:
    """One kidnapped-robot trial in ``pair.query``: scans ``indices`` in this order, the first ``teleport`` of
    them consecutive (tracking at one mapped place), then a teleport to another mapped place ``jump_m`` metres
    away (at least `kidnap_trials`' ``min_jump``) and consecutive scans from there. Every scan of a trial lies in
    the overlap; its ground truth is ``pair.query.poses[indices]`` (nearest map scans:
    ``pair.nearest_map[0][indices]``)."""

    indices: np.ndarray
    teleport: int
    jump_m: float

    @property
    def tracking(self) -> np.ndarray:
        """The query indices before the teleport."""
        return self.indices[: self.teleport]

    @property
    def after(self) -> np.ndarray:
        """The query indices from the teleport on (``after[0]`` is the first scan at the new place)."""
        return self.indices[self.teleport :]


def _plan(
    roads: RoadGraph, rel: tuple[Node, ...], avoid: set[Node] | None = None
) -> tuple[list[Node], list[int]]:
    """The plan through anchor-relative waypoints. The map (``avoid`` None) detours around its own waypoints;
    the new streets of a query (``avoid``: the map's nodes) detour by at most 3 streets around them and skip a
    waypoint they cannot reach so."""
    ai, aj = roads.anchor
    way = [(ai + i, aj + j) for i, j in rel]
    lanes = [0] * (len(way) - 1)
    if avoid is None:
        return connect_waypoints(roads, way, lanes, set(way))
    return connect_waypoints(roads, way, lanes, avoid, max_detour=3, drop_unreachable=True)


def _walk_away(roads: RoadGraph, start: Node, seen: set[Node], n_legs: int) -> list[Node]:
    """Up to ``n_legs`` streets from ``start`` through nodes not in ``seen`` nor visited yet, straight on where
    possible (else the first free neighbour in the graph's order)."""
    walk = [start]
    while len(walk) <= n_legs:
        cur = walk[-1]
        free = [m for m in roads.neighbours(cur) if m not in seen and m not in walk]
        if not free:
            break
        if len(walk) > 1:
            d = (cur[0] - walk[-2][0], cur[1] - walk[-2][1])
            free.sort(key=lambda m: (m[0] - cur[0], m[1] - cur[1]) != d)
        walk.append(free[0])
    return walk


def _layout(roads: RoadGraph) -> Layout:
    ai, aj = roads.anchor
    for lay in LAYOUTS:
        way = [(ai + i, aj + j) for i, j in lay.map]
        if all(roads.has_edge(a, b) for a, b in zip(way[:-1], way[1:], strict=True)):
            return lay
    return LAYOUTS[-1]


def _query_plan(
    roads: RoadGraph, lay: Layout, kind: str, map_nodes: list[Node], map_lanes: list[int]
) -> tuple[list[Node], list[int]]:
    if kind in ("revisit", "sensor"):
        return list(map_nodes), list(map_lanes)
    if kind == "opposite":
        return map_nodes[::-1], map_lanes[::-1]
    seen = set(map_nodes)
    if kind == "disjoint":
        new_nodes, new_lanes = _plan(roads, lay.disjoint, seen)
        if len(new_lanes) < 2:  # the planned streets are missing: the longest walk away from the map
            i_max, j_max = roads.nodes.shape[:2]
            starts = [(i, j) for i in range(i_max) for j in range(j_max) if (i, j) not in seen]
            walks = [_walk_away(roads, n, seen, len(map_lanes)) for n in starts]
            new_nodes = max(walks, key=len, default=[])
            new_lanes = [0] * max(len(new_nodes) - 1, 0)
        nodes, lanes = new_nodes, new_lanes
    else:
        ai, aj = roads.anchor
        cut = map_nodes.index((ai + lay.partial_until[0], aj + lay.partial_until[1]))
        new_nodes, new_lanes = _plan(roads, (lay.partial_until, *lay.partial_new), seen)
        if new_nodes[0] != map_nodes[cut] or len(new_lanes) < 2:  # cannot leave the map as planned
            for c in sorted(range(1, len(map_nodes) - 1), key=lambda c: abs(c - cut)):
                new_nodes = _walk_away(roads, map_nodes[c], seen, 2 * c)
                if len(new_nodes) >= 3:
                    cut, new_lanes = c, [0] * (len(new_nodes) - 1)
                    break
        new_nodes, new_lanes = (
            new_nodes[: 2 * cut + 1],
            new_lanes[: 2 * cut],
        )  # at most twice the shared streets
        nodes, lanes = map_nodes[: cut + 1] + new_nodes[1:], map_lanes[:cut] + new_lanes
    if len(new_lanes) < 2:
        raise ConfigError(
            f"sim.sessions.kind: {kind!r} needs >= 2 streets away from the map's; this world has {len(new_lanes)}"
        )
    return nodes, lanes


def make_session_pair(
    world: str | World = "town",
    sensor: str | SensorModel = "vlp16",
    seed: int = 0,
    kind: str = "revisit",
    n_scans: int | None = None,
    query_sensor: str | SensorModel | None = None,
    overlap_m: float = 5.0,
    query_seed: int | None = None,
    world_seed: int | None = None,
    unit_seed: int | None = None,
    query_t0: float = 86400.0,
    spacing: float = 1.0,
    rate_hz: float | None = None,
    clutter: bool | ClutterConfig = True,
    odometry_drift: OdometryDrift | float | bool | None = None,
    sweep_motion: bool = False,
    map_closes_loop: bool = False,
) -> SessionPair:
    """The two sessions of ``kind`` (see the module docstring) over ``world``.

    ``seed`` seeds the map session (and the world and the sensor unit unless ``world_seed`` / ``unit_seed``);
    ``query_seed`` (default ``seed + 100000``) the second session's noise and suspension motion, ``query_t0`` its
    start time (other clutter). ``n_scans`` cuts each session to at most that many scans (None: the whole plan;
    the overlap figures of the docstring are for whole plans). ``query_sensor`` defaults to ``sensor`` except for
    ``kind="sensor"``. ``spacing``/``rate_hz``, ``clutter``, ``odometry_drift`` and ``sweep_motion`` apply to
    both sessions as in `SimulatedSequence`. ``map_closes_loop``: the map session drives its loop's first street
    once more at the end (a same-direction revisit SLAM can close, as a mapping drive does); the second session's
    route is the same either way."""
    if kind not in KINDS:
        raise ConfigError(f"sim.sessions.kind: unknown kind {kind!r}; allowed: {list(KINDS)}")
    if n_scans is not None and n_scans < 1:
        raise ConfigError(f"sim.sessions.n_scans must be >= 1 or None, got {n_scans}")
    if not overlap_m > 0:
        raise ConfigError(f"sim.sessions.overlap_m must be > 0, got {overlap_m}")
    w = build_world(world, int(seed) if world_seed is None else int(world_seed))
    map_sensor = get_sensor(sensor)
    if query_sensor is None:
        query_sensor = (
            ("vlp16" if map_sensor.name == "os1-64" else "os1-64") if kind == "sensor" else map_sensor
        )
    q_sensor = get_sensor(query_sensor)
    if kind == "sensor" and q_sensor.name == map_sensor.name:
        raise ConfigError(
            f"sim.sessions.query_sensor: kind 'sensor' needs another sensor than {map_sensor.name!r}"
        )
    q_seed = int(seed) + QUERY_SEED_OFFSET if query_seed is None else int(query_seed)
    unit = int(seed) if unit_seed is None else int(unit_seed)
    roads = w.roads
    lay = _layout(roads)
    map_nodes, map_lanes = _plan(roads, lay.map)
    q_nodes, q_lanes = _query_plan(roads, lay, kind, map_nodes, map_lanes)

    def session(
        nodes, lanes, sens: SensorModel, s: int, t0: float, phase: float, role: str
    ) -> SimulatedSequence:
        route = route_from_plan(w, nodes, lanes, name=f"session-{kind}-{role}", spacing=spacing, rate_hz=rate_hz,
                                sensor_height=sens.mount_height, seed=s, t0=t0, phase=phase)  # fmt: skip
        if n_scans is not None:
            route = _cut(route, n_scans)
        return SimulatedSequence(world=w, sensor=sens, seed=s, route=route, clutter=clutter,
                                 odometry_drift=odometry_drift, spacing=spacing, rate_hz=rate_hz, unit_seed=unit,
                                 name=f"sim-{w.preset}-{sens.name}-session-{kind}-{role}-s{s}",
                                 sweep_motion=sweep_motion)  # fmt: skip

    if map_closes_loop:
        map_nodes, map_lanes = [*map_nodes, map_nodes[1]], [*map_lanes, map_lanes[0]]
    mapping = session(map_nodes, map_lanes, map_sensor, int(seed), 0.0, 0.0, "map")
    query = session(q_nodes, q_lanes, q_sensor, q_seed, float(query_t0), 0.5, "query")
    mxy, qxy = mapping.poses[:, :2, 3], query.poses[:, :2, 3]
    dist, idx = cKDTree(mxy).query(qxy)
    idx = np.asarray(idx, dtype=np.int64)
    dist = np.asarray(dist, dtype=np.float64)
    yaw_m = np.arctan2(mapping.poses[:, 1, 0], mapping.poses[:, 0, 0])
    yaw_q = np.arctan2(query.poses[:, 1, 0], query.poses[:, 0, 0])
    dyaw = np.degrees(np.abs((yaw_q - yaw_m[idx] + np.pi) % (2 * np.pi) - np.pi))
    overlap = dist <= overlap_m
    for arr in (idx, dist, dyaw, overlap):
        arr.setflags(write=False)
    return SessionPair(kind, mapping, query, float(overlap_m), overlap, (idx, dist), dyaw)


def _cut(route: Route, n: int) -> Route:
    if n >= len(route):
        return route
    return Route(route.poses[:n], route.timestamps[:n], route.name, [r for r in route.revisits if r.stop <= n],
                 None if route.arc_length is None else route.arc_length[:n], route.plan)  # fmt: skip


def kidnap_trials(
    pair: SessionPair,
    n_trials: int,
    seed: int = 0,
    before: int = 3,
    after: int = 5,
    min_jump: float = 50.0,
    places: np.ndarray | None = None,
) -> list[KidnapTrial]:
    """``n_trials`` kidnapped-robot trials in ``pair.query`` (see `KidnapTrial`): ``before`` consecutive scans of
    tracking at a random place of the overlap, then a teleport to a random place of the overlap at least
    ``min_jump`` metres (horizontally) from every tracked scan, and ``after`` consecutive scans there.

    ``places`` (increasing indices into ``pair.query``, e.g. the last scan of each of its keyframes): the trials
    run over those instead of every scan, each at the pose and overlap of its scan; the trials' ``indices`` are
    then indices into ``places``."""
    for name, v in (("n_trials", n_trials), ("before", before), ("after", after)):
        if int(v) < 1:
            raise ConfigError(f"sim.sessions.kidnap_trials.{name} must be >= 1, got {v}")
    n = len(pair.overlap)
    at = np.arange(n) if places is None else np.asarray(places, dtype=np.int64)
    inside = at.ndim == 1 and (at.size == 0 or (at[0] >= 0 and at[-1] < n and bool((np.diff(at) > 0).all())))
    if not inside:
        raise ConfigError(
            f"sim.sessions.kidnap_trials.places must be increasing indices of the {n} query scans"
        )
    ok = np.asarray(pair.overlap, dtype=np.int64)[at]
    run = np.concatenate([[0], np.cumsum(ok)])

    def starts(k: int) -> np.ndarray:
        return np.flatnonzero(run[k:] - run[:-k] == k) if len(ok) >= k else np.zeros(0, np.int64)

    s_before, s_after = starts(before), starts(after)
    xy = pair.query.poses[at, :2, 3]
    rng = np.random.default_rng([int(seed), 0x1D4A])
    trials: list[KidnapTrial] = []
    for _ in range(100 * n_trials):
        if len(trials) == n_trials or not len(s_before):
            break
        i = int(s_before[rng.integers(len(s_before))])
        track = xy[i : i + before]
        far = np.min(np.linalg.norm(xy[s_after][:, None, :] - track[None], axis=2), axis=1) >= min_jump
        if not far.any():
            continue
        j = int(s_after[far][rng.integers(int(far.sum()))])
        jump = float(np.linalg.norm(xy[j] - track[-1]))
        trials.append(KidnapTrial(np.r_[np.arange(i, i + before), np.arange(j, j + after)], before, jump))
    if len(trials) < n_trials:
        raise ConfigError(
            f"sim.sessions.kidnap_trials: the {pair.kind!r} pair has no {before}+{after} scan runs in its overlap "
            f"{min_jump} m apart (found {len(trials)} of {n_trials} trials)"
        )
    return trials
