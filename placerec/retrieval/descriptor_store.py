"""Rows of float descriptors (SHOT / ISHOT / FPFH) stored as float32, float16 or 8-bit codes, and their exact k-NN.

``dtype``:

* ``"float32"`` — the rows as given (5376 bytes per 1344-d ISHOT row); 2-NN by `knn2` (one BLAS matrix product a
  batch, or ``faiss.knn``), k-NN by ``faiss.knn``.
* ``"float16"`` — half floats (2688 bytes per ISHOT row), in a faiss ``IndexScalarQuantizer`` (``QT_fp16``).
* ``"sq8"`` — one byte per dimension (1344 bytes per ISHOT row): `placerec.quantise.ScalarQuantiser` codes, in a
  faiss ``IndexScalarQuantizer`` (``QT_8bit``) with the quantiser's ranges. The quantiser is fitted on the rows
  first stored: all of them when the store is made from an array (`DescriptorStore.from_rows`, a places
  database); when rows are appended one scan at a time they are kept as float32 until ``fit_rows`` (4096) rows
  have come, then fitted on those and encoded, so later rows outside those ranges are clipped to them.

The compressed stores are searched without decoding the database into float32: ``faiss`` computes distances from
the query to the decoded codes on the fly (SIMD), which on 1344-d ISHOT rows is faster than float32 brute force for
small batches; from `BLAS_BATCH` queries on, blocks of 4096 rows are decoded one at a time and searched with BLAS,
which is faster there (docs/benchmarks.md, 3D nearest neighbours). Either way the distances are exact for the decoded rows, so the result
is that of float32 brute force over the decoded database. `StoreView` is a selection of rows (a prefix or a mask)
searched the same way, its indices local to the selection.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Literal, get_args

import numpy as np

from placerec.errors import ArtifactError, ConfigError, DependencyError, short_repr
from placerec.quantise import ScalarQuantiser
from placerec.threads import import_openmp

__all__ = [
    "StoreDtype",
    "STORE_DTYPES",
    "DescriptorStore",
    "StoreView",
    "knn",
    "knn2",
    "omp_threads",
    "sq_norms",
]

StoreDtype = Literal["float32", "float16", "sq8"]
STORE_DTYPES: tuple[str, ...] = get_args(StoreDtype)
#: bytes per dimension of a stored row
BYTES_PER_DIM = {"float32": 4, "float16": 2, "sq8": 1}
#: queries from which a compressed store is searched by decoding blocks and BLAS instead of in the code domain
BLAS_BATCH = 32
_BLOCK = 4096


def _faiss() -> Any:
    try:
        return import_openmp("faiss")
    except ImportError as exc:  # pragma: no cover - faiss-cpu is a dependency
        raise DependencyError("descriptor search needs faiss-cpu (pip install faiss-cpu)") from exc


@contextmanager
def omp_threads(threads: int | None) -> Iterator[None]:
    """faiss's OpenMP threads set to ``threads`` during the block (None: leave faiss's default)."""
    faiss = _faiss()
    before = faiss.omp_get_max_threads()
    if threads is not None:
        faiss.omp_set_num_threads(int(threads))
    try:
        yield
    finally:
        faiss.omp_set_num_threads(before)


def knn2(
    query: np.ndarray,
    db: np.ndarray,
    backend: str = "faiss",
    threads: int | None = 1,
    db_sq: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Exact 2 nearest neighbours: (distances (Q, 2) Euclidean, indices (Q, 2)); needs ``len(db) >= 2``.

    ``threads``: OpenMP threads for faiss during the call (None: faiss's default, all cores). ``db_sq``: the rows'
    squared norms (`sq_norms`) when the caller keeps them, for the numpy backend (else computed here).
    """
    q = np.ascontiguousarray(query, dtype=np.float32)
    x = np.ascontiguousarray(db, dtype=np.float32)
    if backend == "faiss":
        with omp_threads(threads):
            d2, idx = _faiss().knn(q, x, 2)
    else:
        xx = sq_norms(x) if db_sq is None else db_sq
        d2 = np.empty((q.shape[0], 2), np.float32)
        idx = np.empty((q.shape[0], 2), np.int64)
        for a in range(0, q.shape[0], 512):
            dd = xx[None, :] - 2.0 * (q[a : a + 512] @ x.T)
            part = np.argpartition(dd, 1, axis=1)[:, :2]
            pd = np.take_along_axis(dd, part, axis=1)
            o = np.argsort(pd, axis=1, kind="stable")
            idx[a : a + 512] = np.take_along_axis(part, o, 1)
            d2[a : a + 512] = (
                np.take_along_axis(pd, o, 1) + np.einsum("ij,ij->i", q[a : a + 512], q[a : a + 512])[:, None]
            )
    return np.sqrt(np.maximum(d2, 0.0)), np.asarray(idx, dtype=np.int64)


def sq_norms(rows: np.ndarray) -> np.ndarray:
    """Each row's squared norm, row by row (the same value whichever rows are computed together)."""
    return np.einsum("ij,ij->i", rows, rows)


def knn(query: np.ndarray, db: np.ndarray, k: int, threads: int | None = 1) -> tuple[np.ndarray, np.ndarray]:
    """Exact ``k`` nearest neighbours with faiss: (distances (Q, k) Euclidean, indices (Q, k)); rows beyond the
    database's size get index -1 and an infinite distance."""
    q = np.ascontiguousarray(query, dtype=np.float32)
    x = np.ascontiguousarray(db, dtype=np.float32)
    kk = int(min(k, x.shape[0]))
    dist = np.full((q.shape[0], k), np.inf, np.float32)
    idx = np.full((q.shape[0], k), -1, np.int64)
    if kk > 0 and q.shape[0]:
        with omp_threads(threads):
            d2, i = _faiss().knn(q, x, kk)
        dist[:, :kk] = np.sqrt(np.maximum(d2, 0.0))
        idx[:, :kk] = i
    return dist, idx


def _merge(best: tuple[np.ndarray, np.ndarray], new: tuple[np.ndarray, np.ndarray], k: int) -> tuple:
    d = np.concatenate([best[0], new[0]], axis=1)
    i = np.concatenate([best[1], new[1]], axis=1)
    o = np.argsort(d, axis=1, kind="stable")[:, :k]
    return np.take_along_axis(d, o, 1), np.take_along_axis(i, o, 1)


class DescriptorStore:
    """Growable rows of ``dim``-d descriptors in ``dtype`` (module docstring)."""

    def __init__(self, dim: int, dtype: str = "float32", fit_rows: int = 4096) -> None:
        if dtype not in STORE_DTYPES:
            raise ConfigError(f"descriptor store {dtype!r} is unknown; allowed: {list(STORE_DTYPES)}")
        self.dim, self.dtype, self.fit_rows = int(dim), dtype, int(fit_rows)
        self.quantiser: ScalarQuantiser | None = None
        self._rows = np.zeros(
            (0, self.dim), np.float32
        )  # float32 rows (float32 store, or sq8 before fitting)
        self._n = 0
        self._sq = np.zeros(0, np.float32)  # squared norms of the first float32 rows (`sq_norms_to`)
        self._index: Any = None  # faiss IndexScalarQuantizer holding the codes (float16, fitted sq8)
        if dtype == "float16":
            self._index = self._new_index()

    # -- construction -----------------------------------------------------------------------------------------
    @classmethod
    def from_rows(
        cls, rows: np.ndarray, dtype: str = "float32", quantiser: ScalarQuantiser | None = None
    ) -> DescriptorStore:
        """A store of ``rows`` (N, D); an sq8 store fits its quantiser on all of them unless one is given."""
        x = np.asarray(rows, np.float32)
        store = cls(x.shape[1], dtype)
        if dtype == "float32":
            store._rows, store._n = np.ascontiguousarray(x), x.shape[0]
        elif dtype == "sq8" and (quantiser is not None or x.shape[0]):
            store._fit(quantiser or ScalarQuantiser.fit(x))
            store._add_codes(store._sq8.encode(x))
        else:
            store.append(x)
        return store

    def _new_index(self) -> Any:
        faiss = _faiss()
        qt = faiss.ScalarQuantizer.QT_fp16 if self.dtype == "float16" else faiss.ScalarQuantizer.QT_8bit
        index = faiss.IndexScalarQuantizer(self.dim, qt)
        if self.quantiser is not None:
            faiss.copy_array_to_vector(self.quantiser.trained(), index.sq.trained)
        index.is_trained = True
        return index

    def _fit(self, quantiser: ScalarQuantiser) -> None:
        if quantiser.dim != self.dim:
            raise ConfigError(f"sq8 quantiser of {quantiser.dim} dimensions for {self.dim}-d descriptors")
        self.quantiser = quantiser
        self._index = self._new_index()

    @property
    def _sq8(self) -> ScalarQuantiser:
        """The quantiser of a fitted sq8 store."""
        assert self.quantiser is not None
        return self.quantiser

    def _add_codes(self, codes: np.ndarray) -> None:
        if codes.shape[0]:
            self._index.add_sa_codes(np.ascontiguousarray(codes).view(np.uint8).reshape(codes.shape[0], -1))
        self._n = int(self._index.ntotal)

    def append(self, rows: np.ndarray) -> None:
        """Add float rows (N, D) at the end."""
        x = np.asarray(rows, np.float32).reshape(-1, self.dim)
        if self._index is not None:
            if self.dtype == "float16":
                self._add_codes(x.astype(np.float16))
            else:
                self._add_codes(self._sq8.encode(x))
            return
        if self._n + x.shape[0] > self._rows.shape[0]:  # float32 rows, grown by doubling
            cap = max(1024, 2 * self._rows.shape[0], self._n + x.shape[0])
            grown = np.empty((cap, self.dim), np.float32)
            grown[: self._n] = self._rows[: self._n]
            self._rows = grown
        self._rows[self._n : self._n + x.shape[0]] = x
        self._n += x.shape[0]
        if self.dtype == "sq8" and self._n >= self.fit_rows:
            pending, self._rows = self._rows[: self._n], np.zeros((0, self.dim), np.float32)
            self._sq = np.zeros(0, np.float32)
            self._fit(ScalarQuantiser.fit(pending))
            self._add_codes(self._sq8.encode(pending))

    # -- reading ----------------------------------------------------------------------------------------------
    def __len__(self) -> int:
        return self._n

    def sq_norms_to(self, stop: int) -> np.ndarray:
        """The squared norms of float32 rows ``0:stop``, kept and extended as rows come (rows are only appended),
        so that a search does not read every row again for them."""
        done = self._sq.shape[0]
        if done < stop:
            self._sq = np.concatenate([self._sq, sq_norms(self._rows[done:stop])])
        return self._sq[:stop]

    @property
    def shape(self) -> tuple[int, int]:
        return (self._n, self.dim)

    def __array__(self, dtype: Any = None, copy: bool | None = None) -> np.ndarray:
        """Every row decoded to float32 (``np.asarray(store)``: for small stores and tests; searches never do it)."""
        rows = self.rows()
        return rows if dtype is None else rows.astype(dtype)

    @property
    def encoded(self) -> bool:
        """Whether the rows are held as codes (float16, or sq8 once fitted)."""
        return self._index is not None

    @property
    def nbytes(self) -> int:
        """Bytes held for the rows (the codes, or the float32 buffer with its spare capacity), quantiser included."""
        if self._index is None:
            return int(self._rows.nbytes)
        return int(self._index.codes.size()) + (0 if self.quantiser is None else 8 * self.dim)

    def _codes_view(self) -> np.ndarray:
        """The codes inside the faiss index as an (N, D) array, without a copy (valid until the next append)."""
        n = self._n * self._index.code_size
        raw = _faiss().rev_swig_ptr(self._index.codes.data(), n) if n else np.zeros(0, np.uint8)
        return raw.view(np.float16 if self.dtype == "float16" else np.uint8).reshape(self._n, self.dim)

    def _decode(self, codes: np.ndarray) -> np.ndarray:
        if self.dtype == "float16":
            return codes.astype(np.float32)
        return self._sq8.decode(codes)

    def rows(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        """Rows ``start:stop`` as float32 (decoded; with NumPy, which is 20x faster than faiss's
        ``reconstruct_n`` for the ~100 rows of a place)."""
        stop = self._n if stop is None else min(int(stop), self._n)
        start = min(int(start), stop)
        if self._index is None:
            return self._rows[start:stop]
        return self._decode(self._codes_view()[start:stop])

    def take(self, idx: np.ndarray) -> np.ndarray:
        """Rows ``idx`` as float32 (decoded)."""
        idx = np.asarray(idx, np.int64).reshape(-1)
        if self._index is None:
            return self._rows[idx]
        return self._decode(self._codes_view()[idx])

    def view(self, n: int | None = None, mask: np.ndarray | None = None) -> StoreView:
        """The first ``n`` rows (None: all), or the rows where ``mask`` (over all rows) is True."""
        return StoreView(self, None if n is None else int(n), mask)

    def codes(self) -> np.ndarray:
        """The stored rows as kept: float32 (N, D), float16 (N, D) or sq8 uint8 (N, D) (a copy for the coded)."""
        if self._index is None:
            rows = self._rows[: self._n]
            return rows if self.dtype == "float32" else rows.copy()
        return self._codes_view().copy()

    def converted(self, dtype: str) -> DescriptorStore:
        """This store in ``dtype`` (itself when it is already; an sq8 one is fitted on every row)."""
        if dtype == self.dtype:
            return self
        return DescriptorStore.from_rows(self.rows(), dtype)

    # -- persistence ------------------------------------------------------------------------------------------
    def arrays(self, prefix: str = "descriptors") -> dict[str, np.ndarray]:
        """The arrays to save: ``prefix`` (the rows as stored: float32, float16 or uint8 codes; the float32 rows
        of an sq8 store not fitted yet) and, for a fitted sq8 store, ``sq_vmin`` / ``sq_vdiff``."""
        out = {prefix: np.ascontiguousarray(self.codes())}
        if self.quantiser is not None:
            out["sq_vmin"], out["sq_vdiff"] = self.quantiser.vmin, self.quantiser.vdiff
        return out

    @classmethod
    def from_arrays(
        cls,
        arrays: Mapping[str, np.ndarray],
        dtype: Any,
        dim: int,
        path: str | Path,
        prefix: str = "descriptors",
    ) -> DescriptorStore:
        """The store saved by `arrays` as ``dtype`` (from the file's header); `ArtifactError` naming ``path``
        when the header's store, the rows' dtype and the quantiser disagree."""
        if dtype not in STORE_DTYPES:
            raise ArtifactError(
                f"{path}: descriptor store {short_repr(dtype)} is unknown (expected one of {list(STORE_DTYPES)})"
            )
        rows = arrays[prefix]
        sq = [k for k in ("sq_vmin", "sq_vdiff") if k in arrays]
        want = {"float32": np.float32, "float16": np.float16, "sq8": np.uint8}[dtype]
        if dtype == "sq8" and not sq and rows.dtype == np.float32:
            want = np.float32  # saved before its quantiser was fitted: float32 rows, appended again
        if rows.dtype != want or rows.ndim != 2 or rows.shape[1] != dim:
            raise ArtifactError(
                f"{path}: {prefix!r} is {rows.dtype} {rows.shape}, expected {np.dtype(want)} (N, {dim}) for a "
                f"{dtype} store"
            )
        if dtype != "sq8" or want == np.float32:
            if sq:
                raise ArtifactError(f"{path}: {sq} given for a {dtype} store (only sq8 has a quantiser)")
            if dtype == "float32":
                return cls.from_rows(rows, "float32")
            store = cls(dim, dtype)
            if dtype == "sq8":
                store.append(rows)
            else:
                store._add_codes(rows)
            return store
        if len(sq) != 2:
            raise ArtifactError(f"{path}: an sq8 store needs 'sq_vmin' and 'sq_vdiff', found {sq}")
        vmin, vdiff = arrays["sq_vmin"], arrays["sq_vdiff"]
        for name, v in (("sq_vmin", vmin), ("sq_vdiff", vdiff)):
            if v.dtype != np.float32 or v.shape != (dim,) or not np.isfinite(v).all():
                raise ArtifactError(
                    f"{path}: sq8 quantiser {name!r} is {v.dtype} {v.shape}, expected finite float32 ({dim},)"
                )
        if (vdiff <= 0).any():
            raise ArtifactError(f"{path}: sq8 quantiser 'sq_vdiff' must be positive, holds {vdiff.min()}")
        store = cls(dim, "sq8")
        store._fit(ScalarQuantiser(np.array(vmin), np.array(vdiff)))
        store._add_codes(rows)
        return store


class StoreView:
    """Rows of a `DescriptorStore` selected by a prefix length ``n`` or a ``mask``; searched with `knn` / `knn2`,
    indices local to the selection (row ``i`` of the view)."""

    def __init__(self, store: DescriptorStore, n: int | None, mask: np.ndarray | None) -> None:
        self.store = store
        self.ids: np.ndarray | None = None  # store rows of a masked view
        if mask is not None:
            self.ids = np.flatnonzero(np.asarray(mask, bool)[: len(store)])
            self.n = int(self.ids.size)
        else:
            self.n = len(store) if n is None else min(int(n), len(store))

    def __len__(self) -> int:
        return self.n

    @property
    def shape(self) -> tuple[int, int]:
        return (self.n, self.store.dim)

    def rows(self) -> np.ndarray:
        """The selected rows as float32 (decoded: for small selections)."""
        return self.store.rows(0, self.n) if self.ids is None else self.store.take(self.ids)

    def knn2(self, query: np.ndarray, backend: str = "faiss", threads: int | None = 1) -> tuple:
        """Exact 2-NN (`knn2`) over the selection; needs at least 2 rows."""
        if not self.store.encoded:
            sq = self.store.sq_norms_to(self.n) if self.ids is None else None
            return knn2(query, self.rows(), backend, threads, sq)
        return self.knn(query, 2, threads)

    def knn(self, query: np.ndarray, k: int, threads: int | None = 1) -> tuple[np.ndarray, np.ndarray]:
        """Exact ``k``-NN over the selection: (distances (Q, k) Euclidean, indices (Q, k)), -1 and infinity for
        the neighbours beyond its size."""
        q = np.ascontiguousarray(query, np.float32).reshape(-1, self.store.dim)
        if not self.store.encoded:
            return knn(q, self.rows(), k, threads)
        if self.n == 0 or q.shape[0] == 0:
            return np.full((q.shape[0], k), np.inf, np.float32), np.full((q.shape[0], k), -1, np.int64)
        if q.shape[0] >= BLAS_BATCH:
            return self._blocks(q, k, threads)
        faiss = _faiss()
        index = self.store._index
        sel, bitmap = None, None
        if self.ids is not None:
            mask = np.zeros(len(self.store), bool)
            mask[self.ids] = True
            bitmap = np.packbits(mask, bitorder="little")  # kept alive while faiss reads it
            sel = faiss.IDSelectorBitmap(bitmap)
        elif self.n < len(self.store):
            sel = faiss.IDSelectorRange(0, self.n)
        with omp_threads(threads):
            if sel is None:
                d2, idx = index.search(q, k)
            else:
                d2, idx = index.search(q, k, params=faiss.SearchParameters(sel=sel))
        del bitmap
        found = idx >= 0
        dist = np.where(found, np.sqrt(np.maximum(d2, 0.0)), np.inf).astype(np.float32)
        idx = np.asarray(idx, np.int64)
        if self.ids is not None:
            idx = np.where(found, np.searchsorted(self.ids, np.maximum(idx, 0)), -1)
        return dist, idx

    def _blocks(self, q: np.ndarray, k: int, threads: int | None) -> tuple[np.ndarray, np.ndarray]:
        """k-NN by decoding ``_BLOCK`` selected rows at a time and searching them with BLAS."""
        best = (np.full((q.shape[0], k), np.inf, np.float32), np.full((q.shape[0], k), -1, np.int64))
        for a in range(0, self.n, _BLOCK):
            b = min(a + _BLOCK, self.n)
            rows = self.store.rows(a, b) if self.ids is None else self.store.take(self.ids[a:b])
            d, i = knn(q, rows, k, threads)
            best = _merge(best, (d, np.where(i >= 0, i + a, -1)), k)
        return best
