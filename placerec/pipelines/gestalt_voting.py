"""Bosse & Zlot's keypoint voting (ICRA 2013) on SHOT: the ISHOT paper's baseline (b) of Table III (Sec. V-C).

The ISHOT paper runs "the original keypoint voting approach with Gestalt3D features", with "a uniform sampling
of 10 %", "K = 10 closest features" and "the voting threshold set to parameters from the original paper", and
sums up that approach (Sec. II) as: the non-matching votes are modelled by a log-normal distribution, a
threshold on it eliminates false positives among the place candidates and terminates the keypoint matching.

What is implemented (`GestaltVoting`, registered as ``shot-gestalt-votes``):

1. The query's keypoints are consumed in a uniformly random order (``seed``), ``sample_fraction`` = 10 % of
   them per round; each is matched against every map descriptor and its ``knn`` = 10 nearest neighbours vote
   for the places (map entries) they come from, one vote per (query keypoint, place).
2. After each round the vote counts of the places *other than the most voted one* (those with at least one
   vote) are modelled as log-normal: ``mu``, ``sigma`` = mean and standard deviation of their log counts
   (`lognormal_threshold`). The most voted place is a match candidate when its count exceeds ``exp(mu + z *
   sigma)`` (``z``: ``lognormal_z``); then matching stops and the ``verify.top_k`` most voted places not
   verified yet go through the verification stage every localisation pipeline shares (geometric consistency
   grouping, RANSAC, point-to-plane ICP, eps_ICP = 7 m^2). An accepted place ends the query; otherwise the
   next round goes on. When every keypoint is consumed, the most voted unverified places are verified
   (``verify.fallback_top_k`` of them; every verified place at least ``verify.separation_m`` from the others).

Departures, said plainly:

* **Descriptor**: the Gestalt3D descriptor's published definition (Bosse & Zlot 2013) could not be found in
  the material available here (the ISHOT paper only cites it and gives its radius 7 m and height 12 m), so the
  voting runs on SHOT, hence the name ``shot-gestalt-votes``. The keypoints are the ISS-BR ones all 3D
  pipelines share.
* **Threshold parameters**: the original paper's values (which the ISHOT paper reused) are not available
  either; ``lognormal_z`` = 3 (the most voted place lies 3 standard deviations above the log-normal of the
  others, a one-sided tail of 0.13 %) is ours, as is fitting the model per query on the other places' counts.
* **"Uniform sampling of 10 %"** is read as the share of query keypoints matched per round (a uniform random
  sample), after which the termination test runs; the other reading (keypoints sampled uniformly from the
  cloud, 10 % of the points) would change the front end for this pipeline alone.

The query runs in the loop every voting pipeline shares (`placerec.pipelines.voting_engine`), `LognormalVotes`
its strategy. ``extra``: the engine's diagnostics (``early_stop``: the threshold was passed, ...), ``votes``
and ``threshold`` (the log-normal threshold when the place was verified).
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np
from pydantic import Field

from placerec.params import Params
from placerec.pipelines.keypoint_voting import ARTIFACT_KIND, KeypointVoting, VotingParams
from placerec.pipelines.voting_engine import Query, Shortlist, VoteStrategy

__all__ = [
    "ARTIFACT_KIND",
    "GestaltParams",
    "GestaltVoting",
    "LognormalVotes",
    "lognormal_threshold",
    "place_votes",
]


class GestaltParams(VotingParams):
    """`VotingParams` (front end, map entries, verification) plus Bosse & Zlot's voting (module docstring)."""

    knn: int = Field(
        10, ge=1, description="nearest map descriptors voting per query keypoint (ISHOT paper: 10)"
    )
    sample_fraction: float = Field(
        0.1, gt=0, le=1, description="share of query keypoints matched per round (ISHOT paper: uniform 10 %)"
    )
    lognormal_z: float = Field(
        3.0, gt=0, description="standard deviations above the non-matching log-normal that stop voting (ours)"
    )
    seed: int = Field(0, description="order in which keypoints are consumed")


def place_votes(idx: np.ndarray, row_entry: np.ndarray, n_entries: int) -> np.ndarray:
    """Votes per entry from K-NN row indices ``idx`` (Q, K; -1 = none): each query row votes once for every
    distinct entry among its neighbours."""
    ent = np.where(idx >= 0, row_entry[np.maximum(idx, 0)], -1)
    ent = np.sort(ent, axis=1)
    first = np.ones_like(ent, dtype=bool)
    first[:, 1:] = ent[:, 1:] != ent[:, :-1]
    ok = first & (ent >= 0)
    return np.bincount(ent[ok], minlength=n_entries)


def lognormal_threshold(votes: np.ndarray, z: float) -> float:
    """Bosse & Zlot's test: the vote count above which the most voted entry is not a non-match.

    The counts of the other entries with at least one vote are taken as log-normal samples: ``mu`` and ``sigma``
    (population standard deviation) of their natural logs give ``exp(mu + z sigma)``. Infinite when fewer than two
    other entries have votes (no model yet)."""
    v = np.asarray(votes, np.float64)
    if v.size < 3:
        return math.inf
    others = np.delete(v, int(np.argmax(v)))
    others = others[others > 0]
    if others.size < 2:
        return math.inf
    logs = np.log(others)
    return float(np.exp(logs.mean() + z * logs.std()))


class LognormalVotes(VoteStrategy["GestaltVoting"]):
    """Bosse & Zlot's query (module docstring): rounds of ``sample_fraction`` of the keypoints, K-NN votes, the
    log-normal stop test after each round."""

    stops_early = True

    def __init__(self, rec: GestaltVoting, query: Query) -> None:
        super().__init__(rec, query)
        self.p = rec.params
        self.votes = np.zeros(len(rec.entries), np.int64)
        self.threshold = math.inf

    def possible(self) -> bool:
        return self.n > 0 and self.query.rows.shape[0] > 0

    def order(self) -> np.ndarray:
        return np.random.default_rng(self.p.seed).permutation(self.n)

    def batch_size(self) -> int:
        return max(1, math.ceil(self.p.sample_fraction * self.n))

    def vote(self, batch: np.ndarray) -> None:
        qr = self.query
        _, idx = qr.rows.knn(qr.q[batch], self.p.knn, self.p.search.nn_threads)
        self.votes[: qr.n_entries] += place_votes(idx, qr.row_entry, qr.n_entries)
        self.matched += batch.size
        self.threshold = lognormal_threshold(self.votes[qr.eligible], self.p.lognormal_z)

    def ready(self) -> Shortlist | None:
        return self._shortlist(None) if self.votes.max() > self.threshold else None

    def fallback(self) -> Shortlist:
        return self._shortlist(self.p.verify.fallback_top_k)

    def _shortlist(self, top_k: int | None) -> Shortlist:
        """The most voted eligible entries with a vote (ties: lower id)."""
        votes, n, thr, eligible = self.votes, self.n, self.threshold, self.query.eligible
        ranked = np.lexsort((np.asarray(self.rec.entries.ids), -votes))
        return Shortlist(
            [e for e in ranked if eligible[e] and votes[e] > 0],
            score=lambda e: float(votes[e]) / n,
            extra=lambda e: {"votes": int(votes[e]), "n_query": n, "threshold": thr},
            top_k=top_k,
        )


class GestaltVoting(KeypointVoting):
    """`PlaceRecognizer`: Bosse & Zlot keypoint voting with log-normal early termination (module docstring)."""

    name: ClassVar[str] = "gestalt-voting"
    Params: ClassVar[type[Params]] = GestaltParams
    params: GestaltParams
    Strategy: ClassVar[type[VoteStrategy[Any]]] = LognormalVotes
