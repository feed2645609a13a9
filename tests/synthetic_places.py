"""A synthetic places database for the keypoint-voting tests (imported by the test modules beside it)."""

from __future__ import annotations

import numpy as np


def add_synthetic_places(rec, rng: np.random.Generator, n_places: int, per_place: int, dim: int) -> list:
    """Add ``n_places`` entries 5 m apart on a line to ``rec``, each with its own random unit descriptors (and
    random keypoints); returns the descriptors of every entry."""
    descs = []
    for i in range(n_places):
        d = rng.normal(size=(per_place, dim)).astype(np.float32)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        descs.append(d)
        pose = np.eye(4)
        pose[0, 3] = 5.0 * i
        rec.add_description(i, {"keypoints": rng.normal(size=(per_place, 3)), "descriptors": d}, pose)
    return descs
