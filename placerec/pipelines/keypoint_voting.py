"""The 3D pipeline: ISS-BR keypoints + ISHOT (or SHOT/FPFH) descriptors, ratio-tested NN votes per place.

For every query descriptor the two nearest database descriptors (exact L2, brute force with ``faiss.knn``) give
the ratio ``tau = d1 / d2`` (ISHOT paper, eq. 4); when ``tau < tau_max`` the query descriptor votes for the entry
(place) its 1st neighbour belongs to. Candidates are the entries with most votes. The paper has no hard ratio
threshold (its votes are weighted by a model per tau range); 0.9 was best or tied in a localize sweep on the
simulator (docs/descriptors.md: success 0.55/0.60/0.60 on gator, 0.15/0.25/0.20 on pole for 0.8/0.9/1.0).

Nearest neighbours (`tools/bench_3d_nn.py`, docs/benchmarks.md): at 1344-d a k-d tree is 40-80x slower than
brute force and HNSW takes minutes to build over 100k descriptors, so the search is exact brute force, on one
OpenMP thread by default (``nn_threads``; on the shared 2-core machine one faiss thread beat two). The descriptors
live in a `placerec.retrieval.descriptor_store.DescriptorStore` (``descriptor_store``: float32, float16 or sq8
8-bit codes, searched without decoding the database; a places database's own store by default, float32 for
entries added scan by scan): sq8 takes a quarter of float32's memory (docs/localization.md).

Score (documented, what thresholds apply to): ``score="fraction"`` (default) is votes / number of query
descriptors, in [0, 1], so one threshold works for scans with many or few keypoints; ``score="votes"`` is the raw
vote count; with verification (below) the score is the verified score instead.

Verification (``verify.enabled``, ISHOT paper Sec. IV-F; `placerec.verify.candidates`): the description also
keeps the scan voxelised for ICP (``cloud``), the database each entry's cloud. For each of the ``verify.top_k``
most-voted entries the query descriptors are matched against that entry's descriptors alone (2-NN, ratio
``< tau_max``, the ratio ordering the pairs), the matches go through the paper's geometric consistency grouping
(consensus resolution 7 m, minimum cluster 8), RANSAC and point-to-plane ICP; ``relative_pose`` is the 6-DoF
``T_match_query``, ``score`` the verified score (``extra["retrieval_score"]`` the vote score) and the candidates
are re-ranked by it. A candidate is accepted when its ICP residual is below the paper's eps_ICP (7 m^2)
(``acceptance = "eps_icp"``; a rejected candidate scores 0). Measured on ``configs/demo.yaml``'s sequence
(ishot-votes, 2 shared cores; describe + vote ~700-800 ms per scan): max F1 0.843 unverified (recall at 100 %
precision 0); verifying the top 1 / 3 / 5 with ``eps_icp``: 0.810 / 0.844 / 0.864 (R@P100 0.455 / 0.545 /
0.556) for 20 / 40 / 48 ms per scan, so ``top_k`` = 5; at top 3, ``both`` gives 0.718 (true single-scan pairs
often score below ``min_score``: max F1 sits at 0.19) and ``score`` 0.878. Accepted closures' median translation
error 0.019 m, at most 0.049 m. Off, ``relative_pose`` is None. With ``verify_radius_m > 0`` a candidate is verified
as a local map: its descriptors and those of the (eligible) entries within that distance, their keypoints moved
into its frame by the entries' poses, and ICP against their clouds merged in that frame (cached, the last
``local_map_cache``); the global-localisation presets use 15 m (docs/localization.md).

Entries ("places"):

* default (``place_spacing_m = 0``, ``place_window_m = 0``): every added scan is one entry, described alone;
  match ids are scan ids, which is what the loop and localize evaluators expect.
* ``place_window_m > 0``: an entry accumulates, in its own frame, the voxelised clouds of the scans added just
  before it within that much travelled distance (from the poses given to ``add``; causal, so it also works in
  loop mode), then is described as one cloud (a place of the paper, Sec. IV-B). The paper queries such places
  with dense static scans; a single sweep's descriptors (sparser rings) match accumulated places poorly
  (docs/descriptors.md), so keep 0 when queries are single sweeps.
* ``place_spacing_m > 0``: only scans at least that far from every earlier entry become entries (the others
  only contribute points to later entries); ids stay scan ids, so ``map_poses[match_id]`` is the place pose.
* ``places_db``: a `placerec.three_d.places.PlacesDatabase` file (built offline by ``build_places`` from the
  map sequence) replaces the entries; its place ids are the map's scan indices. ``add`` then only checks that a
  scan with that id and pose is part of the map the database was built from (`ArtifactError` otherwise), so
  the localize evaluator's ``add(i, scan, pose)`` over the map scans is consistent with it.

``max_id``: entries with ``id <= max_id`` only. Descriptor rows are stored in insertion order; when ids were
added in increasing order (the usual case) the eligible rows are a prefix and no copy is made.
"""

from __future__ import annotations

import logging
import time
from collections import OrderedDict
from collections.abc import Callable, Iterable, Mapping, Sequence
from functools import partial
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field

from placerec.errors import ArtifactError, ScanDataError, short_repr
from placerec.intensity import normalize_intensity
from placerec.io.artifact_schema import Member, check_counts, check_unique
from placerec.io.atomic import load_artifact, save_artifact
from placerec.params import Params
from placerec.recognizer import (
    Recognizer,
    check_saved_params,
    params_key,
    require_points,
    require_varying_intensity,
)
from placerec.retrieval.descriptor_store import (
    DescriptorStore,
    StoreDtype,
    StoreView,
    knn,
    knn2,
    omp_threads,
)
from placerec.three_d.descriptors import DESCRIPTOR_DIMS
from placerec.three_d.features import FeatureParams, extract_features
from placerec.three_d.places import PlacesDatabase, merge_clouds
from placerec.types import Candidate, Description, Scan, as_pose
from placerec.verify.candidates import (
    CloudStore,
    Retrieved,
    VerifiedParams,
    scan_cloud,
    verify_candidates,
    voxel_points,
)
from placerec.verify.icp import IcpCloud
from placerec.verify.params import VerifyParams
from placerec.verify.verify import as_target

log = logging.getLogger(__name__)

__all__ = [
    "VotingParams",
    "KeypointVoting",
    "IvfIndex",
    "knn",
    "knn2",
    "nn_ratio",
    "ratio_votes",
    "voting_schema",
]

_KIND = "keypoint-voting-db"
#: 2: descriptors as their store keeps them (``meta["descriptor_store"]``: float32, float16, or sq8 uint8 codes
#: with ``sq_vmin`` / ``sq_vdiff``); 1: float32 descriptors
_VERSION = 2
_READ_VERSIONS = (1, 2)
#: The kind of a saved database (`KeypointVoting.save`), shared by its subclasses.
ARTIFACT_KIND = _KIND


class VotingParams(FeatureParams):
    """The front end (`FeatureParams`: the ISHOT paper's feature settings), ratio test, score, place aggregation
    and verification."""

    tau_max: float = Field(
        0.9, gt=0, le=1, description="NN ratio d1/d2 below which a descriptor votes (eq. 4)"
    )
    verify_tau_max: float | None = Field(
        None,
        gt=0,
        le=1,
        description="ratio d1/d2 below which a query descriptor is paired with a candidate's for verification "
        "(None = tau_max; 1 keeps every nearest neighbour and leaves outliers to the consistency grouping)",
    )
    verify_radius_m: float = Field(
        0.0,
        ge=0,
        description="m; a candidate entry is verified as a local map: with the entries within this distance of it, "
        "their keypoints and ICP clouds in its frame (0: the entry alone)",
    )
    verify_separation_m: float = Field(
        0.0,
        ge=0,
        description="m; candidates within this distance of one already verified for the same query are skipped "
        "(their local maps overlap it), so the verified candidates cover distinct regions (0: none skipped)",
    )
    fallback_top_k: int | None = Field(
        None,
        ge=1,
        description="entries the voting pipelines that stop early (ishot-prob, gestalt-voting) verify when every "
        "query keypoint is consumed without an accepted one (their last resort; None = verify.top_k)",
    )
    local_map_cache: int = Field(
        64,
        ge=1,
        description="local maps kept prepared for ICP (least recently used dropped; ~5 MB each in the simulated "
        "town at 15 m)",
    )
    score: Literal["fraction", "votes"] = Field("fraction", description="votes / query descriptors, or votes")
    backend: Literal["faiss", "numpy"] = Field("faiss", description="exact 2-NN search")
    index: Literal["flat", "ivf"] = Field(
        "flat",
        description="search over the whole database: exact brute force, or approximate (faiss IVF, sub-linear)",
    )
    ivf_nlist: int | None = Field(None, ge=1, description="IVF lists (None = sqrt of the descriptors)")
    ivf_nprobe: int = Field(16, ge=1, description="IVF lists searched per query descriptor")
    nn_threads: int | None = Field(1, ge=1, description="faiss OpenMP threads (None = faiss's default)")
    descriptor_store: StoreDtype | None = Field(
        None,
        description="how descriptors are kept and searched: float32, float16 or sq8 (8-bit codes, 1 byte per "
        "dimension; placerec.retrieval.descriptor_store); None = a places database's own, else float32",
    )
    place_spacing_m: float = Field(
        0.0, ge=0, description="m; only scans this far from every entry become entries"
    )
    place_window_m: float = Field(
        0.0, ge=0, description="m; accumulate scans over this path as a place (Sec. IV-B)"
    )
    places_db: str | None = Field(None, description="a PlacesDatabase file replacing the entries")
    verify: VerifiedParams = Field(
        default_factory=lambda: VerifiedParams(
            top_k=5, verify=VerifyParams(consistency={"enabled": True}, score={"acceptance": "eps_icp"})
        ),
        description="consistency grouping, RANSAC and ICP on the top-k voted entries (ISHOT paper Sec. IV-F)",
    )

    def features(self) -> FeatureParams:
        """The front-end part of these parameters."""
        return FeatureParams(**{name: getattr(self, name) for name in FeatureParams.model_fields})


def nn_ratio(dist: np.ndarray) -> np.ndarray:
    """``tau = d1 / d2`` (eq. 4) of `knn2` distances; 1 where ``d2`` is 0 (two identical neighbours) or infinite
    (an approximate search found fewer than two)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where((dist[:, 1] > 0) & np.isfinite(dist[:, 1]), dist[:, 0] / dist[:, 1], 1.0)


class IvfIndex:
    """Approximate 2-NN over fixed rows: faiss ``IndexIVFFlat`` (L2), ``nlist`` k-means lists (trained on at most
    64 rows per list), ``nprobe`` of them searched per query; rows with no neighbour found get index -1 and an
    infinite distance. Searching visits about ``nprobe / nlist`` of the rows, so its time grows with the square
    root of the database when ``nlist`` does. Over a compressed `DescriptorStore` the lists hold codes of the
    same kind (``IndexIVFScalarQuantizer``, its own ranges fitted on the training rows), filled from blocks of
    decoded rows; the index keeps its own copy of the codes either way."""

    def __init__(
        self,
        rows: np.ndarray | DescriptorStore,
        nlist: int | None = None,
        nprobe: int = 16,
        threads: int | None = 1,
    ):
        import faiss

        store = rows if isinstance(rows, DescriptorStore) else DescriptorStore.from_rows(rows)
        n, d = store.shape
        self.nlist = max(1, min(n, int(nlist or round(np.sqrt(n)))))
        self.threads = threads
        if store.encoded:
            qt = faiss.ScalarQuantizer.QT_fp16 if store.dtype == "float16" else faiss.ScalarQuantizer.QT_8bit
            self.index = faiss.IndexIVFScalarQuantizer(
                faiss.IndexFlatL2(d), d, self.nlist, qt, faiss.METRIC_L2, False
            )
        else:
            self.index = faiss.IndexIVFFlat(faiss.IndexFlatL2(d), d, self.nlist)
        sample = (
            store.rows()
            if n <= 64 * self.nlist
            else store.take(np.sort(np.random.default_rng(0).choice(n, 64 * self.nlist, replace=False)))
        )
        with omp_threads(threads):
            self.index.train(np.ascontiguousarray(sample))
            for a in range(0, n, 4096):
                self.index.add(np.ascontiguousarray(store.rows(a, a + 4096)))
        self.index.nprobe = min(int(nprobe), self.nlist)
        self.n_rows = n

    def knn2(self, query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        q = np.ascontiguousarray(query, dtype=np.float32)
        with omp_threads(self.threads):
            d2, idx = self.index.search(q, 2)
        dist = np.where(idx >= 0, np.sqrt(np.maximum(d2, 0.0)), np.inf)
        return dist, np.asarray(idx, dtype=np.int64)


def ratio_votes(
    dist: np.ndarray, idx: np.ndarray, row_entry: np.ndarray, n_entries: int, tau_max: float
) -> np.ndarray:
    """Votes per entry: each query row votes for the entry of its 1st neighbour when ``d1 / d2 < tau_max``."""
    ok = (nn_ratio(dist) < tau_max) & (idx[:, 0] >= 0)
    return np.bincount(row_entry[idx[ok, 0]], minlength=n_entries)


class KeypointVoting(Recognizer):
    """`PlaceRecognizer`: 3D local descriptors, 2-NN ratio test, vote counting (see the module docstring)."""

    name: ClassVar[str] = "keypoint-voting"
    Params: ClassVar[type[Params]] = VotingParams

    def __init__(self, params: VotingParams | None = None, **overrides: Any) -> None:
        super().__init__(params, **overrides)
        p = self.params
        self._features = p.features()
        self._dim = DESCRIPTOR_DIMS[p.descriptor]
        self._warned = False
        self._reset()
        self._map_poses: np.ndarray | None = (
            None  # the scan poses of the map a places database was built from
        )
        if p.places_db is not None:
            self.use_places(PlacesDatabase.load(p.places_db, features=self._features, mmap=True))

    def _reset(self) -> None:
        self._store = DescriptorStore(self._dim, self.params.descriptor_store or "float32")
        self._row_entry = np.zeros(0, np.int32)
        self._ids: list[int] = []
        self._idset: set[int] = set()
        self._poses: list[np.ndarray] = []
        self._counts: list[int] = []
        self._keypoints: list[np.ndarray] = []
        self._clouds = CloudStore(self.params.verify.verify, dtype=self.params.verify.cloud_store)
        self._local_targets: OrderedDict[tuple[int, ...], IcpCloud] = OrderedDict()
        self._sorted = True
        self._xyz: np.ndarray | None = None
        self._ivf: IvfIndex | None = None
        # trailing window of (id, pose, travelled distance, cloud xyz, cloud intensity) for place aggregation
        self._buffer: list[tuple[int, np.ndarray, float, np.ndarray, np.ndarray]] = []
        self._travelled = 0.0

    # -- construction from a places database ----------------------------------------------------------------
    @classmethod
    def from_places(cls, db: PlacesDatabase, **overrides: Any) -> KeypointVoting:
        """A recognizer serving ``db`` (its descriptor settings must match; `ArtifactError` otherwise)."""
        f = db.params.features
        base = {
            "descriptor": f.descriptor,
            "max_range": f.max_range,
            "voxel_size": f.voxel_size,
            "support_radius": f.support_radius,
            "iss": f.iss,
            "normals": f.normals,
        }
        rec = cls(**{**base, **overrides})
        rec.use_places(db)
        return rec

    def use_places(self, db: PlacesDatabase) -> None:
        """Replace the entries by the places of ``db`` (ids = place ids, poses = place poses). The descriptors are
        served from the database's store as it is (shared, not copied) unless ``descriptor_store`` asks for another
        kind; a place's ICP cloud is made from its stored cloud when a query first verifies it (a database loaded
        from ``places_db`` is memory-mapped, so its clouds take no RAM until then)."""
        db.check_features(self._features)
        self._reset()
        counts = np.diff(db.kp_offsets)
        want = self.params.descriptor_store
        self._store = db.descriptors if want is None else db.descriptors.converted(want)
        self._row_entry = np.repeat(np.arange(len(db), dtype=np.int32), counts)
        self._ids = [int(i) for i in db.ids]
        self._idset = set(self._ids)
        self._sorted = bool(np.all(np.diff(db.ids) > 0))
        self._poses = [np.asarray(T) for T in db.poses]
        self._counts = [int(c) for c in counts]
        self._keypoints = [
            db.keypoints[a:b] for a, b in zip(db.kp_offsets[:-1], db.kp_offsets[1:], strict=True)
        ]
        if self.params.verify.enabled:
            if db.clouds is None:
                raise ArtifactError(
                    f"{self.name}: the places database has no clouds to verify with (build it with "
                    "store_clouds, or set verify.enabled to false)"
                )
            if len(db.clouds) != len(db):
                raise ArtifactError(
                    f"{self.name}: the places database has {len(db.clouds)} clouds for {len(db)} places"
                )
            for k, i in enumerate(self._ids):
                self._clouds.add_deferred(i, partial(_icp_cloud, db.clouds, k, self.params.verify.verify))
        self._map_poses = np.array(db.scan_poses)

    # -- front end -------------------------------------------------------------------------------------------
    @property
    def frontend_key(self) -> str:
        p = self.params
        icp = p.verify.verify.icp
        return params_key(
            "keypoint-voting",
            {
                "features": self._features.model_dump(mode="json"),
                "cloud": p.place_window_m > 0,
                "icp_cloud": [icp.voxel_size, icp.max_range],
            },
        )

    def _normalised(self, scan: Scan) -> Scan:
        if len(scan) and float(np.max(scan.intensity)) > 1.0 + 1e-6:
            if not self._warned:
                log.warning("%s: intensity above 1; normalising with the sensor default", self.name)
                self._warned = True
            scan = normalize_intensity(scan)
        return scan

    def describe(self, scan: Scan) -> Description:
        """Keypoints (K, 3), descriptors (K, D), ``cloud`` (the scan voxelised for ICP, `scan_cloud`); with
        place aggregation also the front end's voxelised cloud and its intensity.

        `ScanDataError` for a scan with too few valid points (`placerec.recognizer.require_points`) and, with the
        ISHOT descriptor, for one whose valid points all have the same intensity (or a non-finite one): every
        intensity difference would be 0, so the intensity half of each descriptor would only repeat the geometry
        and its scores would not be comparable with those of scans with intensity (a scan matched against itself
        with flat intensity scores 0.3-0.4 instead of 1.0 on the simulator). SHOT and FPFH ignore intensity and
        take such scans."""
        ok = require_points(scan, self.name)
        if self.params.descriptor == "ishot":
            why = "ISHOT's intensity signature needs varying intensity (pipeline shot-votes takes scans without it)"
            require_varying_intensity(scan, ok, self.name, why)
        scan = self._normalised(scan)
        cloud = scan_cloud(scan, self.params.verify.verify)
        try:
            lf = extract_features(scan, self._features)
        except ScanDataError as exc:
            log.warning("%s", exc)
            return {
                "keypoints": np.zeros((0, 3), np.float32),
                "descriptors": np.zeros((0, self._dim), np.float32),
                "cloud": cloud,
            }
        out = {
            "keypoints": lf.keypoints.astype(np.float32),
            "descriptors": lf.descriptors.astype(np.float32),
            "cloud": cloud,
        }
        if self.params.place_window_m > 0:
            out["cloud_xyz"] = lf.points.astype(np.float32)
            out["cloud_intensity"] = lf.intensity.astype(np.float32)
        return out

    # -- database --------------------------------------------------------------------------------------------
    def _append_rows(self, desc: np.ndarray, entry: np.ndarray) -> None:
        self._store.append(desc)
        self._row_entry = np.concatenate([self._row_entry, entry.astype(np.int32)])
        self._ivf = None

    def _add_entry(
        self,
        scan_id: int,
        keypoints: np.ndarray,
        desc: np.ndarray,
        pose: np.ndarray | None,
        cloud: np.ndarray | None,
    ) -> None:
        desc = np.asarray(desc, np.float32).reshape(-1, self._dim)
        if self.params.verify.enabled:
            if cloud is None:
                raise ScanDataError(
                    f"{self.name}: verification needs the description's 'cloud' (describe() gives it); set "
                    "verify.enabled to false to add bare descriptors"
                )
            self._clouds.add(scan_id, cloud)
        if self._ids and scan_id <= self._ids[-1]:
            self._sorted = False
        self._append_rows(desc, np.full(desc.shape[0], len(self._ids)))
        self._ids.append(scan_id)
        self._idset.add(scan_id)
        self._poses.append(np.eye(4) if pose is None else as_pose(pose))
        self._counts.append(desc.shape[0])
        self._keypoints.append(np.asarray(keypoints, np.float32).reshape(-1, 3))

    def add_description(self, scan_id: int, description: Description, pose: np.ndarray | None = None) -> None:
        scan_id = int(scan_id)
        p = self.params
        if self._map_poses is not None:
            self._check_map_scan(scan_id, pose)
            return
        if scan_id in self._idset:
            raise ScanDataError(f"{self.name}: id {scan_id} was added already")
        if p.place_window_m <= 0 and p.place_spacing_m <= 0:
            self._add_entry(
                scan_id, description["keypoints"], description["descriptors"], pose, description.get("cloud")
            )
            return
        if pose is None:
            raise ScanDataError(
                f"{self.name}: place_spacing_m/place_window_m need the pose of every added scan"
            )
        T = as_pose(pose)
        if p.place_window_m > 0:
            self._push_buffer(scan_id, T, description)
        if p.place_spacing_m > 0 and self._poses:
            if np.min(np.linalg.norm(self._entry_xyz() - T[:3, 3], axis=1)) < p.place_spacing_m:
                return
        if p.place_window_m > 0:
            kp, desc, cloud = self._describe_buffer(T)
        else:
            kp, desc, cloud = description["keypoints"], description["descriptors"], description.get("cloud")
        self._add_entry(scan_id, kp, desc, T, cloud)

    def _push_buffer(self, scan_id: int, T: np.ndarray, description: Description) -> None:
        if "cloud_xyz" not in description:
            raise ScanDataError(f"{self.name}: description without a cloud (made with place_window_m = 0?)")
        if self._buffer:
            self._travelled += float(np.linalg.norm(T[:3, 3] - self._buffer[-1][1][:3, 3]))
        self._buffer.append(
            (scan_id, T, self._travelled, description["cloud_xyz"], description["cloud_intensity"])
        )
        w = self.params.place_window_m
        while self._buffer and self._travelled - self._buffer[0][2] > w:
            self._buffer.pop(0)

    def _describe_buffer(self, T_world_place: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Keypoints, descriptors and ICP cloud of the place accumulated in the buffer, in its frame."""
        cloud = merge_clouds(
            T_world_place, [(T, Scan(pts, it)) for _, T, _, pts, it in self._buffer], "place"
        )
        icp_cloud = scan_cloud(cloud, self.params.verify.verify)
        try:
            lf = extract_features(cloud, self._features)
        except ScanDataError as exc:
            log.warning("%s", exc)
            return np.zeros((0, 3), np.float32), np.zeros((0, self._dim), np.float32), icp_cloud
        return lf.keypoints, lf.descriptors, icp_cloud

    def _check_map_scan(self, scan_id: int, pose: np.ndarray | None) -> None:
        sp = self._map_poses
        if not 0 <= scan_id < sp.shape[0]:
            raise ArtifactError(
                f"{self.name}: scan {scan_id} is not part of the map the places database was built from"
            )
        if pose is not None and not np.allclose(as_pose(pose), sp[scan_id], atol=1e-6):
            raise ArtifactError(f"{self.name}: scan {scan_id}'s pose differs from the places database's map")

    def _eligible(self, max_id: int | None) -> tuple[StoreView, np.ndarray, int]:
        """(descriptor rows, their entry index, number of eligible entries) for ``id <= max_id``; the rows are a
        view of the store (searched in place, never decoded as a whole)."""
        entry = self._row_entry
        if max_id is None or (self._ids and max_id >= max(self._ids)):
            return self._store.view(), entry, len(self._ids)
        if self._sorted:
            n_ent = int(np.searchsorted(np.asarray(self._ids), max_id, side="right"))
            n = int(np.sum(self._counts[:n_ent]))
            return self._store.view(n), entry[:n], n_ent
        ok = np.asarray(self._ids)[entry] <= max_id
        return self._store.view(mask=ok), entry[ok], len(self._ids)

    def _eligible_entries(self, max_id: int | None) -> np.ndarray:
        """Mask over the entries (insertion order) of those with ``id <= max_id``."""
        ids = np.asarray(self._ids)
        return np.ones(len(ids), bool) if max_id is None else ids <= max_id

    def _pick(self, ranked: Iterable[Any], taken: Iterable[int], k: int) -> list[int]:
        """The first ``k`` entries of ``ranked`` (entry indices, best first) not in ``taken``, skipping those within
        ``verify_separation_m`` of an entry taken before (``taken`` and the ones picked here)."""
        sep = self.params.verify_separation_m
        done = [int(e) for e in taken]
        picked: list[int] = []
        for e in ranked:
            e = int(e)
            if len(picked) == k:
                break
            if e in done:
                continue
            if sep > 0 and done:
                xyz = self._entry_xyz()
                if np.min(np.linalg.norm(xyz[done] - xyz[e], axis=1)) < sep:
                    continue
            picked.append(e)
            done.append(e)
        return picked

    def _verify_chunks(
        self,
        source: Any,
        picked: Sequence[int],
        retrieve: Callable[[int], Retrieved],
        verified: dict[int, Candidate],
        query_id: int,
    ) -> bool:
        """Verify the entries ``picked`` (best first) ``verify.top_k`` at a time until one is accepted (more than
        ``top_k`` come from the fallback's ``fallback_top_k``); ``retrieve(e)`` gives entry ``e``'s correspondences.
        The candidates go into ``verified`` by entry; True when one is accepted."""
        step = self.params.verify.top_k
        for a in range(0, len(picked), step):
            chunk = picked[a : a + step]
            cands = verify_candidates(
                source, [retrieve(e) for e in chunk], self._clouds, self.params.verify, query_id, None
            )
            by_id = {self._ids[e]: e for e in chunk}
            for c in cands:
                verified[by_id[c.match_id]] = c
            if any(c.extra["accepted"] for c in cands):
                return True
        return False

    def _entry_xyz(self) -> np.ndarray:
        """(entries, 3) positions of the entries (their poses' translations)."""
        if self._xyz is None or len(self._xyz) != len(self._poses):
            self._xyz = np.asarray([T[:3, 3] for T in self._poses], np.float64).reshape(-1, 3)
        return self._xyz

    def _entry_starts(self) -> np.ndarray:
        """First descriptor row of every entry, and the row count last: entry ``e`` owns rows
        ``starts[e]:starts[e + 1]``."""
        return np.concatenate([[0], np.cumsum(self._counts)])

    @staticmethod
    def _query_keypoints(description: Description) -> np.ndarray:
        """The query description's keypoints, (K, 3) float32."""
        return np.asarray(description["keypoints"], np.float32).reshape(-1, 3)

    def query_description(
        self, description: Description, k: int = 1, max_id: int | None = None, query_id: int = -1
    ) -> list[Candidate]:
        q = np.asarray(description["descriptors"], np.float32).reshape(-1, self._dim)
        rows, entry, n_ent = self._eligible(max_id)
        if q.shape[0] == 0 or rows.shape[0] < 2:
            return []
        dist, idx = self._search(q, rows)
        votes = ratio_votes(dist, idx, entry, n_ent, self.params.tau_max)
        vp = self.params.verify
        top = np.flatnonzero(votes)
        top = self._pick(
            top[np.lexsort((np.asarray(self._ids)[top], -votes[top]))], (), vp.top_k if vp.enabled else k
        )
        scale = 1.0 / q.shape[0] if self.params.score == "fraction" else 1.0
        extra = [{"votes": int(votes[e]), "n_query": int(q.shape[0])} for e in top]
        if not vp.enabled:
            return [
                Candidate(query_id, self._ids[e], float(votes[e] * scale), None, None, x)
                for e, x in zip(top, extra, strict=True)
            ]
        if "cloud" not in description:
            raise ScanDataError(f"{self.name}: verification needs the query description's 'cloud'")
        qkp, starts = self._query_keypoints(description), self._entry_starts()
        eligible = self._eligible_entries(max_id)
        retrieved = [
            self._matches(e, q, qkp, starts, float(votes[e] * scale), x, eligible)
            for e, x in zip(top, extra, strict=True)
        ]
        return verify_candidates(description["cloud"], retrieved, self._clouds, vp, query_id, k)

    def _search(self, q: np.ndarray, rows: StoreView) -> tuple[np.ndarray, np.ndarray]:
        """2-NN of ``q`` among ``rows`` (the eligible database rows, `StoreView.knn2`), or with ``index = "ivf"``
        and every row eligible, the `IvfIndex` over the database (built on first use after the entries change)."""
        p = self.params
        n = len(self._store)
        if p.index == "ivf" and rows.shape[0] == n:
            if self._ivf is None or self._ivf.n_rows != n:
                self._ivf = IvfIndex(self._store, p.ivf_nlist, p.ivf_nprobe, p.nn_threads)
            return self._ivf.knn2(q)
        return rows.knn2(q, p.backend, p.nn_threads)

    def _matches(
        self,
        e: int,
        q: np.ndarray,
        qkp: np.ndarray,
        starts: np.ndarray,
        score: float,
        extra: dict[str, Any],
        eligible: np.ndarray | None = None,
    ) -> Retrieved:
        """Entry ``e``'s correspondences with the query: 2-NN among its descriptors (with ``verify_radius_m``, those
        of its local map: `_local_entries`), ratio ``< verify_tau_max`` (default ``tau_max``; the time counts in the
        candidate's ``verify_ms``)."""
        t0 = time.perf_counter()
        local = self._local_entries(e, eligible)
        rows = np.concatenate([self._store.rows(starts[j], starts[j + 1]) for j in local])
        if rows.shape[0] < 2:
            return Retrieved(self._ids[e], score, np.zeros((0, 3)), np.zeros((0, 3)), extra=extra)
        dist, idx = knn2(q, rows, self.params.backend, self.params.nn_threads)
        tau = nn_ratio(dist)
        ok = tau < (self.params.tau_max if self.params.verify_tau_max is None else self.params.verify_tau_max)
        dst = self._local_keypoints(e, local)[idx[ok, 0]]
        ms = (time.perf_counter() - t0) * 1e3
        extra = {**extra, "matches": int(ok.sum()), "verify_ms": ms, "local_entries": len(local)}
        target = partial(self._local_target, local) if len(local) > 1 else None
        return Retrieved(self._ids[e], score, qkp[ok], dst, tau[ok], extra=extra, target=target)

    def _local_entries(self, e: int, eligible: np.ndarray | None = None) -> list[int]:
        """Entry ``e`` first, then the entries (``eligible`` ones only, when given) within ``verify_radius_m`` of
        it, nearest first."""
        r = self.params.verify_radius_m
        if r <= 0:
            return [e]
        centres = self._entry_xyz()
        d = np.linalg.norm(centres - centres[e], axis=1)
        near = d <= r
        if eligible is not None:
            near &= eligible
        near[e] = False
        others = np.flatnonzero(near)
        return [e, *(int(j) for j in others[np.argsort(d[others], kind="stable")])]

    def _local_keypoints(self, e: int, local: Sequence[int]) -> np.ndarray:
        """The keypoints of the entries ``local``, stacked in entry ``e``'s frame."""
        return self._in_frame(e, local, lambda j: self._keypoints[j], np.float32)

    def _in_frame(
        self, e: int, local: Sequence[int], points: Callable[[int], np.ndarray], dtype: type = np.float64
    ) -> np.ndarray:
        """``points(j)`` (in entry ``j``'s frame) of every entry ``j`` of ``local``, moved into entry ``e``'s frame
        by the entries' poses (computed in ``dtype``) and stacked."""
        T_e_world = np.linalg.inv(self._poses[e])
        parts = []
        for j in local:
            T = (T_e_world @ self._poses[j]).astype(dtype)
            parts.append(points(j) @ T[:3, :3].T + T[:3, 3])
        return np.concatenate(parts)

    def _local_target(self, local: Sequence[int]) -> IcpCloud:
        """The ICP target of the local map ``local`` (its first entry's frame): the entries' clouds merged and
        voxelised again at ``icp.voxel_size`` (`as_target`); the last ``local_map_cache`` are kept."""
        key = tuple(int(j) for j in local)
        if key in self._local_targets:
            self._local_targets.move_to_end(key)
            return self._local_targets[key]
        vp = self.params.verify.verify
        merged = self._in_frame(key[0], key, lambda j: self._clouds.cloud(self._ids[j]))
        target = as_target(voxel_points(merged, vp.icp.voxel_size), vp)
        self._local_targets[key] = target
        while len(self._local_targets) > self.params.local_map_cache:
            self._local_targets.popitem(last=False)
        return target

    # -- persistence ----------------------------------------------------------------------------------------
    def save(self, path: str | Path) -> None:
        """Entries (ids, poses, keypoints, descriptors) and the aggregation buffer, with the parameters."""
        arrays, meta = self._state()
        save_artifact(path, _KIND, _VERSION, arrays, meta)

    def _state(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """The arrays (`voting_schema`) and header metadata of a saved database: what `_restore` reads back."""
        buf = self._buffer
        arrays = {
            "ids": np.asarray(self._ids, np.int64),
            "poses": np.asarray(self._poses, np.float64).reshape(-1, 4, 4),
            "counts": np.asarray(self._counts, np.int64),
            "keypoints": _cat(self._keypoints, (0, 3)),
            **self._store.arrays(),
            "buffer_ids": np.asarray([b[0] for b in buf], np.int64),
            "buffer_poses": np.asarray([b[1] for b in buf], np.float64).reshape(-1, 4, 4),
            "buffer_travelled": np.asarray([b[2] for b in buf], np.float64),
            "buffer_counts": np.asarray([b[3].shape[0] for b in buf], np.int64),
            "buffer_xyz": _cat([b[3] for b in buf], (0, 3)),
            "buffer_intensity": _cat([b[4] for b in buf], (0,)),
        }
        if self.params.verify.enabled:
            arrays.update(self._clouds.arrays(self._ids))
        meta = {
            "params": self.params.model_dump(mode="json"),
            "travelled": self._travelled,
            "descriptor_store": self._store.dtype,
        }
        return arrays, meta

    def load(self, path: str | Path) -> None:
        arrays, header = load_artifact(path, _KIND, _READ_VERSIONS, voting_schema(self._dim))
        self._restore(path, arrays, header)

    def _restore(self, path: str | Path, arrays: Mapping[str, np.ndarray], header: Mapping[str, Any]) -> None:
        """Replace the database by a loaded one (`_state`'s arrays, checked against `voting_schema`);
        `ArtifactError` if it was made with other parameters or its arrays disagree."""
        check_saved_params(path, dict(header), self.params)
        travelled = _check_saved(path, arrays, header["meta"])
        store = DescriptorStore.from_arrays(
            arrays, header["meta"].get("descriptor_store", "float32"), self._dim, path
        )
        self._reset()
        self._map_poses = None
        kp = np.split(arrays["keypoints"], np.cumsum(arrays["counts"])[:-1]) if len(arrays["ids"]) else []
        self._store = store
        self._row_entry = np.repeat(np.arange(len(arrays["ids"]), dtype=np.int32), arrays["counts"])
        self._ids = [int(i) for i in arrays["ids"]]
        self._idset = set(self._ids)
        self._sorted = bool(np.all(np.diff(arrays["ids"]) > 0))
        self._poses = list(arrays["poses"])
        self._counts = [int(c) for c in arrays["counts"]]
        self._keypoints = list(kp)
        if self.params.verify.enabled:
            if "cloud_xyz" not in arrays:
                raise ArtifactError(f"{path}: database saved without the clouds verification needs")
            self._clouds.from_arrays(self._ids, arrays, path)
        cuts = np.cumsum(arrays["buffer_counts"])[:-1]
        self._buffer = list(
            zip(
                (int(i) for i in arrays["buffer_ids"]),
                arrays["buffer_poses"],
                (float(t) for t in arrays["buffer_travelled"]),
                np.split(arrays["buffer_xyz"], cuts) if len(arrays["buffer_ids"]) else [],
                np.split(arrays["buffer_intensity"], cuts) if len(arrays["buffer_ids"]) else [],
                strict=False,
            )
        )
        self._travelled = travelled
        if self.params.places_db is not None:
            db = PlacesDatabase.load(self.params.places_db, features=self._features, mmap=True)
            self._map_poses = np.array(db.scan_poses)

    def __len__(self) -> int:
        return len(self._ids)


def _icp_cloud(clouds: Sequence[tuple[np.ndarray, np.ndarray]], k: int, params: VerifyParams) -> np.ndarray:
    """The ICP cloud (`scan_cloud`) of place ``k``'s stored cloud."""
    return scan_cloud(clouds[k][0], params)


def _cat(parts: list[np.ndarray], empty: tuple[int, ...]) -> np.ndarray:
    return np.concatenate(parts).astype(np.float32) if parts else np.zeros(empty, np.float32)


def voting_schema(dim: int) -> dict[str, Member]:
    """The arrays of a saved database: entries (ids, poses, per-entry counts of keypoint/descriptor rows) and
    the aggregation buffer (ids, poses, travelled distance, per-scan counts of cloud points)."""
    return {
        "ids": Member("iu", ("n_entries",)),
        "poses": Member("f", ("n_entries", 4, 4), finite=True),
        "counts": Member("iu", ("n_entries",), min_value=0),
        "keypoints": Member("f", ("n_rows", 3), finite=True),
        "descriptors": Member("fu", ("n_rows", dim), finite=True),
        "sq_vmin": Member("f", (dim,), optional=True, finite=True),
        "sq_vdiff": Member("f", (dim,), optional=True, finite=True),
        "buffer_ids": Member("iu", ("n_buffer",)),
        "buffer_poses": Member("f", ("n_buffer", 4, 4), finite=True),
        "buffer_travelled": Member("f", ("n_buffer",), finite=True),
        "buffer_counts": Member("iu", ("n_buffer",), min_value=0),
        "buffer_xyz": Member("f", ("n_points", 3), finite=True),
        "buffer_intensity": Member("f", ("n_points",), finite=True),
        "cloud_counts": Member("iu", ("n_entries",), optional=True, min_value=0),
        "cloud_xyz": Member("f", ("n_cloud", 3), optional=True, finite=True),
    }


def _check_saved(path: str | Path, arrays: Mapping[str, np.ndarray], meta: Mapping[str, Any]) -> float:
    """What `voting_schema` cannot state: unique ids, counts adding up to their rows, the distance travelled (a finite
    number >= 0, reached by the buffer's non-decreasing distances); returns that distance."""
    check_unique(arrays["ids"], path, "ids")
    check_unique(arrays["buffer_ids"], path, "buffer_ids")
    check_counts(arrays["counts"], arrays["descriptors"].shape[0], path, "counts")
    check_counts(arrays["buffer_counts"], arrays["buffer_xyz"].shape[0], path, "buffer_counts")
    travelled = meta.get("travelled", 0.0)
    along = arrays["buffer_travelled"]
    if (
        not isinstance(travelled, int | float)
        or isinstance(travelled, bool)
        or not 0 <= travelled < np.inf
        or (along.size and (along.min() < 0 or along.max() > travelled or (np.diff(along) < 0).any()))
    ):
        raise ArtifactError(
            f"{path}: 'travelled' {short_repr(travelled)} and 'buffer_travelled' must be distances: finite, "
            ">= 0, non-decreasing along the buffer and at most 'travelled'"
        )
    return float(travelled)
