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

from collections.abc import Mapping
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field, SerializeAsAny, ValidationError, model_validator

from placerec.errors import ArtifactError, ScanDataError
from placerec.features.registry import ExtractorParams, extractor_params
from placerec.image import ImageParams, make_image
from placerec.io.artifact_schema import Member, check_counts, check_members, check_unique
from placerec.io.atomic import load_artifact, save_artifact
from placerec.params import Params, SectionError
from placerec.recognizer import (
    Recognizer,
    check_saved_params,
    params_key,
    require_points,
    require_varying_intensity,
)
from placerec.retrieval.hbst import HBST, HBSTParams, default_threshold
from placerec.types import Candidate, Description, Scan

__all__ = [
    "HBSTParams",
    "VisualFrontendParams",
    "VisualParams",
    "VisualFrontend",
    "VisualHBST",
    "yaw_pose",
    "shift_consensus",
    "visual_frontend_key",
    "describe_visual",
    "pack_features",
    "features_schema",
    "stored_features",
    "MAX_IMAGE_WIDTH",
]

_KIND = "visual-hbst-db"
_VERSION = 1
#: Widest intensity image (px) a visual front end makes and a saved database may record (LiDARs have at most a
#: few thousand columns); a wider one is a `ScanDataError` when described, an `ArtifactError` when loaded.
MAX_IMAGE_WIDTH = 1 << 15


class VisualFrontendParams(Params):
    """The intensity-image front end: image formation and a registered feature extractor with its parameters
    (``feature_params``: overrides of that extractor's Table I defaults, validated by its own model)."""

    features: str = Field(
        "orb", description="feature extractor (placerec.features.EXTRACTORS; VPR paper Table I)"
    )
    feature_params: SerializeAsAny[ExtractorParams]
    image: ImageParams = Field(default_factory=ImageParams)

    @model_validator(mode="before")
    @classmethod
    def _extractor_params(cls, data: Any) -> Any:
        """Validate ``feature_params`` with the model of the extractor named by ``features``."""
        if not isinstance(data, Mapping):
            return data
        name = data.get("features", cls.model_fields["features"].default)
        # a bad ``features`` value is reported on that key; the common settings stand in for the extractor's
        model = extractor_params(name) if isinstance(name, str) else ExtractorParams
        given = data.get("feature_params")
        if isinstance(given, model):
            return data
        if isinstance(given, ExtractorParams):
            raise ValueError(
                f"feature_params is a {type(given).__name__}, not the {model.__name__} of {name!r}"
            )
        if given is not None and not isinstance(given, Mapping):
            raise ValueError(f"feature_params must be a mapping of {name!r} parameters")
        try:
            return {**data, "feature_params": model.model_validate(given or {})}
        except ValidationError as exc:
            raise SectionError(exc, model, "feature_params") from None


class VisualParams(VisualFrontendParams):
    """Image formation, features, HBST and verification (see the module docstring)."""

    hbst: HBSTParams = Field(default_factory=HBSTParams)
    verify: Literal["shift", "none"] = Field("shift", description="column-shift consensus or HBST's ratio")
    n_verify: int = Field(10, ge=1, description="best HBST images checked geometrically")
    shift_tolerance_px: int = Field(8, ge=0, description="px; column-shift bin half-width")
    row_tolerance_px: int = Field(4, ge=0, description="px; row difference allowed in a match")


def yaw_pose(yaw_rad: float) -> np.ndarray:
    """4x4 rotation about z by ``yaw_rad``."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    return T


def visual_frontend_key(params: VisualFrontendParams) -> str:
    """Cache key of the intensity-image + features front end: equal for every visual pipeline with the same
    front-end settings, so they share descriptions."""
    front = params.model_dump(mode="json", include={"features", "feature_params", "image"})
    return params_key("visual", front)


def describe_visual(scan: Scan, image_params: ImageParams, extractor: Any) -> Description:
    """The visual front end: intensity image, then features -> keypoints (K, 2), descriptors, image width.

    `ScanDataError` for a scan with too few valid points (`placerec.recognizer.require_points`) or one whose valid
    points all have the same intensity: its image would show only where returns are missing, not the place.
    """
    ok = require_points(scan, "visual front end")
    require_varying_intensity(scan, ok, "visual front end", "intensity images need varying intensity")
    img = make_image(scan, image_params)
    if img.image.shape[1] > MAX_IMAGE_WIDTH:
        raise ScanDataError(
            f"{scan.source or 'scan'}: visual front end: an intensity image {img.image.shape[1]} px wide is "
            f"over {MAX_IMAGE_WIDTH} px (set image.width)"
        )
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
    """The intensity-image front end shared by the visual pipelines: needs ``params`` (`VisualFrontendParams`)
    and ``extractor``; scans with equal front-end settings share their descriptions."""

    params: VisualFrontendParams
    extractor: Any

    @property
    def frontend_key(self) -> str:
        return visual_frontend_key(self.params)

    def describe(self, scan: Scan) -> Description:
        return describe_visual(scan, self.params.image, self.extractor)


class VisualHBST(VisualFrontend, Recognizer):
    """`PlaceRecognizer` of the VPR paper's 2D modality with HBST retrieval (ORB-HBST, BRISK-HBST)."""

    name: ClassVar[str] = "visual-hbst"
    Params: ClassVar[type[Params]] = VisualParams

    def __init__(self, params: VisualParams | None = None, **overrides: Any) -> None:
        super().__init__(params, **overrides)
        from placerec.features import make_extractor

        self.extractor = make_extractor(self.params.features, self.params.feature_params)
        self.tree = self._new_tree()
        self._keypoints: dict[int, np.ndarray] = {}
        self._descriptors: dict[int, np.ndarray] = {}
        self._width: dict[int, int] = {}
        self._order: list[int] = []

    def _new_tree(self) -> HBST:
        hb = self.params.hbst
        return HBST(hb, threshold=hb.threshold or default_threshold(self.extractor.descriptor_size))

    def add_description(self, scan_id: int, description: Description, pose: np.ndarray | None = None) -> None:
        scan_id = int(scan_id)
        if scan_id in self._width:
            raise ScanDataError(f"{self.name}: id {scan_id} was added already")
        self.tree.add(scan_id, description["descriptors"])
        self._keypoints[scan_id] = np.asarray(description["keypoints"], np.float32)
        self._descriptors[scan_id] = np.asarray(description["descriptors"], np.uint8)
        self._width[scan_id] = int(description["width"])
        self._order.append(scan_id)

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
        arrays = pack_features(
            self._order,
            self._keypoints,
            self._descriptors,
            self._width,
            self.extractor.descriptor_size,
            np.uint8,
        )
        save_artifact(path, _KIND, _VERSION, arrays, {"params": self.params.model_dump(mode="json")})

    def load(self, path: str | Path) -> None:
        arrays, header = load_artifact(path, _KIND, (_VERSION,))
        check_saved_params(path, header, self.params)
        check_members(arrays, features_schema(self.extractor.descriptor_size, binary=True), path)
        stored = stored_features(path, arrays, self.params.image)
        self.tree = self._new_tree()
        self._keypoints, self._descriptors, self._width, self._order = {}, {}, {}, []
        for scan_id, desc in stored:
            self.add_description(scan_id, desc)


def pack_features(
    order: list[int],
    keypoints: dict[int, np.ndarray],
    descriptors: dict[int, np.ndarray],
    widths: dict[int, int],
    dim: int,
    dtype: type,
) -> dict[str, np.ndarray]:
    """The arrays of a visual database: per-image counts and widths, stacked keypoints and descriptors."""
    return {
        "ids": np.asarray(order, dtype=np.int64),
        "counts": np.array([keypoints[i].shape[0] for i in order], dtype=np.int64),
        "widths": np.array([widths[i] for i in order], dtype=np.int64),
        "keypoints": _stack([keypoints[i] for i in order], (0, 2), np.float32),
        "descriptors": _stack([descriptors[i] for i in order], (0, dim), dtype),
    }


def features_schema(dim: int, binary: bool) -> dict[str, Member]:
    """The arrays of a saved visual database (`pack_features`) with ``dim``-wide binary or float descriptors."""
    return {
        "ids": Member("iu", ("n_images",)),
        "counts": Member("iu", ("n_images",), min_value=0),
        "widths": Member("iu", ("n_images",), min_value=1),
        "keypoints": Member("f", ("n_features", 2), finite=True),
        "descriptors": Member("u" if binary else "f", ("n_features", dim), finite=True),
    }


def stored_features(
    path: str | Path, arrays: Mapping[str, np.ndarray], image: ImageParams
) -> list[tuple[int, Description]]:
    """(id, description) of every image of a saved visual database whose arrays passed `features_schema`, after
    checking that ids are unique, counts add up, widths are ``image.width`` (when set; else at most
    `MAX_IMAGE_WIDTH`) and keypoints lie in their images (`ArtifactError` otherwise)."""
    ids, counts, widths, kp = arrays["ids"], arrays["counts"], arrays["widths"], arrays["keypoints"]
    check_unique(ids, path, "ids")
    check_counts(counts, kp.shape[0], path, "counts")
    bad = widths != image.width if image.width is not None else widths > MAX_IMAGE_WIDTH
    if bad.any():
        expected = f"{image.width} (image.width)" if image.width is not None else f"at most {MAX_IMAGE_WIDTH}"
        raise ArtifactError(f"{path}: 'widths' holds {int(widths[bad][0])} px; expected {expected}")
    u = kp[:, 0]  # sub-pixel positions may reach half a pixel past the border
    if ((u < -1) | (u > np.repeat(widths, counts))).any():
        raise ArtifactError(f"{path}: 'keypoints' lie outside their images ('widths')")
    offsets = np.r_[0, np.cumsum(counts)]
    desc = arrays["descriptors"]
    return [
        (int(i), {"keypoints": kp[a:b], "descriptors": desc[a:b], "width": np.int64(w)})
        for i, a, b, w in zip(ids, offsets[:-1], offsets[1:], widths, strict=True)
    ]


def _stack(parts: list[np.ndarray], empty_shape: tuple[int, int], dtype: type) -> np.ndarray:
    return np.concatenate(parts).astype(dtype, copy=False) if parts else np.zeros(empty_shape, dtype)
