"""Repeatability and matching score of 2D features on LiDAR intensity images with known relative poses.

The image-matching measures of SuperPoint / HPatches, with the homography replaced by the scans' 3D points and
their relative pose. Each image pixel holds at most one scan point (`placerec.image.correspondence.pixel_points`),
and a keypoint's 3D point is the point of its pixel or of the nearest of its 8 neighbours that has one
(`placerec.image.correspondence.keypoint_points`).

Ground truth, for a pair of images A, B and ``a_to_b`` (A's sensor frame -> B's, ``inv(pose_b) @ pose_a``):

* a keypoint ``i`` of A with 3D point ``p_i`` is **in the overlap** when ``a_to_b p_i`` lies within ``max_dist``
  (0.3 m) of a point of B; its **ground-truth pixel** ``g_i`` is that nearest point's pixel in B
  (`pixel_correspondences` without the mutual check: a point hidden from B, outside B's field of view or range,
  has no such point, so visibility and occlusion are checked by construction). Keypoints without a 3D point
  (holes, interpolated rows) are left out.
* keypoint ``i`` of A and keypoint ``j`` of B **coincide** when ``i`` is in the overlap and either
  ``|a_to_b p_i - p_j| <= max_dist`` (``j`` has a 3D point) or the pixel distance from ``g_i`` to ``j``'s
  position is at most ``px`` (3 px; columns wrap around, the images being 360 degree panoramas).

Per direction (A -> B; B -> A likewise with the roles swapped), over the ``n_A`` keypoints of A in the overlap:

* **repeatability** = (keypoints of A in the overlap that coincide with some keypoint of B) / ``n_A``;
* **matching score** = (mutual nearest-neighbour descriptor matches ``(i, j)``, `placerec.verify.matching.
  mutual_nearest`, Hamming for binary and L2 for float descriptors, with ``i`` in the overlap and ``i``
  coinciding with ``j``) / ``n_A``;
* **precision** = those correct matches / the mutual matches whose A keypoint is in the overlap.

Repeatability has a chance level: with K keypoints spread at random over an H x W image, a pixel lies within
``px`` of one of them with probability about ``1 - exp(-K pi px^2 / (H W))`` (12 % for 300 keypoints, 3 px,
64 x 1024), and much more where a detector crowds its keypoints (e.g. on a few rows, one every few columns).
**Chance repeatability** measures it for the pair's own keypoints: the repeatability of A's keypoints against B's
keypoints turned half a revolution (``u + W/2``, which keeps their rows and spacing and breaks the
correspondence), and the other way round. Matching score and precision have no such floor (a wrong pose gives
~0).

A pair's figure is the mean of its two directions (of those with at least one keypoint in the overlap, resp.
one such match); a pair set's is the mean over its pairs. ``tools/eval_features.py`` runs it on simulator and
real pairs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from placerec.errors import ScanDataError
from placerec.features.base import Features
from placerec.image import ImageParams, make_image
from placerec.image.correspondence import (
    keypoint_points,
    pixel_correspondences,
    pixel_points,
    transform_points,
)
from placerec.types import Scan
from placerec.verify.matching import mutual_nearest

__all__ = [
    "View",
    "PairTruth",
    "PairScores",
    "keypoint_pixels",
    "ground_truth_pixels",
    "coincidence",
    "evaluate_pair",
    "judged_matches",
    "mean_scores",
]


@dataclass(frozen=True)
class View:
    """One scan as the evaluation sees it: the 8-bit intensity ``image`` (H, W) and ``points`` (H, W, 3)
    float32, the sensor-frame scan point behind each pixel (NaN where none)."""

    image: np.ndarray
    points: np.ndarray

    def __post_init__(self) -> None:
        if self.image.ndim != 2 or self.points.shape != self.image.shape + (3,):
            raise ScanDataError(
                f"View: image (H, W) and points (H, W, 3) expected, got {self.image.shape} and {self.points.shape}"
            )

    @classmethod
    def from_scan(cls, scan: Scan, params: ImageParams | None = None) -> View:
        """The intensity image of ``scan`` (`placerec.image.make_image`) and its pixel points."""
        img = make_image(scan, params or ImageParams())
        return cls(img.image, pixel_points(img, scan))

    @property
    def width(self) -> int:
        return int(self.image.shape[1])


def keypoint_pixels(keypoints: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(K,) flat index of the pixel whose 3D point stands behind each keypoint (`keypoint_points` on the pixel
    grid: the keypoint's pixel, else the nearest 8-neighbour holding a point); -1 where none does."""
    h, w = points.shape[:2]
    flat = np.where(np.isfinite(points[..., 0]), np.arange(h * w).reshape(h, w), -1)
    return keypoint_points(keypoints, flat)


def ground_truth_pixels(
    points_a: np.ndarray, points_b: np.ndarray, a_to_b: np.ndarray, max_dist: float = 0.3
) -> np.ndarray:
    """(H_a * W_a,) flat pixel of B whose point is nearest to each pixel point of A moved by ``a_to_b``, when
    within ``max_dist``; -1 elsewhere (`pixel_correspondences` without the mutual check)."""
    corr = pixel_correspondences(points_a, points_b, a_to_b, max_dist=max_dist, mutual=False)
    out = np.full(points_a.shape[0] * points_a.shape[1], -1, np.int64)
    w_a, w_b = points_a.shape[1], points_b.shape[1]
    out[corr.uv_a[:, 1].astype(np.int64) * w_a + corr.uv_a[:, 0]] = (
        corr.uv_b[:, 1].astype(np.int64) * w_b + corr.uv_b[:, 0]
    )
    return out


@dataclass(frozen=True)
class PairTruth:
    """The ground truth of an image pair, shared by every extractor: the views, ``a_to_b`` and the ground-truth
    pixel maps both ways (`ground_truth_pixels`)."""

    a: View
    b: View
    a_to_b: np.ndarray
    gt_ab: np.ndarray
    gt_ba: np.ndarray
    max_dist: float

    @classmethod
    def from_views(cls, a: View, b: View, a_to_b: np.ndarray, max_dist: float = 0.3) -> PairTruth:
        T = np.asarray(a_to_b, np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise ScanDataError(f"a_to_b must be a finite 4x4 transform, got shape {T.shape}")
        b_to_a = np.linalg.inv(T)
        return cls(
            a,
            b,
            T,
            ground_truth_pixels(a.points, b.points, T, max_dist),
            ground_truth_pixels(b.points, a.points, b_to_a, max_dist),
            float(max_dist),
        )

    @property
    def overlap(self) -> float:
        """Share of A's and B's valid pixels that have a ground-truth partner (mean of the two)."""
        shares = [
            float((gt >= 0).sum()) / max(int(np.isfinite(v.points[..., 0]).sum()), 1)
            for gt, v in ((self.gt_ab, self.a), (self.gt_ba, self.b))
        ]
        return float(np.mean(shares))


def coincidence(
    kp_a: np.ndarray,
    kp_b: np.ndarray,
    points_a: np.ndarray,
    points_b: np.ndarray,
    gt_ab: np.ndarray,
    a_to_b: np.ndarray,
    px: float = 3.0,
    max_dist: float = 0.3,
) -> tuple[np.ndarray, np.ndarray]:
    """(in_overlap (K_a,) bool, C (K_a, K_b) bool): which keypoints of A are in the overlap and which pairs
    coincide (module docstring), for keypoints ``kp_a`` / ``kp_b`` (K, 2) ``(u, v)`` of images with pixel points
    ``points_a`` / ``points_b`` and A's ground-truth pixel map ``gt_ab`` (`ground_truth_pixels`)."""
    w_b = points_b.shape[1]
    pix_a = keypoint_pixels(kp_a, points_a)
    gt = np.where(pix_a >= 0, gt_ab[np.maximum(pix_a, 0)], -1)
    overlap = gt >= 0
    C = np.zeros((len(pix_a), len(kp_b)), bool)
    if not overlap.any() or len(kp_b) == 0:
        return overlap, C
    ia = np.flatnonzero(overlap)
    # pixel criterion: ground-truth pixel within px of j (columns wrap)
    g = gt[ia]
    gu, gv = (g % w_b).astype(np.float64), (g // w_b).astype(np.float64)
    kb = np.asarray(kp_b, np.float64).reshape(-1, 2)
    du = np.abs(gu[:, None] - kb[None, :, 0]) % w_b
    du = np.minimum(du, w_b - du)
    dv = gv[:, None] - kb[None, :, 1]
    close = du * du + dv * dv <= px * px
    # 3D criterion: A's point, moved into B's frame, within max_dist of j's point
    pa = transform_points(a_to_b, points_a.reshape(-1, 3)[pix_a[ia]]).astype(np.float64)
    pix_b = keypoint_pixels(kb, points_b)
    has_b = pix_b >= 0
    if has_b.any():
        pb = points_b.reshape(-1, 3)[pix_b[has_b]].astype(np.float64)
        d2 = ((pa[:, None, :] - pb[None, :, :]) ** 2).sum(axis=2)
        close[:, has_b] |= d2 <= max_dist * max_dist
    C[ia] = close
    return overlap, C


@dataclass(frozen=True)
class PairScores:
    """The figures of one pair (module docstring): ``repeatability``, ``matching_score``, ``precision`` (NaN
    where undefined: no keypoint in the overlap, no match), ``chance_repeatability``, mean ``keypoints`` per
    image, mean keypoints in the overlap per direction, the mutual ``matches`` and the ``correct`` ones (counted
    once per direction)."""

    repeatability: float
    matching_score: float
    precision: float
    chance_repeatability: float
    keypoints: float
    overlap_keypoints: float
    matches: int
    correct: float

    def as_dict(self) -> dict[str, float]:
        return dict(self.__dict__)


def _mean(values: list[float]) -> float:
    v = [x for x in values if np.isfinite(x)]
    return float(np.mean(v)) if v else float("nan")


def _half_turn(keypoints: np.ndarray, width: int) -> np.ndarray:
    kp = np.array(keypoints, np.float64).reshape(-1, 2)
    kp[:, 0] = (kp[:, 0] + width / 2.0) % width
    return kp


def _repeated_share(overlap: np.ndarray, C: np.ndarray) -> float:
    n = int(overlap.sum())
    return float(C[overlap].any(axis=1).sum()) / n if n else float("nan")


def evaluate_pair(
    fa: Features, fb: Features, truth: PairTruth, px: float = 3.0, max_dist: float | None = None
) -> PairScores:
    """Repeatability, matching score and precision of features ``fa`` (image A) and ``fb`` (image B) of the pair
    ``truth`` (module docstring); ``max_dist`` defaults to the pair's own."""
    d = truth.max_dist if max_dist is None else float(max_dist)
    sides = (
        (fa, fb, truth.a, truth.b, truth.gt_ab, truth.a_to_b),
        (fb, fa, truth.b, truth.a, truth.gt_ba, np.linalg.inv(truth.a_to_b)),
    )
    found, chance = [], []
    for f, g, v, w, gt, T in sides:
        found.append(coincidence(f.keypoints, g.keypoints, v.points, w.points, gt, T, px, d))
        turned = _half_turn(g.keypoints, w.width)
        chance.append(_repeated_share(*coincidence(f.keypoints, turned, v.points, w.points, gt, T, px, d)))
    (o_a, C_ab), (o_b, C_ba) = found
    qi, mi, _ = mutual_nearest(fa.descriptors, fb.descriptors)
    rep, ms, prec, correct = [], [], [], []
    for o, C, src, dst in ((o_a, C_ab, qi, mi), (o_b, C_ba, mi, qi)):
        n = int(o.sum())
        judged = o[src]
        ok = int(C[src[judged], dst[judged]].sum())
        correct.append(ok)
        rep.append(_repeated_share(o, C))
        ms.append(ok / n if n else float("nan"))
        prec.append(ok / int(judged.sum()) if judged.any() else float("nan"))
    return PairScores(
        repeatability=_mean(rep),
        matching_score=_mean(ms),
        precision=_mean(prec),
        chance_repeatability=_mean(chance),
        keypoints=(len(fa) + len(fb)) / 2.0,
        overlap_keypoints=(int(o_a.sum()) + int(o_b.sum())) / 2.0,
        matches=int(len(qi)),
        correct=float(np.mean(correct)),
    )


def judged_matches(
    fa: Features, fb: Features, truth: PairTruth, px: float = 3.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The mutual nearest-neighbour matches of A -> B, as indices ``(qi, mi)``, with masks ``judged`` (A's keypoint
    is in the overlap) and ``correct`` (judged, and the two coincide), as `evaluate_pair` counts them; for
    figures."""
    overlap, C = coincidence(
        fa.keypoints,
        fb.keypoints,
        truth.a.points,
        truth.b.points,
        truth.gt_ab,
        truth.a_to_b,
        px,
        truth.max_dist,
    )
    qi, mi, _ = mutual_nearest(fa.descriptors, fb.descriptors)
    judged = overlap[qi]
    return qi, mi, judged, judged & C[qi, mi]


def mean_scores(scores: list[PairScores]) -> dict[str, float]:
    """Each figure's mean over the pairs where it is defined, and ``pairs``, the number of pairs."""
    out: dict[str, float] = {"pairs": float(len(scores))}
    for name in PairScores.__dataclass_fields__:
        out[name] = _mean([float(getattr(s, name)) for s in scores])
    return out
