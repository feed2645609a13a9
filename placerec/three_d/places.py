"""The global places database of the ISHOT paper (Sec. IV-B): a mapping sequence cut into described places.

A map is partitioned into places along the trajectory that made it. Place centres are mapping scans at least
``spacing_m`` metres from every earlier centre (greedy, in acquisition order, so a revisit adds no place
where one exists already). A place holds the points of every scan within ``window_m`` metres of travelled
distance (and, optionally, ``window_s`` seconds) of its centre scan, i.e. a contiguous stretch of one pass, in
the SLAM sense; ``member_spacing`` thins those scans to one per that many metres of travel (the same scans for
every place, so overlapping places share them). With the spacing well below the LiDAR range and a window wider
than the spacing, neighbouring places overlap.

Each place's points are mapped into the place frame (``T_world_place`` = the centre scan's pose), cropped and
voxelised with averaged intensity, and described with `placerec.three_d.extract_features` (ISS-BR keypoints +
SHOT/ISHOT/FPFH). The paper gives no numbers for spacing or window; ours (5 m, +-10 m of travel) are chosen so
that a place spans about the 40 m descriptor range of a single scan along the road while places overlap by
three quarters.

`PlacesDatabase` stores the place ids (= centre scan index in the mapping sequence, so the ids index into the
map's poses), place poses, source scans, keypoints (place frame), descriptors and, optionally, the voxelised
place clouds (for later verification), in an atomic versioned artifact (kind ``places-db``, version 4) with the
parameters that made it; `PlacesDatabase.load` refuses a file made with other feature settings.

Compact storage (docs/localization.md, 'The places database's size'): ``descriptor_store`` keeps the descriptors
as float32, float16 or sq8 (one byte per dimension, `placerec.retrieval.descriptor_store`), searched in that form;
``cloud_store = "int16"`` saves each place cloud as int16 fixed point around its centre
(`placerec.quantise.FixedPointCloud`, with ``cloud_centre`` / ``cloud_scale``) and its intensities as uint8.
Versions 3 and 4 record both in the header (``descriptor_store``, ``cloud_store``) and `load` checks every array's
dtype against them; version 4 names the spacing ``spacing_m``, as the 3D pipelines' ``places`` section does.
Versions 1 to 3 (``place_spacing``; 1 and 2 float32 throughout; version 1's feature settings hold an empty
``descriptor_options`` list instead of the ``shot`` / ``fpfh`` sections) are read too.
"""

from __future__ import annotations

from collections.abc import Iterable
from collections.abc import Sequence as SequenceABC
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field

from placerec.errors import ArtifactError, ConfigError, ScanDataError, short_repr
from placerec.io.artifact_schema import Member, check_counts, check_offsets, check_unique
from placerec.io.atomic import load_artifact, save_artifact
from placerec.params import Params, resolve
from placerec.quantise import FixedPointCloud, decode_unit, encode_unit
from placerec.retrieval.descriptor_store import DescriptorStore, StoreDtype
from placerec.three_d.entries import EntryTable, far_from_all
from placerec.three_d.features import FeatureParams
from placerec.types import MAX_TRANSLATION_M, Scan, path_length, rigid_problem

__all__ = [
    "PlacesParams",
    "PlacePartition",
    "PlacesDatabase",
    "partition_places",
    "place_cloud",
    "merge_clouds",
    "features_json",
]

KIND = "places-db"
FORMAT_VERSION = 4
_READ_VERSIONS = (1, 2, 3, 4)
# the arrays of a saved database; n_places, n_rows (keypoints), n_sources and n_cloud (points) tie them together
_SCHEMA = {
    "ids": Member("iu", ("n_places",), min_value=0),
    "poses": Member("f", ("n_places", 4, 4), finite=True),
    "source_counts": Member("iu", ("n_places",), min_value=0),
    "sources": Member("iu", ("n_sources",), min_value=0),
    "kp_offsets": Member("iu", (None,)),
    "keypoints": Member("f", ("n_rows", 3), finite=True),
    "descriptors": Member("fu", ("n_rows", None), finite=True),
    "sq_vmin": Member("f", (None,), optional=True, finite=True),
    "sq_vdiff": Member("f", (None,), optional=True, finite=True),
    "scan_poses": Member("f", ("n_scans", 4, 4), finite=True),
    "cloud_counts": Member("iu", ("n_places",), optional=True, min_value=0),
    "cloud_xyz": Member("fi", ("n_cloud", 3), optional=True, finite=True),
    "cloud_intensity": Member("fu", ("n_cloud",), optional=True, finite=True, min_value=0),
    "cloud_centre": Member("f", ("n_places", 3), optional=True, finite=True),
    "cloud_scale": Member("f", ("n_places",), optional=True, finite=True, min_value=0),
}
#: the arrays of each cloud store besides ``cloud_counts``, and their dtypes
_CLOUD_ARRAYS: dict[str, dict[str, type[np.generic]]] = {
    "float32": {"cloud_xyz": np.float32, "cloud_intensity": np.float32},
    "int16": {
        "cloud_xyz": np.int16,
        "cloud_intensity": np.uint8,
        "cloud_centre": np.float64,
        "cloud_scale": np.float64,
    },
}


class PlacesParams(Params):
    """How a mapping sequence becomes places (see the module docstring) and how places are described."""

    spacing_m: float = Field(5.0, ge=0, description="m between place centres (ISHOT paper Sec. IV-B)")
    window_m: float = Field(10.0, ge=0, description="m travelled merged into a place (ISHOT paper Sec. IV-B)")
    window_s: float | None = Field(None, ge=0, description="s of acquisition merged instead (None = off)")
    member_spacing: float = Field(2.0, ge=0, description="m between the scans merged into a place")
    store_clouds: bool = Field(True, description="keep each place's cloud in the database")
    descriptor_store: StoreDtype = Field(
        "sq8",
        description="descriptors kept and searched as sq8 (8-bit codes, 1 byte a dimension: a quarter of float32, "
        "localisation success within 2 points of float32, docs/localization.md), float16 or float32",
    )
    cloud_store: Literal["float32", "int16"] = Field(
        "int16",
        description="place clouds saved as int16 fixed point (intensity as uint8; error at most half a step, 0.6 mm "
        "within 40 m), or float32",
    )
    features: FeatureParams = Field(default_factory=FeatureParams)


@dataclass(frozen=True)
class PlacePartition:
    """Place centres (scan indices, ascending) and each place's member scans (ascending, centre included)."""

    centres: np.ndarray
    members: list[np.ndarray]

    def __len__(self) -> int:
        return int(self.centres.shape[0])


def features_json(features: FeatureParams) -> Any:
    """The feature settings as plain JSON (what a database records and is checked against)."""
    return features.model_dump(mode="json")


def partition_places(
    poses: np.ndarray, timestamps: np.ndarray | None, params: PlacesParams
) -> PlacePartition:
    """Place centres at least ``spacing_m`` apart (greedy in order) and their time/space windows."""
    P = np.asarray(poses, dtype=np.float64)
    if P.ndim != 3 or P.shape[1:] != (4, 4) or P.shape[0] == 0:
        raise ScanDataError(f"places: poses must have shape (N, 4, 4) with N > 0, got {P.shape}")
    if params.window_s is not None and timestamps is None:
        raise ConfigError("places: window_s needs a sequence with timestamps")
    xyz = P[:, :3, 3]
    centres: list[int] = []
    for i in range(xyz.shape[0]):
        if far_from_all(xyz[centres], xyz[i], params.spacing_m):
            centres.append(i)
    s = path_length(xyz)
    if params.member_spacing > 0:
        bins = np.floor(s / params.member_spacing).astype(np.int64)
        cand = np.flatnonzero(np.r_[True, bins[1:] != bins[:-1]])
    else:
        cand = np.arange(xyz.shape[0])
    c = np.asarray(centres, dtype=np.int64)
    lo = np.searchsorted(s[cand], s[c] - params.window_m, side="left")
    hi = np.searchsorted(s[cand], s[c] + params.window_m, side="right")
    t = None if timestamps is None else np.asarray(timestamps, dtype=np.float64)
    members = []
    for ci, a, b in zip(c, lo, hi, strict=True):
        m = cand[a:b]
        if params.window_s is not None and t is not None:
            m = m[np.abs(t[m] - t[ci]) <= params.window_s]
        members.append(np.union1d(m, [ci]).astype(np.int64))
    return PlacePartition(c, members)


def merge_clouds(T_world_frame: np.ndarray, parts: Iterable[tuple[np.ndarray, Scan]], source: str) -> Scan:
    """One cloud in the frame ``T_world_frame``: the points of every ``(T_world_scan, scan)`` pair (scans in their
    sensor frames) mapped into it and concatenated, with their intensities (and rings when every scan has them);
    the sensor is the first scan's."""
    parts = list(parts)
    if not parts:
        raise ScanDataError(f"{source}: no scans to merge")
    T_frame_world = np.linalg.inv(T_world_frame)
    xyz = []
    for T_world_scan, scan in parts:
        T = T_frame_world @ T_world_scan
        xyz.append(scan.xyz.astype(np.float64) @ T[:3, :3].T + T[:3, 3])
    rings = [scan.ring for _, scan in parts if scan.ring is not None]
    return Scan(
        np.concatenate(xyz),
        np.concatenate([scan.intensity for _, scan in parts]),
        ring=np.concatenate(rings) if len(rings) == len(parts) else None,
        sensor=parts[0][1].sensor,
        source=source,
    )


def place_cloud(scans: dict[int, Scan], poses: np.ndarray, centre: int, members: np.ndarray) -> Scan:
    """The member scans' points (already prepared, sensor frames) mapped into the centre scan's frame."""
    return merge_clouds(poses[centre], [(poses[j], scans[int(j)]) for j in members], f"place@{centre}")


@dataclass
class PlacesDatabase:
    """Described places of one mapping sequence (see the module docstring). Rows of ``keypoints`` and
    ``descriptors`` of place ``p`` are ``kp_offsets[p]:kp_offsets[p + 1]``; keypoints are in the place frame.
    ``descriptors`` is a `DescriptorStore` (a float32 array given here is wrapped in one)."""

    ids: np.ndarray
    poses: np.ndarray
    sources: list[np.ndarray]
    kp_offsets: np.ndarray
    keypoints: np.ndarray
    descriptors: DescriptorStore
    params: PlacesParams
    scan_poses: np.ndarray
    clouds: SequenceABC[tuple[np.ndarray, np.ndarray]] | None = None
    intensity: str = "sensor-default"
    sequence: str = ""

    def __post_init__(self) -> None:
        if not isinstance(self.descriptors, DescriptorStore):
            self.descriptors = DescriptorStore.from_rows(np.asarray(self.descriptors, np.float32))

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    @property
    def descriptor(self) -> str:
        return self.params.features.descriptor

    @property
    def row_place(self) -> np.ndarray:
        """The place index (0..P-1) of every descriptor row."""
        return np.repeat(np.arange(len(self)), np.diff(self.kp_offsets))

    def place_features(self, p: int) -> tuple[np.ndarray, np.ndarray]:
        """(keypoints, descriptors) of place index ``p``."""
        a, b = self.kp_offsets[p], self.kp_offsets[p + 1]
        return self.keypoints[a:b], self.descriptors.rows(a, b)

    def entry_table(self, descriptor_store: str | None = None) -> EntryTable:
        """The places as the entries of a 3D pipeline (ids, poses, keypoints in the place frames), their descriptors
        served from this database's store as it is (shared, not copied), or converted to ``descriptor_store``."""
        store = self.descriptors if descriptor_store is None else self.descriptors.converted(descriptor_store)
        kp = [self.keypoints[a:b] for a, b in zip(self.kp_offsets[:-1], self.kp_offsets[1:], strict=True)]
        return EntryTable.of(store, self.ids, self.poses, np.diff(self.kp_offsets), kp)

    def stored_as(self, descriptor_store: str, cloud_store: str | None = None) -> PlacesDatabase:
        """The same places with the descriptors (and the clouds when saved) in another store: an sq8 store is
        fitted on every descriptor, as `build_places` would fit it."""
        params = self.params.model_copy(
            update={
                "descriptor_store": descriptor_store,
                "cloud_store": cloud_store or self.params.cloud_store,
            }
        )
        return replace(self, descriptors=self.descriptors.converted(descriptor_store), params=params)

    def check_features(self, features: FeatureParams, where: str = "places database") -> None:
        """`ArtifactError` unless the database was described with ``features``."""
        if features_json(self.params.features) != features_json(features):
            raise ArtifactError(
                f"{where} was made with other feature settings: {features_json(self.params.features)} "
                f"(expected {features_json(features)})"
            )

    def save(self, path: str | Path) -> None:
        counts = np.array([len(s) for s in self.sources], dtype=np.int64)
        arrays: dict[str, np.ndarray] = {
            "ids": self.ids.astype(np.int64),
            "poses": self.poses.astype(np.float64),
            "source_counts": counts,
            "sources": np.concatenate(self.sources).astype(np.int64)
            if self.sources
            else np.zeros(0, np.int64),
            "kp_offsets": self.kp_offsets.astype(np.int64),
            "keypoints": self.keypoints.astype(np.float32),
            **self.descriptors.arrays(),
            "scan_poses": self.scan_poses.astype(np.float64),
        }
        if self.clouds is not None:
            arrays.update(_cloud_arrays(self.clouds, self.params.cloud_store))
        meta = {
            "params": self.params.model_dump(mode="json"),
            "descriptor": self.descriptor,
            "dim": int(self.descriptors.shape[1]),
            "intensity": self.intensity,
            "sequence": self.sequence,
            "descriptor_store": self.descriptors.dtype,
            "cloud_store": self.params.cloud_store,
        }
        save_artifact(path, KIND, FORMAT_VERSION, arrays, meta)

    @classmethod
    def load(
        cls,
        path: str | Path,
        features: FeatureParams | None = None,
        intensity: str | None = None,
        mmap: bool = False,
    ) -> PlacesDatabase:
        """Read a database; `ArtifactError` if the file is corrupt or inconsistent (`_check_layout`), or if
        ``features`` (or the ``intensity`` label) differ from the file's. ``mmap``: the arrays are memory maps of
        the file (`load_artifact`), so a float32 store is searched from the page cache and only what is decoded
        or copied (sq8 and float16 codes go into faiss) takes RAM. int16 clouds are decoded one place at a time
        when read."""
        arrays, header = load_artifact(path, KIND, _READ_VERSIONS, _SCHEMA, mmap=mmap)
        meta = header["meta"]
        _check_layout(arrays, meta, path)
        store = DescriptorStore.from_arrays(
            arrays, meta.get("descriptor_store", "float32"), arrays["descriptors"].shape[1], path
        )
        try:
            params = _read_params(meta["params"], header["format_version"])
            src = np.split(arrays["sources"], np.cumsum(arrays["source_counts"])[:-1])
            clouds = None
            if "cloud_counts" in arrays:
                clouds = _read_clouds(arrays)
            db = cls(
                ids=arrays["ids"],
                poses=arrays["poses"],
                sources=list(src) if len(arrays["ids"]) else [],
                kp_offsets=arrays["kp_offsets"],
                keypoints=arrays["keypoints"],
                descriptors=store,
                params=params,
                scan_poses=arrays["scan_poses"],
                clouds=clouds if len(arrays["ids"]) else ([] if clouds is not None else None),
                intensity=str(meta.get("intensity", "")),
                sequence=str(meta.get("sequence", "")),
            )
        except (KeyError, ValueError, TypeError) as exc:
            raise ArtifactError(f"{path}: malformed places database ({exc})") from exc
        if features is not None:
            db.check_features(features, str(path))
        if intensity is not None and db.intensity != intensity:
            raise ArtifactError(
                f"{path}: places database has intensity {db.intensity!r}, expected {intensity!r}"
            )
        return db


def _read_params(stored: Any, version: int) -> PlacesParams:
    """The stored parameters as `PlacesParams`; a version 1 file's empty ``features.descriptor_options`` (the
    descriptors' defaults) is dropped, anything else there is refused; versions 1-3 call ``spacing_m``
    ``place_spacing``."""
    if version <= 3 and isinstance(stored, dict) and "place_spacing" in stored:
        stored = {("spacing_m" if k == "place_spacing" else k): v for k, v in stored.items()}
    if version == 1 and isinstance(stored, dict) and isinstance(stored.get("features"), dict):
        features = dict(stored["features"])
        if features.pop("descriptor_options", []) != []:
            raise ValueError("version 1 descriptor_options other than [] cannot be read")
        stored = {**stored, "features": features}
    return resolve(PlacesParams, stored, where="stored parameters")


def _check_layout(arrays: dict[str, np.ndarray], meta: dict[str, Any], path: str | Path) -> None:
    """The consistency `_SCHEMA` cannot state: offsets and counts cover their rows, ids are unique scans of the
    map, place poses are their scans' poses, the descriptor size and the clouds agree with the header."""
    n, n_scans = arrays["ids"].shape[0], arrays["scan_poses"].shape[0]
    check_unique(arrays["ids"], path, "ids")
    check_offsets(arrays["kp_offsets"], n, arrays["keypoints"].shape[0], path, "kp_offsets")
    check_counts(arrays["source_counts"], arrays["sources"].shape[0], path, "source_counts")
    for name in ("ids", "sources"):
        if arrays[name].size and arrays[name].max() >= n_scans:
            raise ArtifactError(
                f"{path}: {name!r} refers to scan {arrays[name].max()}, the map has {n_scans}"
            )
    problem = rigid_problem(arrays["scan_poses"])
    if problem is not None:
        raise ArtifactError(f"{path}: 'scan_poses' row {problem[0]} is no rigid motion: {problem[1]}")
    if not np.array_equal(arrays["poses"], arrays["scan_poses"][arrays["ids"]]):
        raise ArtifactError(
            f"{path}: place 'poses' differ from the 'scan_poses' of their centre scans ('ids')"
        )
    if meta.get("dim") != arrays["descriptors"].shape[1]:
        raise ArtifactError(
            f"{path}: descriptors have {arrays['descriptors'].shape[1]} columns, the header says dim="
            f"{short_repr(meta.get('dim'))}"
        )
    kind = meta.get("cloud_store", "float32")
    if kind not in _CLOUD_ARRAYS:
        raise ArtifactError(
            f"{path}: cloud_store {short_repr(kind)} is unknown (expected one of {sorted(_CLOUD_ARRAYS)})"
        )
    names = ("cloud_counts", *_CLOUD_ARRAYS[kind])
    others = [k for k in _SCHEMA if k.startswith("cloud_") and k not in names and k in arrays]
    cloud = [k for k in names if k in arrays]
    if others or (cloud and len(cloud) != len(names)):
        raise ArtifactError(f"{path}: {kind} place clouds need {list(names)}, found {cloud + others}")
    if cloud:
        check_counts(arrays["cloud_counts"], arrays["cloud_xyz"].shape[0], path, "cloud_counts")
        for name, dtype in _CLOUD_ARRAYS[kind].items():
            if arrays[name].dtype != dtype:
                raise ArtifactError(
                    f"{path}: {name!r} is {arrays[name].dtype}, expected {np.dtype(dtype)} for {kind} clouds"
                )
        _check_cloud_values(arrays, path)


#: Largest float32 place-cloud intensity: clouds hold intensity normalised to [0, 1] (uint8 codes 0-255 map there).
_MAX_CLOUD_INTENSITY = 1.0 + 1e-6


def _check_cloud_values(arrays: dict[str, np.ndarray], path: str | Path) -> None:
    """Values of the place clouds the schema does not bound: float32 intensities within [0, 1] (NaN and negative
    ones the schema refuses), int16 clouds' ``cloud_scale`` positive (a zero step collapses a cloud onto its centre
    and fails only at query time, in ICP), and their decoded extent within `MAX_TRANSLATION_M`."""
    inten = arrays["cloud_intensity"]
    if inten.dtype.kind == "f" and inten.size and (top := float(inten.max())) > _MAX_CLOUD_INTENSITY:
        place = int(np.searchsorted(np.cumsum(arrays["cloud_counts"]), int(np.argmax(inten)), side="right"))
        raise ArtifactError(
            f"{path}: 'cloud_intensity' holds {top:.6g} (place {place}); expected normalised intensities in [0, 1]"
        )
    if "cloud_scale" not in arrays:
        return
    scale, centre = arrays["cloud_scale"], arrays["cloud_centre"]
    bad = scale <= 0
    if bad.any():
        i = int(np.argmax(bad))
        raise ArtifactError(
            f"{path}: 'cloud_scale' of place {i} is {scale[i]:.6g}; expected a positive step (metres per code)"
        )
    extent = scale * 32767 + (np.abs(centre).max(axis=1) if centre.size else 0.0)
    far = extent > MAX_TRANSLATION_M
    if far.any():
        i = int(np.argmax(far))
        raise ArtifactError(
            f"{path}: 'cloud_scale' {scale[i]:.6g} and 'cloud_centre' of place {i} put its points up to "
            f"{extent[i]:.3g} m away; expected at most {MAX_TRANSLATION_M:g} m"
        )


def _cat(parts: list[np.ndarray], empty: tuple[int, ...]) -> np.ndarray:
    return np.concatenate(parts) if parts else np.zeros(empty, np.float32)


def _cloud_arrays(clouds: SequenceABC[tuple[np.ndarray, np.ndarray]], kind: str) -> dict[str, np.ndarray]:
    """The saved arrays of the place clouds (``cloud_store`` ``kind``)."""
    if kind == "int16" and isinstance(clouds, _FixedPointClouds):
        return clouds.arrays()  # as read: saved again unchanged
    out: dict[str, np.ndarray] = {"cloud_counts": np.array([c[0].shape[0] for c in clouds], dtype=np.int64)}
    if kind == "float32":
        out["cloud_xyz"] = _cat([c[0] for c in clouds], (0, 3)).astype(np.float32)
        out["cloud_intensity"] = _cat([c[1] for c in clouds], (0,)).astype(np.float32)
        return out
    fixed = [FixedPointCloud.encode(c[0]) for c in clouds]
    out["cloud_xyz"] = np.concatenate([f.codes for f in fixed]) if fixed else np.zeros((0, 3), np.int16)
    out["cloud_intensity"] = encode_unit(_cat([c[1] for c in clouds], (0,)))
    out["cloud_centre"] = np.array([f.centre for f in fixed], np.float64).reshape(-1, 3)
    out["cloud_scale"] = np.array([f.scale for f in fixed], np.float64)
    return out


class _FixedPointClouds(SequenceABC):
    """The int16 place clouds of a saved database as (xyz, intensity) float32 pairs, decoded when read."""

    def __init__(self, xyz: list, intensity: list, centres: np.ndarray, scales: np.ndarray) -> None:
        self._parts = list(zip(xyz, intensity, centres, scales, strict=True))

    def __len__(self) -> int:
        return len(self._parts)

    def __getitem__(self, i: int) -> tuple[np.ndarray, np.ndarray]:  # type: ignore[override]
        codes, inten, centre, scale = self._parts[i]
        xyz = FixedPointCloud(np.asarray(codes), np.asarray(centre), float(scale)).decode()
        return xyz, decode_unit(inten)

    def arrays(self) -> dict[str, np.ndarray]:
        """The saved arrays these clouds were read from."""
        parts = self._parts
        return {
            "cloud_counts": np.array([len(p[0]) for p in parts], np.int64),
            "cloud_xyz": np.concatenate([p[0] for p in parts]) if parts else np.zeros((0, 3), np.int16),
            "cloud_intensity": np.concatenate([p[1] for p in parts]) if parts else np.zeros(0, np.uint8),
            "cloud_centre": np.array([p[2] for p in parts], np.float64).reshape(-1, 3),
            "cloud_scale": np.array([p[3] for p in parts], np.float64),
        }


def _read_clouds(arrays: dict[str, np.ndarray]) -> SequenceABC[tuple[np.ndarray, np.ndarray]]:
    """The place clouds (xyz float32, intensity float32) of a saved database (checked by `_check_layout`)."""
    if not arrays["cloud_counts"].size:
        return []
    cuts = np.cumsum(arrays["cloud_counts"])[:-1]
    xyz, inten = np.split(arrays["cloud_xyz"], cuts), np.split(arrays["cloud_intensity"], cuts)
    if arrays["cloud_xyz"].dtype == np.int16:
        return _FixedPointClouds(xyz, inten, arrays["cloud_centre"], arrays["cloud_scale"])
    return list(zip(xyz, inten, strict=True))
