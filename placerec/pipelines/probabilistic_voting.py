"""The ISHOT paper's probabilistic keypoint voting and global localisation (Sec. IV-C to IV-F), end to end.

`ProbabilisticVoting` (registered as ``ishot-prob``) extends `placerec.pipelines.keypoint_voting.KeypointVoting`
(same front end, places and verification) with the paper's query:

1. The query's described keypoints are taken in a random order (``seed``) in batches of ``batch_size`` (16).
2. Each batch is matched against every place's descriptors (2-NN, eq. 4); each descriptor's vote ``{rho_v, tau}``
   multiplies the precomputed vector ``P(rho_i | v)`` of its voted place and ``tau`` range into the posterior over
   places (eq. 6, `placerec.three_d.posterior`), scaled by the keypoint-density correction
   (``density_correction``, Sec. IV-E). The vote model (eq. 7) is the artifact ``vote_model`` written by
   ``placerec fit-votes`` (`placerec.pipelines.vote_fitting`), or the inline ``model`` values.
3. As soon as a place's posterior exceeds ``xi_v`` (15 %) the ``verify.top_k`` most probable places not verified
   yet go through the verification stage every 3D pipeline shares (`placerec.verify.candidates`: the query's
   descriptors matched with the candidate place's, geometric consistency grouping with minimum cluster 8 and
   consensus 7 m, RANSAC, point-to-plane ICP, accepted by eps_ICP = 7 m^2). An accepted candidate ends the query.
   If none is accepted, voting goes on with the next batch (a place verified once is not verified again).
   Two departures, off by default and in the registry preset (docs/localization.md measures them):
   ``stop_radius_m`` tests the posterior summed within that distance of each place (the region a local-map
   verification tests) instead of each place's own, and ``reject_weight`` treats a rejection as evidence: the
   posterior of the places within ``verify_separation_m`` of a rejected candidate is scaled by it (the ratio of
   the verification's rejection rates near the truth and away from it, measured at ~0.02) and the stop test runs
   again on the same votes before the next batch is matched. Matching also ends once nothing is left to verify.
4. When every keypoint is consumed without an accepted candidate, the places are ranked by their vote counts
   (``tau < tau_max``, the paper's fallback) and the top ``fallback_top_k`` not yet verified are verified (the
   registry preset: 30, at least ``verify_separation_m`` = 7.5 m from every place verified before). Without early
   stopping (``early_stop = False``: every keypoint matched in one search, the exhaustive variant) the posterior
   ranks them instead.

Each returned candidate carries the 6-DoF ``relative_pose`` (``T_match_query``, from ICP) and in ``extra``:
``T_world_query`` (the query's pose in the map: the place's pose composed with it), ``keypoints_consumed``
(query descriptors matched against the whole database), ``n_keypoints``, ``early_stop`` (the posterior passed
``xi_v`` at least once), ``match_ms``, ``n_verified`` (places verified for the query), ``posterior`` (the place's probability when it was verified) and ``votes``.

Departures from the paper (measured in docs/localization.md): descriptors are computed for all keypoints in
``describe`` (shared and cached with ``ishot-votes``), so early stopping saves the matching against the database,
not the description, which the paper does batch by batch; the ISHOT descriptors already computed are matched with
the candidate place's instead of SHOT; the registry preset (`placerec.recognizer.LOCALIZE_VERIFY`) verifies each
candidate as a local map of the places within 15 m (``verify_radius_m``), with every nearest neighbour
(``verify_tau_max`` 1), ICP clouds cropped at 40 m like the places, RANSAC from 3 inliers and at least 70 % overlap
(``verify.verify.score.min_fitness``), and skips candidates within 7.5 m of one already verified
(``verify_separation_m``: their local maps overlap it). ``index: ivf`` searches the database approximately
(sub-linear in its size).
"""

from __future__ import annotations

import logging
import time
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field

from placerec.errors import ScanDataError
from placerec.params import Params
from placerec.pipelines.keypoint_voting import ARTIFACT_KIND, KeypointVoting, VotingParams, nn_ratio
from placerec.three_d.posterior import Posterior, PosteriorTable, density_weights
from placerec.three_d.vote_model import VoteModel
from placerec.types import Candidate, Description
from placerec.verify.verify import as_source

log = logging.getLogger(__name__)

__all__ = ["InlineVoteModel", "ProbabilisticParams", "ProbabilisticVoting", "ARTIFACT_KIND"]


class InlineVoteModel(Params):
    """Vote model values used when no ``vote_model`` file is given: fitted by ``tools/eval_localization.py`` on the
    simulator's town map (VLP-16, ISHOT, 121 places 2.5 m apart, 9132 training votes; docs/localization.md)."""

    tau_edges: list[float] = Field([0.0, 0.7, 0.8, 0.85, 0.9, 0.95, 1.0], description="tau range edges")
    sigma: list[float] = Field(
        [3.193, 5.182, 6.582, 9.886, 36.947, 43.746], description="m; half-normal scale per range"
    )
    lam: list[float] = Field(
        [0.8886, 0.7239, 0.6197, 0.4683, 0.8014, 0.8367], description="half-normal weight per range"
    )
    d_max: float = Field(95.979, gt=0, description="m; extent of the uniform tail")

    def build(self) -> VoteModel:
        return VoteModel(self.tau_edges, self.sigma, self.lam, self.d_max, provenance={"source": "inline"})


class ProbabilisticParams(VotingParams):
    """`VotingParams` plus the probabilistic query (ISHOT paper Sec. IV-C/E; defaults: batch 16, xi_v 15 %)."""

    vote_model: str | None = Field(None, description="a vote-model file (placerec fit-votes); None = 'model'")
    model: InlineVoteModel = Field(default_factory=InlineVoteModel)
    batch_size: int = Field(16, ge=1, description="keypoints matched per iteration (ISHOT paper Sec. V-C)")
    xi_v: float = Field(0.15, gt=0, le=1, description="posterior that stops voting (ISHOT paper Sec. V-C)")
    early_stop: bool = Field(True, description="stop at xi_v (False: match every keypoint first)")
    density_correction: bool = Field(True, description="scale votes by the voted place's keypoint density")
    posterior: Literal["sparse", "full"] = Field(
        "sparse", description="precomputed vote vectors: sparse or dense"
    )
    truncation: float = Field(1e-3, gt=0, lt=1, description="relative error of the sparse vectors")
    seed: int = Field(0, description="order in which keypoints are consumed")
    stop_radius_m: float = Field(
        0.0,
        ge=0,
        description="m; the stop test sums the posterior within this distance of each place (the region a local-map "
        "verification tests; 0: each place alone, the paper's test)",
    )
    reject_weight: float = Field(
        1.0,
        gt=0,
        le=1,
        description="posterior factor on the places within verify_separation_m of a rejected candidate: a rejection "
        "is evidence the query is not there (1: ignored, the paper's query)",
    )


class ProbabilisticVoting(KeypointVoting):
    """`PlaceRecognizer`: ISHOT probabilistic voting with early stopping and verification (module docstring)."""

    name: ClassVar[str] = "probabilistic-voting"
    Params: ClassVar[type[Params]] = ProbabilisticParams

    def __init__(self, params: ProbabilisticParams | None = None, **overrides: Any) -> None:
        super().__init__(params, **overrides)
        p = self.params
        self.vote_model = VoteModel.load(p.vote_model) if p.vote_model else p.model.build()
        self._table: PosteriorTable | None = None
        self._region: Any = None  # sparse (places x places): 1 within stop_radius_m

    def _reset(self) -> None:
        super()._reset()
        self._table, self._region = None, None

    def _append_rows(self, desc: np.ndarray, entry: np.ndarray) -> None:
        super()._append_rows(desc, entry)
        # the entries changed: their posterior vectors and regions are rebuilt on the next query
        self._table, self._region = None, None

    def posterior_table(self) -> PosteriorTable:
        """The vote vectors over every entry (built on first use after the entries change)."""
        if self._table is None:
            self._table = PosteriorTable(
                self.vote_model, self._entry_xyz(), self.params.posterior, self.params.truncation
            )
        return self._table

    def query_description(
        self, description: Description, k: int = 1, max_id: int | None = None, query_id: int = -1
    ) -> list[Candidate]:
        p = self.params
        q = np.asarray(description["descriptors"], np.float32).reshape(-1, self._dim)
        rows, entry, n_ent = self._eligible(max_id)
        if q.shape[0] == 0 or rows.shape[0] < 2:
            return []
        table = self.posterior_table()
        eligible = self._eligible_entries(max_id)
        weights = density_weights(self._counts) if p.density_correction else None
        post = Posterior(table, weights)
        post.log[~eligible] = -np.inf
        votes = np.zeros(len(self._ids), np.int64)
        order = np.random.default_rng(p.seed).permutation(q.shape[0])
        verified: dict[int, Candidate] = {}
        qkp, starts = self._query_keypoints(description), self._entry_starts()
        source = None
        consumed, stopped, accepted, exhausted = 0, False, False, False
        match_ms = 0.0
        while consumed < q.shape[0] and not accepted and not exhausted:
            t0 = time.perf_counter()
            # without early stopping every keypoint is matched at once (one BLAS search instead of many small ones)
            batch = order[consumed : consumed + (p.batch_size if p.early_stop else q.shape[0])]
            dist, idx = self._search(q[batch], rows)
            found = idx[:, 0] >= 0
            voted = entry[idx[found, 0]]
            tau = nn_ratio(dist[found])
            post.update(voted, self.vote_model.range_of(tau))
            votes += np.bincount(voted[tau < p.tau_max], minlength=votes.size)
            consumed += batch.size
            match_ms += (time.perf_counter() - t0) * 1e3
            if not p.early_stop:
                continue
            # verify while a place (or region) passes xi_v; a rejection scales its region's posterior by
            # reject_weight and the test runs again on the same votes (at 1 the next batch comes first, as in the paper)
            while not accepted:
                prob = post.probabilities
                if self._stop_mass(prob).max() <= p.xi_v:
                    break
                stopped = True
                if source is None and p.verify.enabled:
                    source = self._source(description)
                todo = [e for e in np.argsort(-prob, kind="stable") if eligible[e] and int(e) not in verified]
                before = len(verified)
                accepted = self._verify(
                    todo, prob, votes, q, qkp, starts, source, verified, query_id, True, eligible
                )
                rejected = list(verified)[before:]
                # nothing left to verify (every place verified or within verify_separation_m of one): stop matching
                exhausted = not accepted and not rejected
                if accepted or exhausted or p.reject_weight >= 1:
                    break
                post.scale(self._near(rejected), p.reject_weight)
        if not accepted:
            prob = post.probabilities
            # the threshold never led to an accepted place: vote counts first (the paper's fallback), then the
            # posterior; without early stopping (exhaustive matching) the posterior ranks
            ranked = np.lexsort((-prob, -votes)) if p.early_stop else np.argsort(-prob, kind="stable")
            todo = [e for e in ranked if eligible[e] and int(e) not in verified]
            if source is None and p.verify.enabled:
                source = self._source(description)
            self._verify(
                todo,
                prob,
                votes,
                q,
                qkp,
                starts,
                source,
                verified,
                query_id,
                not p.early_stop,
                eligible,
                p.fallback_top_k,
            )
        for e, c in verified.items():
            if c.relative_pose is not None:
                c.extra["T_world_query"] = np.asarray(self._poses[e]) @ c.relative_pose
        out = sorted(
            verified.values(),
            key=lambda c: (-c.score, not c.extra["accepted"], -c.extra["retrieval_score"]),
        )
        for c in out:
            c.extra.update(
                keypoints_consumed=consumed,
                n_keypoints=int(q.shape[0]),
                early_stop=stopped,
                match_ms=match_ms,
                n_verified=len(verified),
            )
        return out[:k]

    def _near(self, entries: list[int]) -> np.ndarray:
        """Mask of the entries within ``verify_separation_m`` of any of ``entries`` (those themselves included)."""
        xyz = self._entry_xyz()
        d = np.linalg.norm(xyz[:, None, :] - xyz[None, entries, :], axis=2)
        return (d <= self.params.verify_separation_m).any(axis=1)

    def _stop_mass(self, prob: np.ndarray) -> np.ndarray:
        """What the stop test compares with xi_v: each place's posterior, or the posterior within ``stop_radius_m``."""
        r = self.params.stop_radius_m
        if r <= 0:
            return prob
        if self._region is None:  # built on first use after the entries change
            from scipy.sparse import csr_matrix
            from scipy.spatial import cKDTree

            # sparse (places x places) neighbourhood: memory grows with the places within r, not with their square
            nbrs = cKDTree(self._entry_xyz()).query_ball_point(self._entry_xyz(), r=r)
            cols = np.concatenate([np.asarray(nb, np.int64) for nb in nbrs])
            rows = np.repeat(np.arange(len(nbrs)), [len(nb) for nb in nbrs])
            self._region = csr_matrix((np.ones(cols.size), (rows, cols)), shape=(len(nbrs), len(nbrs)))
        return self._region @ prob

    def _source(self, description: Description) -> Any:
        if "cloud" not in description:
            raise ScanDataError(f"{self.name}: verification needs the query description's 'cloud'")
        return as_source(description["cloud"], self.params.verify.verify)

    def _verify(
        self,
        todo: list[int],
        prob: np.ndarray,
        votes: np.ndarray,
        q: np.ndarray,
        qkp: np.ndarray,
        starts: np.ndarray,
        source: Any,
        verified: dict[int, Candidate],
        query_id: int,
        by_posterior: bool,
        eligible: np.ndarray | None = None,
        top_k: int | None = None,
    ) -> bool:
        """Verify the first ``top_k`` (default ``verify.top_k``) entries of ``todo`` (entry indices) at least
        ``verify_separation_m`` from those verified before; store their candidates in
        ``verified`` by entry; True when one is accepted. The retrieval score is the posterior
        (``by_posterior``) or the vote fraction."""
        vp = self.params.verify
        picked = self._pick(todo, verified, top_k or vp.top_k)
        if not picked:
            return False
        if not vp.enabled:  # retrieval only: the most probable (or most voted) entry, no pose
            for e in picked:
                score = float(prob[e] if by_posterior else votes[e] / q.shape[0])
                extra = {"votes": int(votes[e]), "posterior": float(prob[e]), "n_query": int(q.shape[0])}
                extra.update(accepted=True, retrieval_score=score)
                verified[e] = Candidate(query_id, self._ids[e], score, None, None, extra)
            return True
        return self._verify_chunks(
            source,
            picked,
            lambda e: self._matches(
                e,
                q,
                qkp,
                starts,
                float(prob[e] if by_posterior else votes[e] / q.shape[0]),
                {"votes": int(votes[e]), "posterior": float(prob[e]), "n_query": int(q.shape[0])},
                eligible,
            ),
            verified,
            query_id,
        )
