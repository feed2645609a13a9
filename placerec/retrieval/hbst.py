"""HBST: Hamming binary search tree for incremental binary-descriptor matching (Schlegel & Grisetti, RA-L 2018).

Faithful to srrg_hbst (``srrg_hbst/types/binary_tree.hpp``, ``binary_node.hpp``):

* inner nodes hold a split bit (bit set -> right child, clear -> left); leaves hold descriptors with their image id
  and keypoint index;
* a query descends one path (no backtracking) and is compared by brute force (popcount of XOR) with the
  descriptors of its leaf; a match needs ``distance < threshold`` (strict);
* a leaf holding ``>= leaf_size`` descriptors at depth ``< max_depth`` splits on the bit not yet used on its path
  whose fraction of set bits is closest to 0.5, if ``|0.5 - fraction| < delta_max``; its children split in turn;
* ``match_and_add`` matches all query descriptors, then inserts them in the leaves they reached, then tries to split
  the touched leaves;
* per-image scores: a query descriptor votes at most once per reference image; ratio = votes / query descriptors.

Descriptors are OpenCV-style packed ``uint8`` rows (ORB: 32 bytes, BRISK: 64); bit ``8 * i + v`` is bit ``v`` of
byte ``i``. All work is vectorised over the query descriptors (see `placerec.retrieval.hbst_tree`).
"""

from __future__ import annotations

import logging
import operator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import Field

from placerec.errors import ArtifactError, ConfigError, ScanDataError, short_repr
from placerec.io.artifact_schema import Member, check_unique
from placerec.params import Params, resolve
from placerec.retrieval.bits import to_words, unpack_bits
from placerec.retrieval.hbst_tree import FlatTree

__all__ = ["HBST", "HBSTParams", "HBSTResult", "ImageScores", "default_threshold", "TREE_SCHEMA"]

log = logging.getLogger(__name__)

ARTIFACT_KIND = "hbst"
FORMAT_VERSION = 1
_TREE_MEMBERS = ("split", "child", "leaf_start", "leaf_count", "descriptors", "image_id", "keypoint_id")
# a saved tree (`FlatTree.to_arrays`, all or none of the tree members) and the image ids by insertion index
TREE_SCHEMA = {
    "images": Member("iu", ("n_images",)),
    "split": Member("iu", ("n_nodes",), optional=True),
    "child": Member("iu", ("n_nodes", 2), optional=True),
    "leaf_start": Member("iu", ("n_nodes",), optional=True, min_value=0),
    "leaf_count": Member("iu", ("n_nodes",), optional=True, min_value=0),
    "descriptors": Member("u", ("n_descriptors", None), optional=True),
    "image_id": Member("iu", ("n_descriptors",), optional=True, min_value=0),
    "keypoint_id": Member("iu", ("n_descriptors",), optional=True),
}


class HBSTParams(Params):
    """HBST settings (VPR paper: delta_max 0.1, N_max 50; see `HBST`)."""

    delta_max: float = Field(0.1, ge=0, le=0.5, description="split balance bound (VPR paper: 0.1)")
    leaf_size: int = Field(50, ge=1, description="N_max, descriptors per leaf (VPR paper: 50)")
    max_depth: int = Field(75, ge=0, description="tree depth limit (srrg_hbst default)")
    threshold: int | None = Field(
        None, ge=1, description="max Hamming distance of a match; None = srrg's 25 per 256 bits"
    )


def default_threshold(n_bytes: int) -> int:
    """srrg_hbst's match threshold, 25 for 256-bit descriptors, scaled to ``n_bytes``-byte descriptors."""
    return round(25 * n_bytes * 8 / 256)


@dataclass(frozen=True)
class ImageScores:
    """Per reference image: votes (``n_matches``) and ``matching_ratio`` = votes / query descriptors.

    Only images with at least one vote are listed, best first (ties by image id).
    """

    image_ids: np.ndarray
    n_matches: np.ndarray
    matching_ratio: np.ndarray

    def __len__(self) -> int:
        return int(self.image_ids.shape[0])

    def as_dict(self) -> dict[int, float]:
        """``{image_id: matching_ratio}``."""
        return {int(i): float(r) for i, r in zip(self.image_ids, self.matching_ratio, strict=True)}


@dataclass(frozen=True)
class HBSTResult:
    """Matches of one query image: the best match of each query descriptor in each reference image.

    Parallel arrays sorted by ``query_idx`` (row of the query descriptor), then by the order in which the reference
    images were added: ``image_id`` and ``keypoint_idx`` of the reference descriptor, Hamming ``distance``. Among
    equally close reference descriptors of one image the one inserted first is reported (srrg keeps them all).
    ``n_queries`` is the number of query descriptors (the denominator of the matching ratio).
    """

    query_idx: np.ndarray
    image_id: np.ndarray
    keypoint_idx: np.ndarray
    distance: np.ndarray
    n_queries: int

    def __len__(self) -> int:
        return int(self.query_idx.shape[0])

    def scores_per_image(self) -> ImageScores:
        """Votes per reference image (one per query descriptor and image), best first."""
        ids, votes = np.unique(self.image_id, return_counts=True)
        order = np.lexsort((ids, -votes))
        ratio = votes / self.n_queries if self.n_queries else votes.astype(np.float64)
        return ImageScores(ids[order], votes[order].astype(np.int64), ratio[order])


class HBST:
    """Incremental Hamming binary search tree over packed binary descriptors.

    Parameters (`HBSTParams`, given as a model and/or keyword overrides): ``delta_max`` (split only if the best
    bit's ``|0.5 - fraction| < delta_max``), ``leaf_size`` (N_max: a leaf with at least this many descriptors
    tries to split), ``max_depth`` (leaves at this depth never split; srrg's code default is the descriptor
    length, 75 bounds it for long descriptors), ``threshold`` (a match needs Hamming distance ``< threshold``;
    None: `default_threshold` of the descriptor length). The descriptor length is fixed by the first descriptors
    added.
    """

    def __init__(self, params: HBSTParams | None = None, **overrides: Any) -> None:
        if params is not None and not isinstance(params, HBSTParams):
            raise ConfigError(f"hbst: params must be an HBSTParams, got {type(params).__name__}")
        base = None if params is None else params.model_dump()
        self.params = (
            resolve(HBSTParams, base, overrides, where="hbst") if overrides else params or HBSTParams()
        )
        self._tree: FlatTree | None = None
        self._slots: dict[int, int] = {}  # image id -> dense insertion index stored in the tree
        self._ids = np.zeros(64, dtype=np.int64)  # insertion index -> image id

    # ---------------------------------------------------------------------------------------------- properties
    def __len__(self) -> int:
        return 0 if self._tree is None else self._tree.size

    def __repr__(self) -> str:
        return (
            f"HBST(delta_max={self.delta_max}, leaf_size={self.leaf_size}, max_depth={self.max_depth}, "
            f"threshold={self.threshold}; {len(self)} descriptors, {self.n_images} images, "
            f"{self.n_leaves} leaves, depth {self.depth})"
        )

    @property
    def delta_max(self) -> float:
        return self.params.delta_max

    @property
    def leaf_size(self) -> int:
        return self.params.leaf_size

    @property
    def max_depth(self) -> int:
        return self.params.max_depth

    @property
    def threshold(self) -> int | None:
        """The match threshold: ``params.threshold``, else `default_threshold` of the descriptor length (None
        while no descriptor has been added)."""
        if self.params.threshold is not None:
            return self.params.threshold
        return None if self._tree is None else default_threshold(self._tree.n_bytes)

    @property
    def n_images(self) -> int:
        """Number of distinct image ids added."""
        return len(self._slots)

    @property
    def image_ids(self) -> np.ndarray:
        """Sorted ids of the images added."""
        return np.sort(self._ids[: self.n_images])

    @property
    def depth(self) -> int:
        """Depth of the deepest leaf (0 for a tree that is a single leaf)."""
        return 0 if self._tree is None else self._tree.max_leaf_depth

    @property
    def n_leaves(self) -> int:
        return 1 if self._tree is None else int((self._tree.split_bit[: self._tree.n_nodes] < 0).sum())

    @property
    def n_bytes(self) -> int | None:
        """Descriptor length in bytes (None before the first descriptors are added)."""
        return None if self._tree is None else self._tree.n_bytes

    # ------------------------------------------------------------------------------------------------ public API
    def add(self, image_id: int, descriptors: np.ndarray, keypoint_ids: np.ndarray | None = None) -> None:
        """Insert the descriptors of one image (rows of ``uint8``), then split the leaves they landed in."""
        image_id = self._image_id(image_id)
        desc = self._check(descriptors)
        kp = self._keypoints(keypoint_ids, desc.shape[0])
        if desc.shape[0] == 0:
            return
        tree = self._ensure_tree(desc.shape[1])
        words, bits = to_words(desc), unpack_bits(desc)
        self._insert(tree, image_id, words, kp, tree.descend(bits))

    def match(self, descriptors: np.ndarray, max_image_id: int | None = None) -> HBSTResult:
        """Match the descriptors of a query image against the tree (the tree is not modified).

        ``max_image_id`` restricts matches and votes to reference images with id ``<= max_image_id`` (e.g. to
        exclude the most recent frames).
        """
        desc = self._check(descriptors)
        if self._tree is None or desc.shape[0] == 0:
            return self._empty(desc.shape[0])
        words, bits = to_words(desc), unpack_bits(desc)
        return self._match(words, self._tree.descend(bits), max_image_id)

    def match_and_add(
        self,
        image_id: int,
        descriptors: np.ndarray,
        max_image_id: int | None = None,
        keypoint_ids: np.ndarray | None = None,
    ) -> HBSTResult:
        """Match the query image (before inserting it, as srrg's matchAndAdd does), then add it."""
        image_id = self._image_id(image_id)
        desc = self._check(descriptors)
        kp = self._keypoints(keypoint_ids, desc.shape[0])
        if desc.shape[0] == 0:
            return self._empty(0)
        tree = self._ensure_tree(desc.shape[1])
        words, bits = to_words(desc), unpack_bits(desc)
        leaves = tree.descend(bits)
        result = self._match(words, leaves, max_image_id)
        self._insert(tree, image_id, words, kp, leaves)
        return result

    def scores(self, result: HBSTResult) -> ImageScores:
        """Same as ``result.scores_per_image()``."""
        return result.scores_per_image()

    # ----------------------------------------------------------------------------------------------- persistence
    def to_arrays(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """(arrays, meta) describing the whole tree: what `save` writes and `from_arrays` reads back."""
        arrays = {} if self._tree is None else self._tree.to_arrays()
        arrays["images"] = self._ids[: self.n_images].copy()  # by insertion index, as stored in the tree
        meta = {
            "delta_max": self.delta_max,
            "leaf_size": self.leaf_size,
            "max_depth": self.max_depth,
            "threshold": self.threshold,
            "n_bytes": self.n_bytes,
        }
        return arrays, meta

    def save(self, path: str | Path) -> None:
        """Write the tree atomically as a versioned ``.npz`` artifact (kind ``hbst``)."""
        from placerec.io.atomic import save_artifact

        arrays, meta = self.to_arrays()
        save_artifact(path, ARTIFACT_KIND, FORMAT_VERSION, arrays, meta)
        log.debug("saved %r to %s", self, path)

    @classmethod
    def load(cls, path: str | Path) -> HBST:
        """Read a tree written by `save`; raises `ArtifactError` if the file is corrupt or of another version."""
        from placerec.io.atomic import load_artifact

        arrays, header = load_artifact(path, ARTIFACT_KIND, (FORMAT_VERSION,), TREE_SCHEMA, mmap=True)
        hbst = cls.from_arrays(arrays, header["meta"], path)
        log.debug("loaded %r from %s", hbst, path)
        return hbst

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], meta: dict[str, Any], path: str | Path) -> HBST:
        """The tree `to_arrays` described (checked against `TREE_SCHEMA` by the caller); `ArtifactError` naming
        ``path`` when the arrays or ``meta`` are inconsistent. The restored tree answers and grows exactly as the
        saved one (the split retry state it lacks only prunes attempts that cannot succeed)."""
        present = [k for k in _TREE_MEMBERS if k in arrays]
        if (present and len(present) != len(_TREE_MEMBERS)) or bool(present) != (
            meta.get("n_bytes") is not None
        ):
            raise ArtifactError(
                f"{path}: corrupt hbst artifact: a saved tree needs all of {list(_TREE_MEMBERS)} and the header's "
                f"n_bytes, an empty one none of them; found {present} and n_bytes={short_repr(meta.get('n_bytes'))}"
            )
        check_unique(arrays["images"], path, "images")
        try:
            hbst = cls(**{k: meta[k] for k in ("delta_max", "leaf_size", "max_depth", "threshold")})
            for image_id in np.asarray(arrays["images"], dtype=np.int64).tolist():
                hbst._slot(image_id)
            if hbst.n_images != len(arrays["images"]):
                raise ValueError("duplicate image ids")
            if meta["n_bytes"] is not None:
                hbst._tree = FlatTree.from_arrays(arrays, hbst.leaf_size, hbst.delta_max, hbst.max_depth)
                if hbst._tree.n_bytes != int(meta["n_bytes"]):
                    raise ValueError("descriptor length differs from the header")
                stored = hbst._tree.image[: hbst._tree.size]
                if stored.size and (stored.min() < 0 or stored.max() >= hbst.n_images):
                    raise ValueError("descriptors refer to unknown images")
        except (KeyError, TypeError, ValueError, ConfigError) as exc:
            raise ArtifactError(f"{path}: corrupt hbst artifact ({exc})") from exc
        return hbst

    # ---------------------------------------------------------------------------------------------- internals
    def _match(self, words: np.ndarray, leaves: np.ndarray, max_image_id: int | None) -> HBSTResult:
        tree = self._tree
        threshold = self.threshold
        assert tree is not None and threshold is not None
        query, pos, dist = tree.leaf_distances(words, leaves)
        keep = np.flatnonzero(dist < threshold)
        query, pos, dist = query[keep], pos[keep], dist[keep]
        slot = tree.image[pos]  # the reference image's insertion index
        ids = self._ids[: self.n_images]
        if max_image_id is not None:
            keep = np.flatnonzero(ids[slot] <= operator.index(max_image_id))
            query, pos, dist, slot = query[keep], pos[keep], dist[keep], slot[keep]
        # best match per (query, image): one stable sort on (query, image, distance); ties keep the reference
        # descriptor inserted first
        n_slots = max(self.n_images, 1)
        if (words.shape[0] + 1) * n_slots * threshold < 2**62:
            order = np.argsort((query * n_slots + slot) * threshold + dist, kind="stable")
        else:  # pragma: no cover - astronomically large databases
            order = np.lexsort((dist, slot, query))
        query, pos, dist, slot = query[order], pos[order], dist[order], slot[order]
        first = np.ones(query.shape[0], dtype=bool)
        first[1:] = (query[1:] != query[:-1]) | (slot[1:] != slot[:-1])
        pos = pos[first]
        return HBSTResult(
            query[first],
            ids[slot[first]],
            tree.keypoint[pos].astype(np.int64),
            dist[first],
            int(words.shape[0]),
        )

    def _insert(
        self, tree: FlatTree, image_id: int, words: np.ndarray, kp: np.ndarray, leaves: np.ndarray
    ) -> None:
        slot = self._slot(image_id)
        touched = tree.insert(words, slot, kp, leaves)
        tree.split(touched)

    def _slot(self, image_id: int) -> int:
        """Dense insertion index of an image id (registering it if new)."""
        slot = self._slots.get(image_id)
        if slot is None:
            slot = len(self._slots)
            self._slots[image_id] = slot
            if slot >= self._ids.shape[0]:
                self._ids = np.concatenate([self._ids, np.zeros(max(slot, 64), dtype=np.int64)])
            self._ids[slot] = image_id
        return slot

    def _ensure_tree(self, n_bytes: int) -> FlatTree:
        if self._tree is None:
            self._tree = FlatTree(n_bytes, self.leaf_size, self.delta_max, self.max_depth)
        return self._tree

    def _check(self, descriptors: np.ndarray) -> np.ndarray:
        if not isinstance(descriptors, np.ndarray):
            raise ScanDataError(
                f"HBST descriptors must be a NumPy uint8 array, got {type(descriptors).__name__}"
            )
        if descriptors.dtype != np.uint8:
            raise ScanDataError(
                f"HBST descriptors must be packed uint8 rows (OpenCV binary descriptors), got dtype {descriptors.dtype}"
            )
        if descriptors.ndim != 2:
            raise ScanDataError(f"HBST descriptors must be 2-D (n, n_bytes), got shape {descriptors.shape}")
        n_bytes = descriptors.shape[1]
        if n_bytes == 0:
            raise ScanDataError("HBST descriptors must have at least one byte per row")
        if self._tree is not None and n_bytes != self._tree.n_bytes:
            raise ScanDataError(
                f"HBST descriptors have {n_bytes} bytes per row but the tree holds {self._tree.n_bytes}-byte "
                f"({self._tree.n_bits}-bit) descriptors"
            )
        return np.ascontiguousarray(descriptors)

    @staticmethod
    def _keypoints(keypoint_ids: np.ndarray | None, n: int) -> np.ndarray:
        if keypoint_ids is None:
            return np.arange(n, dtype=np.int32)
        kp = np.asarray(keypoint_ids)
        if kp.shape != (n,) or not np.issubdtype(kp.dtype, np.integer):
            raise ScanDataError(
                f"keypoint_ids must be {n} integers (one per descriptor), got {kp.dtype} {kp.shape}"
            )
        if kp.size and (kp.min() < np.iinfo(np.int32).min or kp.max() > np.iinfo(np.int32).max):
            raise ScanDataError("keypoint_ids must fit in 32 bits")
        return kp.astype(np.int32, copy=False)

    @staticmethod
    def _image_id(image_id: int) -> int:
        try:
            return operator.index(image_id)
        except TypeError as exc:
            raise ScanDataError(f"image_id must be an integer, got {image_id!r}") from exc

    @staticmethod
    def _empty(n_queries: int) -> HBSTResult:
        e = np.zeros(0, dtype=np.int64)
        return HBSTResult(e, e, e, np.zeros(0, dtype=np.int32), int(n_queries))
