"""The verified score: one number in [0, 1] with the same meaning in every pipeline, and the acceptance rule.

    score = (1 - exp(-inliers / inlier_scale)) * fitness * (1 - rmse / fitness_distance)

* the inlier term saturates: 0.63 at ``inlier_scale`` (10) RANSAC inliers, 0.95 at 3x; it is 1 when the
  candidate is verified by ICP alone (no correspondences, e.g. Scan Context's yaw as the initial guess);
* ``fitness``: the share of the query's voxels with a match voxel within ``fitness_distance`` after ICP (overlap);
* the RMSE term: 1 for a perfect fit, 0 when the overlapping voxels are on average ``fitness_distance`` away (the
  RMSE is over those voxels, so it never exceeds that distance).

Each term is in [0, 1] and a candidate scores high only when all three agree. ``acceptance="eps_icp"`` applies
the ISHOT paper's rule instead (ICP residual < eps_ICP = 7 m^2), ``"both"`` requires both. ``min_fitness``
(off by default) adds an overlap gate to any rule: the ICP fitness must reach it. ``min_constraint`` (off by
default) adds another: the overlap must pin the translation down in every direction (`placerec.verify.icp.
alignment_stats`), which a cone of road and one facade, aligned anywhere along the street, does not.
``min_fitness_ratio`` (off by default) judges the fitness against what a right alignment overlaps at the
candidate's displacement ``d`` (two scans of one place overlap less the further apart they were taken):

    fitness >= min_fitness_ratio * expected_fitness * exp(-d / expected_fitness_length_m)

A look-alike place (a repeated block, a row of the same sheds) registers with a small displacement, where a right
alignment would overlap most, but overlaps far less: the gate rejects it where a fixed ``min_fitness`` would also
reject right alignments of scans taken metres apart.
"""

from __future__ import annotations

import math

from placerec.verify.params import ScoreParams

__all__ = ["verified_score", "expected_fitness", "is_accepted", "rejection"]


def verified_score(
    inliers: int | None, fitness: float, rmse: float, params: ScoreParams | None = None
) -> float:
    """The score of the module docstring; ``inliers=None`` (ICP only) makes the inlier term 1; NaN inputs give 0."""
    params = params or ScoreParams()
    if not (math.isfinite(fitness) and math.isfinite(rmse)):
        return 0.0
    inlier_term = 1.0 if inliers is None else 1.0 - math.exp(-max(inliers, 0) / params.inlier_scale)
    fit_term = min(max(fitness, 0.0), 1.0)
    rmse_term = min(max(1.0 - rmse / params.fitness_distance, 0.0), 1.0)
    return inlier_term * fit_term * rmse_term


def expected_fitness(displacement: float, params: ScoreParams | None = None) -> float:
    """The fitness a right alignment of two scans ``displacement`` metres apart reaches (module docstring)."""
    params = params or ScoreParams()
    return params.expected_fitness * math.exp(-max(displacement, 0.0) / params.expected_fitness_length_m)


def is_accepted(
    score: float,
    residual: float,
    params: ScoreParams | None = None,
    fitness: float | None = None,
    constraint: float | None = None,
    displacement: float | None = None,
) -> bool:
    """The acceptance rule chosen by ``params.acceptance``, and the ``min_fitness`` / ``min_constraint`` /
    ``min_fitness_ratio`` gates on ``fitness`` / ``constraint`` / ``fitness`` at ``displacement`` (metres between
    the scans: the translation of the verified pose) when set (see the module docstring)."""
    return rejection(score, residual, params, fitness, constraint, displacement) is None


def rejection(
    score: float,
    residual: float,
    params: ScoreParams | None = None,
    fitness: float | None = None,
    constraint: float | None = None,
    displacement: float | None = None,
) -> str | None:
    """Why `is_accepted` rejects a verified candidate (``"fitness"``, ``"fitness_ratio"``, ``"constraint"``,
    ``"score"`` or ``"residual"``, the keys of `placerec.types.REJECTIONS`), or None when it accepts it."""
    params = params or ScoreParams()
    fit = fitness if fitness is not None and math.isfinite(fitness) else None
    if params.min_fitness is not None and not (fit is not None and fit >= params.min_fitness):
        return "fitness"
    if params.min_fitness_ratio is not None and not (
        fit is not None
        and displacement is not None
        and math.isfinite(displacement)
        and fit >= params.min_fitness_ratio * expected_fitness(displacement, params)
    ):
        return "fitness_ratio"
    if params.min_constraint is not None and not (
        constraint is not None and math.isfinite(constraint) and constraint >= params.min_constraint
    ):
        return "constraint"
    by_score = score >= params.min_score and score > 0.0
    by_eps = math.isfinite(residual) and residual < params.eps_icp
    if params.acceptance in ("score", "both") and not by_score:
        return "score"
    if params.acceptance in ("eps_icp", "both") and not by_eps:
        return "residual"
    return None
