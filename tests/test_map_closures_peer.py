"""The MapClosures peer adapter: ids, exclusion bound and the relative-pose convention."""

import numpy as np
import pytest

pytest.importorskip("map_closures", reason="the optional peer 'map-closures' is not installed")

from placerec.recognizer import make_pipeline  # noqa: E402
from placerec.types import Scan  # noqa: E402


def _walls_world(seed=0):
    rng = np.random.default_rng(seed)
    parts = []
    for _ in range(300):
        c, length, a = rng.uniform(-100, 100, 2), rng.uniform(3, 15), rng.uniform(0, np.pi)
        t = np.linspace(-length / 2, length / 2, int(length * 10))
        xy = c + np.c_[np.cos(a) * t, np.sin(a) * t]
        parts += [np.c_[xy, np.full(len(xy), z)] for z in np.linspace(-1.5, 3, 10)]
    parts.append(np.c_[rng.uniform(-100, 100, (200_000, 2)), np.full(200_000, -1.8)])
    return np.concatenate(parts)


def _scan(world, x, y, yaw):
    T = np.eye(4)
    T[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    T[:2, 3] = [x, y]
    pts = (world - T[:3, 3]) @ T[:3, :3]
    pts = pts[np.linalg.norm(pts[:, :2], axis=1) < 50]
    return Scan(pts, np.ones(len(pts))), T


def test_revisit_found_with_relative_pose_as_T_match_query():
    world = _walls_world()
    peer = make_pipeline("map-closures")
    first, T0 = _scan(world, 0, 0, 0)
    peer.add(0, first)
    for i, (x, y) in enumerate([(60, 60), (-60, 60), (60, -60), (-60, -60)], start=1):
        peer.add(i, _scan(world, x, y, 0)[0])
    query, Tq = _scan(world, 3, 1, 0.3)
    assert peer.query(query, k=3, max_id=-1, query_id=5) == []  # nothing eligible
    again, _ = _scan(world, 3.2, 1, 0.3)
    cands = peer.query(again, k=3, max_id=5, query_id=6)
    assert cands and cands[0].match_id in (0, 5) and cands[0].score >= 5
    best = next(c for c in cands if c.match_id == 0)
    expected = np.linalg.inv(T0) @ _scan(world, 3.2, 1, 0.3)[1]
    assert np.allclose(best.relative_pose[:2, 3], expected[:2, 3], atol=0.5)
    assert np.allclose(best.relative_pose[:3, :3], expected[:3, :3], atol=0.05)


def _pose(x, y, yaw):
    T = np.eye(4)
    T[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    T[:2, 3] = [x, y]
    return T


def test_a_local_map_closure_maps_to_the_nearest_scan_with_its_T_match_query():
    from placerec.baselines.map_closures_peer import closure_to_scan

    M_b = _pose(100.0, 20.0, 0.4)
    poses_b = np.stack([_pose(100.0 + 3 * i, 20.0 + i, 0.4 + 0.05 * i) for i in range(8)])
    M_a, P_q = _pose(-40.0, 5.0, 2.0), _pose(108.2, 22.5, 1.1)
    # exact odometry: the closure between the map frames is inv(M_b) @ M_a
    T_b_a = np.linalg.inv(M_b) @ M_a
    j, T = closure_to_scan(T_b_a, M_a, P_q, M_b, poses_b)
    assert j == 3  # (109, 23) is the scan of map b nearest to the query at (108.2, 22.5)
    assert np.allclose(T, np.linalg.inv(poses_b[3]) @ P_q)
    # drift of the query map's odometry frame cancels: the closure is between local frames
    D = _pose(7.0, -3.0, 0.2)
    j2, T2 = closure_to_scan(T_b_a, D @ M_a, D @ P_q, M_b, poses_b)
    assert j2 == 3 and np.allclose(T2, T)


def test_local_map_mode_closes_maps_by_distance_and_finds_the_revisit():
    world = _walls_world(1)
    peer = make_pipeline("map-closures", {"local_map": True, "local_map_distance": 30.0})
    route = [(x, 0.0) for x in range(0, 61, 4)] + [(60.0, y) for y in range(4, 61, 4)]
    route += [(x, 60.0) for x in range(56, -1, -4)] + [(0.0, y) for y in range(56, -1, -4)]
    route += [(x, 0.0) for x in range(4, 33, 4)]
    found = []
    for i, (x, y) in enumerate(route):
        scan, T = _scan(world, x, y, 0.0)
        cands = peer.query(scan, k=1, query_id=i)
        if cands:
            found.append((i, cands[0], T))
        peer.add(i, scan, T)
    assert len(peer) == len(route) and len(peer._maps) >= 6
    # local maps close every > 30 m of displacement from their first scan, which starts the next one
    firsts = [m.ids[0] for m in [*peer._maps[1:], peer._current]]
    assert all(m.ids[-1] == n for m, n in zip(peer._maps, firsts, strict=True))
    revisits = [(i, c, T) for i, c, T in found if i >= 60]
    assert revisits, "the return to the start is found"
    i, c, T = max(revisits, key=lambda r: r[1].score)
    P_match = _scan(world, *route[c.match_id], 0.0)[1]
    assert np.linalg.norm(P_match[:2, 3] - T[:2, 3]) < 10.0
    assert np.allclose(c.relative_pose[:2, 3], (np.linalg.inv(P_match) @ T)[:2, 3], atol=1.0)


def test_local_maps_from_kiss_icp_odometry_close_where_the_scans_say():
    from placerec.errors import ScanDataError

    world = _walls_world(2)
    peer = make_pipeline(
        "map-closures", {"local_map": True, "local_map_distance": 30.0, "odometry": "kiss-icp"}
    )
    route = [(float(x), 0.0) for x in range(0, 81, 2)]
    for i, (x, y) in enumerate(route):
        scan, _ = _scan(world, x, y, 0.0)
        peer.query(scan, k=1, query_id=i)
        peer.add(i, scan, None)  # poses given to add are not needed: KISS-ICP registers the scans
    # KISS-ICP's poses (from the identity at scan 0) follow the route: maps close past 30 m, i.e. at 32 m and 64 m
    assert [(m.ids[0], m.ids[-1]) for m in peer._maps] == [(0, 16), (16, 32)]
    assert np.allclose(peer._maps[1].poses[-1][:2, 3], [64.0, 0.0], atol=0.5)
    # KISS-ICP registered the query: adding another scan first breaks the loop-closure order
    peer.query(_scan(world, 82.0, 0.0, 0.0)[0], k=1, query_id=41)
    with pytest.raises(ScanDataError, match="loop-closure order"):
        peer.add(42, _scan(world, 84.0, 0.0, 0.0)[0])
