"""DBoW2-style vocabulary tree: training (hierarchical k-means++), TF-IDF weights, vectorised transform, L1 score.

Conventions (as DBoW2 and the ORB-SLAM2 text format): node 0 is the root; every other node has a parent, a centre
(a descriptor) and a weight; the leaves are the *words*, numbered in increasing node id. A descriptor is quantised
by descending from the root to the child whose centre is nearest (Hamming distance for binary descriptors, L2 for
float ones; the first child wins ties) until a leaf. Word weights are IDF = ln(N_images / N_images_with_word) for
``tf-idf``/``idf`` weighting (0 for a word no training image has, or that every image has: such words are "stopped"
and never enter a BoW vector, as in DBoW2), 1 for ``tf``/``binary``.

BoW vectors (`BowVector`) are sparse: sorted word ids and values, L1-normalised. With ``tf-idf`` a word's value is
``n_features_with_word * idf`` before normalisation. The L1 score is DBoW2's ``s(v, w) = 1 - 0.5 |v - w|_1`` in
[0, 1], computed over the common words only (`l1_score`).
"""

from __future__ import annotations

import hashlib
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, NamedTuple, get_args, overload

import numpy as np
from pydantic import Field, model_validator

from placerec.errors import ArtifactError, ScanDataError
from placerec.params import Params, resolve
from placerec.retrieval.bits import popcount, to_words

log = logging.getLogger(__name__)

__all__ = ["BowVector", "Vocabulary", "VocabularyParams", "l1_score", "train_vocabulary", "WEIGHTINGS"]

Weighting = Literal["tf-idf", "tf", "idf", "binary"]
WEIGHTINGS: tuple[str, ...] = get_args(Weighting)
_CHUNK = 1 << 15


class BowVector(NamedTuple):
    """A sparse bag-of-words vector: ``words`` (n,) int32 ascending, ``values`` (n,) float64 (L1-normalised)."""

    words: np.ndarray
    values: np.ndarray

    def __len__(self) -> int:
        return int(self.words.size)

    @classmethod
    def empty(cls) -> BowVector:
        return cls(np.zeros(0, np.int32), np.zeros(0, np.float64))


def l1_score(v: BowVector, w: BowVector) -> float:
    """DBoW2's L1 score of two L1-normalised vectors: ``-0.5 * sum_common(|v_i - w_i| - |v_i| - |w_i|)``,
    which equals ``1 - 0.5 * |v - w|_1``."""
    common, iv, iw = np.intersect1d(v.words, w.words, assume_unique=True, return_indices=True)
    if common.size == 0:
        return 0.0
    a, b = v.values[iv], w.values[iw]
    return float(-0.5 * np.sum(np.abs(a - b) - np.abs(a) - np.abs(b)))


@dataclass(eq=False)
class Vocabulary:
    """A vocabulary tree (see the module docstring).

    ``parents`` (n_nodes,) int32 with ``parents[0] == -1``; ``centres`` (n_nodes, B) uint8 for binary descriptors
    of B bytes or (n_nodes, D) float32 for float ones (row 0, the root, is unused); ``weights`` (n_nodes,) float32
    (the IDF of each word, 0 for inner nodes). ``meta`` holds free provenance (training data, time, version).
    """

    k: int
    L: int
    parents: np.ndarray
    centres: np.ndarray
    weights: np.ndarray
    weighting: str = "tf-idf"
    scoring: str = "l1"
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.parents = np.ascontiguousarray(self.parents, np.int32).reshape(-1)
        n = self.parents.size
        c = np.asarray(self.centres)
        if c.dtype != np.uint8:
            c = c.astype(np.float32)
        self.centres = np.ascontiguousarray(c)
        self.weights = np.ascontiguousarray(self.weights, np.float32).reshape(-1)
        if n == 0 or self.parents[0] != -1:
            raise ArtifactError("vocabulary: node 0 must be the root (parent -1)")
        if self.centres.ndim != 2 or self.centres.shape[0] != n or self.weights.size != n:
            raise ArtifactError(
                f"vocabulary: {n} nodes but centres {self.centres.shape} and weights {self.weights.shape}"
            )
        p = self.parents[1:]
        if p.size and (p.min() < 0 or np.any(p >= np.arange(1, n))):
            raise ArtifactError("vocabulary: every node's parent must be an earlier node")
        if self.weighting not in WEIGHTINGS:
            raise ArtifactError(f"vocabulary: unknown weighting {self.weighting!r}; allowed: {WEIGHTINGS}")
        if self.scoring != "l1":
            log.warning("vocabulary scoring %r: placerec always scores with L1", self.scoring)
        n_children = np.bincount(p, minlength=n)
        self.is_leaf = n_children == 0
        self.is_leaf[0] = False  # the root is never a word
        leaves = np.flatnonzero(self.is_leaf)
        self.word_of_node = np.full(n, -1, np.int32)
        self.word_of_node[leaves] = np.arange(leaves.size, dtype=np.int32)
        self.node_of_word = leaves.astype(np.int32)
        self.depth = _depths(self.parents)
        self.word_weights = self.weights[self.node_of_word].astype(np.float64)
        self._build_descent_tables(p, n_children, leaves)

    def _build_descent_tables(self, p: np.ndarray, n_children: np.ndarray, leaves: np.ndarray) -> None:
        """The descent table ``_next`` (n, kmax): every node's children in node id order, padded with node 0 (the
        root, never a child, so it can serve as a sentinel with an infinite distance), and every leaf its own only
        child, so that all descriptors take the same number of steps without bookkeeping."""
        n = self.n_nodes
        kmax = max(int(n_children.max()) if n > 1 else 1, 1)
        order = np.argsort(p, kind="stable").astype(np.int32) + 1  # children grouped by parent, in id order
        first = np.cumsum(n_children) - n_children
        parent_sorted = self.parents[order]
        nxt = np.zeros((n, kmax), np.int32)
        nxt[parent_sorted, np.arange(order.size) - first[parent_sorted]] = order
        nxt[leaves, 0] = leaves
        self._next = nxt
        self._steps = int(self.depth.max()) if n > 1 else 0
        if self.binary:
            self._centre_words = to_words(self.centres)
            self._penalty = np.zeros(n, np.int32)
            self._penalty[0] = 1 << 20
        else:
            sq = np.einsum("ij,ij->i", self.centres, self.centres, dtype=np.float64).astype(np.float32)
            sq[0] = np.inf
            self._penalty = sq

    @property
    def children(self) -> np.ndarray:
        """(n_nodes, kmax) int32: children of every node in node id order, -1 padded."""
        out = np.where(self._next > 0, self._next, -1)
        out[self.is_leaf] = -1
        return out

    # ------------------------------------------------------------------------------------------ properties
    @property
    def binary(self) -> bool:
        return self.centres.dtype == np.uint8

    @property
    def kind(self) -> Literal["binary", "float"]:
        return "binary" if self.binary else "float"

    @property
    def descriptor_size(self) -> int:
        """Bytes per binary descriptor or dimension of float ones."""
        return int(self.centres.shape[1])

    @property
    def n_nodes(self) -> int:
        return int(self.parents.size)

    @property
    def n_words(self) -> int:
        return int(self.node_of_word.size)

    def __len__(self) -> int:
        return self.n_words

    @property
    def fingerprint(self) -> str:
        """A short hash of the tree and weights (databases record it to refuse another vocabulary)."""
        if not hasattr(self, "_fingerprint"):
            h = hashlib.sha1()
            for arr in (self.parents, self.centres, self.weights):
                h.update(np.ascontiguousarray(arr).tobytes())
            h.update(f"{self.k} {self.L} {self.weighting}".encode())
            self._fingerprint = h.hexdigest()[:16]
        return self._fingerprint

    def __repr__(self) -> str:
        return (
            f"Vocabulary(k={self.k}, L={self.L}, {self.kind} x{self.descriptor_size}, nodes={self.n_nodes}, "
            f"words={self.n_words}, weighting={self.weighting})"
        )

    # ------------------------------------------------------------------------------------------ transform
    def check_descriptors(self, descriptors: np.ndarray) -> np.ndarray:
        d = np.asarray(descriptors)
        if d.ndim != 2 or d.shape[1] != self.descriptor_size:
            raise ScanDataError(
                f"vocabulary expects {self.kind} descriptors of size {self.descriptor_size}, got shape {d.shape}"
            )
        if self.binary and d.dtype != np.uint8:
            raise ScanDataError(f"vocabulary expects binary uint8 descriptors, got {d.dtype}")
        if not self.binary:
            if d.dtype == np.uint8:
                raise ScanDataError("vocabulary expects float descriptors, got uint8 (binary)")
            d = d.astype(np.float32, copy=False)
        return np.ascontiguousarray(d)

    def descend(
        self, descriptors: np.ndarray, node_depth: int | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Leaf node of every descriptor and its ancestor at depth ``node_depth`` (the leaf when shallower;
        the root for depth <= 0). Vectorised: all descriptors move down one level per step."""
        d = self.check_descriptors(descriptors)
        n = d.shape[0]
        leaf = np.zeros(n, np.int64)
        at_depth = np.zeros(n, np.int64)
        for a in range(0, n, _CHUNK):
            leaf[a : a + _CHUNK], at_depth[a : a + _CHUNK] = self._descend_chunk(
                d[a : a + _CHUNK], node_depth
            )
        return leaf, at_depth

    def _descend_chunk(self, d: np.ndarray, node_depth: int | None) -> tuple[np.ndarray, np.ndarray]:
        n = d.shape[0]
        kmax = self._next.shape[1]
        cur: np.ndarray = np.zeros(n, np.int64)
        at_depth = cur
        # np.take and same-shape operands: several times faster than fancy indexing and broadcasting here
        if self.binary:
            x = np.repeat(to_words(d)[:, None, :], kmax, axis=1)
        else:
            x = d[:, :, None]
        for step in range(1, self._steps + 1):
            ch = np.take(self._next, cur, axis=0)  # (n, kmax)
            if self.binary:
                counts = popcount(np.take(self._centre_words, ch, axis=0) ^ x)
                dist = np.take(self._penalty, ch) + counts[:, :, 0]
                for w in range(1, counts.shape[2]):
                    dist += counts[:, :, w]
            else:  # |c|^2 - 2 c.x (|x|^2 is the same for every child)
                dot = np.matmul(np.take(self.centres, ch, axis=0), x)[:, :, 0]
                dist = np.take(self._penalty, ch) - 2.0 * dot
            cur = np.take_along_axis(ch, np.argmin(dist, axis=1)[:, None], axis=1)[:, 0]
            if step == node_depth:
                at_depth = cur
        if node_depth is not None and node_depth >= self._steps:
            at_depth = cur
        return cur, at_depth

    def words_of(self, descriptors: np.ndarray) -> np.ndarray:
        """Word id of every descriptor (int32)."""
        leaf, _ = self.descend(descriptors)
        return self.word_of_node[leaf]

    @overload
    def transform(self, descriptors: np.ndarray, levels_up: None = None) -> BowVector: ...

    @overload
    def transform(self, descriptors: np.ndarray, levels_up: int) -> tuple[BowVector, np.ndarray]: ...

    def transform(
        self, descriptors: np.ndarray, levels_up: int | None = None
    ) -> BowVector | tuple[BowVector, np.ndarray]:
        """The L1-normalised BoW vector of an image's descriptors.

        With ``levels_up`` (DBoW2's direct-index levels) also return, per descriptor, its node at depth
        ``L - levels_up`` (-1 for descriptors of stopped words), which `BowDatabase` keeps as the direct index.
        """
        d = self.check_descriptors(descriptors)
        if self.n_words == 0:  # a root-only vocabulary
            empty = BowVector.empty()
            return empty if levels_up is None else (empty, np.full(d.shape[0], -1, np.int32))
        node_depth = None if levels_up is None else self.L - int(levels_up)
        leaf, at_depth = self.descend(d, node_depth)
        words = self.word_of_node[leaf]
        w = self.word_weights[words] if words.size else np.zeros(0)
        live = w > 0
        bow = self._bow(words[live], w[live])
        if levels_up is None:
            return bow
        nodes = np.where(live, at_depth, -1).astype(np.int32)
        return bow, nodes

    def _bow(self, words: np.ndarray, w: np.ndarray) -> BowVector:
        if words.size == 0:
            return BowVector.empty()
        uniq, inv = np.unique(words, return_inverse=True)
        vals: np.ndarray
        if self.weighting in ("tf-idf", "tf"):
            vals = np.bincount(inv, weights=w, minlength=uniq.size)
        else:  # idf / binary: once per word
            vals = self.word_weights[uniq].copy()
        vals /= np.abs(vals).sum()
        return BowVector(uniq.astype(np.int32), vals)

    def score(self, v: BowVector, w: BowVector) -> float:
        """L1 score (see `l1_score`)."""
        return l1_score(v, w)


def _depths(parents: np.ndarray) -> np.ndarray:
    """Depth of every node (root 0): climb all nodes one level per step until they reach the root."""
    depth = np.zeros(parents.size, np.int32)
    up = parents.astype(np.int64)
    up[0] = 0
    cur = up.copy()
    while True:
        moving = cur > 0
        if not moving.any():
            break
        depth += moving
        cur = np.take(up, cur)
    depth[1:] += 1
    return depth


class VocabularyParams(Params):
    """How `train_vocabulary` builds the tree (DBoW2's defaults: k = 10, L = 5, TF-IDF)."""

    k: int = Field(10, ge=2, le=1000, description="children per node (DBoW2 default)")
    L: int = Field(
        5, ge=1, le=12, description="levels below the root (DBoW2 default); k^L at most 10^8 words"
    )
    weighting: Weighting = Field("tf-idf", description="word weights")
    seed: int = Field(0, description="k-means++ seed")
    max_iterations: int = Field(10, ge=1, le=10_000, description="k-means iterations per node")
    max_fit: int | None = Field(
        None, ge=100, description="fit nodes larger than this on a random subset (None = all descriptors)"
    )

    @model_validator(mode="after")
    def _words_bounded(self) -> VocabularyParams:
        if self.k**self.L > 10**8:
            raise ValueError(f"k^L = {self.k}^{self.L} words is more than 10^8 (k and L)")
        return self


def train_vocabulary(
    descriptors: Sequence[np.ndarray],
    params: VocabularyParams | None = None,
    progress: bool = False,
    meta: dict[str, Any] | None = None,
    **overrides: Any,
) -> Vocabulary:
    """Train a vocabulary on the descriptors of training images (one (n_i, B) uint8 or (n_i, D) float array per
    image; the IDF counts images) with ``params`` and/or keyword overrides of its fields (`ConfigError` for bad
    ones). See `placerec.retrieval.dbow.kmeans` for the clustering."""
    from placerec.retrieval.dbow.kmeans import DescriptorSpace, build_tree

    base = None if params is None else params.model_dump(include=set(VocabularyParams.model_fields))
    p = resolve(VocabularyParams, base, overrides, where="vocabulary")
    k, L, weighting, seed, max_iterations, max_fit = (
        p.k,
        p.L,
        p.weighting,
        p.seed,
        p.max_iterations,
        p.max_fit,
    )
    parts = [np.asarray(p) for p in descriptors]
    if not parts or sum(p.shape[0] for p in parts) == 0:
        raise ScanDataError("vocabulary: no training descriptors")
    dtypes = {p.dtype for p in parts if p.size}
    widths = {p.shape[1] for p in parts if p.ndim == 2}
    if len(widths) != 1 or any(p.ndim != 2 for p in parts):
        raise ScanDataError(f"vocabulary: training descriptors must be 2D arrays of one width, got {widths}")
    binary = dtypes == {np.dtype(np.uint8)}
    if not binary and np.dtype(np.uint8) in dtypes:
        raise ScanDataError("vocabulary: mixed binary (uint8) and float training descriptors")
    allx = np.concatenate([p if binary else p.astype(np.float32) for p in parts])
    space = DescriptorSpace.of(allx)
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    with _progress(progress, L + 1) as advance:
        parents, centres = build_tree(
            space,
            k,
            L,
            rng,
            max_iterations,
            max_fit,
            on_level=lambda lv, n: advance(f"level {lv}: {n} nodes"),
        )
        if binary:
            centres = np.ascontiguousarray(centres).view(np.uint8)[:, : allx.shape[1]]
        voc = Vocabulary(k, L, parents, centres, np.zeros(parents.size, np.float32), weighting)
        voc = _with_weights(voc, parts, weighting)
        advance("weights")
    info = {
        "n_images": len(parts),
        "n_descriptors": int(allx.shape[0]),
        "train_seconds": round(time.perf_counter() - t0, 3),
        "seed": seed,
        "max_iterations": max_iterations,
        "max_fit": max_fit,
    }
    voc.meta = {**info, **(meta or {})}
    log.info("trained %r in %.1f s", voc, info["train_seconds"])
    return voc


def _with_weights(voc: Vocabulary, parts: list[np.ndarray], weighting: str) -> Vocabulary:
    """Set the word weights: IDF over the training images (tf-idf, idf) or 1 (tf, binary)."""
    weights = np.zeros(voc.n_nodes, np.float32)
    if weighting in ("tf", "binary"):
        weights[voc.node_of_word] = 1.0
    else:
        sizes = np.array([p.shape[0] for p in parts])
        image = np.repeat(np.arange(len(parts)), sizes)
        words = voc.words_of(np.concatenate(parts))
        pairs = np.unique(image.astype(np.int64) * voc.n_words + words)
        n_i = np.bincount(pairs % voc.n_words, minlength=voc.n_words)
        idf = np.zeros(voc.n_words)
        seen = n_i > 0
        idf[seen] = np.log(len(parts) / n_i[seen])
        weights[voc.node_of_word] = idf
    return Vocabulary(voc.k, voc.L, voc.parents, voc.centres, weights, weighting, voc.scoring, voc.meta)


class _progress:
    """A rich progress bar over the training steps (or nothing)."""

    def __init__(self, enabled: bool, total: int) -> None:
        self.enabled, self.total = enabled, total

    def __enter__(self):  # noqa: ANN204
        if not self.enabled:
            return lambda msg: None
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        self._bar = Progress(
            TextColumn("vocabulary {task.description:<24}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
        )
        self._bar.__enter__()
        task = self._bar.add_task("clustering", total=self.total)
        return lambda msg: self._bar.update(task, advance=1, description=msg)

    def __exit__(self, *exc: object) -> None:
        if self.enabled:
            self._bar.__exit__(*exc)
