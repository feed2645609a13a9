"""Session pairs (`placerec.sim.sessions`): each kind's overlap, one static world with other clutter, determinism,
kidnap trials, bad arguments. Poses are cheap; only a few scans are rendered."""

from __future__ import annotations

import hashlib
import pickle

import numpy as np
import pytest

from placerec.errors import ConfigError
from placerec.sim import (
    ClutterConfig,
    SimulatedSequence,
    build_world,
    kidnap_trials,
    make_route,
    make_session_pair,
)
from placerec.sim.clutter import build_clutter
from placerec.sim.routes import route_from_plan
from placerec.sim.sessions import KINDS
from placerec.types import Scan, Sequence

WORLDS = ("town", "campus", "industrial")


def _digest(scan: Scan) -> str:
    return hashlib.sha256(scan.xyz.tobytes() + scan.intensity.tobytes() + scan.ring.tobytes()).hexdigest()


@pytest.mark.parametrize("world", WORLDS)
@pytest.mark.parametrize("kind", KINDS)
def test_each_kind_has_its_overlap(world: str, kind: str) -> None:
    pair = make_session_pair(world, "vlp16", seed=0, kind=kind)
    idx, dist = pair.nearest_map
    assert len(pair.overlap) == len(idx) == len(dist) == len(pair.query) > 100
    assert np.array_equal(pair.overlap, dist <= 5.0)
    assert np.all((idx >= 0) & (idx < len(pair.map)))
    mxy, qxy = pair.map.poses[:, :2, 3], pair.query.poses[:, :2, 3]
    brute = np.min(np.linalg.norm(qxy[:, None] - mxy[None], axis=2), axis=1)
    assert np.allclose(dist, brute)
    step = np.linalg.norm(np.diff(pair.query.poses[:, :3, 3], axis=0), axis=1)
    assert np.median(step) == pytest.approx(1.0, abs=0.03)  # sampled every metre, like the benchmark
    frac = pair.overlap_fraction
    if kind in ("revisit", "sensor"):
        assert frac > 0.9
        assert np.all(pair.heading_diff[pair.overlap] < 45.0)
    elif kind == "partial":
        assert 0.2 < frac < 0.8
        assert pair.overlap[0] and not pair.overlap[-1]  # the shared streets first, then new ones
    elif kind == "opposite":
        assert frac > 0.9
        # along the streets the headings are opposite; only in the corners is the nearest map scan turned less
        assert np.mean(pair.heading_diff[pair.overlap] > 135.0) >= 0.95
    else:
        assert frac == 0.0 and dist.min() > 5.0
    if kind == "sensor":
        assert pair.query.sensor.name == "os1-64" and pair.map.sensor.name == "vlp16"
    else:
        assert pair.query.sensor.name == "vlp16"


def test_one_static_world_one_unit_other_clutter() -> None:
    pair = make_session_pair("town", "vlp16", seed=0, kind="revisit")
    assert pair.map.world is pair.query.world
    assert pair.map.spec.world_seed == pair.query.spec.world_seed == 0
    assert pair.map.spec.unit_seed == pair.query.spec.unit_seed == 0
    assert pair.map.seed != pair.query.seed
    assert np.array_equal(pair.map.beam_response.gain, pair.query.beam_response.gain)
    assert pair.query.timestamps[0] >= 86400.0 > pair.map.timestamps[-1]
    # a second build of the same world has the same objects, triangle for triangle
    other = make_session_pair("town", "vlp16", seed=3, kind="revisit", world_seed=0)
    assert other.map.world is pair.map.world
    # the same place seen by both sessions: other moving and parked objects
    k = len(pair.query) // 2
    i = int(pair.nearest_map[0][k])
    cfg = ClutterConfig()
    pose = pair.query.poses[k]
    first = build_clutter(pair.map.world, pose, float(pair.map.timestamps[i]), cfg, pair.map.seed, i)
    second = build_clutter(pair.map.world, pose, float(pair.query.timestamps[k]), cfg, pair.query.seed, k)
    assert first is not None and second is not None
    assert first.vertices.shape != second.vertices.shape or not np.allclose(first.vertices, second.vertices)


def test_same_arguments_same_sessions() -> None:
    a = make_session_pair("town", "vlp16", seed=5, kind="partial", n_scans=30)
    b = make_session_pair("town", "vlp16", seed=5, kind="partial", n_scans=30)
    assert len(a.map) == len(a.query) == 30
    for x, y in ((a.map, b.map), (a.query, b.query)):
        assert isinstance(x, Sequence)
        assert np.array_equal(x.poses, y.poses) and np.array_equal(x.timestamps, y.timestamps)
        assert _digest(x[0]) == _digest(y[0])
    assert np.array_equal(a.overlap, b.overlap)
    assert _digest(a.map[0]) != _digest(a.query[0])  # another drive: other noise and clutter
    back = pickle.loads(pickle.dumps(a.query))
    assert isinstance(back, SimulatedSequence) and _digest(back[0]) == _digest(a.query[0])


def test_another_query_sensor() -> None:
    pair = make_session_pair("town", "os1-64", seed=0, kind="sensor", n_scans=5)
    assert pair.map.sensor.name == "os1-64" and pair.query.sensor.name == "vlp16"
    pair = make_session_pair("town", "vlp16", seed=0, kind="opposite", n_scans=5, query_sensor="hdl64")
    assert pair.query.sensor.name == "hdl64"
    assert pair.query.poses[0, 2, 3] != pair.map.poses[0, 2, 3]  # each sensor at its own mount height


def test_kidnap_trials_teleport_inside_the_overlap() -> None:
    pair = make_session_pair("town", "vlp16", seed=0, kind="partial")
    trials = kidnap_trials(pair, 20, seed=1)
    assert len(trials) == 20
    xy = pair.query.poses[:, :2, 3]
    for t in trials:
        assert t.teleport == 3 and len(t.indices) == 8
        assert np.all(np.diff(t.tracking) == 1) and np.all(np.diff(t.after) == 1)
        assert pair.overlap[t.indices].all()
        gap = np.linalg.norm(xy[t.after[0]] - xy[t.tracking], axis=1)
        assert gap.min() >= 50.0 and t.jump_m == pytest.approx(gap[-1])
    again = kidnap_trials(pair, 20, seed=1)
    assert all(np.array_equal(x.indices, y.indices) for x, y in zip(trials, again, strict=True))
    with pytest.raises(ConfigError, match="disjoint"):
        kidnap_trials(make_session_pair("town", "vlp16", seed=0, kind="disjoint"), 3)
    with pytest.raises(ConfigError, match="after"):
        kidnap_trials(pair, 3, after=0)
    # over places (every third scan, as keyframes' last scans): indices into the places, their poses and overlap
    places = np.arange(0, len(pair.query), 3)
    for t in kidnap_trials(pair, 10, seed=1, places=places):
        scans = places[t.indices]
        assert pair.overlap[scans].all() and np.all(np.diff(t.after) == 1)
        gap = np.linalg.norm(xy[scans[t.teleport]] - xy[scans[: t.teleport]], axis=1)
        assert gap.min() >= 50.0 and t.jump_m == pytest.approx(gap[-1])
    with pytest.raises(ConfigError, match="places"):
        kidnap_trials(pair, 3, places=places[::-1])


def test_plan_routes_sample_like_make_route() -> None:
    world = build_world("town", 0)
    loop = make_route(world, "loop", seed=2)
    again = route_from_plan(world, loop.plan, [0] * (len(loop.plan) - 1), name="loop", seed=2)
    assert np.array_equal(loop.poses, again.poses) and np.array_equal(loop.timestamps, again.timestamps)
    shifted = route_from_plan(world, loop.plan, [0] * (len(loop.plan) - 1), seed=2, phase=0.5)
    assert shifted.arc_length is not None and shifted.arc_length[0] == pytest.approx(0.5)
    ai, aj = world.roads.anchor
    with pytest.raises(ConfigError, match="not a street"):
        route_from_plan(world, [(ai, aj), (ai + 1, aj + 1)], [0])


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        (
            {"kind": "sideways"},
            r"kind.*'sideways'.*\['revisit', 'partial', 'opposite', 'disjoint', 'sensor'\]",
        ),
        ({"world": "moon"}, r"sim\.world.*'moon'.*allowed.*town"),
        ({"n_scans": 0}, r"n_scans must be >= 1"),
        ({"kind": "sensor", "query_sensor": "vlp16"}, r"query_sensor"),
        ({"sensor": "lidar9000"}, r"sim\.sensor.*allowed"),
        ({"overlap_m": 0.0}, r"overlap_m"),
    ],
)
def test_bad_arguments(kwargs: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        make_session_pair(**{"world": "town", "sensor": "vlp16", **kwargs})
