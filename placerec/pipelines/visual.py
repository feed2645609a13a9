"""The 2D visual pipeline (VPR paper): intensity image -> features -> HBST retrieval -> verification.

Front end: the intensity image (`placerec.image`), features, and for verification each keypoint's 3D point
(``keypoint_xyz``: the scan point the projection kept in its pixel, `keypoint_points`) and the scan voxelised for
ICP (``cloud``); the description cache holds them all.

Retrieval: HBST gives each stored image a vote count (one vote per query descriptor that has a match in it,
`placerec.retrieval.hbst`). The registered pipelines match at 50 bits per 256 (``hbst.threshold``) instead of
srrg_hbst's 25: on intensity images the nearest descriptor of a revisit lies 50-70 bits away, and at 25 bits HBST
proposes one image per revisit query (``docs/vpr_results.md``, 'Why ORB-HBST proposed so few candidates').

Verification (``verify.enabled``, default; `placerec.verify.candidates`): the ``verify.top_k`` images with most
votes are verified: correspondences are the mutual nearest features of query and candidate (``verify_matches``,
or the retrieval's own matches), as 3D points -> RANSAC -> ICP (`placerec.verify.verify`). ``score`` is the
verified score in [0, 1], ``relative_pose`` the 6-DoF ``T_match_query``, candidates are re-ranked by it; HBST's
matching ratio moves to ``extra["retrieval_score"]``.

Without verification, ``check="shift"`` checks the ``n_check`` images with most votes: in a cylindrical image a
revisit from (nearly) the same place differs by a yaw, i.e. a circular column shift, and by small row offsets.
It histograms the column shifts of the matches, takes the densest shift (within ``shift_tolerance_px``) among
matches whose rows differ by at most ``row_tolerance_px``, and counts those as inliers; the shift gives the
relative yaw. The score is ``inliers / min(n_query_features, n_match_features)``, and ``T_match_query`` a rotation
about z by ``yaw = 2 pi * shift / W`` where ``shift`` is the query column minus the match column of the same
landmark (eq. 2 columns decrease with azimuth). ``check="none"``: HBST's matching ratio, no relative pose.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import Any, ClassVar, Generic, Literal, TypeVar

import numpy as np
from pydantic import Field, SerializeAsAny, ValidationError, model_validator

from placerec.errors import ArtifactError, ScanDataError, short_repr
from placerec.features.registry import ExtractorParams, extractor_params
from placerec.image import ImageParams, IntensityImage, make_image
from placerec.image.correspondence import keypoint_points
from placerec.io.artifact_schema import check_members
from placerec.io.atomic import load_artifact, save_artifact
from placerec.params import Params, SectionError
from placerec.pipelines.visual_store import MAX_IMAGE_WIDTH, features_schema, pack_features, stored_features
from placerec.recognizer import (
    Recognizer,
    check_saved_params,
    params_key,
    require_points,
    require_varying_intensity,
)
from placerec.retrieval.hbst import HBST, TREE_SCHEMA, HBSTParams, default_threshold
from placerec.threads import side_by_side
from placerec.types import Candidate, Description, MotionPrior, Scan, take_rows
from placerec.verify import VerifyParams
from placerec.verify.candidates import (
    CloudStore,
    Retrieved,
    VerifiedParams,
    feature_arrays,
    scan_cloud,
    verify_candidates,
    verify_near,
)
from placerec.verify.guided import answers, guided_nearest, usable
from placerec.verify.icp import IcpCloud
from placerec.verify.matching import mutual_nearest
from placerec.verify.verify import hypothesise

__all__ = [
    "HBSTParams",
    "VisualFrontendParams",
    "VisualPipelineParams",
    "VisualParams",
    "VisualFrontend",
    "VisualHBST",
    "yaw_pose",
    "shift_consensus",
    "visual_frontend_key",
    "describe_visual",
    "mutual_nearest",
    "pack_features",
    "features_schema",
    "stored_features",
    "MAX_IMAGE_WIDTH",
]

_KIND = "visual-hbst-db"
_VERSION = 2
_TREE_PREFIX = "tree_"


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


class VisualPipelineParams(VisualFrontendParams):
    """The front end plus what every visual pipeline shares: the verification stage (``verify``) or, without it,
    the column-shift check (``check``, ``n_check`` and its tolerances)."""

    verify: VerifiedParams = Field(
        default_factory=VerifiedParams,
        description="RANSAC on the feature matches' 3D points, then ICP, on the top-k retrieved candidates",
    )
    verify_matches: Literal["brute-force", "retrieval"] = Field(
        "brute-force",
        description="correspondences to verify: mutual nearest features of query and candidate, or the "
        "retrieval's own matches (HBST leaves, DBoW direct index)",
    )
    check: Literal["shift", "none"] = Field(
        "shift",
        description="without verification: column-shift consensus (yaw) or the raw retrieval score",
    )
    n_check: int = Field(10, ge=1, description="best retrieved images checked by the column-shift consensus")
    shift_tolerance_px: int = Field(8, ge=0, description="px; column-shift bin half-width")
    row_tolerance_px: int = Field(4, ge=0, description="px; row difference allowed in a match")


class VisualParams(VisualPipelineParams):
    """Image formation, features, HBST and verification (see the module docstring)."""

    hbst: HBSTParams = Field(default_factory=HBSTParams)


def yaw_pose(yaw_rad: float) -> np.ndarray:
    """4x4 rotation about z by ``yaw_rad``."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    return T


def visual_frontend_key(params: VisualPipelineParams) -> str:
    """Cache key of the intensity-image + features front end (and, with verification, the ICP cloud's voxel grid
    and range): equal for every visual pipeline with the same front-end settings, so they share descriptions."""
    front = params.model_dump(mode="json", include={"features", "feature_params", "image"})
    if params.verify.enabled:
        icp = params.verify.icp
        front["cloud"] = {"voxel_size": icp.voxel_size, "max_range": icp.max_range}
    return params_key("visual", front)


def describe_visual(
    scan: Scan,
    image_params: ImageParams,
    extractor: Any,
    verify: VerifyParams | None = None,
    keep: Callable[[np.ndarray], None] | None = None,
) -> Description:
    """The visual front end: intensity image, then features -> keypoints (K, 2), descriptors, image width and
    ``keypoint_xyz`` (K, 3), the scan point of each keypoint's pixel (`keypoint_points`; NaN where there is none);
    with ``verify`` (the verification stage's parameters) also ``cloud``, the scan voxelised for ICP
    (`placerec.verify.candidates.scan_cloud`). ``keep`` is given the intensity image.

    `ScanDataError` for a scan with too few valid points (`placerec.recognizer.require_points`) or one whose valid
    points all have the same intensity: its image would show only where returns are missing, not the place.
    """
    # the image and its features on the helper thread while this one checks the scan and voxelises the ICP cloud
    # (`placerec.threads.side_by_side`: both mostly outside the GIL); a refused scan's image is never used
    image_job = side_by_side(_image_features, scan, image_params, extractor)
    ok = require_points(scan, "visual front end")
    require_varying_intensity(scan, ok, "visual front end", "intensity images need varying intensity")
    cloud = None if verify is None else scan_cloud(take_rows(scan.xyz, ok), verify)
    img, feats = image_job.result()
    if keep is not None:
        keep(img.image)
    keypoints = np.asarray(feats.keypoints, np.float32).reshape(-1, 2)
    idx = keypoint_points(keypoints, img.point_index)
    kp_xyz = np.full((idx.size, 3), np.nan, np.float32)
    kp_xyz[idx >= 0] = scan.xyz[idx[idx >= 0]]
    out = {
        "keypoints": keypoints,
        "descriptors": np.ascontiguousarray(feats.descriptors),
        "width": np.array(img.image.shape[1], np.int64),
        "keypoint_xyz": kp_xyz,
    }
    if cloud is not None:
        out["cloud"] = cloud
    return out


def _image_features(scan: Scan, image_params: ImageParams, extractor: Any) -> tuple[IntensityImage, Any]:
    """The intensity image of ``scan`` (refused over `MAX_IMAGE_WIDTH` px) and ``extractor``'s features of it."""
    img = make_image(scan, image_params)
    if img.image.shape[1] > MAX_IMAGE_WIDTH:
        raise ScanDataError(
            f"{scan.source or 'scan'}: visual front end: an intensity image {img.image.shape[1]} px wide is "
            f"over {MAX_IMAGE_WIDTH} px (set image.width)"
        )
    return img, extractor.extract(img.image)


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


#: a candidate to match: (match id, retrieval score, query feature ids, match feature ids, extra)
_ToMatch = tuple[int, float, np.ndarray, np.ndarray, dict[str, Any]]

#: the parameters class of a visual pipeline
VP = TypeVar("VP", bound=VisualPipelineParams)


class VisualFrontend(Generic[VP]):
    """The intensity-image front end and verification state shared by the visual pipelines: needs ``params``
    (`VisualPipelineParams`) and ``extractor``; scans with equal front-end settings share their descriptions.
    A subclass calls `_reset_features` with its database, `_add_features` in ``add_description`` and `_verified`
    for the candidates it retrieved."""

    name: ClassVar[str]
    params: VP
    extractor: Any
    #: (scan, its intensity image) of the scan `describe` saw last, so that a viewer shows the image without
    #: making it again (a viewer compares the scan by identity)
    last_image: tuple[Scan, np.ndarray] | None = None

    @property
    def frontend_key(self) -> str:
        return visual_frontend_key(self.params)

    def describe(self, scan: Scan) -> Description:
        """`describe_visual` with this pipeline's settings; the intensity image is kept as `last_image`."""
        p = self.params

        def keep(image: np.ndarray) -> None:
            self.last_image = (scan, image)

        return describe_visual(scan, p.image, self.extractor, p.verify if p.verify.enabled else None, keep)

    def _reset_features(self) -> None:
        """Empty the per-image features (keypoints, descriptors, image width), their 3D points and ICP clouds. The
        keypoints, points and descriptors are kept within their share of ``verify.cloud_budget_mb``, the oldest
        beyond it in the clouds' spill file (`placerec.verify.candidates.feature_arrays`)."""
        self._clouds = CloudStore.for_pipeline(self.params.verify)
        self._keypoints, self._descriptors, self._kp_xyz = feature_arrays(self._clouds, 3)
        self._width: dict[int, int] = {}

    def _add_features(self, scan_id: int, description: Description, descriptors: np.ndarray) -> None:
        """Keep a description being added: its keypoints, ``descriptors`` (as the retrieval stores them), image
        width, the keypoints' 3D points and (with verification) the ICP cloud; `ScanDataError` for an id added
        already."""
        if scan_id in self._width:
            raise ScanDataError(f"{self.name}: id {scan_id} was added already")
        n = np.asarray(description["keypoints"]).reshape(-1, 2).shape[0]
        self._kp_xyz[scan_id] = _keypoint_xyz(self.name, description, n)
        if self.params.verify.enabled:
            self._clouds.add(scan_id, _cloud(self.name, description))
        self._keypoints[scan_id] = np.asarray(description["keypoints"], np.float32).reshape(-1, 2)
        self._descriptors[scan_id] = descriptors
        self._width[scan_id] = int(description["width"])

    def _verified(
        self,
        description: Description,
        retrieved: list[Retrieved],
        query_id: int,
        k: int,
        prior: MotionPrior | None = None,
        max_id: int | None = None,
    ) -> list[Candidate]:
        """`placerec.verify.candidates.verify_candidates` on ``retrieved`` (best retrieval first). With a motion
        ``prior`` and ``verify.guided.near_metres`` the second chances come in order of how well they register:
        the candidates on their own matches first; where none is an answer (`answers`), the place `verify_near`
        registers among the entries up to ``max_id`` (a place predicted near, by ICP from the prediction); only
        where none is either, the second chances of the candidates RANSAC rejected: their matching within the
        prior (``retrieved``'s ``guided``), which may pose a place tens of metres away (one `verify_candidates`
        call, ``between`` its two steps: nothing is verified twice)."""
        vp = self.params.verify
        cloud = _cloud(self.name, description)
        g = vp.guided
        if prior is None or not g.enabled or g.near_metres is None:
            return verify_candidates(cloud, retrieved, self._clouds, vp, query_id, k)

        def eligible(match_id: int) -> bool:
            return match_id in self._width and (max_id is None or match_id <= max_id)

        def near_first(own: list[Candidate], source: np.ndarray | IcpCloud) -> list[Candidate] | None:
            if answers(own, prior, g):
                return own
            near = verify_near(source, prior, self._clouds, vp, eligible, query_id)
            if near is not None:
                return [near, *own][:k]
            return None if any(r.guided is not None for r in retrieved[: vp.top_k]) else own

        return verify_candidates(cloud, retrieved, self._clouds, vp, query_id, k, between=near_first)

    def _retrieved_all(
        self,
        description: Description,
        todo: list[_ToMatch],
        spent_ms: float = 0.0,
        prior: MotionPrior | None = None,
    ) -> list[Retrieved]:
        """`_retrieved` of each (match id, score, query feature ids, match feature ids, extra) in ``todo``, in its
        order, each with its RANSAC hypothesis (`Retrieved.hypothesis`). Every other candidate is matched and
        hypothesised on the helper thread (`placerec.threads.side_by_side`: the compiled matching and RANSAC search
        run without the GIL, so one thread's RANSAC overlaps the other's matching; each candidate's matches and
        hypothesis are what they are alone, RANSAC seeded per call, and the hand-over is one for all of them):
        SuperPoint's 300 x 256 floats take ~4 ms a candidate, so a real HDL-64 query's 20 go from 104 to 67 ms;
        40 candidates of 1000 ORB features (the Avia's keyframes) 84 -> 42 ms, of 300 ORB features 8.7 -> 4.6 ms,
        on 2 idle cores. With a motion ``prior`` and ``verify.guided`` each also carries its matching within the
        prior (`_guided`), made only if RANSAC finds no pose on these."""
        vp = self.params.verify

        def hypothesised(r: Retrieved) -> Retrieved:
            t0 = time.perf_counter()
            r.hypothesis = hypothesise(r.src_kp, r.dst_kp, r.init, vp, r.quality)
            r.verify_ms += (time.perf_counter() - t0) * 1e3
            return r

        def each(part: list[_ToMatch]) -> list[Retrieved]:
            return [hypothesised(self._retrieved(description, *item, spent_ms)) for item in part]

        # with the retrieval's own matches (verify_matches="retrieval") there is no matching to share
        matching = self.params.verify_matches == "brute-force"
        theirs = side_by_side(each, todo[1::2]) if len(todo) > 1 and matching else None
        if theirs is None:
            out = each(todo)
        else:
            mine = each(todo[::2])
            other = iter(theirs.result())
            out = [mine[j // 2] if j % 2 == 0 else next(other) for j in range(len(todo))]
        if prior is not None and self.params.verify.guided.enabled:
            for r in out:
                r.guided = partial(self._guided, description, r, prior)
        return out

    def _guided(self, description: Description, retrieved: Retrieved, prior: MotionPrior) -> Retrieved:
        """``retrieved`` with the correspondences ``prior`` allows (`placerec.verify.guided.guided_nearest`; none
        where it predicts nothing for the candidate, or only more loosely than ``verify.guided.max_metres``),
        marked ``guided`` in its ``extra``."""
        t0 = time.perf_counter()
        match_id = retrieved.match_id
        prediction = usable(prior.predict(match_id), self.params.verify.guided)
        desc = np.asarray(description["descriptors"])
        xq = _keypoint_xyz(self.name, description, desc.shape[0])
        xm = self._kp_xyz[match_id]
        if prediction is None:
            qi, mi, dist = np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
        else:
            qi, mi, dist = guided_nearest(desc, xq, self._descriptors[match_id], xm, prediction)
        ms = retrieved.verify_ms + (time.perf_counter() - t0) * 1e3
        return replace(
            retrieved,
            src_kp=xq[qi],
            dst_kp=xm[mi],
            quality=dist,
            extra={**retrieved.extra, "matches": int(qi.size), "guided": 1},
            verify_ms=ms,
            pairs=np.stack([qi, mi], axis=1),
            guided=None,
            hypothesis=None,
        )

    def _retrieved(
        self,
        description: Description,
        match_id: int,
        score: float,
        query_idx: np.ndarray,
        match_idx: np.ndarray,
        extra: dict[str, Any],
        spent_ms: float = 0.0,
    ) -> Retrieved:
        """A candidate to verify: with ``verify_matches="retrieval"`` the retrieval's feature matches (query
        feature ``query_idx[i]`` <-> the candidate's ``match_idx[i]``), else the `mutual_nearest` features; the
        pairs whose keypoints both have a 3D point become correspondences (descriptor distance as quality). The
        time taken, plus ``spent_ms`` already spent on this candidate's matches, is its ``verify_ms`` (the runner's
        verify stage)."""
        t0 = time.perf_counter()
        desc = description["descriptors"]
        quality = None
        if self.params.verify_matches == "brute-force":
            query_idx, match_idx, quality = mutual_nearest(desc, self._descriptors[match_id])
        n = np.asarray(desc).shape[0]
        src = _keypoint_xyz(self.name, description, n)[query_idx]
        dst = self._kp_xyz[match_id][match_idx]
        ok = np.isfinite(src).all(axis=1) & np.isfinite(dst).all(axis=1)
        q = None if quality is None else quality[ok]
        ms = spent_ms + (time.perf_counter() - t0) * 1e3
        pairs = np.stack([np.asarray(query_idx)[ok], np.asarray(match_idx)[ok]], axis=1)
        return Retrieved(
            match_id,
            score,
            src[ok],
            dst[ok],
            q,
            extra={**extra, "matches": int(ok.sum())},
            verify_ms=ms,
            pairs=pairs,
        )


def _keypoint_xyz(name: str, description: Description, n: int) -> np.ndarray:
    xyz = description.get("keypoint_xyz")
    if xyz is None:
        raise ScanDataError(f"{name}: the description has no 'keypoint_xyz' (describe() gives it)")
    xyz = np.asarray(xyz, np.float32)
    if xyz.shape != (n, 3):
        raise ScanDataError(f"{name}: 'keypoint_xyz' has shape {xyz.shape} for {n} keypoints")
    return xyz


def _cloud(name: str, description: Description) -> np.ndarray:
    if "cloud" not in description:
        raise ScanDataError(
            f"{name}: verification needs the description's 'cloud' (describe() gives it with verify.enabled)"
        )
    return description["cloud"]


class VisualHBST(VisualFrontend[VisualParams], Recognizer[VisualParams]):
    """`PlaceRecognizer` of the VPR paper's 2D modality with HBST retrieval (ORB-HBST, BRISK-HBST)."""

    name: ClassVar[str] = "visual-hbst"
    Params: ClassVar[type[Params]] = VisualParams

    def __init__(self, params: VisualParams | None = None, **overrides: Any) -> None:
        super().__init__(params, **overrides)
        from placerec.features import make_extractor

        self.extractor = make_extractor(self.params.features, self.params.feature_params)
        self._reset()

    def _reset(self) -> None:
        hb = self.params.hbst
        self.tree = HBST(hb, threshold=hb.threshold or default_threshold(self.extractor.descriptor_size))
        self._order: list[int] = []
        self._reset_features()

    def add_description(self, scan_id: int, description: Description, pose: np.ndarray | None = None) -> None:
        scan_id = int(scan_id)
        self._add_features(scan_id, description, np.asarray(description["descriptors"], np.uint8))
        self.tree.add(scan_id, description["descriptors"])
        self._order.append(scan_id)

    def query_description(
        self,
        description: Description,
        k: int = 1,
        max_id: int | None = None,
        query_id: int = -1,
        prior: MotionPrior | None = None,
    ) -> list[Candidate]:
        desc = description["descriptors"]
        n_q = int(desc.shape[0])
        if n_q == 0 or len(self.tree) == 0:
            return []
        result = self.tree.match(desc, max_image_id=max_id)
        votes = result.scores_per_image()
        if len(votes) == 0:
            return []
        p = self.params
        if p.verify.enabled:
            todo = []
            for image_id, n_votes, ratio in zip(
                votes.image_ids[: p.verify.top_k], votes.n_matches, votes.matching_ratio, strict=False
            ):
                sel = result.image_id == image_id
                extra = {"votes": int(n_votes)}
                todo.append(
                    (int(image_id), float(ratio), result.query_idx[sel], result.keypoint_idx[sel], extra)
                )
            return self._verified(
                description, self._retrieved_all(description, todo, prior=prior), query_id, k, prior, max_id
            )
        if p.check == "none":
            return [
                Candidate(query_id, int(i), float(r), None, int(n), {"votes": int(n)})
                for i, n, r in zip(
                    votes.image_ids[:k], votes.n_matches[:k], votes.matching_ratio[:k], strict=True
                )
            ]
        kq = np.asarray(description["keypoints"], np.float32)
        width = int(description["width"])
        out = []
        for image_id, n_votes in zip(votes.image_ids[: p.n_check], votes.n_matches, strict=False):
            sel = result.image_id == image_id
            kr = self._keypoints[int(image_id)]
            q_kp, r_kp = kq[result.query_idx[sel]], kr[result.keypoint_idx[sel]]
            inliers, shift = shift_consensus(
                q_kp[:, 0],
                q_kp[:, 1],
                r_kp[:, 0],
                r_kp[:, 1],
                width,
                p.shift_tolerance_px,
                p.row_tolerance_px,
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
        """Store every added image's keypoints (with their 3D points), descriptors and, with verification, ICP
        cloud (in insertion order) with the parameters, and the HBST itself (its arrays, ``tree_*``), so that
        `load` restores the tree instead of re-inserting every image (~10x faster for a large map; the restored
        tree is the one a re-insertion builds: HBST is deterministic in the insertion order)."""
        arrays = pack_features(self, self._order, self._descriptors, self.extractor.descriptor_size, np.uint8)
        tree, tree_meta = self.tree.to_arrays()
        arrays.update({f"{_TREE_PREFIX}{k}": v for k, v in tree.items()})
        save_artifact(path, _KIND, _VERSION, arrays, {"params": self.params.saved_dump(), "tree": tree_meta})

    def load(self, path: str | Path) -> None:
        """Read a database `save` wrote (format 2: the tree restored; format 1: rebuilt by re-insertion)."""
        arrays, header = load_artifact(path, _KIND, (1, _VERSION), mmap=True)
        check_saved_params(path, header, self.params)
        tree = {k[len(_TREE_PREFIX) :]: arrays.pop(k) for k in list(arrays) if k.startswith(_TREE_PREFIX)}
        schema = features_schema(self.extractor.descriptor_size, True, self.params.verify.enabled)
        check_members(arrays, schema, path)
        stored = stored_features(path, arrays, self.params.image)
        self._reset()
        if header["format_version"] == 1:
            for scan_id, desc in stored:
                self.add_description(scan_id, desc)
            return
        check_members(tree, TREE_SCHEMA, path)
        meta = header["meta"].get("tree")
        if not isinstance(meta, dict):
            raise ArtifactError(f"{path}: header 'meta.tree' must be a JSON object, got {short_repr(meta)}")
        restored = HBST.from_arrays(tree, meta, path)
        if (
            restored.image_ids.tolist() != sorted(int(i) for i, _ in stored)
            or restored.threshold != self.tree.threshold
        ):
            raise ArtifactError(
                f"{path}: the saved tree does not hold the saved images (or another threshold)"
            )
        for scan_id, desc in stored:
            self._add_features(scan_id, desc, np.asarray(desc["descriptors"], np.uint8))
            self._order.append(scan_id)
        self.tree = restored
