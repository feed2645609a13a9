"""The 2D visual pipeline with DBoW2-style retrieval (VPR paper: ORB-DBoW2, SURF-DBoW2).

Front end: the same as `placerec.pipelines.visual.VisualHBST` (intensity image, then features; the same
``frontend_key`` for the same image/feature settings, so the runner computes the description once for ORB-HBST
and ORB-DBoW). Each image becomes an L1-normalised TF-IDF bag of words (`placerec.retrieval.dbow`), stored in an
inverse-index database with a direct index; a query is one database query (DBoW2's L1 score).

Score (what thresholds apply to):

* ``verify.enabled`` (default): the ``verify.top_k`` best database results are verified as in
  `placerec.pipelines.visual` (mutual nearest features, or with ``verify_matches="retrieval"`` the direct-index
  matches below, as 3D points -> RANSAC -> ICP): verified score in [0, 1], 6-DoF ``relative_pose``, re-ranked;
  ``extra["bow_score"]`` keeps the L1 score.
* otherwise ``check="none"``: the DBoW2 L1 score ``s = 1 - 0.5 |v_q - v_m|_1`` in [0, 1] (divided by the score
  against the previous frame when ``loop.use_nss``, as DLoopDetector's normalised similarity score).
* otherwise ``check="shift"``: the ``n_check`` best database results are checked geometrically:
  query features are matched to the candidate's features under the same vocabulary node at depth
  ``L - levels_up`` (the direct index; default depth 2, as ORB-SLAM2's levelsup 4 with L = 6; nearest neighbour
  with ratio test ``nn_ratio`` and distance cap ``max_distance``, one query feature per candidate feature, as
  DLoopDetector's ``GEOM_DI``), then the column-shift consensus of VisualHBST (`shift_consensus`) counts the
  inliers and gives the yaw. Score ``inliers / min(n_query_features, n_match_features)``.

DLoopDetector's normalised score with ``alpha`` (``loop``) is off by default: the paper queries DBoW2's database as
is. Its islands and temporal consistency are the loop detector's optional filter (`placerec.loop_filter`): they keep
state between queries, which a recognizer's query must not change.

Vocabulary: ``vocabulary`` is a path (absolute or relative to the working directory; a missing relative path whose
file name is a shipped vocabulary picks that one); None picks the shipped vocabulary for the feature type
(``orb_k10L5.dbow``, ``surf_k10L4.dbow``: package data in ``placerec/vocab/``, found with `importlib.resources`).
Vocabularies are loaded once per process and shared.
"""

from __future__ import annotations

import importlib.resources
import logging
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, ClassVar, cast

import numpy as np
from pydantic import Field

from placerec.errors import ArtifactError
from placerec.io.artifact_schema import check_members
from placerec.io.atomic import load_artifact, save_artifact
from placerec.params import Params
from placerec.pipelines.visual import VisualFrontend, VisualPipelineParams, shift_consensus, yaw_pose
from placerec.pipelines.visual_store import features_schema, pack_features, stored_features
from placerec.recognizer import Recognizer, check_saved_params
from placerec.retrieval.bits import hamming, to_words
from placerec.retrieval.dbow.database import BowDatabase, candidate_pairs
from placerec.retrieval.dbow.loop_detector import LoopDetectorParams, normalised_results
from placerec.retrieval.dbow.vocabulary import BowVector, Vocabulary, l1_score
from placerec.types import Candidate, Description, MotionPrior

log = logging.getLogger(__name__)

__all__ = ["DBoWParams", "VisualDBoW", "default_vocabulary_path", "resolve_vocabulary", "VOCAB_DIR"]

_KIND = "visual-dbow-db"
_VERSION = 1
#: The shipped vocabularies: package data, installed as files with the package (editable install or wheel).
VOCAB_DIR = Path(str(importlib.resources.files("placerec").joinpath("vocab")))
#: Shipped vocabulary per feature extractor (SURF's descriptor with FAST or SURF keypoints share one).
SHIPPED = {
    "orb": "orb_k10L5.dbow",
    "fast-surf": "surf_k10L4.dbow",
    "surf": "surf_k10L4.dbow",
    "superpoint": "superpoint_k10L4.dbow",
}
_TRAIN_CONFIG = {
    "orb": "configs/vocab_orb.yaml",
    "fast-surf": "configs/vocab_surf.yaml",
    "surf": "configs/vocab_surf.yaml",
    "superpoint": "configs/vocab_superpoint.yaml",
}
_CACHE: dict[tuple[str, int, int], Vocabulary] = {}


class DBoWParams(VisualPipelineParams):
    """Front end, verification and check (as `VisualParams`), vocabulary, direct index depth, DLoopDetector
    options and direct-index matching."""

    vocabulary: str | None = Field(
        None, description="vocabulary file; None = the shipped one for the features"
    )
    levels_up: int | None = Field(
        None,
        ge=0,
        description="direct index at depth L - levels_up (>= 1); None = depth 2 (ORB-SLAM2's 4, L=6)",
    )
    loop: LoopDetectorParams = Field(default_factory=LoopDetectorParams)
    nn_ratio: float = Field(
        0.8, gt=0, le=1, description="nearest-neighbour ratio test (DLoopDetector GEOM_DI)"
    )
    max_distance: float | None = Field(
        None, gt=0, description="descriptor distance cap; None = 50 per 256 bits (binary), none (float)"
    )


def default_vocabulary_path(features: str) -> Path:
    """The shipped vocabulary for a feature extractor name."""
    name = SHIPPED.get(features, f"{features}_k10L5.dbow")
    return VOCAB_DIR / name


def resolve_vocabulary(path: str | None, features: str) -> Path:
    """Where the vocabulary for ``path``/``features`` is (see the module docstring); `ArtifactError` if absent."""
    if path is None:
        found = default_vocabulary_path(features)
    else:
        p = Path(path).expanduser()
        shipped = VOCAB_DIR / p.name
        found = shipped if not (p.is_absolute() or p.exists()) and shipped.is_file() else p
    if not found.is_file():
        cfg = _TRAIN_CONFIG.get(features, "configs/vocab_orb.yaml (with 'features' set)")
        raise ArtifactError(
            f"DBoW vocabulary {found} not found (features {features!r}). Train one with "
            f"`placerec train-vocab --config {cfg}` or set the pipeline parameter 'vocabulary' to a vocabulary "
            "file (placerec .dbow or ORB-SLAM2 text)."
        )
    return found


def _load_cached(path: Path) -> Vocabulary:
    from placerec.retrieval.dbow.io import load_vocabulary

    st = path.stat()
    key = (str(path.resolve()), st.st_mtime_ns, st.st_size)
    if key not in _CACHE:
        if len(_CACHE) >= 4:
            _CACHE.pop(next(iter(_CACHE)))
        _CACHE[key] = load_vocabulary(path)
    return _CACHE[key]


class VisualDBoW(VisualFrontend[DBoWParams], Recognizer[DBoWParams]):
    """`PlaceRecognizer` of the VPR paper's 2D modality with DBoW2 retrieval (ORB-DBoW, SURF-DBoW)."""

    name: ClassVar[str] = "visual-dbow"
    Params: ClassVar[type[Params]] = DBoWParams

    def __init__(self, params: DBoWParams | None = None, **overrides: Any) -> None:
        super().__init__(params, **overrides)
        from placerec.features import make_extractor

        p = self.params
        self.extractor = make_extractor(p.features, p.feature_params)
        self.vocabulary_path = resolve_vocabulary(p.vocabulary, p.features)
        self.vocabulary = _load_cached(self.vocabulary_path)
        voc = self.vocabulary
        size = self.extractor.descriptor_size
        if voc.kind != self.extractor.descriptor_kind or voc.descriptor_size != size:
            raise ArtifactError(
                f"{self.vocabulary_path}: a {voc.kind} vocabulary of size {voc.descriptor_size} does not fit "
                f"{p.features} descriptors ({self.extractor.descriptor_kind}, size {size})"
            )
        levels_up = max(voc.L - 2, 0) if p.levels_up is None else p.levels_up
        self.levels_up = min(levels_up, voc.L - 1)  # direct index at depth L - levels_up >= 1
        self._reset()

    def _reset(self) -> None:
        self.db = BowDatabase(self.vocabulary, self.levels_up)
        #: (description, its descriptors, BoW vector, direct-index nodes) of the last query, for its insert
        self._queried: tuple[Description, Any, BowVector, np.ndarray] | None = None
        self._reset_features()

    def _transform(self, description: Description, desc: np.ndarray) -> tuple[BowVector, np.ndarray]:
        """The BoW vector and direct-index nodes of ``description``'s descriptors ``desc``: those of the last
        query when it was this very description (a loop detector queries a scan, then inserts it), else made."""
        last = self._queried
        if last is not None and last[0] is description and last[1] is description["descriptors"]:
            return last[2], last[3]
        return self.vocabulary.transform(desc, self.levels_up)

    def add_description(self, scan_id: int, description: Description, pose: np.ndarray | None = None) -> None:
        scan_id = int(scan_id)
        desc = np.ascontiguousarray(description["descriptors"])
        self._add_features(scan_id, description, desc)
        bow, nodes = self._transform(description, desc)
        self._queried = None
        self.db.add(bow, nodes, scan_id)

    def __len__(self) -> int:
        return len(self.db)

    def query_description(
        self,
        description: Description,
        k: int = 1,
        max_id: int | None = None,
        query_id: int = -1,
        prior: MotionPrior | None = None,
    ) -> list[Candidate]:
        p = self.params
        desc = np.ascontiguousarray(description["descriptors"])
        if desc.shape[0] == 0 or len(self.db) == 0:
            return []
        bow, nodes = self._transform(description, desc)
        self._queried = (description, description["descriptors"], bow, nodes)
        n_check = p.verify.top_k if p.verify.enabled else p.n_check if p.check == "shift" else k
        n_res = max(k, n_check, p.loop.max_db_results if p.loop.enabled else 0)
        res = self.db.query(bow, n_res, max_id)
        ids, scores, status = res.ids, res.scores, "ok"
        if p.loop.enabled:
            last = self.db.last_id
            eta = l1_score(bow, self.db.bow(last)) if p.loop.use_nss and last is not None else None
            lr = normalised_results(p.loop, ids, scores, eta)
            ids, scores, status = lr.ids, lr.scores, lr.status
        if p.verify.enabled:
            top = [int(i) for i in ids[: p.verify.top_k]]
            return self._verify_matches(description, top, scores, nodes, query_id, k, prior, max_id)
        if p.check == "none":
            return [
                Candidate(query_id, int(i), float(s), None, None, {"bow_score": float(s), "status": status})
                for i, s in zip(ids[:k], scores[:k], strict=True)
            ]
        kq = np.asarray(description["keypoints"], np.float32).reshape(-1, 2)
        out = self._check(
            [int(i) for i in ids[: p.n_check]],
            scores[: p.n_check],
            desc,
            nodes,
            kq,
            int(description["width"]),
            query_id,
        )
        out.sort(key=lambda c: (-c.score, c.match_id))
        return out[:k]

    def _verify_matches(
        self,
        description: Description,
        image_ids: list[int],
        scores: np.ndarray,
        nodes: np.ndarray,
        query_id: int,
        k: int,
        prior: MotionPrior | None = None,
        max_id: int | None = None,
    ) -> list[Candidate]:
        """The best database results verified (`VisualFrontend._verified`) with their direct-index matches
        (``verify_matches="retrieval"``) or mutual nearest features (`VisualFrontend._retrieved`); ``prior`` as in
        `VisualFrontend._retrieved_all` and `VisualFrontend._verified`, which entries up to ``max_id`` it may
        propose."""
        t0 = time.perf_counter()
        empty = np.zeros(0, np.int64)
        by_index = self.params.verify_matches == "retrieval" and image_ids
        desc = np.ascontiguousarray(description["descriptors"])
        cand, qi, ri = self._match(desc, nodes, image_ids) if by_index else (empty, empty, empty)
        share = (time.perf_counter() - t0) * 1e3 / max(len(image_ids), 1)
        bounds = np.searchsorted(cand, np.arange(len(image_ids) + 1))
        todo = [
            (
                i,
                float(s),
                qi[bounds[c] : bounds[c + 1]],
                ri[bounds[c] : bounds[c + 1]],
                {"bow_score": float(s)},
            )
            for c, (i, s) in enumerate(zip(image_ids, scores, strict=False))
        ]
        retrieved = self._retrieved_all(description, todo, share, prior)
        return self._verified(description, retrieved, query_id, k, prior, max_id)

    def _check(
        self,
        image_ids: list[int],
        bow_scores: np.ndarray,
        desc: np.ndarray,
        nodes: np.ndarray,
        kq: np.ndarray,
        width: int,
        query_id: int,
    ) -> list[Candidate]:
        """Match against all candidates at once, then the column-shift consensus per candidate."""
        if not image_ids:
            return []
        t0 = time.perf_counter()
        p = self.params
        cand, qi, ri = self._match(desc, nodes, image_ids)
        bounds = np.searchsorted(cand, np.arange(len(image_ids) + 1))
        out = []
        for c, (image_id, bow_score) in enumerate(zip(image_ids, bow_scores, strict=True)):
            sel = slice(bounds[c], bounds[c + 1])
            q, r = qi[sel], ri[sel]
            kr = self._keypoints[image_id]
            inliers, shift = shift_consensus(
                kq[q, 0], kq[q, 1], kr[r, 0], kr[r, 1], width, p.shift_tolerance_px, p.row_tolerance_px
            )
            score = inliers / max(1, min(desc.shape[0], kr.shape[0]))
            yaw = (2.0 * np.pi * shift / width + np.pi) % (2 * np.pi) - np.pi
            extra = {"bow_score": float(bow_score), "matches": int(q.size), "yaw_deg": float(np.degrees(yaw))}
            out.append(Candidate(query_id, image_id, float(score), yaw_pose(yaw), inliers, extra))
        per = (time.perf_counter() - t0) * 1e3 / len(out)
        return [replace(c, verify_ms=per) for c in out]

    def _match(
        self, dq: np.ndarray, nq: np.ndarray, image_ids: list[int]
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Direct-index matching against several stored images at once: for every (candidate, query feature) the
        nearest candidate feature under the same vocabulary node, kept if it passes the ratio test and the
        distance cap; then at most one query feature per candidate feature (the closest). Returns (candidate
        index, query feature, candidate feature), sorted by candidate."""
        n_nodes = self.vocabulary.n_nodes
        # the database keeps a direct index whenever matches come from retrieval
        r_nodes = cast(list[np.ndarray], [self.db.feature_nodes(i) for i in image_ids])
        sizes = np.array([x.size for x in r_nodes])
        r_cand = np.repeat(np.arange(len(image_ids)), sizes)
        r_local = np.arange(int(sizes.sum())) - np.repeat(np.cumsum(sizes) - sizes, sizes)
        rn = np.concatenate(r_nodes).astype(np.int64)
        nq64 = nq.astype(np.int64)
        # one join over (candidate, node) keys; -1 never matches
        key_r = np.where(rn >= 0, r_cand * n_nodes + rn, -1)
        key_q = np.where(nq64 >= 0, np.arange(len(image_ids))[:, None] * n_nodes + nq64, -1).ravel()
        ia, jb = candidate_pairs(key_q, key_r)
        empty = np.zeros(0, np.int64)
        if ia.size == 0:
            return empty, empty, empty
        qa = ia % nq.size
        dr = np.concatenate([self._descriptors[i] for i in image_ids])
        if self.vocabulary.binary:
            d = hamming(np.take(to_words(dq), qa, axis=0), np.take(to_words(dr), jb, axis=0)).astype(
                np.float64
            )
            cap = self.params.max_distance
            cap = 50.0 * dq.shape[1] * 8 / 256 if cap is None else cap
        else:  # per pair (no BLAS: multithreaded small GEMMs are slow on a busy machine)
            diff = np.take(dq, qa, axis=0) - np.take(dr, jb, axis=0)
            d = np.sqrt(np.einsum("ij,ij->i", diff, diff)).astype(np.float64)
            cap = np.inf if self.params.max_distance is None else self.params.max_distance
        order = np.lexsort((d, ia))  # ia identifies (candidate, query feature)
        ia, jb, d = ia[order], jb[order], d[order]
        new = np.ones(ia.size, bool)
        new[1:] = ia[1:] != ia[:-1]
        best = np.flatnonzero(new)
        nxt = best + 1
        has2 = nxt < ia.size
        has2[has2] = ~new[nxt[has2]]
        d2 = np.full(best.size, np.inf)
        d2[has2] = d[nxt[has2]]
        d1 = d[best]
        keep = best[(d1 <= self.params.nn_ratio * d2) & (d1 <= cap)]
        ia, jb = ia[keep], jb[keep]
        order = np.lexsort((d[keep], jb))  # jb identifies (candidate, candidate feature)
        ia, jb = ia[order], jb[order]
        first = np.ones(jb.size, bool)
        first[1:] = jb[1:] != jb[:-1]
        ia, jb = ia[first], jb[first]
        order = np.argsort(r_cand[jb], kind="stable")
        ia, jb = ia[order], jb[order]
        return r_cand[jb], ia % nq.size, r_local[jb]

    # ------------------------------------------------------------------------------------------ persistence
    def save(self, path: str | Path) -> None:
        """Store every added image's keypoints and descriptors (insertion order) with the parameters and the
        vocabulary's fingerprint; `load` re-adds them (the transform is deterministic)."""
        arrays = pack_features(
            self, self.db.ids.tolist(), self._descriptors, self.vocabulary.descriptor_size, self._dtype
        )
        meta = {"params": self.params.saved_dump(), "vocabulary": self.vocabulary.fingerprint}
        save_artifact(path, _KIND, _VERSION, arrays, meta)

    @property
    def _dtype(self) -> type:
        return np.uint8 if self.vocabulary.binary else np.float32

    def load(self, path: str | Path) -> None:
        arrays, header = load_artifact(path, _KIND, (_VERSION,), mmap=True)
        check_saved_params(path, header, self.params)
        saved_voc = header["meta"].get("vocabulary")
        if saved_voc != self.vocabulary.fingerprint:
            raise ArtifactError(
                f"{path}: database was made with vocabulary {saved_voc}, "
                f"not {self.vocabulary_path} ({self.vocabulary.fingerprint})"
            )
        voc = self.vocabulary
        check_members(
            arrays, features_schema(voc.descriptor_size, voc.binary, self.params.verify.enabled), path
        )
        stored = stored_features(path, arrays, self.params.image)
        self._reset()
        for scan_id, desc in stored:
            self.add_description(scan_id, desc)
