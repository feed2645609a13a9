"""DBoW2-style image database: inverse index (word -> entries) for L1-scored queries, direct index for matching.

Inverse index: a CSR table over words (``indptr``, then per posting the entry index and the word's value in that
entry) plus an append buffer for recent entries; the buffer is merged into the CSR table (one stable sort) when it
grows past a quarter of the table, so adding is amortised O(1) and a query reads the CSR rows of its words plus one
vectorised pass over the buffer.

Query score (DBoW2's L1 scoring): for every entry sharing words with the query,
``s = -0.5 * sum_common(|q_i - d_i| - |q_i| - |d_i|)``, which equals ``1 - 0.5 |q - d|_1`` for L1-normalised
vectors; accumulated over the postings of the query's words in one compiled pass (Numba). Entries sharing no
word score 0 and are not returned. ``max_id`` keeps only entries whose caller id is ``<= max_id`` (the exclusion window).

Direct index: per entry, the vocabulary node at depth ``L - levels_up`` of every feature (DBoW2's FeatureVector),
so that features are matched only against features under the same node (`candidate_pairs`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numba import njit

from placerec.errors import ArtifactError, ScanDataError, short_repr
from placerec.io.artifact_schema import Member, check_counts, check_unique
from placerec.io.atomic import load_artifact, save_artifact
from placerec.retrieval.dbow.vocabulary import BowVector, Vocabulary

log = logging.getLogger(__name__)

__all__ = ["BowDatabase", "QueryResults", "candidate_pairs"]

_KIND = "dbow-database"
_VERSION = 1
# entries (ids, BoW vector lengths, direct-index lengths) and their concatenated postings and nodes
_SCHEMA = {
    "ids": Member("iu", ("n_entries",)),
    "bow_lens": Member("iu", ("n_entries",), min_value=0),
    "bow_words": Member("iu", ("n_postings",), min_value=0),
    "bow_values": Member("f", ("n_postings",), finite=True),
    "node_lens": Member("iu", ("n_entries",), min_value=0),
    "nodes": Member("iu", ("n_nodes",)),
    "has_nodes": Member("b", ("n_entries",)),
}
_MIN_BUFFER = 1 << 14


@dataclass(frozen=True)
class QueryResults:
    """Entries best first: caller ``ids`` (int64) and L1 ``scores`` (float64)."""

    ids: np.ndarray
    scores: np.ndarray

    def __len__(self) -> int:
        return int(self.ids.size)


class BowDatabase:
    """Inverse + direct index over BoW vectors of a `Vocabulary` (see the module docstring).

    ``levels_up``: depth of the direct index nodes, counted up from the leaves (DBoW2's ``di_levels``;
    None = no direct index).
    """

    def __init__(self, vocabulary: Vocabulary, levels_up: int | None = 0) -> None:
        self.vocabulary = vocabulary
        self.levels_up = levels_up
        nw = vocabulary.n_words
        self._indptr = np.zeros(nw + 1, np.int64)
        self._entry = np.zeros(0, np.int32)
        self._value = np.zeros(0, np.float64)
        self._buf_word = np.zeros(1024, np.int32)
        self._buf_entry = np.zeros(1024, np.int32)
        self._buf_value = np.zeros(1024, np.float64)
        self._buf_n = 0
        self._ids: list[int] = []
        self._ids_arr = np.zeros(0, np.int64)
        self._bows: list[BowVector] = []
        self._nodes: list[np.ndarray | None] = []
        self._index_of: dict[int, int] = {}

    # ---------------------------------------------------------------------------------------------- adding
    def __len__(self) -> int:
        return len(self._ids)

    @property
    def ids(self) -> np.ndarray:
        """Caller ids of the entries, in insertion order."""
        if self._ids_arr.size != len(self._ids):
            self._ids_arr = np.asarray(self._ids, np.int64)
        return self._ids_arr

    def add_descriptors(self, descriptors: np.ndarray, entry_id: int | None = None) -> int:
        """Transform an image's descriptors and add them; returns the entry id."""
        if self.levels_up is None:
            return self.add(self.vocabulary.transform(descriptors), None, entry_id)
        bow, nodes = self.vocabulary.transform(descriptors, self.levels_up)
        return self.add(bow, nodes, entry_id)

    def add(
        self, bow: BowVector, feature_nodes: np.ndarray | None = None, entry_id: int | None = None
    ) -> int:
        """Add a BoW vector (and its direct-index nodes) under ``entry_id`` (default: the number of entries)."""
        eid = len(self._ids) if entry_id is None else int(entry_id)
        if eid in self._index_of:
            raise ScanDataError(f"BowDatabase: entry id {eid} was already added")
        words = np.asarray(bow.words, np.int32)
        if words.size and (words.min() < 0 or words.max() >= self.vocabulary.n_words):
            raise ScanDataError(f"BowDatabase: word ids out of range 0..{self.vocabulary.n_words - 1}")
        index = len(self._ids)
        self._index_of[eid] = index
        self._ids.append(eid)
        self._bows.append(BowVector(words, np.asarray(bow.values, np.float64)))
        self._nodes.append(None if feature_nodes is None else np.asarray(feature_nodes, np.int32))
        self._append(words, index, bow.values)
        return eid

    def _append(self, words: np.ndarray, index: int, values: np.ndarray) -> None:
        n, m = self._buf_n, words.size
        if n + m > self._buf_word.size:
            cap = max(2 * self._buf_word.size, n + m)
            for name in ("_buf_word", "_buf_entry", "_buf_value"):
                old = getattr(self, name)
                new = np.zeros(cap, old.dtype)
                new[:n] = old[:n]
                setattr(self, name, new)
        self._buf_word[n : n + m] = words
        self._buf_entry[n : n + m] = index
        self._buf_value[n : n + m] = values
        self._buf_n = n + m
        if self._buf_n >= max(_MIN_BUFFER, self._entry.size // 4):
            self._merge()

    def _merge(self) -> None:
        """Fold the append buffer into the CSR table (stable: postings of a word stay in insertion order)."""
        n = self._buf_n
        if n == 0:
            return
        counts = np.diff(self._indptr)
        words = np.concatenate(
            [np.repeat(np.arange(counts.size, dtype=np.int32), counts), self._buf_word[:n]]
        )
        order = np.argsort(words, kind="stable")
        self._entry = np.concatenate([self._entry, self._buf_entry[:n]])[order]
        self._value = np.concatenate([self._value, self._buf_value[:n]])[order]
        self._indptr = np.r_[0, np.cumsum(np.bincount(words, minlength=counts.size))].astype(np.int64)
        self._buf_n = 0

    # ---------------------------------------------------------------------------------------------- queries
    def bow(self, entry_id: int) -> BowVector:
        return self._bows[self._index(entry_id)]

    def feature_nodes(self, entry_id: int) -> np.ndarray | None:
        """Direct index of an entry: the node of each of its features (-1 for stopped features)."""
        return self._nodes[self._index(entry_id)]

    def _index(self, entry_id: int) -> int:
        try:
            return self._index_of[int(entry_id)]
        except KeyError:
            raise ScanDataError(f"BowDatabase: no entry {entry_id}") from None

    @property
    def last_id(self) -> int | None:
        """Id of the most recently added entry (DLoopDetector's previous frame)."""
        return self._ids[-1] if self._ids else None

    def query(self, bow: BowVector, max_results: int = 1, max_id: int | None = None) -> QueryResults:
        """Entries most similar to ``bow`` by the L1 score, best first (ties: lower id first)."""
        n_entries = len(self._ids)
        qw = np.asarray(bow.words, np.int64)
        if n_entries == 0 or qw.size == 0 or max_results <= 0:
            return QueryResults(np.zeros(0, np.int64), np.zeros(0))
        qv = np.asarray(bow.values, np.float64)
        acc = np.zeros(n_entries)
        _accumulate_postings(self._indptr, self._entry, self._value, qw, qv, acc)
        if self._buf_n:
            dense = np.zeros(self.vocabulary.n_words)
            dense[qw] = qv
            n = self._buf_n
            _accumulate_buffer(self._buf_word[:n], self._buf_entry[:n], self._buf_value[:n], dense, acc)
        ok = acc < 0
        if max_id is not None:
            ok &= self.ids <= max_id
        cand = np.flatnonzero(ok)
        if cand.size == 0:
            return QueryResults(np.zeros(0, np.int64), np.zeros(0))
        scores = -0.5 * acc[cand]
        if cand.size > max_results:
            part = np.argpartition(-scores, max_results - 1)[:max_results]
            cand, scores = cand[part], scores[part]
        ids = self.ids[cand]
        order = np.lexsort((ids, -scores))
        return QueryResults(ids[order], scores[order])

    # ---------------------------------------------------------------------------------------------- persistence
    def save(self, path: str | Path) -> None:
        """Write the entries (ids, BoW vectors, direct index) atomically with the vocabulary's fingerprint."""
        lens = np.array([b.words.size for b in self._bows], np.int64)
        nodes = [np.zeros(0, np.int32) if n is None else n for n in self._nodes]
        arrays = {
            "ids": self.ids,
            "bow_lens": lens,
            "bow_words": _cat([b.words for b in self._bows], np.int32),
            "bow_values": _cat([b.values for b in self._bows], np.float64),
            "node_lens": np.array([n.size for n in nodes], np.int64),
            "nodes": _cat(nodes, np.int32),
            "has_nodes": np.array([n is not None for n in self._nodes], bool),
        }
        meta = {"vocabulary": self.vocabulary.fingerprint, "levels_up": self.levels_up}
        save_artifact(path, _KIND, _VERSION, arrays, meta)

    @classmethod
    def load(cls, path: str | Path, vocabulary: Vocabulary) -> BowDatabase:
        """Read a database saved with ``vocabulary``; `ArtifactError` if the file is corrupt or inconsistent (counts
        that do not add up, repeated ids, words outside the vocabulary) or was built with another vocabulary."""
        arrays, header = load_artifact(path, _KIND, (_VERSION,), _SCHEMA, mmap=True)
        meta = header["meta"]
        if meta.get("vocabulary") != vocabulary.fingerprint:
            raise ArtifactError(
                f"{path}: database was built with vocabulary {short_repr(meta.get('vocabulary'))}, "
                f"not the given one ({vocabulary.fingerprint})"
            )
        levels_up = meta.get("levels_up")
        if levels_up is not None and (type(levels_up) is not int or not 0 <= levels_up <= vocabulary.L):
            raise ArtifactError(
                f"{path}: levels_up must be None or 0..{vocabulary.L}, got {short_repr(levels_up)}"
            )
        check_unique(arrays["ids"], path, "ids")
        check_counts(arrays["bow_lens"], arrays["bow_words"].shape[0], path, "bow_lens")
        check_counts(arrays["node_lens"], arrays["nodes"].shape[0], path, "node_lens")
        if arrays["bow_words"].size and arrays["bow_words"].max() >= vocabulary.n_words:
            raise ArtifactError(
                f"{path}: 'bow_words' refer to words beyond the vocabulary's {vocabulary.n_words}"
            )
        db = cls(vocabulary, levels_up)
        b_off = np.r_[0, np.cumsum(arrays["bow_lens"])]
        n_off = np.r_[0, np.cumsum(arrays["node_lens"])]
        for i, eid in enumerate(arrays["ids"]):
            bow = BowVector(
                arrays["bow_words"][b_off[i] : b_off[i + 1]], arrays["bow_values"][b_off[i] : b_off[i + 1]]
            )
            nodes = arrays["nodes"][n_off[i] : n_off[i + 1]] if arrays["has_nodes"][i] else None
            db.add(bow, nodes, int(eid))
        return db


@njit(cache=True, nogil=True)
def _accumulate_postings(
    indptr: np.ndarray, entry: np.ndarray, value: np.ndarray, qw: np.ndarray, qv: np.ndarray, acc: np.ndarray
) -> None:  # pragma: no cover - compiled
    """``acc[e] += |q - d| - |q| - |d|`` over the CSR postings of the query's words, in the order the words and
    postings come (so the sums are those of one `np.bincount` over the gathered postings)."""
    for k in range(qw.size):
        q = qv[k]
        aq = abs(q)
        for p in range(indptr[qw[k]], indptr[qw[k] + 1]):
            d = value[p]
            acc[entry[p]] += abs(q - d) - aq - abs(d)


@njit(cache=True, nogil=True)
def _accumulate_buffer(
    word: np.ndarray, entry: np.ndarray, value: np.ndarray, dense: np.ndarray, acc: np.ndarray
) -> None:  # pragma: no cover - compiled
    """The same over the append buffer: postings whose word the query holds (``dense[word] != 0``)."""
    for p in range(word.size):
        q = dense[word[p]]
        if q != 0.0:
            d = value[p]
            acc[entry[p]] += abs(q - d) - abs(q) - abs(d)


def candidate_pairs(nodes_a: np.ndarray, nodes_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All index pairs (i, j) with ``nodes_a[i] == nodes_b[j] >= 0`` (features under the same direct-index node)."""
    a = np.asarray(nodes_a, np.int64)
    b = np.asarray(nodes_b, np.int64)
    order = np.argsort(b, kind="stable")
    bs = np.take(b, order)
    lo = np.searchsorted(bs, a, side="left")
    hi = np.searchsorted(bs, a, side="right")
    lens = np.where(a >= 0, hi - lo, 0)
    total = int(lens.sum())
    ia = np.repeat(np.arange(a.size), lens)
    offsets = np.cumsum(lens) - lens
    jb = np.take(order, np.repeat(lo - offsets, lens) + np.arange(total))
    return ia, jb


def _cat(parts: list[np.ndarray], dtype: type) -> np.ndarray:
    return np.concatenate(parts).astype(dtype) if parts else np.zeros(0, dtype)
