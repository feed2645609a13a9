"""The ISHOT paper's probabilistic keypoint voting and global localisation (Sec. IV-C to IV-F), end to end.

`ProbabilisticVoting` (registered as ``ishot-prob``) extends
`placerec.pipelines.keypoint_voting.KeypointVoting` (same front end, places and verification) with the paper's
query:

1. The query's described keypoints are taken in a random order (``seed``) in batches of ``batch_size`` (16).
2. Each batch is matched against every place's descriptors (2-NN, eq. 4); each descriptor's vote ``{rho_v,
   tau}`` multiplies the precomputed vector ``P(rho_i | v)`` of its voted place and ``tau`` range into the
   posterior over places (eq. 6, `placerec.three_d.posterior`), scaled by the keypoint-density correction
   (``density_correction``, Sec. IV-E). The vote model (eq. 7) is the artifact ``vote_model`` written by
   ``placerec fit-votes`` (`placerec.artifacts.votes`), or the inline ``model`` values.
3. As soon as a place's posterior exceeds ``xi_v`` (15 %) the ``verify.top_k`` most probable places not
   verified yet go through the verification stage every 3D pipeline shares (`placerec.verify.candidates`: the
   query's descriptors matched with the candidate place's, geometric consistency grouping with minimum cluster
   8 and consensus 7 m, RANSAC, point-to-plane ICP, accepted by eps_ICP = 7 m^2). An accepted candidate ends
   the query. If none is accepted, voting goes on with the next batch (a place verified once is not verified
   again). Two departures, off by default and in the registry preset (docs/localization.md measures them):
   ``stop_radius_m`` tests the posterior summed within that distance of each place (the region a local-map
   verification tests) instead of each place's own, and ``reject_weight`` treats a rejection as evidence: the
   posterior of the places within ``verify.separation_m`` of a rejected candidate is scaled by it (the ratio
   of the verification's rejection rates near the truth and away from it, measured at ~0.02) and the stop test
   runs again on the same votes before the next batch is matched. Matching also ends once nothing is left to
   verify.
4. When every keypoint is consumed without an accepted candidate, the places are ranked by their vote counts
   (``tau < tau_max``, the paper's fallback) and the top ``verify.fallback_top_k`` not yet verified are verified (the
   registry preset: 30, at least ``verify.separation_m`` = 7.5 m from every place verified before). Without
   early stopping (``early_stop = False``: every keypoint matched in one search, the exhaustive variant) the
   posterior ranks them instead.

The query runs in the loop every voting pipeline shares (`placerec.pipelines.voting_engine`); `PosteriorVotes`
is its strategy. Each returned candidate carries the 6-DoF ``relative_pose`` (``T_match_query``, from ICP) and
``T_world_query`` (the query's pose in the map), and in ``extra``: the engine's diagnostics
(``keypoints_consumed``, ``early_stop``: the posterior passed ``xi_v`` at least once, ...), ``posterior`` (the
place's probability when it was verified) and ``votes``.

Departures from the paper (measured in docs/localization.md): descriptors are computed for all keypoints in
``describe`` (shared and cached with ``ishot-votes``), so early stopping saves the matching against the
database, not the description, which the paper does batch by batch; the ISHOT descriptors already computed are
matched with the candidate place's instead of SHOT; the registry preset
(`placerec.recognizer.LOCALIZE_VERIFY`) verifies each candidate as a local map of the places within 15 m
(``verify.radius_m``), with every nearest neighbour (``verify.tau_max`` 1), ICP clouds cropped at 40 m like
the places, RANSAC from 3 inliers and at least 70 % overlap (``verify.score.min_fitness``), and skips
candidates within 7.5 m of one already verified (``verify.separation_m``: their local maps overlap it).
``search.index: ivf`` searches the database approximately (sub-linear in its size).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field, model_validator

from placerec.params import Params
from placerec.pipelines.keypoint_voting import ARTIFACT_KIND, KeypointVoting, VotingParams
from placerec.pipelines.voting_engine import Query, Shortlist, VoteStrategy
from placerec.retrieval.nearest import nn_ratio
from placerec.three_d.posterior import Posterior, PosteriorTable, density_weights
from placerec.three_d.vote_model import TauEdges, VoteModel

log = logging.getLogger(__name__)

__all__ = [
    "InlineVoteModel",
    "PosteriorStep",
    "PosteriorVotes",
    "ProbabilisticParams",
    "ProbabilisticVoting",
    "ARTIFACT_KIND",
]


class InlineVoteModel(Params):
    """Vote model values used when no ``vote_model`` file is given: fitted by ``tools/eval_localization.py`` on the
    simulator's town map (VLP-16, ISHOT, 121 places 2.5 m apart, 9132 training votes; docs/localization.md)."""

    tau_edges: TauEdges = Field([0.0, 0.7, 0.8, 0.85, 0.9, 0.95, 1.0], description="tau range edges")
    sigma: list[float] = Field(
        [3.193, 5.182, 6.582, 9.886, 36.947, 43.746], description="m; half-normal scale per range"
    )
    lam: list[float] = Field(
        [0.8886, 0.7239, 0.6197, 0.4683, 0.8014, 0.8367], description="half-normal weight per range"
    )
    d_max: float = Field(95.979, gt=0, description="m; extent of the uniform tail")

    @model_validator(mode="after")
    def _one_value_per_range(self) -> InlineVoteModel:
        r = len(self.tau_edges) - 1
        if len(self.sigma) != r or len(self.lam) != r:
            raise ValueError(
                f"{len(self.tau_edges)} tau_edges make {r} ranges: sigma and lam need {r} values each, got "
                f"{len(self.sigma)} and {len(self.lam)}"
            )
        return self

    def build(self) -> VoteModel:
        return VoteModel(
            np.asarray(self.tau_edges, np.float64),
            np.asarray(self.sigma, np.float64),
            np.asarray(self.lam, np.float64),
            self.d_max,
            provenance={"source": "inline"},
        )


class ProbabilisticParams(VotingParams):
    """`VotingParams` plus the probabilistic query (ISHOT paper Sec. IV-C/E; defaults: batch 16, xi_v 15 %)."""

    vote_model: str | None = Field(None, description="a vote-model file (placerec fit-votes); None = 'model'")
    model: InlineVoteModel = Field(default_factory=InlineVoteModel)
    batch_size: int = Field(
        16, ge=1, le=100_000, description="keypoints matched per iteration (ISHOT paper Sec. V-C)"
    )
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
        description="posterior factor on the places within verify.separation_m of a rejected candidate: a rejection "
        "is evidence the query is not there (1: ignored, the paper's query)",
    )


@dataclass(frozen=True)
class PosteriorStep:
    """The posterior after one batch of a query's keypoints (what `ProbabilisticVoting.posterior_observer`
    sees): ``query_id``, ``matched`` keypoints so far of ``n`` described, ``ids`` (E,) the entries' ids and
    ``probabilities`` (E,) the posterior over them (0 for the entries the query may not match)."""

    query_id: int
    matched: int
    n: int
    ids: np.ndarray
    probabilities: np.ndarray


class PosteriorVotes(VoteStrategy["ProbabilisticVoting"]):
    """The paper's query (module docstring): batches of keypoints in a random order update the posterior over the
    entries; a place (or region) above ``xi_v`` is verified; a rejection may scale its region's posterior."""

    stops_early = True

    def __init__(self, rec: ProbabilisticVoting, query: Query) -> None:
        super().__init__(rec, query)
        p = rec.params
        self.p = p
        self.vote_model = rec.vote_model
        self.votes = np.zeros(len(rec.entries), np.int64)

    @cached_property
    def post(self) -> Posterior:
        """The posterior over the entries (built when the first batch is matched: there are entries then)."""
        rec = self.rec
        weights = density_weights(rec.entries.counts) if self.p.density_correction else None
        post = Posterior(rec.posterior_table(), weights)
        post.log[~self.query.eligible] = -np.inf
        return post

    def order(self) -> np.ndarray:
        return np.random.default_rng(self.p.seed).permutation(self.n)

    def batch_size(self) -> int:
        # without early stopping every keypoint is matched at once (one BLAS search instead of many small ones)
        return self.p.batch_size if self.p.early_stop else self.n

    def vote(self, batch: np.ndarray) -> None:
        qr = self.query
        dist, idx = self.rec.search(qr.q[batch], qr.rows)
        found = idx[:, 0] >= 0
        voted = qr.row_entry[idx[found, 0]]
        tau = nn_ratio(dist[found])
        self.post.update(voted, self.vote_model.range_of(tau))
        self.votes += np.bincount(voted[tau < self.p.search.tau_max], minlength=self.votes.size)
        self.matched += batch.size
        observer = self.rec.posterior_observer
        if observer is not None:
            ids = np.asarray(self.rec.entries.ids, np.int64)
            observer(PosteriorStep(qr.query_id, self.matched, self.n, ids, self.post.probabilities))

    def ready(self) -> Shortlist | None:
        if not self.p.early_stop:
            return None
        prob = self.post.probabilities
        if self.rec.stop_mass(prob).max() <= self.p.xi_v:
            return None
        ranked = [e for e in np.argsort(-prob, kind="stable") if self.query.eligible[e]]
        return self._shortlist(ranked, prob, by_posterior=True, top_k=None)

    def rejected(self, entries: list[int]) -> bool:
        """With ``reject_weight < 1`` the posterior near the rejected places is scaled and tested again."""
        if self.p.reject_weight >= 1:
            return False
        self.post.scale(self.rec.near(entries), self.p.reject_weight)
        return True

    def fallback(self) -> Shortlist:
        # the threshold never led to an accepted place: vote counts first (the paper's fallback), then the
        # posterior; without early stopping (exhaustive matching) the posterior ranks
        prob = self.post.probabilities
        order = np.lexsort((-prob, -self.votes)) if self.p.early_stop else np.argsort(-prob, kind="stable")
        ranked = [e for e in order if self.query.eligible[e]]
        return self._shortlist(
            ranked, prob, by_posterior=not self.p.early_stop, top_k=self.p.verify.fallback_top_k
        )

    def _shortlist(
        self, ranked: list[Any], prob: np.ndarray, by_posterior: bool, top_k: int | None
    ) -> Shortlist:
        """The entries ``ranked``; the retrieval score is the posterior (``by_posterior``) or the vote fraction."""
        votes, n = self.votes, self.n
        return Shortlist(
            ranked,
            score=lambda e: float(prob[e] if by_posterior else votes[e] / n),
            extra=lambda e: {"votes": int(votes[e]), "posterior": float(prob[e]), "n_query": n},
            top_k=top_k,
            final=True,
        )


class ProbabilisticVoting(KeypointVoting):
    """`PlaceRecognizer`: ISHOT probabilistic voting with early stopping and verification (module docstring)."""

    name: ClassVar[str] = "probabilistic-voting"
    Params: ClassVar[type[Params]] = ProbabilisticParams
    params: ProbabilisticParams
    Strategy: ClassVar[type[VoteStrategy[Any]]] = PosteriorVotes
    #: called with the posterior after every batch of every query (e.g. `placerec.viewer`); None: nothing is
    #: computed for it
    posterior_observer: Callable[[PosteriorStep], None] | None = None

    def __init__(self, params: ProbabilisticParams | None = None, **overrides: Any) -> None:
        super().__init__(params, **overrides)
        p = self.params
        self.vote_model = VoteModel.load(p.vote_model) if p.vote_model else p.model.build()

    def posterior_table(self) -> PosteriorTable:
        """The vote vectors over every entry (built on first use after the entries change)."""
        p = self.params
        return self.derived(
            "posterior",
            lambda: PosteriorTable(self.vote_model, self.entries.xyz(), p.posterior, p.truncation),
        )

    def near(self, entries: list[int]) -> np.ndarray:
        """Mask of the entries within ``verify.separation_m`` of any of ``entries`` (those themselves included)."""
        xyz = self.entries.xyz()
        d = np.linalg.norm(xyz[:, None, :] - xyz[None, entries, :], axis=2)
        return (d <= self.params.verify.separation_m).any(axis=1)

    def stop_mass(self, prob: np.ndarray) -> np.ndarray:
        """What the stop test compares with xi_v: each place's posterior, or the posterior within ``stop_radius_m``."""
        r = self.params.stop_radius_m
        if r <= 0:
            return prob
        return self.derived("region", lambda: _region(self.entries.xyz(), r)) @ prob


def _region(xyz: np.ndarray, r: float) -> Any:
    """Sparse (places x places) neighbourhood, 1 within ``r``: memory grows with the places within r, not with
    their square."""
    from scipy.sparse import csr_matrix
    from scipy.spatial import cKDTree

    nbrs = cKDTree(xyz).query_ball_point(xyz, r=r)
    cols = np.concatenate([np.asarray(nb, np.int64) for nb in nbrs])
    rows = np.repeat(np.arange(len(nbrs)), [len(nb) for nb in nbrs])
    return csr_matrix((np.ones(cols.size), (rows, cols)), shape=(len(nbrs), len(nbrs)))
