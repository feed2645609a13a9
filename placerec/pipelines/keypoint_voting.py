"""The 3D pipeline: ISS-BR keypoints + ISHOT (or SHOT/FPFH) descriptors, ratio-tested NN votes per entry.

For every query descriptor the two nearest database descriptors (exact L2: brute force, or pruned by a bound with
``search.index: pca``, `placerec.retrieval.nearest.ProjectedIndex`; or approximate with ``search.index: ivf``,
`placerec.retrieval.nearest.IvfIndex`) give the ratio ``tau = d1 / d2`` (ISHOT paper, eq. 4);
when ``tau < tau_max`` the query descriptor votes for the entry its 1st neighbour belongs to. Candidates are
the entries with most votes. The paper has no hard ratio threshold (its votes are weighted by a model per tau
range); 0.9 was chosen in a localisation sweep on the simulator (docs/benchmarks.md, component figures). The
descriptors live in a `placerec.retrieval.descriptor_store.DescriptorStore` (``search.descriptor_store``: float32,
float16 or sq8 8-bit codes, searched without decoding; a places database's own store by default, float32 for
entries added scan by scan).

`KeypointVoting` is also the base of the other 3D pipelines: it holds the front end, the entries
(`placerec.three_d.entries.EntryTable`), their ICP clouds, place aggregation and persistence, and answers a
query with the shared loop of `placerec.pipelines.voting_engine` and its strategy (``Strategy``: here
`RatioVotes`).

Score (what thresholds apply to): ``score="fraction"`` (default) is votes / number of query descriptors, in
[0, 1]; ``score="votes"`` the raw vote count; with verification the verified score instead.

Verification (``verify.enabled``, ISHOT paper Sec. IV-F; `placerec.verify.candidates`): the description keeps
the scan voxelised for ICP (``cloud``), the database each entry's cloud. The ``verify.top_k`` most-voted
entries are matched with the query alone (2-NN among the entry's descriptors, ratio ``< verify.tau_max``),
then go through the paper's geometric consistency grouping (consensus resolution 7 m, minimum cluster 8),
RANSAC and point-to-plane ICP; ``relative_pose`` is the 6-DoF ``T_match_query``, ``score`` the verified score
(``retrieval_score`` the vote score), and a candidate is accepted when its ICP residual is below the paper's
eps_ICP (7 m^2). With ``verify.radius_m > 0`` a candidate is verified as a local map
(`placerec.pipelines.local_maps`). The measured effect of ``top_k`` and the acceptance rules is in
docs/benchmarks.md (component figures).

Entries:

* default (``places.spacing_m = 0``, ``places.window_m = 0``): every added scan is one entry, described alone;
  match ids are scan ids, which is what the loop and localize evaluators expect.
* ``places.window_m > 0``: an entry is described from the scans within that much travel before it, merged in
  its frame (`placerec.pipelines.place_window`). The paper queries such places with dense static scans; single
  sweeps match them poorly (docs/descriptors.md), so keep 0 when queries are single sweeps.
* ``places.spacing_m > 0``: only scans at least that far from every earlier entry become entries
  (`placerec.three_d.entries.far_from_all`, the rule of the offline places database); ids stay scan ids.
* ``places.database``: a `placerec.three_d.places.PlacesDatabase` file replaces the entries; its place ids are the
  map's scan indices. ``add`` then only checks that a scan with that id and pose is part of the map the
  database was built from (`ArtifactError` otherwise).
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping
from functools import partial
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from placerec.errors import ArtifactError, ScanDataError
from placerec.intensity import normalize_intensity
from placerec.io.artifact_schema import Member, check_counts, check_unique
from placerec.io.atomic import load_artifact, save_artifact
from placerec.params import Params, deep_merge
from placerec.pipelines.local_maps import LocalMaps
from placerec.pipelines.place_window import WINDOW_SCHEMA, PlaceWindow
from placerec.pipelines.voting_engine import Query, Shortlist, VoteStrategy, run_query
from placerec.pipelines.voting_params import VotingParams
from placerec.recognizer import (
    Recognizer,
    check_saved_params,
    params_key,
    require_points,
    require_varying_intensity,
)
from placerec.retrieval.descriptor_store import DescriptorStore, StoreView, knn, knn2
from placerec.retrieval.nearest import IvfIndex, ProjectedIndex, nn_ratio, ratio_votes
from placerec.three_d.descriptors import DESCRIPTOR_DIMS
from placerec.three_d.entries import EntryTable, far_from_all
from placerec.three_d.features import extract_features
from placerec.three_d.places import PlacesDatabase
from placerec.types import Candidate, Description, MotionPrior, Scan, as_pose
from placerec.verify.candidates import CloudStore, Retrieved, scan_cloud
from placerec.verify.params import VerifyParams

log = logging.getLogger(__name__)

__all__ = [
    "VotingParams",
    "KeypointVoting",
    "RatioVotes",
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


class RatioVotes(VoteStrategy["KeypointVoting"]):
    """Vote counting: every keypoint matched at once; each whose ratio ``tau < tau_max`` votes for its nearest
    neighbour's entry; the most voted entries (ties: lower id) are the candidates."""

    def vote(self, batch: np.ndarray) -> None:
        qr = self.query
        dist, idx = self.rec.search(qr.q[batch], qr.rows)
        self.votes = ratio_votes(dist, idx, qr.row_entry, qr.n_entries, self.rec.params.search.tau_max)
        self.matched += batch.size

    def fallback(self) -> Shortlist:
        votes, ids = self.votes, np.asarray(self.rec.entries.ids)
        top = np.flatnonzero(votes)
        scale = 1.0 / self.n if self.rec.params.score == "fraction" else 1.0
        return Shortlist(
            top[np.lexsort((ids[top], -votes[top]))],
            score=lambda e: float(votes[e] * scale),
            extra=lambda e: {"votes": int(votes[e]), "n_query": self.n},
        )


class KeypointVoting(Recognizer[VotingParams]):
    """`PlaceRecognizer`: 3D local descriptors, 2-NN ratio test, vote counting (see the module docstring)."""

    name: ClassVar[str] = "keypoint-voting"
    Params: ClassVar[type[Params]] = VotingParams
    #: how a query ranks the entries (`placerec.pipelines.voting_engine`)
    Strategy: ClassVar[type[VoteStrategy[Any]]] = RatioVotes

    def __init__(self, params: VotingParams | None = None, **overrides: Any) -> None:
        super().__init__(params, **overrides)
        p = self.params
        self._features = p.features
        self._dim = DESCRIPTOR_DIMS[p.features.descriptor]
        self._warned = False
        self._reset()
        if p.places.database is not None:
            self.use_places(PlacesDatabase.load(p.places.database, features=self._features, mmap=True))

    def _reset(self, entries: EntryTable | None = None) -> None:
        p = self.params
        self.entries = entries or EntryTable.empty(self._dim, p.search.descriptor_store or "float32")
        self.clouds = CloudStore.for_pipeline(p.verify)
        self.local_maps = LocalMaps(
            self.entries, self.clouds, p.verify.radius_m, p.verify.local_map_cache, p.verify
        )
        self.window = PlaceWindow(p.places.window_m, self.name)
        #: the scan poses of the map a places database was built from
        self._map_poses: np.ndarray | None = None
        self._derived: dict[str, tuple[int, Any]] = {}

    def derived(self, name: str, build: Any) -> Any:
        """What ``build()`` makes from the entries, kept until they change (an index, vote vectors, ...)."""
        version = self.entries.version
        got = self._derived.get(name)
        if got is None or got[0] != version:
            got = (version, build())
            self._derived[name] = got
        return got[1]

    # -- construction from a places database ----------------------------------------------------------------
    @classmethod
    def from_places(cls, db: PlacesDatabase, **overrides: Any) -> KeypointVoting:
        """A recognizer serving ``db`` (its feature settings are taken; `ArtifactError` if ``overrides`` change
        them)."""
        rec = cls(**deep_merge({"features": db.params.features.model_dump()}, overrides))
        rec.use_places(db)
        return rec

    def use_places(self, db: PlacesDatabase) -> None:
        """Replace the entries by the places of ``db`` (ids = place ids, poses = place poses). The descriptors are
        served from the database's store as it is (shared, not copied) unless ``search.descriptor_store`` asks for another
        kind; a place's ICP cloud is made from its stored cloud when a query first verifies it (a database loaded
        from ``places.database`` is memory-mapped, so its clouds take no RAM until then)."""
        db.check_features(self._features)
        self._reset(db.entry_table(self.params.search.descriptor_store))
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
            for k, i in enumerate(self.entries.ids):
                self.clouds.add_deferred(i, partial(_icp_cloud, db.clouds, k, self.params.verify))
        self._map_poses = np.array(db.scan_poses)

    # -- front end -------------------------------------------------------------------------------------------
    @property
    def frontend_key(self) -> str:
        p = self.params
        icp = p.verify.icp
        return params_key(
            "keypoint-voting",
            {
                "features": self._features.model_dump(mode="json"),
                "cloud": p.places.window_m > 0,
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
        and its scores would not be comparable with those of scans with intensity. SHOT and FPFH ignore intensity
        and take such scans."""
        ok = require_points(scan, self.name)
        if self.params.features.descriptor == "ishot":
            why = "ISHOT's intensity signature needs varying intensity (pipeline shot-votes takes scans without it)"
            require_varying_intensity(scan, ok, self.name, why)
        scan = self._normalised(scan)
        cloud = scan_cloud(scan, self.params.verify)
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
        if self.params.places.window_m > 0:
            out["cloud_xyz"] = lf.points.astype(np.float32)
            out["cloud_intensity"] = lf.intensity.astype(np.float32)
        return out

    # -- database --------------------------------------------------------------------------------------------
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
            self.clouds.add(scan_id, cloud)
        self.entries.append(scan_id, pose, keypoints, desc)

    def add_description(self, scan_id: int, description: Description, pose: np.ndarray | None = None) -> None:
        scan_id = int(scan_id)
        p = self.params
        if self._map_poses is not None:
            self._check_map_scan(scan_id, pose)
            return
        if scan_id in self.entries:
            raise ScanDataError(f"{self.name}: id {scan_id} was added already")
        if p.places.window_m <= 0 and p.places.spacing_m <= 0:
            self._add_entry(
                scan_id, description["keypoints"], description["descriptors"], pose, description.get("cloud")
            )
            return
        if pose is None:
            raise ScanDataError(
                f"{self.name}: places.spacing_m/places.window_m need the pose of every added scan"
            )
        T = as_pose(pose)
        if p.places.window_m > 0:
            self.window.push(scan_id, T, description)
        if p.places.spacing_m > 0 and not far_from_all(self.entries.xyz(), T[:3, 3], p.places.spacing_m):
            return
        cloud: np.ndarray | None
        if p.places.window_m > 0:
            kp, desc, cloud = self._describe_window(T)
        else:
            kp, desc, cloud = description["keypoints"], description["descriptors"], description.get("cloud")
        self._add_entry(scan_id, kp, desc, T, cloud)

    def _describe_window(self, T_world_place: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Keypoints, descriptors and ICP cloud of the place accumulated in the window, in its frame."""
        cloud = self.window.cloud(T_world_place)
        icp_cloud = scan_cloud(cloud, self.params.verify)
        try:
            lf = extract_features(cloud, self._features)
        except ScanDataError as exc:
            log.warning("%s", exc)
            return np.zeros((0, 3), np.float32), np.zeros((0, self._dim), np.float32), icp_cloud
        return lf.keypoints, lf.descriptors, icp_cloud

    def _check_map_scan(self, scan_id: int, pose: np.ndarray | None) -> None:
        sp = self._map_poses
        assert sp is not None
        if not 0 <= scan_id < sp.shape[0]:
            raise ArtifactError(
                f"{self.name}: scan {scan_id} is not part of the map the places database was built from"
            )
        if pose is not None and not np.allclose(as_pose(pose), sp[scan_id], atol=1e-6):
            raise ArtifactError(f"{self.name}: scan {scan_id}'s pose differs from the places database's map")

    # -- query ------------------------------------------------------------------------------------------------
    def query_description(
        self,
        description: Description,
        k: int = 1,
        max_id: int | None = None,
        query_id: int = -1,
        prior: MotionPrior | None = None,
    ) -> list[Candidate]:
        q = np.asarray(description["descriptors"], np.float32).reshape(-1, self._dim)
        qkp = np.asarray(description["keypoints"], np.float32).reshape(-1, 3)
        rows, row_entry, n_entries = self.entries.eligible(max_id)
        eligible = self.entries.eligible_mask(max_id)
        query = Query(description, q, qkp, rows, row_entry, n_entries, eligible, query_id, k)
        return run_query(self, self.Strategy, query)

    def search(self, q: np.ndarray, rows: StoreView) -> tuple[np.ndarray, np.ndarray]:
        """2-NN of ``q`` among ``rows`` (the eligible database rows, `StoreView.knn2`), or with every row eligible
        and ``search.index`` "ivf" or "pca", the `IvfIndex` / `ProjectedIndex` over the database (built on first use
        after the entries change)."""
        p = self.params
        store = self.entries.store
        if p.search.index != "flat" and rows.shape[0] == len(store):
            build = {
                "ivf": lambda: IvfIndex(store, p.search.ivf_nlist, p.search.ivf_nprobe, p.search.nn_threads),
                "pca": lambda: ProjectedIndex(store, p.search.pca_dims),
            }[p.search.index]
            return self.derived(p.search.index, build).knn2(q)
        return rows.knn2(q, p.search.backend, p.search.nn_threads)

    def pick(self, ranked: Iterable[Any], taken: Iterable[int], k: int) -> list[int]:
        """The first ``k`` entries of ``ranked`` (entry indices, best first) not in ``taken``, skipping those within
        ``verify.separation_m`` of an entry taken before (``taken`` and the ones picked here)."""
        sep = self.params.verify.separation_m
        done = [int(e) for e in taken]
        picked: list[int] = []
        for e in ranked:
            e = int(e)
            if len(picked) == k:
                break
            if e in done:
                continue
            if sep > 0 and done:
                xyz = self.entries.xyz()
                if np.min(np.linalg.norm(xyz[done] - xyz[e], axis=1)) < sep:
                    continue
            picked.append(e)
            done.append(e)
        return picked

    def local_matches(self, e: int, query: Query, score: float, extra: dict[str, Any]) -> Retrieved:
        """Entry ``e``'s correspondences with the query, over its local map (`LocalMaps.matches`)."""
        p = self.params
        tau = p.search.tau_max if p.verify.tau_max is None else p.verify.tau_max
        return self.local_maps.matches(
            e, query.q, query.qkp, score, extra, tau, p.search.backend, p.search.nn_threads, query.eligible
        )

    # -- persistence ----------------------------------------------------------------------------------------
    def save(self, path: str | Path) -> None:
        """Entries (ids, poses, keypoints, descriptors) and the aggregation window, with the parameters."""
        arrays, meta = self._state()
        save_artifact(path, _KIND, _VERSION, arrays, meta)

    def _state(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """The arrays (`voting_schema`) and header metadata of a saved database: what `_restore` reads back."""
        arrays = {**self.entries.arrays(), **self.window.arrays()}
        if self.params.verify.enabled:
            arrays.update(self.clouds.arrays(self.entries.ids))
        meta = {
            "params": self.params.saved_dump(),
            "travelled": self.window.travelled,
            "descriptor_store": self.entries.store.dtype,
        }
        return arrays, meta

    def load(self, path: str | Path) -> None:
        arrays, header = load_artifact(path, _KIND, _READ_VERSIONS, voting_schema(self._dim))
        self._restore(path, arrays, header)

    def _restore(self, path: str | Path, arrays: Mapping[str, np.ndarray], header: Mapping[str, Any]) -> None:
        """Replace the database by a loaded one (`_state`'s arrays, checked against `voting_schema`);
        `ArtifactError` if it was made with other parameters or its arrays disagree."""
        check_saved_params(path, dict(header), self.params)
        check_unique(arrays["ids"], path, "ids")
        check_counts(arrays["counts"], arrays["descriptors"].shape[0], path, "counts")
        window = PlaceWindow(self.params.places.window_m, self.name)
        window.restore(path, arrays, header["meta"])
        store = DescriptorStore.from_arrays(
            arrays, header["meta"].get("descriptor_store", "float32"), self._dim, path
        )
        self._reset(EntryTable.from_arrays(arrays, store, path))
        if self.params.verify.enabled:
            if "cloud_xyz" not in arrays:
                raise ArtifactError(f"{path}: database saved without the clouds verification needs")
            self.clouds.from_arrays(self.entries.ids, arrays, path)
        self.window = window
        if self.params.places.database is not None:
            db = PlacesDatabase.load(self.params.places.database, features=self._features, mmap=True)
            self._map_poses = np.array(db.scan_poses)

    def __len__(self) -> int:
        return len(self.entries)


def _icp_cloud(clouds: Any, k: int, params: VerifyParams) -> np.ndarray:
    """The ICP cloud (`scan_cloud`) of place ``k``'s stored cloud."""
    return scan_cloud(clouds[k][0], params)


def voting_schema(dim: int) -> dict[str, Member]:
    """The arrays of a saved database: entries (ids, poses, per-entry counts of keypoint/descriptor rows), the
    aggregation window (`WINDOW_SCHEMA`) and the entries' ICP clouds."""
    return {
        "ids": Member("iu", ("n_entries",)),
        "poses": Member("f", ("n_entries", 4, 4), finite=True),
        "counts": Member("iu", ("n_entries",), min_value=0),
        "keypoints": Member("f", ("n_rows", 3), finite=True),
        "descriptors": Member("fu", ("n_rows", dim), finite=True),
        "sq_vmin": Member("f", (dim,), optional=True, finite=True),
        "sq_vdiff": Member("f", (dim,), optional=True, finite=True),
        **WINDOW_SCHEMA,
        "cloud_counts": Member("iu", ("n_entries",), optional=True, min_value=0),
        "cloud_xyz": Member("f", ("n_cloud", 3), optional=True, finite=True),
    }
