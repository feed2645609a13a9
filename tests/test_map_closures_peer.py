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
