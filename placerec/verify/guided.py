"""Feature matching guided by a motion prior: a second chance for a candidate RANSAC found no pose for.

A candidate whose mutual nearest features leave RANSAC without ``min_inliers`` consistent pairs is usually either
another place or the right place seen from 10-30 m away, where a look-alike feature elsewhere in the image is
nearer in descriptor space than the true one. A detector with odometry knows roughly where the query is relative
to the candidate (`placerec.types.Prediction`: the gate's predicted ``T_match_query`` and the bounds it
admits). Only the pairs of keypoints that a pose within those bounds can bring together are then possible
correspondences: query keypoint ``x`` (its 3D point) may pair with a candidate keypoint within

    metres + radians * |x|

of ``T_match_query @ x`` (a rotation error of ``radians`` moves a point at range ``|x|`` by at most that arc).
Among those pairs the mutual nearest descriptors are the correspondences (each side's nearest the first of equal
distances, as in `placerec.verify.matching.mutual_nearest`), and RANSAC runs on them as on any others. The gate
still judges the verified pose, so nothing it would refuse is admitted; what the prior adds is which features
are compared, so the pose RANSAC finds rests on the same geometric evidence as any other.

``GuidedParams.max_metres``: only predictions whose translation bound is at most this are matched within (with the
gate's default bounds, 2 m is the first 25 m of odometry after a closure); ``min_score``: a candidate posed this
way is accepted only from that verified score (it scores 0 below it). A prior over tens or hundreds of metres of
odometry also lets right places registered 0.5-1.2 m off through (and, where the bound is metres wide, 2-8 m off
ones), scoring up to 0.25; within 2 m of reach none scored 0.15 or more on the E1R-like sensor's tuning cells,
where both defaults were chosen (docs/sensors.md, "Matching within the odometry's prediction").

``near_metres``: a query whose candidates give no answer (`answers`: none accepted from ``min_score`` within its
prediction) registers, by ICP alone from the prediction, the places the prior predicts within that distance with a
bound of at most ``max_metres`` (`placerec.types.MotionPrior.near`; `placerec.verify.candidates.verify_near`),
nearest first, at most ``near_candidates``; the first accepted from ``min_score`` within the prediction's bounds
answers. A 2D pipeline tries this before matching within the prior, which may pose a retrieved place tens of metres
away less precisely (`placerec.pipelines.visual.VisualFrontend._verified`). The defaults (30 m, 4) were chosen on
the E1R-like sensor's tuning cells (docs/sensors.md, "Places predicted near"); None turns it off.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from pydantic import Field
from scipy.spatial import cKDTree

from placerec.params import Params
from placerec.retrieval.bits import hamming, to_words
from placerec.types import Candidate, MotionPrior, Prediction

__all__ = ["GuidedParams", "answers", "guided_nearest", "guides", "usable", "within"]


class GuidedParams(Params):
    """Matching guided by the caller's motion prior (module docstring); used only where a prior is given."""

    enabled: bool = Field(
        False,
        description="match a candidate RANSAC finds no pose for again, within the caller's motion prior (a "
        "detector with the odometry gate)",
    )
    min_score: float = Field(
        0.15,
        ge=0,
        le=1,
        allow_inf_nan=False,
        description="a guided candidate is accepted from this verified score only (0 below)",
    )
    max_metres: float | None = Field(
        2.0,
        gt=0,
        allow_inf_nan=False,
        description="only predictions whose translation bound is at most this (m; None: any)",
    )
    near_metres: float | None = Field(
        30.0,
        gt=0,
        allow_inf_nan=False,
        description="with no answer from min_score, ICP from the prediction onto places predicted this near (m)",
    )
    near_candidates: int = Field(4, ge=1, description="places predicted near, tried nearest first")


def within(prediction: Prediction, T_match_query: np.ndarray) -> bool:
    """Whether a relative pose lies within a prediction's bounds (the gate's test: translation apart, then the
    angle between the rotations)."""
    T = np.linalg.solve(prediction.T_match_query, np.asarray(T_match_query, np.float64))
    angle = float(np.arccos(np.clip((np.trace(T[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))
    return float(np.linalg.norm(T[:3, 3])) <= prediction.metres and angle <= prediction.radians


def answers(candidates: Sequence[Candidate], prior: MotionPrior, params: GuidedParams) -> bool:
    """Whether one of ``candidates`` is an answer a gate with the ``prior`` would keep: one with an `answer_pose`
    within its prediction (where the prior has one)."""
    for c in candidates:
        pose = answer_pose(c, params)
        if pose is not None:
            prediction = prior.predict(c.match_id)
            if prediction is None or within(prediction, pose):
                return True
    return False


def answer_pose(candidate: Candidate, params: GuidedParams) -> np.ndarray | None:
    """The pose of a candidate that may answer a query with a prior (accepted, scoring at least ``min_score``),
    else None."""
    if candidate.accepted and candidate.score >= params.min_score:
        return candidate.relative_pose
    return None


def guides(params: object) -> bool:
    """Whether a pipeline's parameters (any recognizer's) match within a motion prior: a ``verify`` section whose
    ``guided`` matching is enabled."""
    guided = getattr(getattr(params, "verify", None), "guided", None)
    return isinstance(guided, GuidedParams) and guided.enabled


def usable(prediction: Prediction | None, params: GuidedParams) -> Prediction | None:
    """``prediction`` where ``params`` match within it: none without one, or one looser than ``max_metres``."""
    if prediction is None or (params.max_metres is not None and prediction.metres > params.max_metres):
        return None
    return prediction


def guided_nearest(
    dq: np.ndarray, xq: np.ndarray, dm: np.ndarray, xm: np.ndarray, prediction: Prediction
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(query rows, match rows, descriptor distances) of the mutual nearest descriptors among the keypoint pairs
    ``prediction`` allows (module docstring): ``dq`` / ``dm`` packed binary (uint8, Hamming) or float (Euclidean)
    descriptors, ``xq`` / ``xm`` their keypoints' 3D points (NaN rows: no point, never paired)."""
    empty = np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    okq = np.flatnonzero(np.isfinite(xq).all(axis=1))
    okm = np.flatnonzero(np.isfinite(xm).all(axis=1))
    if okq.size == 0 or okm.size == 0:
        return empty
    T = np.asarray(prediction.T_match_query, np.float64)
    src = np.asarray(xq, np.float64)[okq]
    moved = src @ T[:3, :3].T + T[:3, 3]
    reach = prediction.metres + prediction.radians * np.linalg.norm(src, axis=1)
    near = cKDTree(np.asarray(xm, np.float64)[okm]).query_ball_point(moved, reach)
    counts = np.fromiter((len(n) for n in near), np.int64, okq.size)
    if counts.sum() == 0:
        return empty
    qi = np.repeat(np.arange(okq.size), counts)
    mi = np.concatenate([np.asarray(n, np.int64) for n in near if n])
    if dq.dtype == np.uint8:
        dist = hamming(to_words(dq)[okq[qi]], to_words(dm)[okm[mi]]).astype(np.float64)
    else:
        diff = dq[okq[qi]].astype(np.float64) - dm[okm[mi]].astype(np.float64)
        dist = np.sqrt(np.einsum("ij,ij->i", diff, diff))
    row = _first_nearest(qi, dist, mi)
    col = _first_nearest(mi, dist, qi)
    mutual = np.intersect1d(row, col)
    return okq[qi[mutual]], okm[mi[mutual]], dist[mutual]


def _first_nearest(group: np.ndarray, dist: np.ndarray, other: np.ndarray) -> np.ndarray:
    """Per value of ``group``, the index of its pair with the smallest ``dist`` (ties: the smallest ``other``)."""
    order = np.lexsort((other, dist, group))
    first = np.ones(order.size, bool)
    first[1:] = group[order][1:] != group[order][:-1]
    return order[first]
