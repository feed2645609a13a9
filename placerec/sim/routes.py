"""Routes through a simulated world, with revisits, and the ground truth of where the revisits are.

A route is planned on the world's road graph as a list of nodes (relative to the graph's anchor node) and a lane
per leg, turned into a smooth path (right-hand traffic: lane ``k`` is ``(k + 0.5) * lane_width`` right of the
centre line; corners are rounded with a ~6 m moving average, lane changes ramp over 25 m), given a speed profile
(``speed`` m/s on straights, at most 2 m/s^2 lateral acceleration in turns, 1.5 m/s^2 longitudinal) and sampled
every ``spacing`` metres (default 1 m) or at ``rate_hz`` (e.g. 10 Hz, the scan rate of a spinning LiDAR).

Route kinds (``ROUTES``):

* ``default`` — about 360 scans in the town preset. Anchor-relative nodes
  (0,0) (1,0) (1,1) (0,1) (0,0) | (1,0) (2,0) (2,1) (1,1) (1,0): a loop around one block, then the loop's first
  street again in the same direction but one lane to the left (lateral offset 3.5 m on the town's avenue), then
  three new streets (no revisits), then the loop's second street in the opposite direction (3.5 m apart).
  Intersections crossed twice give short "crossing" revisits.
* ``loop`` — the block loop driven twice in the same direction.
* ``long`` — ``default``, then a drive over streets not yet visited (long stretches without revisits) of about
  1.2 km, back to the anchor by the shortest way, and the block loop clockwise (opposite direction).

If ``n_scans`` asks for more scans than the plan gives, the route continues over unvisited streets; if fewer, it is
cut. `find_revisits` derives the revisit segments from the sampled poses themselves, so the description is
always exactly what the poses show.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from placerec.errors import ConfigError
from placerec.sim.geometry import euler_rotation
from placerec.sim.site import RoadGraph
from placerec.sim.world import World

__all__ = [
    "Revisit",
    "Route",
    "ROUTES",
    "make_route",
    "route_from_plan",
    "connect_waypoints",
    "find_revisits",
    "poses_from_xy_yaw",
]

Node = tuple[int, int]

_BLOCK = [(0, 0), (1, 0), (1, 1), (0, 1), (0, 0)]
ROUTES: dict[str, tuple[list[Node], list[int]]] = {
    "default": (_BLOCK + [(1, 0), (2, 0), (2, 1), (1, 1), (1, 0)], [0, 0, 0, 0, 1, 0, 0, 0, 0]),
    "loop": (_BLOCK + _BLOCK[1:], [0] * 8),
    "long": (_BLOCK + [(1, 0), (2, 0), (2, 1), (1, 1), (1, 0)], [0, 0, 0, 0, 1, 0, 0, 0, 0]),
}


@dataclass(frozen=True)
class Revisit:
    """Scans ``start..stop-1`` revisit the place of scans ``ref_start..ref_stop-1``.

    ``kind`` is ``same`` (heading within 45 deg of the earlier pass), ``opposite`` (beyond 135 deg) or ``crossing``;
    ``mean_distance`` is the mean distance (m) from each scan to its nearest earlier scan of the reference pass.
    """

    start: int
    stop: int
    ref_start: int
    ref_stop: int
    kind: str
    mean_distance: float

    def as_dict(self) -> dict:
        return {"start": self.start, "stop": self.stop, "ref_start": self.ref_start, "ref_stop": self.ref_stop,
                "kind": self.kind, "mean_distance": round(self.mean_distance, 3)}  # fmt: skip


@dataclass
class Route:
    """Poses ``T_world_sensor`` (N, 4, 4), timestamps (N,) and the revisit segments of a route."""

    poses: np.ndarray
    timestamps: np.ndarray
    name: str = "route"
    revisits: list[Revisit] = field(default_factory=list)
    arc_length: np.ndarray | None = None
    plan: list[Node] = field(default_factory=list)

    def __len__(self) -> int:
        return int(self.poses.shape[0])

    def describe(self) -> dict:
        """A plain description (for ``simulation.yaml`` and logs)."""
        length = float(self.arc_length[-1]) if self.arc_length is not None and len(self.arc_length) else 0.0
        return {"name": self.name, "n_scans": len(self), "length_m": round(length, 1), "plan_nodes": [list(n) for n in self.plan],
                "revisits": [r.as_dict() for r in self.revisits]}  # fmt: skip


def poses_from_xy_yaw(
    xy: np.ndarray,
    z: np.ndarray,
    yaw: np.ndarray,
    pitch: np.ndarray | None = None,
    roll: np.ndarray | None = None,
) -> np.ndarray:
    """(N, 4, 4) poses from positions and Z-Y-X Euler angles (yaw about z, then pitch about y, roll about x)."""
    n = len(xy)
    pitch = np.zeros(n) if pitch is None else pitch
    roll = np.zeros(n) if roll is None else roll
    T = np.zeros((n, 4, 4))
    T[:, :3, :3] = euler_rotation(yaw, pitch, roll)
    T[:, 0, 3] = xy[:, 0]
    T[:, 1, 3] = xy[:, 1]
    T[:, 2, 3] = z
    T[:, 3, 3] = 1.0
    return T


def _edge_key(a: Node, b: Node) -> tuple[Node, Node]:
    return (a, b) if a <= b else (b, a)


def _bfs(roads: RoadGraph, start: Node, goal_fn) -> list[Node]:
    prev: dict[Node, Node | None] = {start: None}
    q = deque([start])
    while q:
        n = q.popleft()
        if goal_fn(n) and n != start:
            path = [n]
            while (back := prev[path[-1]]) is not None:
                path.append(back)
            return path[::-1]
        for m in roads.neighbours(n):
            if m not in prev:
                prev[m] = n
                q.append(m)
    return [start]


def connect_waypoints(
    roads: RoadGraph,
    waypoints: list[Node],
    lanes: list[int],
    avoid: set[Node] | frozenset[Node] = frozenset(),
    max_detour: int | None = None,
    drop_unreachable: bool = False,
) -> tuple[list[Node], list[int]]:
    """A plan through ``waypoints`` (absolute nodes) with a lane per leg: a leg whose street exists is driven
    directly, a missing one (the campus drops some paths) by the shortest detour through nodes not in ``avoid``
    (at most ``max_detour`` streets; the detour keeps the leg's lane). A waypoint that cannot be reached so is
    skipped with ``drop_unreachable`` (the plan goes on to the next one; an unreachable first leg drops the first
    waypoint), else a `ConfigError`; so is a waypoint off the graph."""
    i_max, j_max = roads.nodes.shape[:2]
    for w in waypoints:
        if not (0 <= w[0] < i_max and 0 <= w[1] < j_max):
            raise ConfigError(f"sim.route: waypoint {w} is outside the road graph ({i_max} x {j_max} nodes)")
    nodes, out_lanes = [waypoints[0]], []
    for b, lane in zip(waypoints[1:], lanes, strict=True):
        a = nodes[-1]
        leg = _detour(roads, a, b, set(avoid) - {a, b}, max_detour)
        if leg is None:
            if not drop_unreachable:
                raise ConfigError(
                    f"sim.route: no street from {a} to {b} avoiding {sorted(set(avoid) - {a, b})}"
                )
            if len(nodes) == 1:
                nodes = [b]
            continue
        nodes.extend(leg[1:])
        out_lanes.extend([lane] * (len(leg) - 1))
    return nodes, out_lanes


def _detour(roads: RoadGraph, a: Node, b: Node, blocked: set[Node], max_len: int | None) -> list[Node] | None:
    """``[a, b]`` when the street exists, else the shortest path from a to b around ``blocked`` (None if there is
    none of at most ``max_len`` streets)."""
    if roads.has_edge(a, b):
        return [a, b]
    prev: dict[Node, Node | None] = {a: None}
    q = deque([a])
    while q and b not in prev:
        n = q.popleft()
        for m in roads.neighbours(n):
            if m not in prev and m not in blocked:
                prev[m] = n
                q.append(m)
    if b not in prev:
        return None
    leg = [b]
    while (back := prev[leg[-1]]) is not None:
        leg.append(back)
    return leg[::-1] if max_len is None or len(leg) - 1 <= max_len else None


def _extend(
    roads: RoadGraph, nodes: list[Node], lanes: list[int], metres: float, rng: np.random.Generator
) -> None:
    """Continue over unvisited edges (preferring straight on) for about ``metres``."""
    visited = {_edge_key(a, b) for a, b in zip(nodes[:-1], nodes[1:], strict=True)}
    added = 0.0
    while added < metres:
        cur, prev = nodes[-1], nodes[-2] if len(nodes) > 1 else None
        options = [m for m in roads.neighbours(cur) if _edge_key(cur, m) not in visited]
        if options:
            straight = [
                m
                for m in options
                if prev is not None and (m[0] - cur[0], m[1] - cur[1]) == (cur[0] - prev[0], cur[1] - prev[1])
            ]
            nxt = straight[0] if straight and rng.random() < 0.6 else options[int(rng.integers(len(options)))]
            step = [cur, nxt]
        else:
            step = _bfs(
                roads, cur, lambda n: any(_edge_key(n, m) not in visited for m in roads.neighbours(n))
            )
            if len(step) < 2:
                break
        for a, b in zip(step[:-1], step[1:], strict=True):
            nodes.append(b)
            lanes.append(0)
            visited.add(_edge_key(a, b))
            added += float(np.linalg.norm(np.diff(roads.polyline(a, b), axis=0), axis=1).sum())


def _densify(p: np.ndarray, step: float) -> np.ndarray:
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(int(np.ceil(s[-1] / step)), 1)
    t = np.linspace(0.0, s[-1], n + 1)
    return np.c_[np.interp(t, s, p[:, 0]), np.interp(t, s, p[:, 1])]


def _offset(p: np.ndarray, off: np.ndarray) -> np.ndarray:
    t = np.gradient(p, axis=0)
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-9)
    right = np.c_[t[:, 1], -t[:, 0]]
    return p + right * off[:, None]


def _join(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Join two offset legs at their corner: cut both at the intersection of their end lines (or U-turn)."""
    d1 = a[-1] - a[-2]
    d2 = b[1] - b[0]
    d1 /= np.linalg.norm(d1)
    d2 /= np.linalg.norm(d2)
    cross = d1[0] * d2[1] - d1[1] * d2[0]
    if abs(cross) < 0.1:
        if np.dot(d1, d2) > 0:
            return np.concatenate([a, b[1:]])
        c = (a[-1] + b[0]) / 2  # U-turn: a half circle
        r = np.linalg.norm(a[-1] - b[0]) / 2
        start = np.arctan2(*(a[-1] - c)[::-1])
        sign = np.sign(d1[0] * (b[0] - a[-1])[1] - d1[1] * (b[0] - a[-1])[0]) or 1.0
        ang = start + sign * np.linspace(0, np.pi, 9)[1:-1]
        return np.concatenate([a, c + r * np.c_[np.cos(ang), np.sin(ang)], b])
    w = b[0] - a[-1]
    t = (w[0] * d2[1] - w[1] * d2[0]) / cross
    x = a[-1] + t * d1
    m = min(len(a), 15)  # only the ends of the two legs may be cut, never earlier passes
    tail = a[-m:]
    head = b[:15]
    return np.concatenate(
        [a[:-m], tail[(tail - x) @ d1 < -1e-6], x[None], head[(head - x) @ d2 > 1e-6], b[15:]]
    )


def _smooth(p: np.ndarray, window: int, passes: int = 2) -> np.ndarray:
    k = np.ones(window) / window
    h = window // 2
    for _ in range(passes):
        head = p[0] + (p[0] - p[1 : h + 1][::-1])
        tail = p[-1] + (p[-1] - p[-h - 1 : -1][::-1])
        q = np.concatenate([head, p, tail])
        p = np.c_[np.convolve(q[:, 0], k, "valid"), np.convolve(q[:, 1], k, "valid")]
    return p


def _path(roads: RoadGraph, nodes: list[Node], lanes: list[int]) -> np.ndarray:
    path = None
    prev_off = None
    for (a, b), lane in zip(zip(nodes[:-1], nodes[1:], strict=True), lanes, strict=True):
        p = _densify(roads.polyline(a, b), 1.0)
        off = (lane + 0.5) * roads.lane_width
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
        offs = np.full(len(p), off)
        if prev_off is not None and prev_off != off:
            ramp = np.clip(s / min(25.0, s[-1] / 2), 0.0, 1.0)
            offs = prev_off + (off - prev_off) * ramp
        q = _offset(p, offs)
        path = q if path is None else _join(path, q)
        prev_off = off
    assert path is not None  # a route has at least one edge
    return _smooth(_densify(path, 0.5), 13)


def _speed_profile(s: np.ndarray, heading: np.ndarray, vmax: float) -> np.ndarray:
    ds = np.maximum(np.diff(s), 1e-6)
    kappa = np.abs(np.gradient(heading, s))
    v = np.minimum(vmax, np.sqrt(2.0 / np.maximum(kappa, 1e-6)))
    for i in range(1, len(v)):  # acceleration limit forwards and backwards
        v[i] = min(v[i], np.sqrt(v[i - 1] ** 2 + 2 * 1.5 * ds[i - 1]))
    for i in range(len(v) - 2, -1, -1):
        v[i] = min(v[i], np.sqrt(v[i + 1] ** 2 + 2 * 1.5 * ds[i]))
    return np.maximum(v, 1.0)


def make_route(
    world: World,
    kind: str = "default",
    n_scans: int | None = None,
    spacing: float = 1.0,
    rate_hz: float | None = None,
    sensor_height: float = 1.8,
    speed: float = 9.0,
    seed: int = 0,
    t0: float = 0.0,
) -> Route:
    """Plan, smooth and sample a route of ``kind`` (see the module docstring) in ``world``."""
    if kind not in ROUTES:
        raise ConfigError(f"sim.route: unknown route {kind!r}; allowed: {sorted(ROUTES)}")
    _check_sampling(spacing, rate_hz)
    roads = world.roads
    ai, aj = roads.anchor
    rel, lanes = ROUTES[kind]
    nodes = [(ai + i, aj + j) for i, j in rel]
    lanes = list(lanes)
    rng = np.random.default_rng([int(seed), 0x2077])
    if kind == "long":
        _extend(roads, nodes, lanes, 1200.0, rng)
        back = _bfs(roads, nodes[-1], lambda n: n == (ai, aj))
        for n in back[1:]:
            nodes.append(n)
            lanes.append(0)
        for n in [(ai, aj + 1), (ai + 1, aj + 1), (ai + 1, aj), (ai, aj)]:
            nodes.append(n)
            lanes.append(0)
    return _sample_route(
        world, nodes, lanes, kind, n_scans, spacing, rate_hz, sensor_height, speed, seed, t0, rng
    )


def route_from_plan(
    world: World,
    nodes: list[Node],
    lanes: list[int],
    name: str = "plan",
    n_scans: int | None = None,
    spacing: float = 1.0,
    rate_hz: float | None = None,
    sensor_height: float = 1.8,
    speed: float = 9.0,
    seed: int = 0,
    t0: float = 0.0,
    phase: float = 0.0,
) -> Route:
    """A route along an explicit plan: absolute road-graph ``nodes`` (each consecutive pair an edge) and a lane per
    leg, smoothed and sampled like `make_route`'s (``n_scans`` beyond the plan continues over unvisited streets).

    ``phase`` in [0, 1) shifts the samples by that fraction of a step (``phase * spacing`` metres, or
    ``phase / rate_hz`` seconds), so a second drive along the same plan does not take its scans at the very spots
    of the first."""
    if len(nodes) < 2 or len(lanes) != len(nodes) - 1:
        raise ConfigError(
            f"sim.route: a plan needs >= 2 nodes and one lane per leg, got {len(nodes)} nodes and {len(lanes)} lanes"
        )
    for a, b in zip(nodes[:-1], nodes[1:], strict=True):
        if not world.roads.has_edge(a, b):
            raise ConfigError(
                f"sim.route: the plan's leg {a} -> {b} is not a street of world {world.preset!r}"
            )
    _check_sampling(spacing, rate_hz, phase)
    rng = np.random.default_rng([int(seed), 0x2077])
    return _sample_route(
        world,
        list(nodes),
        list(lanes),
        name,
        n_scans,
        spacing,
        rate_hz,
        sensor_height,
        speed,
        seed,
        t0,
        rng,
        phase,
    )


def _check_sampling(spacing: float, rate_hz: float | None, phase: float = 0.0) -> None:
    if spacing <= 0 or (rate_hz is not None and rate_hz <= 0):
        raise ConfigError("sim.route: spacing and rate_hz must be positive")
    if not 0.0 <= phase < 1.0:
        raise ConfigError(f"sim.route: phase must be in [0, 1), got {phase}")


def _sample_route(
    world: World,
    nodes: list[Node],
    lanes: list[int],
    name: str,
    n_scans: int | None,
    spacing: float,
    rate_hz: float | None,
    sensor_height: float,
    speed: float,
    seed: int,
    t0: float,
    rng: np.random.Generator,
    phase: float = 0.0,
) -> Route:
    """Smooth the plan, sample it (extending it over unvisited streets while ``n_scans`` asks for more) and give
    each sample its pose on the terrain with a little suspension motion."""
    roads = world.roads
    for _ in range(50):
        xy, s, heading, v = _sample_path(roads, nodes, lanes, speed)
        t_of_s = np.concatenate([[0.0], np.cumsum(np.diff(s) / (0.5 * (v[1:] + v[:-1])))])
        if rate_hz is None:
            samples = np.arange(phase * spacing, s[-1], spacing)
        else:
            samples = np.interp(np.arange(phase / rate_hz, t_of_s[-1], 1.0 / rate_hz), t_of_s, s)
        if n_scans is None or len(samples) >= n_scans:
            break
        _extend(
            roads,
            nodes,
            lanes,
            (n_scans - len(samples)) * (spacing if rate_hz is None else speed / rate_hz) + 50.0,
            rng,
        )
    if n_scans is not None:
        samples = samples[:n_scans]
    px = np.interp(samples, s, xy[:, 0])
    py = np.interp(samples, s, xy[:, 1])
    yaw = np.interp(samples, s, heading)
    times = t0 + np.interp(samples, s, t_of_s)
    pxy = np.c_[px, py]
    z = world.ground_height(px, py)
    e = 0.5
    fx = (
        world.ground_height(px + e * np.cos(yaw), py + e * np.sin(yaw))
        - world.ground_height(px - e * np.cos(yaw), py - e * np.sin(yaw))
    ) / (2 * e)
    fy = (
        world.ground_height(px - e * np.sin(yaw), py + e * np.cos(yaw))
        - world.ground_height(px + e * np.sin(yaw), py - e * np.cos(yaw))
    ) / (2 * e)
    wob = np.random.default_rng([int(seed), 0x3B0B])
    wobble = wob.uniform(0, 2 * np.pi, 4)
    pitch = -np.arctan(fx) + np.radians(0.3) * np.sin(samples / 7.0 + wobble[0]) * np.sin(
        samples / 23.0 + wobble[1]
    )
    roll = np.arctan(fy) + np.radians(0.3) * np.sin(samples / 5.0 + wobble[2]) * np.sin(
        samples / 17.0 + wobble[3]
    )
    poses = poses_from_xy_yaw(pxy, z + sensor_height, yaw, pitch, roll)
    return Route(
        poses=poses,
        timestamps=times,
        name=name,
        revisits=find_revisits(poses, samples),
        arc_length=samples,
        plan=nodes,
    )


def _sample_path(
    roads: RoadGraph, nodes: list[Node], lanes: list[int], speed: float
) -> tuple[np.ndarray, ...]:
    xy = _path(roads, nodes, lanes)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    d = np.gradient(xy, axis=0)
    heading = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    return xy, s, heading, _speed_profile(s, heading, speed)


def find_revisits(
    poses: np.ndarray,
    arc_length: np.ndarray | None = None,
    radius: float = 6.0,
    min_gap: float = 50.0,
    min_scans: int = 3,
) -> list[Revisit]:
    """Revisit segments: runs of scans whose nearest earlier scan (at least ``min_gap`` metres of travel back) lies
    within ``radius`` metres, split where the kind or the reference pass changes."""
    xy = poses[:, :2, 3]
    n = len(xy)
    if arc_length is None:
        arc_length = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    yaw = np.arctan2(poses[:, 1, 0], poses[:, 0, 0])
    tree = cKDTree(xy)
    ref = np.full(n, -1)
    dist = np.full(n, np.inf)
    for i, js in enumerate(tree.query_ball_point(xy, radius)):
        js = np.asarray(js, dtype=int)
        js = js[(js < i) & (arc_length[i] - arc_length[js] > min_gap)] if len(js) else js
        if len(js):
            d = np.linalg.norm(xy[js] - xy[i], axis=1)
            k = int(np.argmin(d))
            ref[i], dist[i] = js[k], d[k]
    dyaw = np.abs((yaw - yaw[np.maximum(ref, 0)] + np.pi) % (2 * np.pi) - np.pi)
    kind = np.where(dyaw < np.pi / 4, 0, np.where(dyaw > 3 * np.pi / 4, 1, 2))
    names = ("same", "opposite", "crossing")
    out: list[Revisit] = []
    i = 0
    while i < n:
        if ref[i] < 0:
            i += 1
            continue
        j = i + 1
        while j < n and ref[j] >= 0 and kind[j] == kind[i] and abs(ref[j] - ref[j - 1]) <= 5:
            j += 1
        if j - i >= min_scans:
            r = ref[i:j]
            out.append(
                Revisit(i, j, int(r.min()), int(r.max()) + 1, names[int(kind[i])], float(dist[i:j].mean()))
            )
        i = j
    return out
