"""The map artifact: a folder a user builds once (``placerec map build``, ``placerec slam --save-map``) and then
localises against (`placerec.maps.localizer.Localizer`) or extends with a new session (``--prior-map``).

Layout (``MAP_FORMAT_VERSION`` 1)::

    calibration.npz       the intensity calibration table, when the map's scans were calibrated
    manifest.json         what the map is: pipelines (name, parameters, operating threshold, database file), sensor,
                          intensity, preprocessing, keyframe count, sessions, extent, the config that built it, and
                          the size and SHA-256 of every other file
    keyframes.npz         kind "map-keyframes": poses (N, 4, 4) T_world_keyframe, timestamps (N,) (NaN: unknown),
                          session (N,) int32, scan_index (N,) int64 (the keyframe's scan in its source sequence)
    clouds.npz            kind "map-clouds": every keyframe's voxelised cloud in its own frame as int16 codes
                          (`placerec.quantise.FixedPointCloud`, <= 2 mm error for a cloud 120 m across): codes
                          (M, 3), offsets (N + 1,), centre (N, 3), scale (N,); memory-mapped on open
    graph.npz, graph.g2o  the pose graph's factors (odometry, loops) when the map came from SLAM
    pipelines/NAME.npz    each pipeline's own database (its ``save``), entry ``i`` = keyframe ``i``
    trajectory.png        a figure of the keyframes

`MapWriter` builds the folder beside the target under a temporary name and renames it into place only when
everything (manifest last) is written: an interrupted or failed build leaves no map. `MapArtifact.open` checks the
manifest (every key known, types, counts), that exactly the listed files are there with their sizes, the hash of
every file up to `HASH_ON_OPEN_BYTES` (all of them with ``check_hashes=True`` or ``placerec info --check``), and
each array file against its schema; any difference is an `ArtifactError` naming the file and what is wrong.
Nothing else is read until asked: pipelines load on first use, clouds are pages of a memory map.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import hashlib
import json
import os
import shutil
import tempfile
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from placerec._version import __version__
from placerec.errors import ArtifactError, ConfigError, short_repr
from placerec.io.artifact_schema import Member, check_offsets
from placerec.io.atomic import atomic_write, json_object, load_artifact, save_artifact
from placerec.io.npz import mapped_without_crc
from placerec.params import Params
from placerec.preprocess import PreprocessParams
from placerec.quantise import FixedPointCloud
from placerec.slam.graph import LoopFactor, PoseGraph, write_g2o
from placerec.types import PlaceRecognizer, SensorInfo, as_pose, rigid_problem

__all__ = [
    "MAP_FORMAT_VERSION",
    "HASH_ON_OPEN_BYTES",
    "MapMismatchError",
    "MapPipeline",
    "MapSession",
    "MapManifest",
    "MapGraph",
    "MapArtifact",
    "MapWriter",
    "is_map_folder",
    "pose_fit",
    "check_pose_fit",
    "pose_fit_probes",
    "MIN_POSE_FIT",
]

MAP_KIND: Literal["placerec-map"] = "placerec-map"
MAP_FORMAT_VERSION = 1
MANIFEST = "manifest.json"
#: the intensity calibration table of a map whose scans were calibrated (``preprocess.intensity.calibration``)
CALIBRATION = "calibration.npz"
#: files up to this size are hashed every time a map opens; bigger ones (clouds, databases) with ``check_hashes``
HASH_ON_OPEN_BYTES = 64 << 20
_MAX_MANIFEST_BYTES = 64 << 20
_KEYFRAMES_KIND, _CLOUDS_KIND, _GRAPH_KIND = "map-keyframes", "map-clouds", "map-graph"
_KEYFRAMES_SCHEMA = {
    "poses": Member("f", ("n", 4, 4), finite=True),
    "timestamps": Member("f", ("n",)),
    "session": Member("i", ("n",), min_value=0),
    "scan_index": Member("i", ("n",)),
}
_CLOUDS_SCHEMA = {
    "codes": Member("i", (None, 3)),
    "offsets": Member("i", ("n1",)),
    "centre": Member("f", ("n", 3), finite=True),
    "scale": Member("f", ("n",), finite=True),
}
_GRAPH_SCHEMA = {
    "odometry_ids": Member("i", ("e", 2), min_value=0),
    "odometry_T": Member("f", ("e", 4, 4), finite=True),
    "odometry_sigmas": Member("f", ("e", 6), finite=True),
    "loop_ids": Member("i", ("l", 2), min_value=0),
    "loop_T": Member("f", ("l", 4, 4), finite=True),
    "loop_score": Member("f", ("l",)),
    "loop_sigmas": Member("f", (6,), finite=True),
}


class MapMismatchError(ConfigError):
    """A map cannot serve a query or a session: it was built with another pipeline, pipeline parameters,
    intensity or sensor than the caller uses (the message names what differs)."""


class FileEntry(BaseModel):
    """A file of the map folder: its size and SHA-256 (a record, not a parameter: sizes pass 10^9 bytes)."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)

    bytes: int = Field(ge=0, le=1 << 50)
    sha256: str = Field(pattern=r"^[0-9a-f]{64}$")


class MapPipeline(Params):
    """A pipeline whose database the map holds."""

    name: str = Field(description="registered pipeline name (or module:Class)")
    params: dict[str, Any] = Field(description="its parameters, as its database records them")
    threshold: float | None = Field(description="the operating threshold its closures were accepted at")
    file: str = Field(description="the database file, relative to the map folder")
    frontend_key: str = Field(description="the front end's key: equal keys give identical descriptions")


class MapSession(Params):
    """One mapping session's keyframes: ``first`` .. ``first + count - 1``."""

    name: str
    first: int = Field(ge=0)
    count: int = Field(ge=0)


class MapManifest(Params):
    """``manifest.json`` (module docstring); every key is checked when a map opens."""

    kind: Literal["placerec-map"] = MAP_KIND
    format_version: int = MAP_FORMAT_VERSION
    placerec_version: str = __version__
    created: str = Field(description="UTC time the map was written, ISO 8601")
    name: str = Field(description="what the map is of, e.g. its sequence")
    n_keyframes: int = Field(ge=0)
    poses_source: str = Field(description="slam, file, ground-truth, merged")
    pipelines: list[MapPipeline]
    sensor: dict[str, Any] | None = Field(description="the SensorInfo of the mapping scans")
    intensity: str = Field(description="the intensity the databases were described with")
    preprocess: dict[str, Any] = Field(description="the preprocessing applied before description")
    cloud_voxel_m: float = Field(gt=0, description="voxel size of the stored clouds (m)")
    sessions: list[MapSession]
    extent: list[list[float]] = Field(description="[[x, y, z] min, [x, y, z] max] of the keyframe positions")
    config: dict[str, Any] = Field(description="the configuration that built the map")
    files: dict[str, FileEntry]


@dataclass
class MapGraph:
    """The pose graph of a map: odometry factors ``(i, j, T_ij, sigmas)`` (sigmas: rotation rad x3, then
    translation m x3, GTSAM's order) and loop factors with the loop sigmas they were added with."""

    odometry: list[tuple[int, int, np.ndarray, np.ndarray]] = field(default_factory=list)
    loops: list[LoopFactor] = field(default_factory=list)
    loop_sigmas: np.ndarray = field(default_factory=lambda: np.ones(6))

    @classmethod
    def from_pose_graph(cls, graph: PoseGraph) -> MapGraph:
        p = graph.params
        sig = np.array([np.radians(p.loop_sigma_rotation_deg)] * 3 + [p.loop_sigma_translation] * 3)
        return cls(list(graph.odometry), list(graph.loops), sig)

    def arrays(self) -> dict[str, np.ndarray]:
        odo, loops = self.odometry, self.loops
        return {
            "odometry_ids": np.array([(i, j) for i, j, _, _ in odo], np.int64).reshape(-1, 2),
            "odometry_T": np.array([T for _, _, T, _ in odo], np.float64).reshape(-1, 4, 4),
            "odometry_sigmas": np.array([s for _, _, _, s in odo], np.float64).reshape(-1, 6),
            "loop_ids": np.array([(lp.match_id, lp.query_id) for lp in loops], np.int64).reshape(-1, 2),
            "loop_T": np.array([lp.T_match_query for lp in loops], np.float64).reshape(-1, 4, 4),
            "loop_score": np.array([lp.score for lp in loops], np.float64),
            "loop_sigmas": np.asarray(self.loop_sigmas, np.float64),
        }

    @classmethod
    def from_arrays(cls, a: Mapping[str, np.ndarray], n: int, where: Path) -> MapGraph:
        for key in ("odometry_ids", "loop_ids"):
            if a[key].size and int(a[key].max()) >= n:
                raise ArtifactError(f"{where}: {key!r} names keyframe {int(a[key].max())} of {n}")
        odo = [
            (int(i), int(j), np.array(T), np.array(s))
            for (i, j), T, s in zip(a["odometry_ids"], a["odometry_T"], a["odometry_sigmas"], strict=True)
        ]
        loops = [
            LoopFactor(int(m), int(q), np.array(T), float(s))
            for (m, q), T, s in zip(a["loop_ids"], a["loop_T"], a["loop_score"], strict=True)
        ]
        return cls(odo, loops, np.array(a["loop_sigmas"]))


#: consecutive keyframes' clouds must overlap at least this much at their poses (fitness at 0.5 m); measured on the
#: simulated town, keyframes 1 m apart: 0.81-0.84 at the right poses, 0.15-0.37 with the poses inverted
#: (T_sensor_world) and 0.16-0.27 in a camera frame (z forward, KITTI's poses.txt)
MIN_POSE_FIT = 0.5


def pose_fit(T_a: np.ndarray, cloud_a: np.ndarray, T_b: np.ndarray, cloud_b: np.ndarray) -> float:
    """How well two keyframes' clouds (each in its own frame) overlap when placed by their poses ``T_world_*``: the
    share of ``cloud_b``'s points within 0.5 m of ``cloud_a``'s after ``inv(T_a) @ T_b`` (NaN: a cloud too small)."""
    from placerec.verify.icp import alignment_stats, prepare_target

    if len(cloud_a) < 10 or len(cloud_b) < 10:
        return float("nan")
    target = prepare_target(np.asarray(cloud_a, np.float64))
    T = np.linalg.inv(T_a) @ T_b
    return alignment_stats(np.asarray(cloud_b, np.float64), target, T, 0.5, None, 2000)[0]


def pose_fit_probes(n: int, pairs: int = 8) -> np.ndarray:
    """The first keyframes of up to ``pairs`` consecutive pairs ``(i, i + 1)`` spread over ``n`` keyframes: those
    `pose_fit` compares (none when ``n`` < 2)."""
    if n < 2:
        return np.zeros(0, np.int64)
    return np.unique(np.linspace(0, n - 2, min(pairs, n - 1)).astype(np.int64))


def check_pose_fit(fits: list[float], where: str) -> None:
    """`MapMismatchError` naming ``where`` when the median of ``fits`` (`pose_fit` of consecutive keyframes) is below
    `MIN_POSE_FIT`: poses in another convention than ``T_world_sensor`` of the LiDAR, or not the scans' poses."""
    ok = [f for f in fits if np.isfinite(f)]
    if ok and float(np.median(ok)) < MIN_POSE_FIT:
        raise MapMismatchError(
            f"{where}: the poses do not fit the scans: consecutive keyframes overlap {np.median(ok):.0%} at their "
            f"poses (median of {len(ok)} pairs; at least {MIN_POSE_FIT:.0%} expected). placerec poses are "
            "T_world_sensor of the LiDAR frame; inverted poses (T_sensor_world) or a camera frame (KITTI's "
            "poses.txt before its calibration is applied) do not fit"
        )


def is_map_folder(path: str | Path) -> bool:
    """Whether ``path`` is a folder holding a map's manifest (what ``placerec info`` uses to tell a map)."""
    return Path(path).is_dir() and (Path(path) / MANIFEST).is_file()


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while chunk := fh.read(1 << 20):
            h.update(chunk)
    return h.hexdigest()


def _safe_relative(name: str, where: Path) -> Path:
    """``name`` as a path inside the map folder; `ArtifactError` for an absolute path or one leaving it."""
    p = PurePosixPath(name)
    if p.is_absolute() or ".." in p.parts or not p.parts or "\\" in name:
        raise ArtifactError(f"{where}: file name {short_repr(name)} is not a path inside the map folder")
    return Path(*p.parts)


def sensor_dict(sensor: SensorInfo | None) -> dict[str, Any] | None:
    """``sensor`` as JSON data for the manifest (tuples as lists)."""
    if sensor is None:
        return None
    return json.loads(json.dumps(asdict(sensor)))


class MapArtifact:
    """An opened map folder (module docstring). Open with `MapArtifact.open`."""

    def __init__(
        self,
        path: Path,
        manifest: MapManifest,
        keyframes: dict[str, np.ndarray],
        clouds: dict[str, np.ndarray],
    ) -> None:
        self.path = path
        self.manifest = manifest
        self.poses: np.ndarray = keyframes["poses"]
        self.timestamps: np.ndarray = keyframes["timestamps"]
        self.session: np.ndarray = keyframes["session"]
        self.scan_index: np.ndarray = keyframes["scan_index"]
        self._clouds = clouds
        self._tree: Any = None
        self._recognizers: dict[str, PlaceRecognizer] = {}
        self._hashed = False  # whether every file's SHA-256 was checked when the map opened

    # -- opening ---------------------------------------------------------------------------------------------
    @classmethod
    def open(cls, path: str | Path, check_hashes: bool = False) -> MapArtifact:
        """Open and check the map at ``path`` (module docstring); ``check_hashes`` hashes every file."""
        path = Path(path)
        if not path.is_dir():
            raise ArtifactError(f"{path}: no such map folder")
        manifest = _read_manifest(path)
        _check_files(path, manifest, check_hashes)
        n = manifest.n_keyframes
        kf_path = path / "keyframes.npz"
        kf, _ = load_artifact(kf_path, _KEYFRAMES_KIND, (MAP_FORMAT_VERSION,), _KEYFRAMES_SCHEMA)
        if kf["poses"].shape[0] != n:
            raise ArtifactError(f"{kf_path}: {kf['poses'].shape[0]} keyframes, the manifest says {n}")
        problem = rigid_problem(kf["poses"])
        if problem is not None:
            raise ArtifactError(
                f"{kf_path}: pose of keyframe {problem[0]} is not a rigid motion ({problem[1]})"
            )
        cl_path = path / "clouds.npz"
        with _unread(manifest, "clouds.npz", check_hashes):
            cl, _ = load_artifact(cl_path, _CLOUDS_KIND, (MAP_FORMAT_VERSION,), _CLOUDS_SCHEMA, mmap=True)
        if cl["centre"].shape[0] != n:
            raise ArtifactError(f"{cl_path}: {cl['centre'].shape[0]} clouds for {n} keyframes")
        check_offsets(cl["offsets"], n, int(cl["codes"].shape[0]), cl_path, "offsets")
        if (cl["scale"] <= 0).any():
            raise ArtifactError(f"{cl_path}: array 'scale' holds values <= 0")
        sessions = manifest.sessions
        if sum(s.count for s in sessions) != n or any(
            s.first != sum(t.count for t in sessions[:k]) for k, s in enumerate(sessions)
        ):
            raise ArtifactError(f"{path / MANIFEST}: 'sessions' do not cover the {n} keyframes in order")
        if len(sessions) and int(kf["session"].max(initial=0)) >= len(sessions):
            raise ArtifactError(f"{kf_path}: 'session' names a session the manifest does not list")
        _check_pipelines(path / MANIFEST, manifest.pipelines)
        table = (manifest.preprocess.get("intensity") or {}).get("calibration")
        if table is not None and table != CALIBRATION:
            raise ArtifactError(
                f"{path / MANIFEST}: 'preprocess' names calibration {short_repr(table)}, not the map's"
            )
        if (table is not None) != (CALIBRATION in manifest.files):
            raise ArtifactError(f"{path / MANIFEST}: 'files' and 'preprocess' disagree on {CALIBRATION}")
        artifact = cls(path, manifest, kf, cl)
        artifact.preprocess()
        artifact._hashed = check_hashes
        return artifact

    def __len__(self) -> int:
        return int(self.manifest.n_keyframes)

    def __repr__(self) -> str:
        names = ", ".join(p.name for p in self.manifest.pipelines)
        return f"MapArtifact({str(self.path)!r}, {len(self)} keyframes, pipelines: {names})"

    # -- keyframes -------------------------------------------------------------------------------------------
    def cloud(self, i: int) -> np.ndarray:
        """(M, 3) float32: keyframe ``i``'s voxelised cloud in the keyframe's own frame."""
        if not 0 <= int(i) < len(self):
            raise IndexError(f"keyframe {i} of {len(self)}")
        c = self._clouds
        a, b = int(c["offsets"][i]), int(c["offsets"][i + 1])
        return FixedPointCloud(np.asarray(c["codes"][a:b]), c["centre"][i], float(c["scale"][i])).decode()

    def positions(self) -> np.ndarray:
        """(N, 3) keyframe positions in the map frame."""
        return self.poses[:, :3, 3]

    def nearest(
        self, xyz: np.ndarray, k: int = 1, radius: float | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """(ids, distances) of the ``k`` keyframes nearest to ``xyz`` (3,), nearest first; only those within
        ``radius`` m when given."""
        if self._tree is None:
            from scipy.spatial import cKDTree

            self._tree = cKDTree(self.positions())
        if len(self) == 0:
            return np.zeros(0, np.int64), np.zeros(0)
        k = min(int(k), len(self))
        d, idx = self._tree.query(np.asarray(xyz, np.float64).reshape(3), k=k)
        d, idx = np.atleast_1d(d), np.atleast_1d(idx).astype(np.int64)
        if radius is not None:
            keep = d <= radius
            d, idx = d[keep], idx[keep]
        return idx, d

    # -- pipelines -------------------------------------------------------------------------------------------
    def pipeline(self, name: str | None = None) -> MapPipeline:
        """The map's pipeline ``name`` (default: the first); `MapMismatchError` naming those it has."""
        pipes = self.manifest.pipelines
        if not pipes:
            raise MapMismatchError(f"map {self.path} holds no pipeline database")
        if name is None:
            return pipes[0]
        for p in pipes:
            if p.name == name:
                return p
        raise MapMismatchError(
            f"map {self.path} has no database for pipeline {name!r}; it has {[p.name for p in pipes]}"
        )

    def recognizer(self, name: str | None = None, fresh: bool = False) -> PlaceRecognizer:
        """Pipeline ``name``'s database (default: the first pipeline), loaded once and kept; its entry ``i`` is
        keyframe ``i``. Query it only (``query_description``): adding to it changes the map in memory. ``fresh``:
        a new copy loaded from the file and not kept (to extend, e.g. into a merged map's database)."""
        pipe = self.pipeline(name)
        if fresh or pipe.name not in self._recognizers:
            from placerec.recognizer import make_pipeline

            params_at = f"pipelines[{pipe.name}].params"
            rec = make_pipeline(pipe.name, pipe.params, path=params_at)  # checked on open
            with _unread(self.manifest, pipe.file, self._hashed):
                rec.load(self.path / _safe_relative(pipe.file, self.path))
            if fresh:
                return rec
            self._recognizers[pipe.name] = rec
        return self._recognizers[pipe.name]

    def check_pipeline(self, name: str, params: Mapping[str, Any] | None = None) -> MapPipeline:
        """The map's entry for pipeline ``name`` if it was built with the same front end and parameters as
        ``params`` (a mapping over the pipeline's preset and its settings on the map's sensor,
        `placerec.sensor_presets`, which the map was built with); `MapMismatchError` naming what differs."""
        from placerec.recognizer import make_pipeline

        pipe = self.pipeline(name)
        sensor = self.manifest.sensor.get("name") if self.manifest.sensor else None
        wanted = make_pipeline(name, params, sensor=sensor)
        if wanted.frontend_key != pipe.frontend_key:
            raise MapMismatchError(
                f"map {self.path}: pipeline {name!r} was built with another front end "
                f"({pipe.frontend_key}, here {wanted.frontend_key}); parameters that differ: "
                f"{_differences(pipe.params, _saved_params(wanted))}"
            )
        return pipe

    def check_query(
        self, sensor: SensorInfo | None = None, intensity: str | None = None, allow_other_sensor: bool = False
    ) -> None:
        """`MapMismatchError` when queries from ``sensor`` / with ``intensity`` cannot use this map: another
        intensity than the databases were described with, or another sensor unless ``allow_other_sensor``."""
        if intensity is not None and intensity != self.manifest.intensity:
            raise MapMismatchError(
                f"map {self.path} was described with intensity {self.manifest.intensity!r}, the queries use "
                f"{intensity!r}"
            )
        mine = (self.manifest.sensor or {}).get("name")
        if sensor is not None and mine not in (None, "unknown") and sensor.name != "unknown":
            if sensor.name != mine and not allow_other_sensor:
                raise MapMismatchError(
                    f"map {self.path} was built from sensor {mine!r}, the queries come from {sensor.name!r} "
                    "(allow it explicitly to query across sensors: --allow-other-sensor)"
                )

    def preprocess(self) -> PreprocessParams:
        """The preprocessing the map's scans had, which queries must have too; a calibration table is the map's own
        copy (``calibration.npz`` in the folder)."""
        data = json.loads(json.dumps(self.manifest.preprocess))
        intensity = data.get("intensity") or {}
        if intensity.get("calibration") is not None:
            intensity["calibration"] = str(self.path / _safe_relative(intensity["calibration"], self.path))
        try:
            return PreprocessParams.model_validate(data)
        except ConfigError as exc:
            raise ArtifactError(f"{self.path / MANIFEST}: 'preprocess': {exc}") from None

    def check_pose_fit(self, pairs: int = 8) -> None:
        """`MapMismatchError` unless up to ``pairs`` consecutive keyframes spread over the map overlap at their
        poses (`pose_fit`, `check_pose_fit`): a map whose poses follow another convention."""
        same = [int(i) for i in pose_fit_probes(len(self), pairs) if self.session[i] == self.session[i + 1]]
        fits = [pose_fit(self.poses[i], self.cloud(i), self.poses[i + 1], self.cloud(i + 1)) for i in same]
        check_pose_fit(fits, f"map {self.path}")

    # -- graph -----------------------------------------------------------------------------------------------
    def graph(self) -> MapGraph | None:
        """The map's pose graph (None when it was built without one)."""
        if "graph.npz" not in self.manifest.files:
            return None
        gp = self.path / "graph.npz"
        arrays, _ = load_artifact(gp, _GRAPH_KIND, (MAP_FORMAT_VERSION,), _GRAPH_SCHEMA)
        return MapGraph.from_arrays(arrays, len(self), gp)

    # -- summary ---------------------------------------------------------------------------------------------
    @property
    def places(self) -> dict[str, Any] | None:
        """The keyframe settings its places were accumulated with (`placerec map build`'s ``keyframes``, a SLAM
        run's ``loops.keyframes``, as the manifest's config records them); None: single scans."""
        config = self.manifest.config
        if "keyframes" in config:
            return config["keyframes"]
        loops = config.get("loops")
        return loops.get("keyframes") if isinstance(loops, dict) else None

    def places_mismatch(self, keyframes: bool) -> str | None:
        """Why places of the kind ``keyframes`` says (keyframes, or single scans) are not the map's (`places`),
        or None when they are: closures and fixes between the two compare unlike places."""
        if (self.places is None) == (not keyframes):
            return None
        mine = "single scans" if self.places is None else f"keyframes {self.places}"
        return f"{self.path}: the map's places are {mine}, these are {'keyframes' if keyframes else 'single scans'}"

    def summary(self) -> dict[str, Any]:
        """What ``placerec info MAP`` prints."""
        m = self.manifest
        pos = self.positions()
        length = float(np.linalg.norm(np.diff(pos, axis=0), axis=1).sum()) if len(pos) > 1 else 0.0
        sizes = {name: e.bytes for name, e in m.files.items()}
        lo, hi = np.round(m.extent, 1)
        return {
            "path": str(self.path),
            "kind": "map",
            "name": m.name,
            "format_version": m.format_version,
            "created": m.created,
            "placerec_version": m.placerec_version,
            "keyframes": m.n_keyframes,
            "places": "single scans" if self.places is None else f"keyframes {self.places}",
            "sessions": {s.name: f"keyframes {s.first}..{s.first + s.count - 1}" for s in m.sessions},
            "poses_source": m.poses_source,
            "path_length_m": round(length, 1),
            "extent_m": {
                f"{a}_{end}": float(v[k])
                for end, v in (("min", lo), ("max", hi))
                for k, a in enumerate("xyz")
            },
            "sensor": (m.sensor or {}).get("name"),
            "intensity": m.intensity,
            "pipelines": {
                p.name: f"threshold {p.threshold}, {sizes.get(p.file, 0) / 1e6:.1f} MB" for p in m.pipelines
            },
            "cloud_points": int(self._clouds["codes"].shape[0]),
            "cloud_voxel_m": m.cloud_voxel_m,
            "graph": "graph.npz" in m.files,
            "bytes": int(sum(sizes.values()) + (self.path / MANIFEST).stat().st_size),
            "figure": str(self.path / "trajectory.png") if "trajectory.png" in m.files else None,
        }


def _saved_params(rec: PlaceRecognizer) -> dict[str, Any]:
    params = getattr(rec, "params", None)
    return params.saved_dump() if isinstance(params, Params) else {}


def _differences(a: Any, b: Any, prefix: str = "") -> str:
    """The dotted keys whose values differ between two parameter dumps (at most 5), for an error message."""
    out: list[str] = []

    def walk(x: Any, y: Any, key: str) -> None:
        if isinstance(x, dict) and isinstance(y, dict):
            for k in sorted(set(x) | set(y)):
                walk(x.get(k), y.get(k), f"{key}.{k}" if key else k)
        elif x != y:
            out.append(f"{key}: map {short_repr(x, 30)}, here {short_repr(y, 30)}")

    walk(a, b, prefix)
    return "; ".join(out[:5]) + (f" (+{len(out) - 5} more)" if len(out) > 5 else "") if out else "none listed"


def _read_manifest(path: Path) -> MapManifest:
    mp = path / MANIFEST
    if not mp.is_file():
        raise ArtifactError(f"{path}: not a placerec map (no {MANIFEST})")
    if mp.stat().st_size > _MAX_MANIFEST_BYTES:
        raise ArtifactError(f"{mp}: {mp.stat().st_size} bytes, more than a manifest can be")
    data = json_object(mp.read_bytes(), str(mp))
    if data.get("kind") != MAP_KIND:
        raise ArtifactError(f"{mp}: kind is {short_repr(data.get('kind'))}, expected {MAP_KIND!r}")
    if data.get("format_version") != MAP_FORMAT_VERSION:
        raise ArtifactError(
            f"{mp}: map format version {short_repr(data.get('format_version'))} is not supported (this placerec "
            f"reads {[MAP_FORMAT_VERSION]})"
        )
    try:
        manifest = MapManifest.model_validate(data)
    except ConfigError as exc:
        raise ArtifactError(f"{mp}: {exc}") from None
    if len(manifest.extent) != 2 or any(len(v) != 3 for v in manifest.extent):
        raise ArtifactError(f"{mp}: 'extent' must be [[x, y, z], [x, y, z]]")
    return manifest


def _unread(manifest: MapManifest, name: str, hashed: bool) -> contextlib.AbstractContextManager[None]:
    """Load ``name`` without reading its memory-mapped data for CRCs when its hash was not checked on open (a file
    above `HASH_ON_OPEN_BYTES`): a big map opens without reading its bulk; ``check_hashes`` reads and checks all."""
    entry = manifest.files.get(name)
    if hashed or entry is None or entry.bytes <= HASH_ON_OPEN_BYTES:
        return contextlib.nullcontext()
    return mapped_without_crc()


def _check_pipelines(where: Path, pipelines: list[MapPipeline]) -> None:
    """Every pipeline of the manifest is a registered one (a map never imports a module it names) whose recorded
    parameters are valid for it; `ArtifactError` naming the manifest otherwise."""
    from placerec.recognizer import PIPELINES, pipeline_params

    names = [p.name for p in pipelines]
    if len(set(names)) != len(names):
        raise ArtifactError(f"{where}: a pipeline is listed twice: {names}")
    for p in pipelines:
        if p.name not in PIPELINES:
            raise ArtifactError(
                f"{where}: pipeline {short_repr(p.name)} is not a registered pipeline ({', '.join(PIPELINES)})"
            )
        try:
            pipeline_params(p.name, p.params, path=f"pipelines[{p.name}].params")
        except ConfigError as exc:
            raise ArtifactError(f"{where}: {exc}") from None


def _check_files(path: Path, manifest: MapManifest, check_hashes: bool) -> None:
    """Exactly the manifest's files (and ``manifest.json``) are in the folder, with their sizes and hashes."""
    mp = path / MANIFEST
    for required in ("keyframes.npz", "clouds.npz"):
        if required not in manifest.files:
            raise ArtifactError(f"{mp}: 'files' does not list {required!r}")
    listed = {_safe_relative(name, mp) for name in manifest.files}
    for pipe in manifest.pipelines:
        if _safe_relative(pipe.file, mp) not in listed:
            raise ArtifactError(f"{mp}: pipeline {pipe.name!r}'s database {pipe.file!r} is not in 'files'")
    present = {p.relative_to(path) for p in path.rglob("*") if p.is_file()} - {Path(MANIFEST)}
    extra = sorted(str(p) for p in present - listed)
    if extra:
        raise ArtifactError(f"{path}: files the manifest does not list: {extra[:5]}")
    for name, entry in manifest.files.items():
        f = path / _safe_relative(name, mp)
        if not f.is_file():
            raise ArtifactError(f"{f}: missing (the manifest lists it)")
        size = f.stat().st_size
        if size != entry.bytes:
            raise ArtifactError(f"{f}: {size} bytes, the manifest says {entry.bytes} (truncated or replaced)")
        if (check_hashes or size <= HASH_ON_OPEN_BYTES) and _sha256(f) != entry.sha256:
            raise ArtifactError(f"{f}: its SHA-256 differs from the manifest's (the file was changed)")


class MapWriter:
    """Writes a map folder (module docstring): `add_keyframe` for keyframes 0, 1, ... in order, then `finish`.

    ``pipelines``: registered pipeline name -> (recognizer, operating threshold); each recognizer must hold
    keyframe ``i`` under id ``i`` when `finish` saves it. ``overwrite``: replace an existing map at ``out`` (else `ConfigError` at once).
    Use as a context manager, or call `abort` on failure: either removes the temporary folder."""

    def __init__(
        self,
        out: str | Path,
        pipelines: Mapping[str, tuple[PlaceRecognizer, float | None]],
        *,
        name: str,
        sensor: SensorInfo | None = None,
        intensity: str = "sensor-default",
        preprocess: Mapping[str, Any] | None = None,
        config: Mapping[str, Any] | None = None,
        poses_source: str = "file",
        cloud_voxel_m: float = 0.4,
        overwrite: bool = False,
    ) -> None:
        self.out = Path(out)
        if self.out.exists() and not (overwrite and is_map_folder(self.out)):
            why = "pass overwrite / --overwrite to replace it" if is_map_folder(self.out) else "not a map"
            raise ConfigError(f"{self.out}: already exists ({why})")
        if not cloud_voxel_m > 0:
            raise ConfigError(f"cloud_voxel_m must be > 0, got {cloud_voxel_m}")
        from placerec.recognizer import PIPELINES

        for key in pipelines:
            if key not in PIPELINES:
                raise ConfigError(
                    f"map pipelines: {key!r} is not a registered pipeline ({', '.join(PIPELINES)}); a map names its "
                    "pipelines by registry name, so that opening it never imports code"
                )
        self.out.parent.mkdir(parents=True, exist_ok=True)
        self.pipelines = dict(pipelines)
        preprocess = json.loads(json.dumps(dict(preprocess or {})))
        table = (preprocess.get("intensity") or {}).get("calibration")
        if table is not None:
            from placerec.calibration.table import load_calibration

            load_calibration(table)  # a table that cannot serve the queries fails here, before any work
        self._meta = dict(
            name=name,
            sensor=sensor_dict(sensor),
            intensity=intensity,
            preprocess=preprocess,
            config=json.loads(json.dumps(dict(config or {}), default=str)),
            poses_source=poses_source,
            cloud_voxel_m=float(cloud_voxel_m),
        )
        self.voxel = float(cloud_voxel_m)
        self.tmp = Path(tempfile.mkdtemp(prefix=f".{self.out.name}.{os.getpid()}.", dir=self.out.parent))
        if table is not None:  # the map carries the table its intensities were calibrated with
            shutil.copyfile(table, self.tmp / CALIBRATION)
            preprocess["intensity"]["calibration"] = CALIBRATION
        self._codes = open(self.tmp / ".codes.raw", "wb")  # noqa: SIM115 - closed in finish / abort
        self._counts: list[int] = []
        self._centres: list[np.ndarray] = []
        self._scales: list[float] = []
        self._poses: list[np.ndarray] = []
        self._times: list[float] = []
        self._session: list[int] = []
        self._scan_index: list[int] = []
        self._session_names: list[str] = []
        self._done = False

    def __enter__(self) -> MapWriter:
        return self

    def __exit__(self, exc_type: Any, *_: Any) -> None:
        if not self._done:
            self.abort()

    def __len__(self) -> int:
        return len(self._poses)

    def add_session(self, name: str) -> int:
        """Start a new session (keyframes added from now on belong to it); returns its index."""
        self._session_names.append(str(name))
        return len(self._session_names) - 1

    def add_keyframe(
        self,
        pose: np.ndarray,
        xyz: np.ndarray,
        timestamp: float | None = None,
        scan_index: int = -1,
    ) -> int:
        """Add the next keyframe: its pose ``T_world_keyframe`` and its points in its own frame (voxelised here
        to ``cloud_voxel_m``); returns its id."""
        from placerec.verify.voxel_grid import voxel_points

        T = as_pose(pose, f"map keyframe {len(self)}")
        if not self._session_names:
            self.add_session(self._meta["name"])
        pts = np.asarray(xyz, np.float64).reshape(-1, 3)
        pts = voxel_points(pts[np.isfinite(pts).all(axis=1)], self.voxel)
        cloud = FixedPointCloud.encode(pts)
        self._codes.write(np.ascontiguousarray(cloud.codes, np.int16).tobytes())
        self._counts.append(len(cloud))
        self._centres.append(cloud.centre)
        self._scales.append(cloud.scale)
        self._poses.append(np.array(T, np.float64))
        self._times.append(float("nan") if timestamp is None else float(timestamp))
        self._session.append(len(self._session_names) - 1)
        self._scan_index.append(int(scan_index))
        return len(self) - 1

    def abort(self) -> None:
        """Remove the temporary folder; nothing is left at ``out``."""
        if not self._codes.closed:
            self._codes.close()
        shutil.rmtree(self.tmp, ignore_errors=True)
        self._done = True

    def finish(self, poses: np.ndarray | None = None, graph: PoseGraph | MapGraph | None = None) -> Path:
        """Write everything and move the folder into place; ``poses`` (N, 4, 4) replace the keyframe poses given
        so far (e.g. the SLAM's batch solution), ``graph`` is stored as graph.npz and graph.g2o."""
        if self._done:
            raise ConfigError(f"{self.out}: this map writer has already finished")
        try:
            return self._finish(poses, graph)
        except BaseException:
            self.abort()
            raise

    def _finish(self, poses: np.ndarray | None, graph: PoseGraph | MapGraph | None) -> Path:
        n = len(self)
        P = np.stack(self._poses) if n else np.zeros((0, 4, 4))
        if poses is not None:
            poses = np.asarray(poses, np.float64)
            if poses.shape != (n, 4, 4):
                raise ConfigError(f"map {self.out}: {poses.shape} poses for {n} keyframes")
            P = np.stack([as_pose(T, f"map keyframe {i}") for i, T in enumerate(poses)]) if n else P
        self._codes.close()
        raw = self.tmp / ".codes.raw"
        total = int(sum(self._counts))
        codes = np.memmap(raw, np.int16, "r", shape=(total, 3)) if total else np.zeros((0, 3), np.int16)
        save_artifact(
            self.tmp / "clouds.npz",
            _CLOUDS_KIND,
            MAP_FORMAT_VERSION,
            {
                "codes": codes,
                "offsets": np.r_[0, np.cumsum(self._counts)].astype(np.int64),
                "centre": np.array(self._centres, np.float64).reshape(n, 3),
                "scale": np.array(self._scales, np.float64),
            },
        )
        del codes
        raw.unlink()
        save_artifact(
            self.tmp / "keyframes.npz",
            _KEYFRAMES_KIND,
            MAP_FORMAT_VERSION,
            {
                "poses": P,
                "timestamps": np.array(self._times, np.float64),
                "session": np.array(self._session, np.int32),
                "scan_index": np.array(self._scan_index, np.int64),
            },
        )
        pipes = []
        (self.tmp / "pipelines").mkdir()
        for key, (rec, threshold) in self.pipelines.items():
            rel = f"pipelines/{key}.npz"
            rec.save(self.tmp / rel)
            pipes.append(
                MapPipeline(
                    name=key,
                    params=_saved_params(rec),
                    threshold=None if threshold is None else float(threshold),
                    file=rel,
                    frontend_key=rec.frontend_key,
                )
            )
        if graph is not None:
            mg = MapGraph.from_pose_graph(graph) if isinstance(graph, PoseGraph) else graph
            save_artifact(self.tmp / "graph.npz", _GRAPH_KIND, MAP_FORMAT_VERSION, mg.arrays())
            write_g2o(self.tmp / "graph.g2o", P, mg.odometry, mg.loops, mg.loop_sigmas)
        if n:
            _trajectory_figure(self.tmp / "trajectory.png", P, np.array(self._session), self._meta["name"])
        files = {}
        for f in sorted(p for p in self.tmp.rglob("*") if p.is_file()):
            files[f.relative_to(self.tmp).as_posix()] = FileEntry(bytes=f.stat().st_size, sha256=_sha256(f))
        counts = np.bincount(np.array(self._session, np.int64), minlength=len(self._session_names))
        firsts = np.r_[0, np.cumsum(counts)[:-1]]
        pos = P[:, :3, 3] if n else np.zeros((1, 3))
        manifest = MapManifest(
            created=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            n_keyframes=n,
            pipelines=pipes,
            sessions=[
                MapSession(name=s, first=int(f), count=int(c))
                for s, f, c in zip(self._session_names, firsts, counts, strict=True)
            ],
            extent=[pos.min(axis=0).tolist(), pos.max(axis=0).tolist()],
            files=files,
            **self._meta,
        )
        with atomic_write(self.tmp / MANIFEST, "w") as fh:
            fh.write(json.dumps(manifest.model_dump(mode="json"), indent=1))
        _replace_folder(self.tmp, self.out)
        self._done = True
        return self.out


def _replace_folder(src: Path, dst: Path) -> None:
    """Move the finished folder ``src`` to ``dst``; an existing map there is moved aside first and removed only
    once the new one is in place."""
    old = None
    if dst.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{dst.name}.old.", dir=dst.parent))
        os.rename(dst, old / dst.name)
    try:
        os.rename(src, dst)
    except OSError:
        if old is not None:
            os.rename(old / dst.name, dst)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def _trajectory_figure(path: Path, poses: np.ndarray, session: np.ndarray, title: str) -> None:
    """A bird's-eye figure of the keyframes, one colour per session (drawn here: the experiment figure helpers
    are a layer above the maps)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 6), dpi=100)
    for s in np.unique(session):
        p = poses[session == s, :3, 3]
        ax.plot(p[:, 0], p[:, 1], ".-", ms=2, lw=0.6, label=f"session {int(s)}")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"map {title}: {len(poses)} keyframes")
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    with atomic_write(path) as fh:
        fig.savefig(fh, format="png")
    plt.close(fig)
