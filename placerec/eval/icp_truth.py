"""The VPR paper's ground truth: a revisit counts only if the scans are near **and** an ICP between them succeeds.

Di Giammarino et al. (Sec. IV): "A pair is a match if the scans' recording locations are close according to the
external system, and an ICP registration succeeds (up to 1 m in translation and 20 deg in rotation)". Here a pair
within ``gt_distance`` (`placerec.eval.ground_truth`) is registered by point-to-plane ICP started at the true
relative pose; it succeeds when ICP moves the pose by at most ``max_translation`` (1 m) and ``max_rotation_deg``
(20 deg) and at least ``min_fitness`` (0.5) of the query's voxels then lie within 0.5 m of the match (without
this, two scans that share nothing "succeed" because ICP has nothing to move them with). A query is a revisit when
one of its eligible near scans passes (nearest first); a candidate is a true match when it is near and passes.
ICP results are cached per pair.

`IcpGroundTruth` has the interface `placerec.eval.metrics.loop_metrics` reads, like `LoopGroundTruth`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from placerec.eval.ground_truth import LoopGroundTruth
from placerec.eval.pose_error import pose_errors
from placerec.eval.pose_truth import relative_truth

__all__ = ["IcpTruthSettings", "IcpGroundTruth", "icp_ground_truth"]


@dataclass(frozen=True)
class IcpTruthSettings:
    """The tolerances of the ICP check (module docstring); ``voxel`` is the ICP target voxel (m)."""

    max_translation: float = 1.0
    max_rotation_deg: float = 20.0
    min_fitness: float = 0.5
    voxel: float = 0.5


@dataclass(eq=False)
class IcpGroundTruth:
    """A distance ground truth whose pairs must also pass the ICP check; ``clouds`` are the scans' points in
    their sensor frames (voxelised), ``poses`` the true ``T_world_sensor``."""

    base: LoopGroundTruth
    clouds: Sequence[np.ndarray]
    poses: np.ndarray
    settings: IcpTruthSettings = field(default_factory=IcpTruthSettings)
    is_revisit: np.ndarray = field(init=False)
    _passed: dict[tuple[int, int], bool] = field(default_factory=dict, init=False, repr=False)
    _prepared: dict[tuple[int, str], Any] = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self) -> None:
        revisit = np.zeros(len(self.base), dtype=bool)
        for q in np.flatnonzero(self.base.is_revisit):
            near = self.base.true_matches(int(q))
            d = np.linalg.norm(self.base.positions[near] - self.base.positions[q], axis=1)
            revisit[q] = any(self.passes(int(q), int(m)) for m in near[np.argsort(d, kind="stable")])
        self.is_revisit = revisit

    def __len__(self) -> int:
        return len(self.base)

    @property
    def max_eligible(self) -> np.ndarray:
        return self.base.max_eligible

    @property
    def n_revisits(self) -> int:
        return int(self.is_revisit.sum())

    def _cloud(self, i: int, role: str) -> Any:
        from placerec.verify.icp import IcpParams, prepare_source, prepare_target

        key = (i, role)
        if key not in self._prepared:
            params = IcpParams(voxel_size=self.settings.voxel, source_voxel_size=self.settings.voxel)
            prepare = prepare_target if role == "target" else prepare_source
            self._prepared[key] = prepare(self.clouds[i], params)
        return self._prepared[key]

    def passes(self, query: int, match: int) -> bool:
        """Whether ICP from the true ``T_match_query`` succeeds (cached)."""
        from placerec.verify.icp import IcpParams, refine

        key = (query, match)
        if key not in self._passed:
            truth = relative_truth(self.poses, np.array([query]), np.array([match]))[0]
            params = IcpParams(voxel_size=self.settings.voxel, source_voxel_size=self.settings.voxel)
            res = refine(self._cloud(query, "source"), self._cloud(match, "target"), truth, params)
            t_err, r_err = pose_errors(res.T, truth)
            self._passed[key] = bool(
                t_err[0] <= self.settings.max_translation
                and r_err[0] <= self.settings.max_rotation_deg
                and res.fitness >= self.settings.min_fitness
            )
        return self._passed[key]

    def is_true_match(self, query: Any, match: Any) -> np.ndarray:
        """Element-wise: near (the base truth) and the ICP check passes."""
        q, m = np.broadcast_arrays(np.asarray(query, dtype=np.int64), np.asarray(match, dtype=np.int64))
        near = self.base.is_true_match(q, m)
        out = np.zeros(q.shape, dtype=bool)
        for idx in zip(*np.nonzero(near), strict=True):
            out[idx] = self.passes(int(q[idx]), int(m[idx]))
        return out


def icp_ground_truth(
    base: LoopGroundTruth,
    clouds: Sequence[np.ndarray],
    poses: np.ndarray,
    settings: IcpTruthSettings | None = None,
) -> IcpGroundTruth:
    """`IcpGroundTruth` over a distance ground truth ``base`` (revisits decided at construction)."""
    return IcpGroundTruth(base, clouds, np.asarray(poses, dtype=np.float64), settings or IcpTruthSettings())
