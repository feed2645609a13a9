"""Hierarchical k-means++ for vocabulary trees, vectorised over all nodes of a level at once.

DBoW2 (``TemplatedVocabulary::HKmeansStep``) clusters one node at a time; here every node of a level is clustered
in the same NumPy passes. Descriptors are kept sorted by node, so a node is a contiguous *segment* of rows, and
the per-segment steps are segment-wise array operations (cumulative sums + ``searchsorted`` for the k-means++ draw,
one sparse-matrix product for the centres). After the first pass only nodes whose assignments changed are
iterated again (the others are at a fixed point).

What follows DBoW2:

* k-means++ seeding: the first centre is a uniformly drawn member; each further centre is drawn with probability
  proportional to the member's distance to its nearest chosen centre (DBoW2's ``F::distance``: Hamming distance for
  binary descriptors, *squared* L2 for float ones, i.e. the classic D(x)^2 rule). Seeding stops early when every
  member coincides with a chosen centre (fewer than k clusters).
* Lloyd iterations: assign to the nearest centre (first one on ties), recompute centres (binary: bit set when at
  least ceil(n/2) members have it; float: the mean). DBoW2 iterates until no assignment changes; we stop there
  too, or after ``max_iterations`` (default 10; on ORB descriptors of intensity images fewer than 3 % of the
  assignments of a level still change at the 10th iteration, mostly near-ties between two centres).
* a node with at most k descriptors gets one child per descriptor; a child is split further only if it holds more
  than one descriptor and the depth is below L.

What differs: a cluster that ends empty (possible with binary majority centres) gets no node (DBoW2 keeps a node
with no descriptor, weight 0); nodes larger than ``max_fit`` descriptors are fitted on a random subset of that
size and all their members assigned to the fitted centres afterwards (None: use all, as DBoW2).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from placerec.retrieval.bits import popcount, to_words

log = logging.getLogger(__name__)

__all__ = ["DescriptorSpace", "build_tree"]

_CHUNK = 1 << 16


@dataclass
class DescriptorSpace:
    """Training descriptors: ``kind`` "binary" with ``raw`` (N, B) uint8 and ``words`` (N, W) uint64 (for Hamming
    distances), or "float" with ``raw`` (N, D) float32."""

    kind: str
    raw: np.ndarray
    words: np.ndarray | None = None

    @classmethod
    def of(cls, descriptors: np.ndarray) -> DescriptorSpace:
        d = np.ascontiguousarray(descriptors)
        if d.dtype == np.uint8:
            return cls("binary", d, to_words(d))
        return cls("float", np.ascontiguousarray(d, dtype=np.float32))

    def __len__(self) -> int:
        return int(self.raw.shape[0])

    def features(self) -> np.ndarray:
        """The array distances are computed on (uint64 words or float32 vectors)."""
        if self.kind == "binary":
            assert self.words is not None  # `of` sets them for binary descriptors
            return self.words
        return self.raw

    def distance_to(self, rows: np.ndarray, centres: np.ndarray) -> np.ndarray:
        """DBoW2 distance of ``rows`` (of features()) to one centre per row: Hamming or squared L2 (float64)."""
        if self.kind == "binary":
            counts = popcount(np.bitwise_xor(rows, centres))
            out = counts[:, 0].astype(np.float64)
            for w in range(1, counts.shape[1]):
                out += counts[:, w]
            return out
        diff = rows - centres
        return np.einsum("ij,ij->i", diff, diff, dtype=np.float64)

    def group_centres(
        self, rows: np.ndarray, key: np.ndarray, n_groups: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """Centres of the groups ``key`` (0..n_groups-1) of ``rows``: (group ids that have members, centres).

        Binary: bit set when at least ceil(n/2) members have it, packed to uint64 words; float: the mean. Group
        sums are one sparse-matrix product (segment reductions along rows are slow in NumPy).
        """
        import scipy.sparse as sp

        counts = np.bincount(key, minlength=n_groups)
        filled = np.flatnonzero(counts)
        compact = np.searchsorted(filled, key)
        member = sp.csr_matrix(
            (np.ones(rows.size, np.float32), (compact, np.arange(rows.size))), shape=(filled.size, rows.size)
        )
        c = counts[filled][:, None]
        if self.kind == "float":
            sums = member.astype(np.float64) @ self.raw[rows].astype(np.float64)
            return filled, (sums / c).astype(np.float32)
        raw = self.raw[rows]
        n_bytes = raw.shape[1]
        major = np.empty((filled.size, 8 * n_bytes), np.uint8)
        for a in range(0, n_bytes, 8):  # 64 bit columns at a time
            bits = np.unpackbits(raw[:, a : a + 8], axis=1, bitorder="little").astype(np.float32)
            major[:, 8 * a : 8 * a + bits.shape[1]] = 2 * (member @ bits) >= c
        return filled, to_words(np.packbits(major, axis=1, bitorder="little"))


def _segment_ids(lengths: np.ndarray) -> np.ndarray:
    return np.repeat(np.arange(lengths.size), lengths)


def _assign(
    space: DescriptorSpace, rows: np.ndarray, seg: np.ndarray, centres: np.ndarray, valid: np.ndarray
) -> np.ndarray:
    """Index (0..k-1) of the nearest valid centre of each row's segment (first one on ties)."""
    feats = space.features()
    labels = np.empty(rows.size, np.int64)
    chunk = _CHUNK if space.kind == "binary" else _CHUNK // 4
    for a in range(0, rows.size, chunk):
        s = seg[a : a + chunk]
        x = np.take(feats, rows[a : a + chunk], axis=0)
        cs = np.take(centres, s, axis=0)  # (m, k, ...); np.take is much faster than fancy indexing
        if space.kind == "binary":
            counts = popcount(cs ^ np.repeat(x[:, None, :], cs.shape[1], axis=1))
            dist = counts[:, :, 0].astype(np.float64)
            for w in range(1, counts.shape[2]):
                dist += counts[:, :, w]
        else:
            dist = np.einsum("mkd,mkd->mk", cs, cs) - 2.0 * np.einsum("mkd,md->mk", cs, x)
        dist[~np.take(valid, s, axis=0)] = np.inf
        labels[a : a + chunk] = np.argmin(dist, axis=1)
    return labels


def _seed(
    space: DescriptorSpace,
    rows: np.ndarray,
    lengths: np.ndarray,
    k: int,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """k-means++ seeding of every segment at once: (centres (S, k, ...), valid (S, k))."""
    feats = space.features()
    n_seg = lengths.size
    starts = np.r_[0, np.cumsum(lengths)[:-1]]
    seg = _segment_ids(lengths)
    x = feats[rows]
    centres = np.zeros((n_seg, k) + feats.shape[1:], feats.dtype)
    valid = np.zeros((n_seg, k), bool)
    first = starts + np.minimum((rng.random(n_seg) * lengths).astype(np.int64), lengths - 1)
    centres[:, 0] = x[first]
    valid[:, 0] = True
    min_d = space.distance_to(x, centres[seg, 0])
    active = np.ones(n_seg, bool)
    for j in range(1, k):
        cum = np.cumsum(min_d)
        before = np.r_[0.0, cum][starts]
        totals = np.r_[0.0, cum][starts + lengths] - before
        active &= totals > 0
        if not active.any():
            break
        u = 1.0 - rng.random(n_seg)  # in (0, 1]: never lands on an already chosen (zero-distance) member
        pick = np.searchsorted(cum, before + u * totals, side="left")
        pick = np.clip(pick, starts, starts + lengths - 1)
        centres[active, j] = x[pick[active]]
        valid[active, j] = True
        row_active = active[seg]
        d = space.distance_to(x[row_active], centres[seg[row_active], j])
        min_d[row_active] = np.minimum(min_d[row_active], d)
    return centres, valid


def _kmeans_segments(
    space: DescriptorSpace,
    rows: np.ndarray,
    lengths: np.ndarray,
    k: int,
    rng: np.random.Generator,
    max_iterations: int,
    max_fit: int | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cluster every segment (rows sorted by segment, all longer than k). Returns the label of each row,
    the centres (S, k, ...) and which centres exist (S, k)."""
    seg = _segment_ids(lengths)
    fit_rows, fit_len = rows, lengths
    subsample = max_fit is not None and bool((lengths > max_fit).any())
    if subsample and max_fit is not None:
        keep = np.ones(rows.size, bool)
        starts = np.r_[0, np.cumsum(lengths)[:-1]]
        for s in np.flatnonzero(lengths > max_fit):
            pos = starts[s] + np.sort(rng.choice(lengths[s], max_fit, replace=False))
            keep[starts[s] : starts[s] + lengths[s]] = False
            keep[pos] = True
        fit_rows, fit_len = rows[keep], np.minimum(lengths, max_fit)
    fit_seg = _segment_ids(fit_len)
    n_seg = lengths.size
    centres, valid = _seed(space, fit_rows, fit_len, k, rng)
    flat = centres.reshape((n_seg * k,) + centres.shape[2:])
    labels = _assign(space, fit_rows, fit_seg, centres, valid)
    active = np.ones(n_seg, bool)
    for it in range(max_iterations):
        # only segments whose assignments changed in the last pass can move (the others are at a fixed point)
        sel = np.flatnonzero(active[fit_seg])
        rows_a, seg_a, lab_a = fit_rows[sel], fit_seg[sel], labels[sel]
        filled, new_centres = space.group_centres(rows_a, seg_a * k + lab_a, n_seg * k)
        flat[filled] = new_centres
        new = _assign(space, rows_a, seg_a, centres, valid)
        moved = new != lab_a
        labels[sel] = new
        active = np.zeros(n_seg, bool)
        active[seg_a[moved]] = True
        log.debug(
            "k-means iteration %d: %d assignments changed in %d nodes", it + 1, moved.sum(), active.sum()
        )
        if not active.any():
            break
    if subsample:
        labels = _assign(space, rows, seg, centres, valid)
    return labels, centres, valid


def build_tree(
    space: DescriptorSpace,
    k: int,
    L: int,
    rng: np.random.Generator,
    max_iterations: int = 10,
    max_fit: int | None = None,
    on_level: Callable[[int, int], None] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Hierarchical k-means++ of ``space`` into a tree of branching ``k`` and depth ``L``.

    Returns ``parents`` (n_nodes,) int32 (root 0 has parent -1) and ``centres`` (n_nodes, ...) (uint64 words for
    binary, float32 vectors for float; the root's centre is zero). Node ids are breadth-first: the children of a
    node are consecutive, in cluster order. ``on_level(level, n_nodes)`` is called after each level.
    """
    feats = space.features()
    parents = [np.array([-1], np.int32)]
    centre_parts = [np.zeros((1,) + feats.shape[1:], feats.dtype)]
    n_nodes = 1
    # rows grouped by the node they sit in; nodes to split at this level and their row counts
    rows = np.arange(len(space), dtype=np.int64)
    split_nodes = np.array([0], np.int64) if len(space) > 0 else np.zeros(0, np.int64)
    lengths = np.array([len(space)], np.int64) if len(space) > 0 else np.zeros(0, np.int64)
    for level in range(1, L + 1):
        if split_nodes.size == 0:
            break
        seg = _segment_ids(lengths)
        labels = np.empty(rows.size, np.int64)
        cluster_centres = np.zeros((split_nodes.size, k) + feats.shape[1:], feats.dtype)
        cluster_valid = np.zeros((split_nodes.size, k), bool)
        small = lengths <= k
        row_small = small[seg]
        if small.any():  # one cluster per descriptor
            starts = np.r_[0, np.cumsum(lengths)[:-1]]
            labels[row_small] = (np.arange(rows.size) - starts[seg])[row_small]
            lab_s = labels[row_small]
            cluster_centres[seg[row_small], lab_s] = feats[rows[row_small]]
            cluster_valid[seg[row_small], lab_s] = True
        big = np.flatnonzero(~small)
        if big.size:
            row_big = ~row_small
            lab_b, cen_b, val_b = _kmeans_segments(
                space, rows[row_big], lengths[big], k, rng, max_iterations, max_fit
            )
            labels[row_big] = lab_b
            cluster_centres[big] = cen_b
            cluster_valid[big] = val_b
        # children: non-empty clusters, numbered segment by segment in cluster order
        key = seg * k + labels
        counts = np.bincount(key, minlength=split_nodes.size * k)
        nonempty = counts > 0
        child_of_key = np.full(split_nodes.size * k, -1, np.int64)
        child_of_key[nonempty] = n_nodes + np.arange(int(nonempty.sum()))
        key_seg = np.repeat(np.arange(split_nodes.size), k)
        parents.append(split_nodes[key_seg[nonempty]].astype(np.int32))
        centre_parts.append(cluster_centres.reshape((-1,) + feats.shape[1:])[nonempty])
        n_new = int(nonempty.sum())
        # next level: children with more than one descriptor, rows regrouped by child
        order = np.argsort(key, kind="stable")
        rows = rows[order]
        child_rows = counts[nonempty]
        child_ids = child_of_key[nonempty]
        n_nodes += n_new
        if on_level is not None:
            on_level(level, n_nodes)
        go = child_rows > 1
        keep_rows = np.repeat(go, child_rows)
        rows = rows[keep_rows]
        split_nodes = child_ids[go]
        lengths = child_rows[go]
    return np.concatenate(parents), np.concatenate(centre_parts)
