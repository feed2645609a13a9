"""Scan Context (Kim & Kim, IROS 2018): a geometry-only baseline, faithful to the reference implementation
(irapkaist/scancontext, cpp/module/Scancontext).

Descriptor
----------
A polar grid of ``num_rings`` x ``num_sectors`` (20 x 60) cells up to ``max_radius`` (80 m) in the xy plane of the
sensor. A cell holds the maximum height ``z + lidar_height`` of its points (``lidar_height`` = 2 m, the reference
``LIDAR_HEIGHT``, lifts ground returns above 0); a cell without points holds 0 (a cell whose highest point lies
below ``-lidar_height`` keeps its negative value, as in the reference code).

* Ring ``r`` covers ranges ``(r, r + 1] * max_radius / num_rings``; range 0 falls in ring 0.
* Sector ``s`` covers azimuths ``(s, s + 1] * 360 / num_sectors`` degrees, azimuth measured counter-clockwise from
  the sensor's +x axis in [0, 360); azimuth 0 falls in sector 0 (the reference ``ceil`` convention).
* Points beyond ``max_radius`` and points with non-finite coordinates are ignored; an empty scan gives an all-zero
  descriptor.

Retrieval
---------
Ring key = row means (rotation invariant), searched with a KD-tree (scipy cKDTree) rebuilt every
``tree_rebuild_every`` additions; entries added since the last rebuild are brute-forced, so the ``num_candidates``
(10) nearest ring keys are exact. Each candidate is compared with the query by the Scan Context distance
``1 - mean cosine similarity of the columns non-empty in both`` (1 when no column is), minimised over column
shifts: coarse shift = argmin over shifts of the sector-key (column mean) difference, then the shifts within
``+-round(0.5 * search_ratio * num_sectors)`` (+-3) around it; ``full_shift_search`` tries all shifts.

Candidates: ``score = 1 - distance`` in [-1, 1] (1 = identical; the reference accepts a loop when distance < 0.13,
i.e. score > 0.87; no threshold is applied here). ``shift`` is the column shift ``s`` such that
``np.roll(match_descriptor, s, axis=1)`` best matches the query: the scene appears rotated by ``+s`` sectors in
the query, so ``relative_pose = T_match_query`` is a rotation about z by ``-s * 360 / num_sectors`` degrees,
reported as ``extra["yaw_deg"]`` (wrapped to (-180, 180]).

Verification (``verify.enabled``; `placerec.verify.candidates`): the description also keeps the scan voxelised
for ICP (``cloud``), the database each entry's cloud. The ``verify.top_k`` best candidates by Scan Context
distance are verified by ICP alone (`placerec.verify.verify_icp`) from their yaw rotation: ``relative_pose``
becomes the full 6-DoF ICP pose, ``score`` the verified score in [0, 1] (the Scan Context score moves to
``extra["retrieval_score"]``, ``yaw_deg``/``shift`` stay), and the candidates are re-ranked by it. Off, the
candidates are the reference's (yaw-only pose, ``score = 1 - distance``). How ``verify.top_k`` (default 3) was
chosen, and what verification costs, is in docs/benchmarks.md (Scan Context).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from pydantic import Field
from scipy.spatial import cKDTree

from placerec.errors import ArtifactError, ScanDataError
from placerec.io.artifact_schema import Member, check_unique
from placerec.io.atomic import load_artifact, save_artifact
from placerec.params import Params
from placerec.recognizer import Recognizer, params_key, require_points
from placerec.types import Candidate, MotionPrior, Scan
from placerec.verify.candidates import CloudStore, Retrieved, VerifiedParams, scan_cloud, verify_candidates
from placerec.verify.params import IcpParams

log = logging.getLogger(__name__)

__all__ = [
    "ScanContextParams",
    "ScanContext",
    "make_descriptor",
    "ring_key",
    "sector_key",
    "scan_context_distance",
]

ARTIFACT_KIND = "scan-context-db"
FORMAT_VERSION = 1
_DESCRIPTOR_PARAMS = ("num_rings", "num_sectors", "max_radius", "lidar_height")
_SCHEMA = {
    "descriptors": Member("f", ("n_entries", None, None), finite=True),
    "ids": Member("iu", ("n_entries",)),
    "cloud_counts": Member("iu", ("n_entries",), optional=True, min_value=0),
    "cloud_xyz": Member("f", ("n_points", 3), optional=True, finite=True),
}


class ScanContextParams(Params):
    """Scan Context parameters (defaults: the paper / reference implementation).

    The descriptor parameters (``num_rings``, ``num_sectors``, ``max_radius``, ``lidar_height``) are stored with a
    saved database and must match on load; the others only affect queries (a database saved without clouds
    cannot be loaded with ``verify.enabled``).
    """

    num_rings: int = Field(20, ge=1, description="rings N_r (Scan Context paper; reference PC_NUM_RING)")
    num_sectors: int = Field(
        60, ge=1, description="sectors N_s (Scan Context paper; reference PC_NUM_SECTOR)"
    )
    max_radius: float = Field(
        80.0, gt=0, description="m; L_max (Scan Context paper; reference PC_MAX_RADIUS)"
    )
    lidar_height: float = Field(2.0, description="m; added to z (reference LIDAR_HEIGHT)")
    num_candidates: int = Field(
        10, ge=1, description="ring-key neighbours re-ranked (reference NUM_CANDIDATES)"
    )
    search_ratio: float = Field(
        0.1, ge=0, le=1, description="fine shift search width (reference SEARCH_RATIO)"
    )
    full_shift_search: bool = Field(
        False, description="try every column shift instead of the two-stage search"
    )
    tree_rebuild_every: int = Field(
        50, ge=1, description="additions between KD-tree rebuilds (reference: 50)"
    )
    verify: VerifiedParams = Field(
        default_factory=lambda: VerifiedParams(icp=IcpParams(max_iterations=15)),
        description="ICP from the Scan Context yaw on the top-k candidates (placerec.verify.candidates); 15 ICP "
        "iterations: the same closures as 30 on the demo, wrong candidates cost half",
    )

    @property
    def search_radius(self) -> int:
        """Half-width of the fine shift search (reference: round(0.5 * SEARCH_RATIO * sectors), half away from 0)."""
        return int(np.floor(0.5 * self.search_ratio * self.num_sectors + 0.5))

    def descriptor_dict(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in _DESCRIPTOR_PARAMS}

    def cloud_dict(self) -> dict[str, Any] | None:
        """What the description's ICP cloud depends on (None without verification)."""
        icp = self.verify.icp
        return {"voxel_size": icp.voxel_size, "max_range": icp.max_range} if self.verify.enabled else None


def make_descriptor(scan: Scan | np.ndarray, params: ScanContextParams | None = None) -> np.ndarray:
    """The (num_rings, num_sectors) float32 Scan Context of a scan or (N, 3) point array (see module docstring)."""
    p = params or ScanContextParams()
    xyz = scan.xyz if isinstance(scan, Scan) else np.asarray(scan, dtype=np.float32)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ScanDataError(f"scan-context: points must have shape (N, 3), got {xyz.shape}")
    R, S = p.num_rings, p.num_sectors
    flat = np.full(R * S + 1, -np.inf, dtype=np.float32)  # last cell: sink for dropped points
    if xyz.shape[0]:
        x = np.array(xyz[:, 0], dtype=np.float32)  # contiguous copies, modified in place below
        y = np.array(xyz[:, 1], dtype=np.float32)
        z = xyz[:, 2] + np.float32(p.lidar_height)
        r = np.sqrt(x * x + y * y)
        keep = (r <= p.max_radius) & np.isfinite(z)  # NaN ranges compare False and drop out too
        with np.errstate(invalid="ignore"):  # NaN -> int casts of dropped points
            # azimuth in [0, 2 pi) = atan2(-y, -x) + pi, in units of sectors; ceil convention of the reference
            u = np.arctan2(np.negative(y, out=y), np.negative(x, out=x))
            u *= np.float32(S / (2.0 * np.pi))
            u += np.float32(S / 2.0)
            sector = np.ceil(u, out=u).astype(np.int32)
            r *= np.float32(R / p.max_radius)
            ring = np.ceil(r, out=r).astype(np.int32)
        np.clip(sector, 1, S, out=sector)
        np.clip(ring, 1, R, out=ring)
        cell = ring * S + sector - (S + 1)  # (ring - 1) * S + (sector - 1)
        cell[~keep] = R * S
        np.maximum.at(flat, cell, z)
    flat = flat[:-1]
    flat[np.isneginf(flat)] = 0.0
    return flat.reshape(R, S)


def ring_key(desc: np.ndarray) -> np.ndarray:
    """Rotation-invariant ring key: the mean of each ring (row), shape (..., num_rings)."""
    return np.asarray(desc).mean(axis=-1)


def sector_key(desc: np.ndarray) -> np.ndarray:
    """Sector key used for coarse alignment: the mean of each sector (column), shape (..., num_sectors)."""
    return np.asarray(desc).mean(axis=-2)


def scan_context_distance(
    query: np.ndarray,
    candidates: np.ndarray,
    search_radius: int | None = 3,
) -> tuple[np.ndarray, np.ndarray]:
    """Scan Context distance of a (R, S) query to (M, R, S) candidates, minimised over column shifts.

    Returns ``(distance (M,), shift (M,))`` where ``np.roll(candidates[m], shift[m], axis=1)`` is the best aligned
    candidate. ``search_radius=None`` tries all shifts; otherwise the shifts within ``+-search_radius`` of the
    sector-key alignment (the reference's two-stage search). Vectorised over candidates, shifts and columns.
    """
    Q = np.asarray(query, dtype=np.float64)
    C = np.asarray(candidates, dtype=np.float64)
    if C.ndim == 2:
        C = C[None]
    M, R, S = C.shape
    if Q.shape != (R, S):
        raise ScanDataError(f"scan-context: query shape {Q.shape} does not match candidates {(R, S)}")
    if M == 0:
        return np.zeros(0), np.zeros(0, dtype=np.int64)
    cols = np.arange(S)
    if search_radius is None or 2 * search_radius + 1 >= S:
        shifts = np.broadcast_to(cols, (M, S))
    else:
        roll_idx = (cols[None, :] - cols[:, None]) % S  # [s, j] -> column of the candidate landing on j
        diff = sector_key(Q)[None, None, :] - sector_key(C)[:, roll_idx]  # (M, shift, S)
        coarse = np.argmin(np.einsum("msj,msj->ms", diff, diff), axis=1)
        shifts = (coarse[:, None] + np.arange(-search_radius, search_radius + 1)[None, :]) % S
    # Only the query's columns holding points count (an empty column's pairs are not valid), so the products are
    # formed for those alone: a limited field of view's query (a fifth of the columns) costs a fifth.
    qn = np.linalg.norm(Q, axis=0)
    occupied = np.flatnonzero(qn > 0)
    Qo = Q if occupied.size == S else Q[:, occupied]  # a full query's products as before, bit for bit
    src = (
        occupied[None, None, :] - shifts[:, :, None]
    ) % S  # (M, shifts, occupied): candidate column landing on query column occupied[j]
    pair = np.matmul(Qo.T[None], C)  # (M, occupied, S): query column occupied[j] . candidate column c
    m_idx = np.arange(M)[:, None, None]
    dots = pair[m_idx, np.arange(occupied.size)[None, None, :], src]
    cn = np.linalg.norm(C, axis=1)[m_idx, src]
    valid = cn > 0
    sim = np.divide(dots, qn[occupied][None, None, :] * cn, out=np.zeros_like(dots), where=valid)
    n_eff = valid.sum(axis=2)
    dist = np.where(n_eff > 0, 1.0 - sim.sum(axis=2) / np.maximum(n_eff, 1), 1.0)
    best = np.argmin(dist, axis=1)
    rows = np.arange(M)
    return dist[rows, best], shifts[rows, best].astype(np.int64)


def _walk(d: Any, *keys: str) -> Any:
    """``d[k1][k2]...`` of a saved header's nested mappings, None where one is missing or not a mapping."""
    for k in keys:
        d = d.get(k) if isinstance(d, Mapping) else None
    return d


def _yaw_pose(yaw_deg: float) -> np.ndarray:
    a = np.radians(yaw_deg)
    T = np.eye(4)
    T[0, 0], T[0, 1], T[1, 0], T[1, 1] = np.cos(a), -np.sin(a), np.sin(a), np.cos(a)
    return T


class ScanContext(Recognizer[ScanContextParams]):
    """Scan Context place recognizer, a `placerec.recognizer.Recognizer` (see module docstring).

    ``ScanContext()`` uses the paper's defaults; ``ScanContext(params)`` or keyword overrides
    (``ScanContext(full_shift_search=True)``) change them. ``add`` ignores ``pose``. ``describe`` gives
    ``{"scan_context": (R, S) array}``; ``frontend_key`` depends on the descriptor parameters only.
    """

    name: ClassVar[str] = "scan-context"
    Params: ClassVar[type[Params]] = ScanContextParams

    def __init__(self, params: ScanContextParams | Mapping[str, Any] | None = None, **overrides: Any) -> None:
        super().__init__(params, **overrides)
        R, S = self.params.num_rings, self.params.num_sectors
        self._desc = np.zeros((0, R, S), dtype=np.float32)
        self._keys = np.zeros((0, R), dtype=np.float64)
        self._ids = np.zeros(0, dtype=np.int64)
        self._index: dict[int, int] = {}
        self._n = 0
        self._tree: cKDTree | None = None
        self._n_tree = 0
        self._clouds = CloudStore.for_pipeline(self.params.verify)

    def __len__(self) -> int:
        return self._n

    @property
    def ids(self) -> np.ndarray:
        """The ids in the database, in insertion order."""
        return self._ids[: self._n].copy()

    @property
    def frontend_key(self) -> str:
        """Identifies the descriptor and its parameters (equal keys give identical descriptions)."""
        cloud = self.params.cloud_dict()
        extra = {} if cloud is None else {"cloud": cloud}
        return params_key(self.name, {**self.params.descriptor_dict(), **extra})

    def describe(self, scan: Scan) -> dict[str, np.ndarray]:
        """``{"scan_context": descriptor}`` of the scan with this recognizer's parameters (and ``cloud``, the scan
        voxelised for ICP, with verification); `ScanDataError` for a scan with too few valid points (a blank scan
        would otherwise match every other blank scan)."""
        require_points(scan, self.name)
        out = {"scan_context": make_descriptor(scan, self.params)}
        if self.params.verify.enabled:
            out["cloud"] = scan_cloud(scan, self.params.verify)
        return out

    def _cloud(self, description: Mapping[str, np.ndarray] | np.ndarray) -> np.ndarray | None:
        if not self.params.verify.enabled:
            return None
        if not isinstance(description, Mapping) or "cloud" not in description:
            raise ScanDataError(
                "scan-context: verification needs the description's 'cloud' (describe() gives it); "
                "set verify.enabled to false to use bare descriptors"
            )
        return description["cloud"]

    def _unwrap(self, description: Mapping[str, np.ndarray] | np.ndarray) -> np.ndarray:
        d = description["scan_context"] if isinstance(description, Mapping) else description
        d = np.asarray(d, dtype=np.float32)
        if d.shape != self._desc.shape[1:]:
            raise ScanDataError(f"scan-context: descriptor shape {d.shape}, expected {self._desc.shape[1:]}")
        return d

    # ------------------------------------------------------------------ database

    def add_description(
        self,
        scan_id: int,
        description: Mapping[str, np.ndarray] | np.ndarray,
        pose: np.ndarray | None = None,
    ) -> None:
        """Insert a precomputed description (``describe``'s dict, or the bare (R, S) array without verification)
        under ``scan_id``."""
        sid = int(scan_id)
        if sid in self._index:
            raise ScanDataError(f"scan-context: id {sid} is already in the database")
        d = self._unwrap(description)
        cloud = self._cloud(description)
        if cloud is not None:
            self._clouds.add(sid, cloud)
        if self._n == self._desc.shape[0]:
            self._grow(max(64, 2 * self._n))
        self._desc[self._n] = d
        self._keys[self._n] = ring_key(d)
        self._ids[self._n] = sid
        self._index[sid] = self._n
        self._n += 1
        if self._n - self._n_tree >= self.params.tree_rebuild_every:
            self._rebuild_tree()

    def _grow(self, capacity: int) -> None:
        n = self._n
        desc = np.zeros((capacity,) + self._desc.shape[1:], dtype=np.float32)
        keys = np.zeros((capacity, self._keys.shape[1]), dtype=np.float64)
        ids = np.zeros(capacity, dtype=np.int64)
        desc[:n], keys[:n], ids[:n] = self._desc[:n], self._keys[:n], self._ids[:n]
        self._desc, self._keys, self._ids = desc, keys, ids

    def _rebuild_tree(self) -> None:
        self._n_tree = self._n
        self._tree = cKDTree(self._keys[: self._n].copy()) if self._n else None

    # ------------------------------------------------------------------ query

    def _nearest_keys(self, key: np.ndarray, want: int, max_id: int | None) -> tuple[np.ndarray, np.ndarray]:
        """Storage rows and ring-key distances of the ``want`` nearest eligible ring keys (exact)."""
        n, nt = self._n, self._n_tree
        elig = None if max_id is None else self._ids[:n] <= max_id
        rows = [np.arange(nt, n)]  # added since the last rebuild: brute force
        if nt:
            n_elig = nt if elig is None else int(elig[:nt].sum())
            if elig is not None and n_elig < nt // 2:
                rows.append(np.flatnonzero(elig[:nt]))  # few eligible in the tree: brute force them
            elif n_elig and self._tree is not None:
                kq = min(nt, want if elig is None else 2 * want)
                while True:
                    _, j = self._tree.query(key, k=kq)
                    j = np.atleast_1d(j)
                    j = j[j < nt]
                    if elig is not None:
                        j = j[elig[j]]
                    if j.size >= min(want, n_elig) or kq >= nt:
                        break
                    kq = min(nt, 4 * kq)
                rows.append(j)
        cand = np.concatenate(rows).astype(np.int64)
        if elig is not None:
            cand = cand[elig[cand]]
        d = np.linalg.norm(self._keys[cand] - key, axis=1)
        order = np.argsort(d, kind="stable")[:want]
        return cand[order], d[order]

    def query_description(
        self,
        description: Mapping[str, np.ndarray] | np.ndarray,
        k: int = 1,
        max_id: int | None = None,
        query_id: int = -1,
        prior: MotionPrior | None = None,
    ) -> list[Candidate]:
        """Up to ``k`` candidates, best (highest score) first, among entries with ``id <= max_id``, for a
        description (``describe``'s dict or the bare (R, S) array): ``max(k, num_candidates)`` ring-key
        neighbours re-ranked by the Scan Context distance; with verification the ``verify.top_k`` best of them
        verified by ICP and re-ranked by verified score (module docstring)."""
        if k < 1:
            raise ScanDataError(f"scan-context: k must be >= 1, got {k}")
        q = self._unwrap(description)
        query_cloud = self._cloud(description)
        if self._n == 0:
            return []
        vp = self.params.verify
        n_out = max(k, vp.top_k) if vp.enabled else k
        want = max(n_out, self.params.num_candidates)
        rows, key_d = self._nearest_keys(ring_key(q).astype(np.float64), want, max_id)
        if rows.size == 0:
            return []
        radius = None if self.params.full_shift_search else self.params.search_radius
        dist, shift = scan_context_distance(q, self._desc[rows], radius)
        order = np.argsort(dist, kind="stable")[:n_out]
        S = self.params.num_sectors
        out = []
        for i in order:
            s = int(shift[i])
            yaw = -s * 360.0 / S
            yaw = (yaw + 180.0) % 360.0 - 180.0
            yaw = 180.0 if yaw == -180.0 else yaw
            out.append(
                Candidate(
                    query_id=int(query_id),
                    match_id=int(self._ids[rows[i]]),
                    score=float(1.0 - dist[i]),
                    relative_pose=_yaw_pose(yaw),
                    extra={
                        "yaw_deg": yaw,
                        "shift": s,
                        "distance": float(dist[i]),
                        "ringkey_distance": float(key_d[i]),
                    },
                )
            )
        if query_cloud is None:
            return out
        retrieved = [Retrieved(c.match_id, c.score, init=c.relative_pose, extra=c.extra) for c in out]
        return verify_candidates(query_cloud, retrieved, self._clouds, vp, int(query_id), k)

    # ------------------------------------------------------------------ persistence

    def save(self, path: str | Path) -> None:
        """Write the database atomically (kind ``scan-context-db``, format version 1, parameters in the header)."""
        n = self._n
        arrays: dict[str, np.ndarray] = {"descriptors": self._desc[:n], "ids": self._ids[:n]}
        if self.params.verify.enabled:
            arrays.update(self._clouds.arrays(self._ids[:n].tolist()))
        save_artifact(path, ARTIFACT_KIND, FORMAT_VERSION, arrays, meta={"params": self.params.saved_dump()})

    def load(self, path: str | Path) -> None:
        """Replace the database with a saved one; `ArtifactError` if it is corrupt or its descriptor parameters
        differ from this recognizer's."""
        arrays, header = load_artifact(path, ARTIFACT_KIND, (FORMAT_VERSION,), _SCHEMA, mmap=True)
        saved = (header.get("meta") or {}).get("params") or {}
        mine = self.params.descriptor_dict()
        theirs = {k: saved.get(k) for k in _DESCRIPTOR_PARAMS}
        if theirs != mine:
            diff = {k: (theirs[k], mine[k]) for k in mine if theirs[k] != mine[k]}
            raise ArtifactError(
                f"{path}: database was made with other Scan Context parameters (saved, ours): {diff}"
            )
        desc, ids = arrays["descriptors"], arrays["ids"]
        if desc.shape[1:] != (self.params.num_rings, self.params.num_sectors):
            raise ArtifactError(f"{path}: descriptors of shape {desc.shape[1:]} for parameters {mine}")
        check_unique(ids, path, "ids")
        icp = _walk(saved, "verify", "icp")
        saved_cloud = (
            {"voxel_size": icp.get("voxel_size"), "max_range": icp.get("max_range")}
            if isinstance(icp, dict) and _walk(saved, "verify", "enabled") is True
            else None
        )
        if self.params.verify.enabled and (
            saved_cloud != self.params.cloud_dict() or "cloud_xyz" not in arrays
        ):
            raise ArtifactError(
                f"{path}: database saved without the clouds verification needs (or with other voxel "
                f"parameters): {saved_cloud}"
            )
        clouds = CloudStore.for_pipeline(self.params.verify)
        if self.params.verify.enabled:
            clouds.from_arrays(ids.tolist(), arrays, path)
        n = int(ids.size)
        self._desc = np.ascontiguousarray(desc, dtype=np.float32)
        self._keys = ring_key(self._desc).astype(np.float64)
        self._ids = ids.astype(np.int64)
        self._index = {int(v): i for i, v in enumerate(self._ids)}
        self._n = n
        self._clouds = clouds
        self._rebuild_tree()
        log.debug("loaded a scan-context database of %d entries from %s", n, path)
