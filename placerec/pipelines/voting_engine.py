"""The query loop every 3D voting pipeline shares, and the strategies' plug-in interface.

One query runs:

1. **search a batch**: the strategy's next batch of query keypoints (``VoteStrategy.order`` / ``batch_size``)
   is matched against the eligible database rows and turned into evidence for the entries (``vote``);
2. **stop test**: ``ready`` returns a `Shortlist` of entries to verify now, or None to keep matching;
3. **verify**: the shortlist's best ``top_k`` entries not verified yet (at least ``verify.separation_m`` from
   those verified before) go through the shared verification (`placerec.verify.candidates`),
   ``verify.at_once`` (None: ``verify.top_k``) at a time, until one is accepted; an accepted candidate ends the
   query. A rejection is reported to the strategy (``rejected``), which may change its evidence and ask for the
   stop test again on the same votes;
   when the shortlist was ``final`` and nothing was left to verify, matching stops;
4. **fallback**: when every keypoint is consumed without an accepted candidate, ``fallback`` ranks the entries
   once more and that shortlist is verified;
5. **decorate**: the candidates, best verified score first (ties: accepted, then retrieval score), the best
   ``k`` returned (the time of the others' verification shared among them), each with ``T_world_query`` (the
   entry's pose composed with the verified ``T_match_query``) and the diagnostics ``keypoints_consumed``
   (query keypoints matched against the whole database), ``n_keypoints``, ``match_ms``, ``n_verified`` and,
   for a strategy that can stop early, ``early_stop``.

Without verification (``verify.enabled`` false) the first shortlist is the answer: its best ``k`` entries with
their retrieval scores, ``accepted`` None.

A strategy is a `VoteStrategy` subclass made once per query: the ratio-test vote counts
(`placerec.pipelines.keypoint_voting`), the probabilistic posterior (`probabilistic_voting`), Bosse & Zlot's
log-normal test (`gestalt_voting`), global registration (`global_registration`) and DELIGHT's ranking
(`delight`).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, ClassVar, Generic, TypeVar

import numpy as np

from placerec.errors import ScanDataError
from placerec.retrieval.descriptor_store import StoreView
from placerec.types import Candidate, Description
from placerec.verify.candidates import Retrieved, verify_candidates
from placerec.verify.verify import as_source

if TYPE_CHECKING:
    from placerec.pipelines.keypoint_voting import KeypointVoting

__all__ = ["Query", "Shortlist", "VoteStrategy", "run_query"]

#: the recognizer a strategy serves (its params and entries)
R = TypeVar("R", bound="KeypointVoting")


@dataclass
class Query:
    """One query: its descriptors ``q`` (Q, D) and keypoints ``qkp`` (Q, 3), the eligible database rows
    (``rows``, their entry index ``row_entry``, ``n_entries`` the indices range over) and the eligible entries."""

    description: Description
    q: np.ndarray
    qkp: np.ndarray
    rows: StoreView
    row_entry: np.ndarray
    n_entries: int
    eligible: np.ndarray
    query_id: int
    k: int


@dataclass
class Shortlist:
    """Entries to verify, best first (``ranked``: entry indices), ``top_k`` of them (None: ``verify.top_k``), with
    each one's retrieval ``score`` and diagnostics (``extra``); ``retrieve`` gives an entry's correspondences when
    the strategy found them itself (default: matched against its local map). ``final``: the ranking covers every
    eligible entry, so when none is left to verify matching more keypoints cannot add one."""

    ranked: Iterable[Any]
    score: Callable[[int], float]
    extra: Callable[[int], dict[str, Any]]
    top_k: int | None = None
    final: bool = False
    retrieve: Callable[[int], Retrieved] | None = None


class VoteStrategy(Generic[R]):
    """How one query turns matched keypoints into a ranking of the entries (see the module docstring). The base
    matches every keypoint at once and never stops early; subclasses set what differs."""

    #: whether the strategy has a stop test (its candidates then report ``early_stop``)
    stops_early: ClassVar[bool] = False

    def __init__(self, rec: R, query: Query) -> None:
        self.rec = rec
        self.query = query
        self.n = int(query.q.shape[0])
        #: query keypoints matched against the whole database so far
        self.matched = 0

    def possible(self) -> bool:
        """Whether there is anything to match: query descriptors and at least two eligible rows (the ratio test)."""
        return self.n > 0 and self.query.rows.shape[0] >= 2

    def order(self) -> np.ndarray:
        """The order in which query keypoints are consumed."""
        return np.arange(self.n)

    def batch_size(self) -> int:
        return self.n

    def vote(self, batch: np.ndarray) -> None:
        """Match the query keypoints ``batch`` (indices into ``query.q``) and update the evidence."""

    def ready(self) -> Shortlist | None:
        """The stop test: entries to verify now, or None to match more keypoints."""
        return None

    def rejected(self, entries: list[int]) -> bool:
        """``entries`` were verified and rejected; True to run the stop test again on the same votes."""
        return False

    def fallback(self) -> Shortlist | None:
        """Entries to verify once every keypoint is consumed without an accepted candidate."""
        return None


def run_query(rec: R, strategy: type[VoteStrategy[R]], query: Query) -> list[Candidate]:
    """The query loop (module docstring) of ``rec`` with ``strategy``."""
    s = strategy(rec, query)
    if not s.possible():
        return []
    vp = rec.params.verify
    if vp.enabled and "cloud" not in query.description:
        raise ScanDataError(f"{rec.name}: verification needs the query description's 'cloud'")
    verifier = _Verifier(rec, query)
    order = s.order()
    consumed, stopped, accepted, exhausted, match_ms = 0, False, False, False, 0.0
    while consumed < s.n and not accepted and not exhausted:
        t0 = time.perf_counter()
        batch = order[consumed : consumed + s.batch_size()]
        s.vote(batch)
        consumed += batch.size
        match_ms += (time.perf_counter() - t0) * 1e3
        while not accepted:
            short = s.ready()
            if short is None:
                break
            stopped = True
            before = len(verifier.verified)
            accepted = verifier.verify(short)
            rejected = list(verifier.verified)[before:]
            exhausted = not accepted and not rejected and short.final
            if accepted or not rejected or not s.rejected(rejected):
                break
    if not accepted:
        short = s.fallback()
        if short is not None:
            verifier.verify(short)
    return _decorate(rec, s, verifier.verified, query.k, stopped, match_ms)


class _Verifier:
    """The candidates of one query's verified entries (by entry index), and the verification of a shortlist."""

    def __init__(self, rec: KeypointVoting, query: Query) -> None:
        self.rec = rec
        self.query = query
        self.verified: dict[int, Candidate] = {}
        self._source: Any = None

    def verify(self, short: Shortlist) -> bool:
        """Verify ``short``'s best entries not verified yet; True when one is accepted (without verification:
        when there was one to answer with)."""
        rec, query = self.rec, self.query
        vp = rec.params.verify
        if not vp.enabled:
            picked = rec.pick(short.ranked, self.verified, max(query.k, short.top_k or vp.top_k))
            for e in picked:
                score = float(short.score(e))
                extra = short.extra(e)
                self.verified[e] = Candidate(
                    query.query_id, rec.entries.ids[e], score, None, None, extra, retrieval_score=score
                )
            return bool(picked)
        picked = rec.pick(short.ranked, self.verified, short.top_k or vp.top_k)
        if self._source is None and picked:
            self._source = as_source(query.description["cloud"], vp)
        retrieve = short.retrieve or (lambda e: rec.local_matches(e, query, short.score(e), short.extra(e)))
        step = vp.at_once or vp.top_k
        for a in range(0, len(picked), step):
            chunk = picked[a : a + step]
            cands = verify_candidates(
                self._source, [retrieve(e) for e in chunk], rec.clouds, vp, query.query_id, None
            )
            by_id = {rec.entries.ids[e]: e for e in chunk}
            for c in cands:
                self.verified[by_id[c.match_id]] = c
            if any(c.accepted for c in cands):
                return True
        return False


def _decorate(
    rec: KeypointVoting,
    s: VoteStrategy[Any],
    verified: dict[int, Candidate],
    k: int,
    stopped: bool,
    match_ms: float,
) -> list[Candidate]:
    out = sorted(verified.values(), key=_rank_key)
    kept = out[:k]
    dropped_ms = sum(c.verify_ms for c in out[len(kept) :])
    entry_of = {c.match_id: e for e, c in verified.items()}
    answer = []
    for c in kept:
        c.extra.update(
            keypoints_consumed=s.matched, n_keypoints=s.n, match_ms=match_ms, n_verified=len(verified)
        )
        if s.stops_early:
            c.extra["early_stop"] = stopped
        T = None
        if c.relative_pose is not None:
            T = np.asarray(rec.entries.poses[entry_of[c.match_id]]) @ c.relative_pose
        answer.append(replace(c, verify_ms=c.verify_ms + dropped_ms / len(kept), T_world_query=T))
    return answer


def _rank_key(c: Candidate) -> tuple[float, bool, float]:
    """Best verified score first; ties: accepted first, then the better retrieval score."""
    return (-c.score, not c.accepted, -(c.retrieval_score or 0.0))
