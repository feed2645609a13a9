"""`verify`: the one verification stage every pipeline calls for a retrieved candidate.

correspondences (query keypoints <-> match keypoints)
  -> optional geometric consistency grouping (ISHOT paper; the largest cluster is kept)
  -> RANSAC (6-DoF or 4-DoF) -> ``T_match_query`` initial guess
  -> ICP between the voxelised scans (small_gicp point-to-plane by default)
  -> verified score in [0, 1] and acceptance (`placerec.verify.score`).

Without correspondences (`verify_icp`), ICP starts from the given initial guess (e.g. Scan Context's yaw): coarse
stages first (``icp_only_coarse_distances``, on ``icp_only_coarse_voxel_size``'s grid), which end it, rejected as
``coarse_fitness``, when they leave less overlap than ``icp_only_min_coarse_fitness``.
``T_match_query`` maps query points into the match scan's frame (`placerec.types` conventions), so that
``T_world_query ~= T_world_match @ T_match_query``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from placerec.errors import ScanDataError
from placerec.types import Verification
from placerec.verify.consistency import group_correspondences
from placerec.verify.icp import (
    IcpCloud,
    IcpResult,
    coarser_source,
    finer_source,
    prepare_source,
    prepare_target,
    refine,
)
from placerec.verify.kabsch import check_pairs
from placerec.verify.params import VerifyParams
from placerec.verify.ransac import RansacResult, ransac_pose, refit
from placerec.verify.score import rejection, verified_score

__all__ = [
    "Verification",
    "Hypothesis",
    "hypothesise",
    "complete",
    "verify",
    "verify_icp",
    "as_source",
    "as_target",
]


def as_source(query: Any, params: VerifyParams | None = None) -> IcpCloud:
    """The query scan prepared for ICP (pass the result to several `verify` calls to prepare it once)."""
    params = params or VerifyParams()
    if isinstance(query, IcpCloud):
        _check_cloud(query, "source", params)
        return query
    return prepare_source(query, params.icp)


def as_target(match: Any, params: VerifyParams | None = None) -> IcpCloud:
    """The matched scan prepared for ICP (cache it per database scan)."""
    params = params or VerifyParams()
    if isinstance(match, IcpCloud):
        _check_cloud(match, "target", params)
        return match
    return prepare_target(match, params.icp)


def _check_cloud(cloud: IcpCloud, role: str, params: VerifyParams) -> None:
    voxel = params.icp.voxel_size if role == "target" else params.icp.source_voxel_size
    if cloud.role != role or cloud.backend != params.icp.backend or cloud.voxel_size != voxel:
        raise ScanDataError(
            f"a {cloud.role} cloud for {cloud.backend} at {cloud.voxel_size} m was given where a {role} cloud for"
            f" {params.icp.backend} at {voxel} m is needed"
        )


@dataclass(frozen=True)
class Hypothesis:
    """The correspondence stage of `verify` (`hypothesise`): ``T_match_query`` is ICP's start (the RANSAC pose, or
    the initial guess without correspondences), ``rejected_at`` the stage that ended it (None: ICP comes next);
    the other fields as in `Verification`."""

    T_match_query: np.ndarray
    inliers: int | None
    correspondences: int
    ransac_iterations: int = 0
    rejected_at: str | None = None
    timings_ms: dict[str, float] = field(default_factory=dict)
    inlier_mask: np.ndarray | None = None

    def rejected(self, stage: str | None = None) -> Verification:
        """This hypothesis as a rejected `Verification` (score 0, no ICP statistics), at ``stage`` (default: its
        own ``rejected_at``; e.g. ``"rank"`` when ICP was spent on other candidates)."""
        nan = float("nan")
        timings = {**self.timings_ms, "total": sum(self.timings_ms.values())}
        return Verification(
            self.T_match_query,
            0.0,
            False,
            self.inliers,
            self.correspondences,
            nan,
            nan,
            nan,
            self.ransac_iterations,
            0,
            stage or self.rejected_at,
            timings,
            self.inlier_mask,
            stage or self.rejected_at,
        )


def hypothesise(
    src_kp_xyz: np.ndarray | None,
    dst_kp_xyz: np.ndarray | None,
    init: np.ndarray | None = None,
    params: VerifyParams | None = None,
    quality: np.ndarray | None = None,
) -> Hypothesis:
    """The correspondence stage of `verify`: consistency grouping (when enabled) and RANSAC on ``src_kp_xyz[i] <->
    dst_kp_xyz[i]``; without correspondences the hypothesis is ``init`` (None: identity), for ICP alone."""
    params = params or VerifyParams()
    T0 = _initial(init)
    if src_kp_xyz is None and dst_kp_xyz is None:
        return Hypothesis(T0, None, 0)
    if src_kp_xyz is None or dst_kp_xyz is None:
        raise ScanDataError("verify: give both keypoint arrays (src_kp_xyz and dst_kp_xyz) or neither")
    timings: dict[str, float] = {}
    src, dst = check_pairs(src_kp_xyz, dst_kp_xyz)
    n_corr = src.shape[0]
    t = time.perf_counter()
    subsets = [np.arange(n_corr)]
    if params.consistency.enabled and n_corr:
        clusters = group_correspondences(src, dst, quality, params.consistency)
        subsets = [
            c for c in clusters[: params.consistency.max_clusters] if len(c) >= params.min_correspondences
        ]
    timings["grouping"] = (time.perf_counter() - t) * 1e3
    if not subsets or n_corr < params.min_correspondences:
        return Hypothesis(T0, 0, n_corr, 0, "grouping", timings)
    t = time.perf_counter()
    results = [(ransac_pose(src[c], dst[c], params.ransac), c) for c in subsets]
    rr, chosen = max(results, key=lambda r: (r[0].n_inliers, -len(r[1])))
    ransac_iters = sum(r.iterations for r, _ in results)
    sample = 3 if params.ransac.mode == "6dof" else 2
    if len(chosen) < n_corr and rr.n_inliers >= sample:  # a cluster's pose: its inliers among all pairs
        T_all, inlier_mask = refit(rr.T, src, dst, params.ransac)
        rr = RansacResult(T_all, inlier_mask, int(inlier_mask.sum()), rr.iterations, True)
    else:
        inlier_mask = np.zeros(n_corr, dtype=bool)
        inlier_mask[chosen[rr.inliers]] = True
    timings["ransac"] = (time.perf_counter() - t) * 1e3
    inliers = rr.n_inliers
    if inliers < params.ransac.min_inliers:
        return Hypothesis(T0, inliers, n_corr, ransac_iters, "ransac", timings, inlier_mask)
    return Hypothesis(rr.T, inliers, n_corr, ransac_iters, None, timings, inlier_mask)


def complete(
    query_pts: Any, match_pts: Any, hypothesis: Hypothesis, params: VerifyParams | None = None
) -> Verification:
    """The ICP stage of `verify` from ``hypothesis`` (one `hypothesise` accepted): ICP between the scans, the
    verified score and acceptance. ``query_pts`` / ``match_pts`` as in `verify` (``match_pts`` may be a callable)."""
    params = params or VerifyParams()
    if hypothesis.rejected_at is not None:
        return hypothesis.rejected()
    t_start = time.perf_counter()
    timings = dict(hypothesis.timings_ms)
    source = as_source(query_pts, params)
    target = as_target(match_pts() if callable(match_pts) else match_pts, params)
    timings["prepare"] = (time.perf_counter() - t_start) * 1e3
    sp = params.score
    T0, coarse_ms = hypothesis.T_match_query, 0.0
    if hypothesis.inliers is None:  # a rough initial guess: coarse gates first, on a coarser query grid
        coarse_source = coarser_source(source, params.icp_only_coarse_voxel_size, params.icp)
        step, coarse_ms = _gated(coarse_source, target, T0, params.icp_only_coarse_distances, params)
        T0 = T0 if step is None else step.T
        floor = params.icp_only_min_coarse_fitness
        if step is not None and floor is not None and not step.fitness >= floor:  # NaN: nothing overlapped
            _stage_time(timings, "icp", coarse_ms)
            return replace(
                hypothesis.rejected("coarse_fitness"),
                T_match_query=step.T,
                fitness=step.fitness,
                rmse=step.rmse,
                icp_iterations=step.iterations,
                timings_ms=timings,
            )
    measure_constraint = sp.min_constraint is not None
    icp = refine(
        source, target, T0, params.icp, sp.fitness_distance, sp.eps_icp_max_range, measure_constraint
    )
    icp_ms = icp.ms + coarse_ms
    if hypothesis.inliers is None:  # from a rough guess: the tighter gates, each from the last pose
        fine, fine_ms = _gated(
            source, target, icp.T, params.icp_only_fine_distances, params, measure_constraint
        )
        icp, icp_ms = icp if fine is None else fine, icp_ms + fine_ms
    _stage_time(timings, "icp", icp_ms)
    score = verified_score(hypothesis.inliers, icp.fitness, icp.rmse, sp)
    why = rejection(score, icp.residual, sp, icp.fitness, icp.constraint, float(np.linalg.norm(icp.T[:3, 3])))
    T = icp.T
    if why is None and params.refine.enabled:
        T = _refined(source, target, T, params, timings)
    return Verification(
        T_match_query=T,
        score=score,
        accepted=why is None,
        inliers=hypothesis.inliers,
        correspondences=hypothesis.correspondences,
        fitness=icp.fitness,
        rmse=icp.rmse,
        residual=icp.residual,
        ransac_iterations=hypothesis.ransac_iterations,
        icp_iterations=icp.iterations,
        timings_ms=timings,
        inlier_mask=hypothesis.inlier_mask,
        rejection=why,
        constraint=icp.constraint,
    )


def _refined(
    source: IcpCloud, target: IcpCloud, T: np.ndarray, params: VerifyParams, timings: dict[str, float]
) -> np.ndarray:
    """The accepted pose ``T`` refined (`RefineParams`): `_refinement`'s pose; ``T`` itself when that moved
    farther than ``refine.max_shift`` or is not finite."""
    out = _refinement(source, target, T, params, timings)
    moved = float(np.linalg.norm(out[:3, 3] - T[:3, 3]))
    return out if np.isfinite(out).all() and moved <= params.refine.max_shift else T


def _refinement(
    source: IcpCloud, target: IcpCloud, T: np.ndarray, params: VerifyParams, timings: dict[str, float]
) -> np.ndarray:
    """ICP of the query on its finer grid (``refine.voxel_size``) from ``T``: the pose it ends at. Its
    milliseconds (the query's finer grid made the first time included) go to ``timings["refine"]``."""
    rp = params.refine
    t0 = time.perf_counter()
    fine = finer_source(source, max(rp.voxel_size, params.icp.voxel_size), params.icp)
    icp = params.icp.model_copy(
        update={
            "method": rp.method,
            "max_correspondence_distance": rp.max_correspondence_distance,
            "max_iterations": rp.max_iterations,
        }
    )
    out = refine(fine, target, T, icp, params.score.fitness_distance).T
    _stage_time(timings, "refine", (time.perf_counter() - t0) * 1e3)
    return out


def _gated(
    source: IcpCloud,
    target: IcpCloud,
    T: np.ndarray,
    gates: list[float],
    params: VerifyParams,
    constraint: bool = False,
) -> tuple[IcpResult | None, float]:
    """ICP with each correspondence gate of ``gates`` in turn, the first from ``T``, each next from the last one's
    pose: the last stage's result (None without gates) and the stages' milliseconds."""
    sp, step, ms = params.score, None, 0.0
    for gate in gates:
        icp = params.icp.model_copy(update={"max_correspondence_distance": gate})
        start = T if step is None else step.T
        step = refine(source, target, start, icp, sp.fitness_distance, sp.eps_icp_max_range, constraint)
        ms += step.ms
    return step, ms


def _stage_time(timings: dict[str, float], stage: str, ms: float) -> None:
    """Record ``stage``'s milliseconds in ``timings`` and their new total (every stage but the total itself)."""
    timings[stage] = ms
    timings["total"] = sum(v for k, v in timings.items() if k != "total")


def verify(
    query_pts: Any,
    match_pts: Any,
    src_kp_xyz: np.ndarray | None,
    dst_kp_xyz: np.ndarray | None,
    init: np.ndarray | None = None,
    params: VerifyParams | None = None,
    quality: np.ndarray | None = None,
) -> Verification:
    """Verify a candidate: ``query_pts`` / ``match_pts`` are the two scans ((N, 3) arrays, `Scan` objects or
    clouds from `as_source` / `as_target`); ``src_kp_xyz[i]`` (query frame) corresponds to ``dst_kp_xyz[i]``
    (match frame). ``match_pts`` may also be a zero-argument callable returning one of those, called only when
    ICP runs, so a candidate rejected before ICP never prepares its scan. ``quality`` (lower is better, e.g.
    descriptor distance) orders the consistency grouping. ``init`` (T_match_query) is the ICP start when no
    correspondences are given (None: identity); with correspondences the RANSAC pose is the start.
    `hypothesise` then `complete`; the query is prepared only when ICP runs too.
    """
    params = params or VerifyParams()
    return complete(query_pts, match_pts, hypothesise(src_kp_xyz, dst_kp_xyz, init, params, quality), params)


def verify_icp(
    query_pts: Any, match_pts: Any, init: np.ndarray | None = None, params: VerifyParams | None = None
) -> Verification:
    """Verify by ICP alone from ``init`` (T_match_query, e.g. Scan Context's yaw rotation), coarse to fine
    (``params.icp_only_coarse_distances``, then the ICP's own gate); see `verify`."""
    return verify(query_pts, match_pts, None, None, init=init, params=params)


def _initial(init: np.ndarray | None) -> np.ndarray:
    if init is None:
        return np.eye(4)
    T = np.asarray(init, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ScanDataError(f"init must be a finite 4x4 pose, got shape {T.shape}")
    R = T[:3, :3]
    if (
        not np.allclose(T[3], [0, 0, 0, 1])
        or not np.allclose(R @ R.T, np.eye(3), atol=1e-6)
        or np.linalg.det(R) < 0
    ):
        raise ScanDataError("init must be a rigid transform (orthonormal rotation, last row 0 0 0 1)")
    return T
