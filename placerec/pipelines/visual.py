"""The 2D visual pipeline (VPR paper): intensity image -> features -> HBST retrieval -> optional yaw check.

Score (documented, what thresholds apply to): HBST gives each stored image a vote count (one vote per query
descriptor that has a match in it, `placerec.retrieval.hbst`); the ``n_verify`` images with most votes are
checked geometrically. In a cylindrical image a revisit from (nearly) the same place differs by a yaw, i.e. a
circular column shift, and by small row offsets. ``verify="shift"`` histograms the column shifts of the matches,
takes the densest shift (within ``shift_tolerance_px``) among matches whose rows differ by at most
``row_tolerance_px``, and counts those as inliers; the shift gives the relative yaw. The score is
``inliers / min(n_query_features, n_match_features)`` — the fraction of the smaller feature set that agrees on one
yaw — which makes one threshold work across places with many or few features. With ``verify="none"`` the score
is HBST's matching ratio (votes / query features) and no relative pose is returned.

Relative pose: ``T_match_query`` is a rotation about z by ``yaw = 2 pi * shift / W`` where ``shift`` is the query
column minus the match column of the same landmark (eq. 2 columns decrease with azimuth).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np

from placerec.errors import ArtifactError
from placerec.image import ImageParams, make_image
from placerec.io.atomic import load_artifact, save_artifact
from placerec.recognizer import Description, DescriptorRecognizer, params_key
from placerec.retrieval.hbst import HBST
from placerec.types import Candidate, Scan

__all__ = ["VisualParams", "VisualFrontend", "VisualHBST", "yaw_pose", "shift_consensus", "visual_frontend_key", "describe_visual"]

_KIND = "visual-hbst-db"
_VERSION = 1


@dataclass(frozen=True)
class HBSTParams:
    """HBST settings (paper: delta_max 0.1, N_max 50). ``threshold`` None = srrg's 25 for 256-bit ORB, scaled
    with the descriptor length (50 for 512-bit BRISK)."""

    delta_max: float = 0.1
    leaf_size: int = 50
    max_depth: int = 75
    threshold: int | None = None


@dataclass(frozen=True)
class VisualParams:
    """Image formation, features (registry name + overrides of its Table I defaults), HBST and verification."""

    features: str = "orb"
    feature_params: dict[str, Any] = field(default_factory=dict)
    image: ImageParams = field(default_factory=ImageParams)
    hbst: HBSTParams = field(default_factory=HBSTParams)
    verify: Literal["shift", "none"] = "shift"
    n_verify: int = 10
    shift_tolerance_px: int = 8
    row_tolerance_px: int = 4


def yaw_pose(yaw_rad: float) -> np.ndarray:
    """4x4 rotation about z by ``yaw_rad``."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    return T


def visual_frontend_key(params: Any) -> str:
    """Cache key of the intensity-image + features front end (``params`` has ``features``, ``feature_params``
    and ``image``): equal for every visual pipeline with the same front-end settings, so they share descriptions."""
    return params_key(
        "visual", {"features": params.features, "fp": params.feature_params, "image": asdict(params.image)}
    )


def describe_visual(scan: Scan, image_params: ImageParams, extractor: Any) -> Description:
    """The visual front end: intensity image, then features -> keypoints (K, 2), descriptors, image width."""
    img = make_image(scan, image_params)
    feats = extractor.extract(img.image)
    return {
        "keypoints": np.asarray(feats.keypoints, np.float32).reshape(-1, 2),
        "descriptors": np.ascontiguousarray(feats.descriptors),
        "width": np.array(img.image.shape[1], np.int64),
    }


def shift_consensus(
    uq: np.ndarray, vq: np.ndarray, ur: np.ndarray, vr: np.ndarray, width: int, shift_tol: int, row_tol: int
) -> tuple[int, float]:
    """Inlier count and best column shift (query minus reference, circular) of matched keypoints."""
    ok = np.abs(vq - vr) <= row_tol
    if not ok.any():
        return 0, 0.0
    shifts = np.mod(uq[ok] - ur[ok], width)
    # circular density: count matches within +-shift_tol of every candidate shift via a wrapped cumulative sum
    hist = np.bincount(np.floor(shifts).astype(np.int64) % width, minlength=width)
    cum = np.concatenate([[0], np.cumsum(np.r_[hist, hist, hist])])
    centres = np.arange(width) + width
    counts = cum[centres + shift_tol + 1] - cum[centres - shift_tol]
    best = int(np.argmax(counts))
    d = np.mod(shifts - best + width / 2, width) - width / 2
    inl = np.abs(d) <= shift_tol + 0.5
    refined = best + float(np.mean(d[inl])) if inl.any() else float(best)
    return int(inl.sum()), refined


class VisualFrontend:
    """The intensity-image front end shared by the visual pipelines: needs ``params`` (with ``image`` and the
    feature settings) and ``extractor``; scans with equal front-end settings share their descriptions."""

    params: Any
    extractor: Any

    @property
    def frontend_key(self) -> str:
        return visual_frontend_key(self.params)

    def describe(self, scan: Scan) -> Description:
        return describe_visual(scan, self.params.image, self.extractor)


class VisualHBST(VisualFrontend, DescriptorRecognizer):
    """`PlaceRecognizer` of the VPR paper's 2D modality with HBST retrieval (ORB-HBST, BRISK-HBST)."""

    name: ClassVar[str] = "visual-hbst"
    Params: ClassVar[type] = VisualParams

    def __init__(self, params: VisualParams | None = None, **overrides: Any) -> None:
        super().__init__(params, **overrides)
        from placerec.features import make_extractor

        self.extractor = make_extractor(self.params.features, **self.params.feature_params)
        self.tree = self._new_tree()
        self._keypoints: dict[int, np.ndarray] = {}
        self._descriptors: dict[int, np.ndarray] = {}
        self._width: dict[int, int] = {}
        self._order: list[int] = []

    def _new_tree(self) -> HBST:
        hb = self.params.hbst
        threshold = hb.threshold or round(25 * self.extractor.descriptor_size * 8 / 256)
        return HBST(hb.delta_max, hb.leaf_size, hb.max_depth, threshold)

    def add_description(self, scan_id: int, description: Description, pose: np.ndarray | None = None) -> None:
        scan_id = int(scan_id)
        self.tree.add(scan_id, description["descriptors"])
        self._keypoints[scan_id] = np.asarray(description["keypoints"], np.float32)
        self._descriptors[scan_id] = np.asarray(description["descriptors"], np.uint8)
        self._width[scan_id] = int(description["width"])
        self._order.append(scan_id)

    @property
    def _n_bytes(self) -> int:
        return self.tree.n_bytes or 32

    def query_description(
        self, description: Description, k: int = 1, max_id: int | None = None, query_id: int = -1
    ) -> list[Candidate]:
        desc = description["descriptors"]
        n_q = int(desc.shape[0])
        if n_q == 0 or len(self.tree) == 0:
            return []
        result = self.tree.match(desc, max_image_id=max_id)
        votes = result.scores_per_image()
        if len(votes) == 0:
            return []
        if self.params.verify == "none":
            return [
                Candidate(query_id, int(i), float(r), None, int(n), {"votes": int(n)})
                for i, n, r in zip(
                    votes.image_ids[:k], votes.n_matches[:k], votes.matching_ratio[:k], strict=True
                )
            ]
        kq = np.asarray(description["keypoints"], np.float32)
        width = int(description["width"])
        out = []
        for image_id, n_votes in zip(votes.image_ids[: self.params.n_verify], votes.n_matches, strict=False):
            sel = result.image_id == image_id
            kr = self._keypoints[int(image_id)]
            q_kp, r_kp = kq[result.query_idx[sel]], kr[result.keypoint_idx[sel]]
            inliers, shift = shift_consensus(
                q_kp[:, 0],
                q_kp[:, 1],
                r_kp[:, 0],
                r_kp[:, 1],
                width,
                self.params.shift_tolerance_px,
                self.params.row_tolerance_px,
            )
            score = inliers / max(1, min(n_q, kr.shape[0]))
            yaw = 2.0 * np.pi * shift / width
            yaw = (yaw + np.pi) % (2 * np.pi) - np.pi
            out.append(
                Candidate(
                    query_id,
                    int(image_id),
                    float(score),
                    yaw_pose(yaw),
                    inliers,
                    {"votes": int(n_votes), "yaw_deg": float(np.degrees(yaw))},
                )
            )
        out.sort(key=lambda c: (-c.score, c.match_id))
        return out[:k]

    def save(self, path: str | Path) -> None:
        """Store every added image's keypoints and descriptors (in insertion order) with the parameters; `load`
        re-inserts them, which rebuilds the identical tree (HBST is deterministic in the insertion order)."""
        ids = np.array(self._order, dtype=np.int64)
        arrays = {
            "ids": ids,
            "counts": np.array([self._keypoints[i].shape[0] for i in self._order], dtype=np.int64),
            "widths": np.array([self._width[i] for i in self._order], dtype=np.int64),
            "keypoints": _stack([self._keypoints[i] for i in self._order], (0, 2), np.float32),
            "descriptors": _stack([self._descriptors[i] for i in self._order], (0, self._n_bytes), np.uint8),
        }
        save_artifact(path, _KIND, _VERSION, arrays, {"params": _jsonable(self.params)})

    def load(self, path: str | Path) -> None:
        arrays, header = load_artifact(path, _KIND, (_VERSION,))
        if header["meta"].get("params") != _jsonable(self.params):
            raise ArtifactError(
                f"{path}: database was made with other parameters: {header['meta'].get('params')}"
            )
        self.tree = self._new_tree()
        self._keypoints, self._descriptors, self._width, self._order = {}, {}, {}, []
        offsets = np.r_[0, np.cumsum(arrays["counts"])]
        for i, a, b, w in zip(arrays["ids"], offsets[:-1], offsets[1:], arrays["widths"], strict=True):
            desc = {
                "keypoints": arrays["keypoints"][a:b],
                "descriptors": arrays["descriptors"][a:b],
                "width": w,
            }
            self.add_description(int(i), desc)


def _stack(parts: list[np.ndarray], empty_shape: tuple[int, int], dtype: type) -> np.ndarray:
    return np.concatenate(parts) if parts else np.zeros(empty_shape, dtype)


def _jsonable(params: Any) -> Any:
    import json

    return json.loads(json.dumps(asdict(params), default=str))
