"""The parameters of the 3D voting pipelines, in sections: features, search, places, verify.

* ``features`` (`placerec.three_d.features.FeatureParams`): the front end, ISS-BR keypoints and their descriptors
  (the ISHOT paper's feature settings); what a description, and a places database, are made with.
* ``search`` (`SearchParams`): how the query's descriptors find their nearest database descriptors, and the ratio
  test that makes a nearest neighbour a vote.
* ``places`` (`EntryParams`): which added scans become entries and what an entry holds; or a places database that
  replaces them.
* ``verify`` (`VotingVerifyParams`): the verification every 3D pipeline shares (`VerifiedParams`: RANSAC,
  consistency grouping, ICP, acceptance) and how a voted entry is matched with the query for it.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from placerec.params import Params
from placerec.retrieval.descriptor_store import StoreDtype
from placerec.three_d.features import FeatureParams
from placerec.verify.candidates import VerifiedParams
from placerec.verify.params import ConsistencyParams, ScoreParams

__all__ = ["EntryParams", "SearchParams", "VotingParams", "VotingVerifyParams"]


class SearchParams(Params):
    """Nearest database descriptors of the query's (exact brute force, or an approximate index) and the ratio
    test (ISHOT paper eq. 4)."""

    tau_max: float = Field(
        0.9, gt=0, le=1, description="NN ratio d1/d2 below which a descriptor votes (eq. 4)"
    )
    backend: Literal["faiss", "numpy"] = Field(
        "numpy",
        description="how the exact 2-NN of a float32 store are computed, the same neighbours either way: 'numpy', one "
        "BLAS matrix product a batch; 'faiss', faiss's exact search (one query at a time below faiss's BLAS "
        "threshold: ~4x slower for 16-keypoint batches over 100k ISHOT rows, docs/benchmarks.md)",
        json_schema_extra={"runtime": True},
    )
    index: Literal["flat", "pca", "ivf"] = Field(
        "flat",
        description="search over the whole database: exact brute force; 'pca', exact with most rows pruned by a "
        "lower bound from their projection on pca_dims principal axes (the same neighbours, built on first use "
        "after the entries change: for fixed maps); or approximate (faiss IVF, sub-linear)",
    )
    pca_dims: int = Field(256, ge=1, description="principal axes of index 'pca' (4 bytes a row each)")
    ivf_nlist: int | None = Field(None, ge=1, description="IVF lists (None = sqrt of the descriptors)")
    ivf_nprobe: int = Field(16, ge=1, description="IVF lists searched per query descriptor")
    nn_threads: int | None = Field(
        1,
        ge=1,
        description="faiss OpenMP threads (None = faiss's default)",
        json_schema_extra={"runtime": True},
    )
    descriptor_store: StoreDtype | None = Field(
        None,
        description="how descriptors are kept and searched: float32, float16 or sq8 (8-bit codes, 1 byte per "
        "dimension; placerec.retrieval.descriptor_store); None = a places database's own, else float32",
    )


class EntryParams(Params):
    """Which added scans become entries (ISHOT paper Sec. IV-B places), or a places database instead."""

    spacing_m: float = Field(0.0, ge=0, description="m; only scans this far from every entry become entries")
    window_m: float = Field(
        0.0, ge=0, description="m; accumulate scans over this path as a place (Sec. IV-B)"
    )
    database: str | None = Field(None, description="a places database file replacing the entries")


class VotingVerifyParams(VerifiedParams):
    """`VerifiedParams` (defaults: top 5, consistency grouping on, accepted by eps_ICP: ISHOT paper Sec. IV-F) plus
    how a voted entry is matched with the query for verification."""

    top_k: int = Field(5, ge=1, description="voted entries verified per query (best first); the rest dropped")
    at_once: int | None = Field(
        None,
        ge=1,
        description="entries of a shortlist verified together (the best verified score of them answers) before an "
        "accepted one ends the query (None = top_k; 1: one at a time in rank order, the first accepted answers)",
    )
    tau_max: float | None = Field(
        None,
        gt=0,
        le=1,
        description="ratio d1/d2 below which a query descriptor is paired with a candidate's for verification "
        "(None = search.tau_max; 1 keeps every nearest neighbour and leaves outliers to the consistency grouping)",
    )
    radius_m: float = Field(
        0.0,
        ge=0,
        description="m; a candidate entry is verified as a local map: with the entries within this distance of it, "
        "their keypoints and ICP clouds in its frame (0: the entry alone)",
    )
    separation_m: float = Field(
        0.0,
        ge=0,
        description="m; candidates within this distance of one already verified for the same query are skipped "
        "(their local maps overlap it), so the verified candidates cover distinct regions (0: none skipped)",
    )
    fallback_top_k: int | None = Field(
        None,
        ge=1,
        description="entries the voting pipelines that stop early (ishot-prob, gestalt-voting) verify when every "
        "query keypoint is consumed without an accepted one (their last resort; None = top_k)",
    )
    local_map_cache: int = Field(
        64,
        ge=1,
        description="local maps kept prepared for ICP (least recently used dropped; ~5 MB each in the simulated "
        "town at 15 m)",
    )


def _verify_defaults() -> VotingVerifyParams:
    return VotingVerifyParams(
        consistency=ConsistencyParams(enabled=True), score=ScoreParams(acceptance="eps_icp")
    )


class VotingParams(Params):
    """The 3D voting pipelines' parameters (module docstring) and the score thresholds apply to."""

    features: FeatureParams = Field(
        default_factory=FeatureParams, description="ISS-BR keypoints and descriptors"
    )
    search: SearchParams = Field(
        default_factory=SearchParams, description="nearest descriptors and ratio test"
    )
    places: EntryParams = Field(default_factory=EntryParams, description="what becomes an entry")
    verify: VotingVerifyParams = Field(
        default_factory=_verify_defaults,
        description="consistency grouping, RANSAC and ICP on the top-k voted entries (ISHOT paper Sec. IV-F)",
    )
    score: Literal["fraction", "votes"] = Field("fraction", description="votes / query descriptors, or votes")
