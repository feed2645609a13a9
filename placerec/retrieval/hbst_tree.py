"""Flat-array storage of a Hamming binary search tree (the data structure behind `placerec.retrieval.hbst`).

Nodes live in parallel NumPy arrays indexed by node id (root = 0): ``split_bit`` (split bit, -1 for a leaf), ``child``
((n, 2): left = bit clear, right = bit set; a leaf points to itself so that a vectorised descent can run a fixed
number of steps), ``depth``, ``used`` (packed mask of the split bits on the path from the root) and, for leaves,
``start``/``count``/``cap``: the leaf's block of rows in the descriptor *pool*.

The pool keeps each leaf's descriptors contiguous (rows ``start .. start + count`` of ``words``/``image``/
``keypoint``), so the brute-force search in a leaf reads one contiguous run. A leaf that outgrows its block moves
to a new block (1.5 times the size) at the end of the pool; a split partitions the parent's block in place between
its two children. The holes left behind are squeezed out when they exceed half the live blocks.

Every operation works on all descriptors (or all touched leaves) at once: no Python loop runs per descriptor.
"""

from __future__ import annotations

import numpy as np

from placerec.retrieval.bits import hamming, to_words, unpack_bits

__all__ = ["FlatTree", "choose_split_bits", "segment_bit_counts", "segment_positions"]


def segment_positions(starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Concatenation of ``arange(s, s + c)`` for every (s, c): the pool rows of a set of blocks."""
    counts = np.asarray(counts, dtype=np.int64)
    total = int(counts.sum())
    offsets = np.cumsum(counts) - counts
    return np.repeat(np.asarray(starts, dtype=np.int64) - offsets, counts) + np.arange(total, dtype=np.int64)


def segment_bit_counts(packed: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Per consecutive segment of rows of ``packed`` (T, n_bytes) uint8: how many rows have each bit set.

    ``counts`` (k,) are the segment lengths (all >= 1, summing to T); returns (k, 8 n_bytes) int64. The unpacked
    0/1 bytes are summed eight at a time as byte lanes of uint64 words (SWAR), in chunks of at most 255 rows so
    that no lane overflows.
    """
    counts = np.asarray(counts, dtype=np.int64)
    k = counts.shape[0]
    n_chunks = -(-counts // 255)
    chunk_seg = np.repeat(np.arange(k), n_chunks)
    first_chunk = np.cumsum(n_chunks) - n_chunks
    chunk_start = (np.cumsum(counts) - counts)[chunk_seg] + 255 * (
        np.arange(chunk_seg.shape[0]) - first_chunk[chunk_seg]
    )
    lanes = unpack_bits(packed).view(np.uint64)
    sums = np.add.reduceat(lanes, chunk_start, axis=0).view(np.uint8).astype(np.int64)
    if sums.shape[0] == k:
        return sums
    return np.add.reduceat(sums, first_chunk, axis=0)


def choose_split_bits(
    ones: np.ndarray, sizes: np.ndarray, used: np.ndarray, delta_max: float
) -> tuple[np.ndarray, np.ndarray]:
    """srrg_hbst's even split rule for k leaves at once.

    ``ones`` (k, n_bits): number of descriptors with each bit set; ``sizes`` (k,): descriptors per leaf; ``used``
    (k, n_bits) bool: bits already split on along the path. Returns (bit, ok): per leaf the unused bit whose
    fraction of set bits is closest to 0.5 (lowest index on ties, like srrg's ascending scan with a strict ``<``),
    and whether ``|0.5 - fraction| < delta_max`` so that the leaf may split.
    """
    score = np.abs(0.5 - ones / np.asarray(sizes, dtype=np.float64)[:, None])
    score[used] = np.inf
    bit = np.argmin(score, axis=1)
    ok = score[np.arange(score.shape[0]), bit] < delta_max
    return bit, ok


class FlatTree:
    """Nodes and leaf-contiguous descriptor pool of an HBST; see the module docstring."""

    #: per node (capacity rows, the first ``n_nodes`` in use; made by `_alloc_nodes`)
    split_bit: np.ndarray
    sbit: np.ndarray
    child: np.ndarray
    depth: np.ndarray
    used: np.ndarray
    start: np.ndarray
    count: np.ndarray
    cap: np.ndarray
    fail_score: np.ndarray
    fail_count: np.ndarray
    #: per pool row (the first ``top`` handed out; made by `_alloc_pool`)
    words: np.ndarray
    image: np.ndarray
    keypoint: np.ndarray

    def __init__(self, n_bytes: int, leaf_size: int, delta_max: float, max_depth: int) -> None:
        self.n_bytes = int(n_bytes)
        self.n_words = -(-self.n_bytes // 8)
        self.n_bits = 8 * self.n_bytes
        self.leaf_size = int(leaf_size)
        self.delta_max = float(delta_max)
        self.max_depth = int(max_depth)
        self.n_nodes = 1
        self.top = 0  # pool rows handed out (live blocks and holes)
        self.size = 0  # descriptors stored
        self.max_leaf_depth = 0
        self._alloc_nodes(64)
        self._alloc_pool(1024)

    # ----------------------------------------------------------------------------------------------- storage
    def _alloc_nodes(self, capacity: int) -> None:
        old = self.n_nodes if hasattr(self, "split_bit") else 0
        fresh: dict[str, np.ndarray] = {
            "split_bit": np.full(capacity, -1, dtype=np.int32),
            "sbit": np.zeros(capacity, dtype=np.int64),  # split bit, 0 for leaves (safe gather index)
            "child": np.zeros((capacity, 2), dtype=np.int64),
            "depth": np.zeros(capacity, dtype=np.int32),
            "used": np.zeros((capacity, self.n_bytes), dtype=np.uint8),
            "start": np.zeros(capacity, dtype=np.int64),
            "count": np.zeros(capacity, dtype=np.int64),
            "cap": np.zeros(capacity, dtype=np.int64),
            "fail_score": np.zeros(capacity, dtype=np.float64),  # best score of the last failed split attempt
            "fail_count": np.zeros(capacity, dtype=np.int64),  # leaf size at that attempt
        }
        for name, arr in fresh.items():
            if old:
                arr[:old] = getattr(self, name)[:old]
            setattr(self, name, arr)
        if not old:
            self.child[0] = 0

    def _alloc_pool(self, capacity: int) -> None:
        words = np.zeros((capacity, self.n_words), dtype=np.uint64)
        image = np.zeros(capacity, dtype=np.int32)
        keypoint = np.zeros(capacity, dtype=np.int32)
        if hasattr(self, "words"):
            words[: self.top] = self.words[: self.top]
            image[: self.top] = self.image[: self.top]
            keypoint[: self.top] = self.keypoint[: self.top]
        self.words, self.image, self.keypoint = words, image, keypoint

    def _leaf_ids(self) -> np.ndarray:
        return np.flatnonzero(self.split_bit[: self.n_nodes] < 0)

    def _reserve(self, rows: int) -> None:
        """Make room for ``rows`` more pool rows after ``top``: squeeze out holes or grow the pool."""
        if self.top + rows <= self.words.shape[0]:
            return
        leaves = self._leaf_ids()
        live = int(self.cap[leaves].sum())
        if 2 * (self.top - live) > live:
            self._compact(leaves)
        # keep free room of at least half the data, so that compactions (O(live)) stay rare: amortised O(1)
        need = max(self.top + rows, self.top + self.top // 2)
        if need > self.words.shape[0]:
            self._alloc_pool(max(self.words.shape[0] + self.words.shape[0] // 2, need))

    def _compact(self, leaves: np.ndarray) -> None:
        leaves = leaves[np.argsort(self.start[leaves], kind="stable")]
        caps = self.cap[leaves]
        new_start = np.cumsum(caps) - caps
        src = segment_positions(self.start[leaves], self.count[leaves])
        dst = segment_positions(new_start, self.count[leaves])
        capacity = self.words.shape[0]
        words = np.zeros((capacity, self.n_words), dtype=np.uint64)
        image = np.zeros(capacity, dtype=np.int32)
        keypoint = np.zeros(capacity, dtype=np.int32)
        words[dst], image[dst], keypoint[dst] = self.words[src], self.image[src], self.keypoint[src]
        self.words, self.image, self.keypoint = words, image, keypoint
        self.start[leaves] = new_start
        self.top = int(caps.sum())

    def _move_rows(self, dst: np.ndarray, src: np.ndarray) -> None:
        """Copy pool rows ``src`` to ``dst`` (the sources are read before anything is written)."""
        for arr in (self.words, self.image, self.keypoint):
            arr[dst] = arr[src]

    def _relocate(self, leaves: np.ndarray, need: np.ndarray) -> None:
        """Move ``leaves`` to fresh blocks at the end of the pool with room for at least ``need`` rows."""
        new_cap = np.maximum(need + need // 2, 8)
        self._reserve(int(new_cap.sum()))
        new_start = self.top + np.cumsum(new_cap) - new_cap
        src = segment_positions(self.start[leaves], self.count[leaves])
        dst = segment_positions(new_start, self.count[leaves])
        self._move_rows(dst, src)
        self.start[leaves] = new_start
        self.cap[leaves] = new_cap
        self.top += int(new_cap.sum())

    # ------------------------------------------------------------------------------------------------ search
    def descend(self, bits: np.ndarray) -> np.ndarray:
        """Leaf reached by each descriptor, given its unpacked bits (n, n_bits): one path, no backtracking."""
        n = bits.shape[0]
        node = np.zeros(n, dtype=np.int64)
        if self.max_leaf_depth == 0 or n == 0:
            return node
        flat = bits.ravel()
        base = np.arange(n, dtype=np.int64) * self.n_bits
        child = self.child.ravel()
        sbit = self.sbit
        for _ in range(self.max_leaf_depth):
            node = child[2 * node + flat[base + sbit[node]]]
        return node

    def leaf_distances(
        self, words: np.ndarray, leaves: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Brute force in the leaves: every (query, descriptor of its leaf) pair as (query, pool row, distance)."""
        counts = self.count[leaves]
        pos = segment_positions(self.start[leaves], counts)
        query = np.repeat(np.arange(leaves.shape[0], dtype=np.int64), counts)
        dist = hamming(self.words[pos], np.repeat(words, counts, axis=0))
        return query, pos, dist

    # ------------------------------------------------------------------------------------------------ growth
    def insert(self, words: np.ndarray, image: int, keypoint: np.ndarray, leaves: np.ndarray) -> np.ndarray:
        """Append descriptors to the leaves they reached; returns the touched leaves (unique)."""
        n = leaves.shape[0]
        if n == 0:
            return leaves
        order = np.argsort(leaves, kind="stable")
        sorted_leaves = leaves[order]
        first = np.concatenate([[0], np.flatnonzero(sorted_leaves[1:] != sorted_leaves[:-1]) + 1])
        touched = sorted_leaves[first]
        added = np.diff(np.append(first, n))
        need = self.count[touched] + added
        grow = need > self.cap[touched]
        if grow.any():
            self._relocate(touched[grow], need[grow])
        dest = np.repeat(self.start[touched] + self.count[touched] - first, added) + np.arange(
            n, dtype=np.int64
        )
        self.words[dest] = words[order]
        self.image[dest] = image
        self.keypoint[dest] = keypoint[order]
        self.count[touched] = need
        self.size += n
        return touched

    def split(self, leaves: np.ndarray) -> None:
        """Try to split ``leaves`` (and, recursively, the children they spawn), as srrg's spawnLeafs does."""
        while leaves.size:
            count = self.count[leaves]
            # A leaf whose last attempt failed with best score s at size n0 cannot succeed before it has grown:
            # with m = n - n0 new descriptors every fraction moves by at most m / n, so skip while
            # s - m / n stays above delta_max (exact pruning: the outcome equals srrg's retry).
            slack = self.fail_score[leaves] - (count - self.fail_count[leaves]) / np.maximum(count, 1)
            leaves = leaves[
                (count >= self.leaf_size)
                & (self.depth[leaves] < self.max_depth)
                & (slack <= self.delta_max + 1e-9)
            ]
            if leaves.size == 0:
                return
            leaves = self._split_once(leaves)

    def _split_once(self, leaves: np.ndarray) -> np.ndarray:
        counts = self.count[leaves]
        pos = segment_positions(self.start[leaves], counts)
        packed = self.words.view(np.uint8)[pos, : self.n_bytes]
        ones = segment_bit_counts(packed, counts)
        used = unpack_bits(self.used[leaves]).astype(bool)
        bit, ok = choose_split_bits(ones, counts, used, self.delta_max)
        failed = leaves[~ok]
        if failed.size:
            score = np.abs(0.5 - ones[~ok, bit[~ok]] / counts[~ok])
            self.fail_score[failed], self.fail_count[failed] = score, counts[~ok]
        if not ok.any():
            return leaves[:0]
        # partition each splitting leaf's block in place: bit clear (left child) first, then bit set (right)
        row_leaf = np.repeat(np.arange(leaves.shape[0]), counts)
        rows = ok[row_leaf]
        pos, row_leaf, packed = pos[rows], row_leaf[rows], packed[rows]
        b = bit[row_leaf]
        bit_value = (packed[np.arange(b.shape[0]), b >> 3] >> (b & 7).astype(np.uint8)) & 1
        src = pos[np.lexsort((bit_value, row_leaf))]
        self._move_rows(pos, src)

        parents, bit = leaves[ok], bit[ok]
        n_right = ones[ok, bit]
        n_left = counts[ok] - n_right
        m = parents.shape[0]
        if self.n_nodes + 2 * m > self.split_bit.shape[0]:
            self._alloc_nodes(max(2 * self.split_bit.shape[0], self.n_nodes + 2 * m))
        left = self.n_nodes + np.arange(m, dtype=np.int64)
        right = left + m
        self.n_nodes += 2 * m
        kids = np.concatenate([left, right])
        both = np.concatenate([parents, parents])
        kid_bit = np.concatenate([bit, bit])
        self.split_bit[kids], self.sbit[kids], self.child[kids] = -1, 0, kids[:, None]
        self.depth[kids] = self.depth[both] + 1
        used_rows = self.used[both]
        used_rows[np.arange(2 * m), kid_bit >> 3] |= np.uint8(1) << (kid_bit & 7).astype(np.uint8)
        self.used[kids] = used_rows
        self.fail_score[kids], self.fail_count[kids] = 0.0, 0
        self.start[left], self.count[left], self.cap[left] = self.start[parents], n_left, n_left
        self.start[right], self.count[right] = self.start[parents] + n_left, n_right
        self.cap[right] = self.cap[parents] - n_left
        self.split_bit[parents], self.sbit[parents] = bit, bit
        self.child[parents, 0], self.child[parents, 1] = left, right
        self.start[parents] = self.count[parents] = self.cap[parents] = 0
        self.max_leaf_depth = max(self.max_leaf_depth, int(self.depth[kids].max()))
        return kids

    # ------------------------------------------------------------------------------------------ persistence
    def to_arrays(self) -> dict[str, np.ndarray]:
        """Compact arrays describing the tree (leaf blocks packed tightly, in leaf-id order)."""
        n = self.n_nodes
        leaves = self._leaf_ids()
        counts = self.count[leaves]
        rows = segment_positions(self.start[leaves], counts)
        start = np.zeros(n, dtype=np.int64)
        start[leaves] = np.cumsum(counts) - counts
        child = self.child[:n].copy()
        child[leaves] = -1
        return {
            "split": self.split_bit[:n].copy(),
            "child": child,
            "leaf_start": start,
            "leaf_count": self.count[:n].copy(),
            "descriptors": self.words[rows].view(np.uint8)[:, : self.n_bytes].copy(),
            "image_id": self.image[rows].copy(),
            "keypoint_id": self.keypoint[rows].copy(),
        }

    @classmethod
    def from_arrays(
        cls, arrays: dict[str, np.ndarray], leaf_size: int, delta_max: float, max_depth: int
    ) -> FlatTree:
        """Inverse of `to_arrays`; raises ValueError on inconsistent arrays."""
        split = np.asarray(arrays["split"], dtype=np.int32)
        child = np.asarray(arrays["child"], dtype=np.int64)
        start = np.asarray(arrays["leaf_start"], dtype=np.int64)
        count = np.asarray(arrays["leaf_count"], dtype=np.int64)
        desc = np.asarray(arrays["descriptors"])
        image = np.asarray(arrays["image_id"], dtype=np.int64)
        keypoint = np.asarray(arrays["keypoint_id"], dtype=np.int64)
        n = split.shape[0]
        if desc.dtype != np.uint8 or desc.ndim != 2 or desc.shape[1] == 0:
            raise ValueError("descriptors must be a 2-D uint8 array")
        if n == 0 or child.shape != (n, 2) or start.shape != (n,) or count.shape != (n,):
            raise ValueError("node arrays have inconsistent shapes")
        if not (image.shape == keypoint.shape == (desc.shape[0],)):
            raise ValueError("image/keypoint ids do not match the descriptors")
        i32 = np.iinfo(np.int32)
        if (
            desc.shape[0]
            and min(image.min(), keypoint.min()) < i32.min
            or max(image.max(initial=0), keypoint.max(initial=0)) > i32.max
        ):
            raise ValueError("image/keypoint ids out of range")
        tree = cls(desc.shape[1], leaf_size, delta_max, max_depth)
        inner = np.flatnonzero(split >= 0)
        leaves = np.flatnonzero(split < 0)
        kids = child[inner]
        parents_per_node = np.bincount(kids[(kids >= 0) & (kids < n)].ravel(), minlength=n)
        tight = np.cumsum(count[leaves]) - count[leaves]
        if (
            (split >= tree.n_bits).any()
            or (kids <= inner[:, None]).any()
            or (kids >= n).any()
            or parents_per_node[0] != 0
            or (parents_per_node[1:] != 1).any()
            or (count[leaves] < 0).any()
            or (count[inner] != 0).any()
            or int(count[leaves].sum()) != desc.shape[0]
            or (start[leaves] != tight).any()
        ):
            raise ValueError("node arrays do not describe a valid tree")
        tree._alloc_nodes(max(64, n))
        tree.n_nodes = n
        tree.split_bit[:n] = split
        tree.sbit[:n] = np.maximum(split, 0)
        tree.child[:n] = child
        tree.child[leaves] = leaves[:, None]
        # depth and used-bit masks, level by level from the root
        level = np.zeros(1, dtype=np.int64)
        while level.size:
            level = level[split[level] >= 0]
            b = split[level].astype(np.int64)
            for side in (0, 1):
                kid = child[level, side]
                tree.depth[kid] = tree.depth[level] + 1
                tree.used[kid] = tree.used[level]
                tree.used[kid, b >> 3] |= np.uint8(1) << (b & 7).astype(np.uint8)
            level = child[level].ravel()
        tree.count[leaves] = count[leaves]
        tree.cap[leaves] = count[leaves]
        tree.start[leaves] = start[leaves]
        tree._alloc_pool(max(1024, desc.shape[0]))
        tree.top = tree.size = desc.shape[0]
        tree.words[: tree.size] = to_words(desc)
        tree.image[: tree.size] = image
        tree.keypoint[: tree.size] = keypoint
        tree.max_leaf_depth = int(tree.depth[leaves].max())
        return tree
