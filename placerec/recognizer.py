"""The base class of every place recognizer, the pipeline registry, and the check for scans nothing can match.

`Recognizer` implements the `placerec.types.PlaceRecognizer` protocol's ``add``/``query`` from ``describe`` +
``add_description`` + ``query_description``; a subclass sets ``name`` and ``Params`` (a `placerec.params.Params`
model with the paper's defaults) and writes those three plus ``save``/``load``.

Pipelines are registered by name in `PIPELINES` (a `PipelineEntry`: ``"module:Class"``, a parameter preset and a
one-line summary). `make_pipeline` also accepts a ``"module:Class"`` path, so pipelines from other packages work
without registration; such a path must name a class implementing the protocol, checked before anything is called.
"""

from __future__ import annotations

import importlib
import inspect
import numbers
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Generic, TypeVar, cast

import numpy as np
from pydantic import ValidationError

from placerec.errors import ArtifactError, ConfigError, ScanDataError, short_repr
from placerec.hashing import stable_hash
from placerec.params import Params, deep_merge, resolve
from placerec.sensor_presets import SENSOR_PRESETS, SensorPreset
from placerec.types import (
    MAX_RANGE_M,
    Candidate,
    Description,
    MotionPrior,
    PlaceRecognizer,
    Scan,
    valid_points,
)

__all__ = [
    "Description",
    "Recognizer",
    "PipelineEntry",
    "PIPELINES",
    "pipeline_class",
    "pipeline_params",
    "make_pipeline",
    "params_key",
    "check_saved_params",
    "valid_points",
    "require_points",
    "require_varying_intensity",
    "MIN_POINTS",
    "MAX_RANGE_M",
]

#: Fewest valid points a scan needs to be described; fewer is a `ScanDataError` in every pipeline.
MIN_POINTS = 100


def require_points(scan: Scan, where: str, minimum: int = MIN_POINTS) -> np.ndarray:
    """`valid_points` of ``scan``; `ScanDataError` naming ``where`` when fewer than ``minimum`` are valid."""
    ok = valid_points(scan)
    n = int(ok.sum())
    if n < minimum:
        src = f"{scan.source}: " if scan.source else ""
        raise ScanDataError(
            f"{src}{where}: the scan has {n} valid points of {len(scan)} (finite, not at the origin, closer "
            f"than {MAX_RANGE_M:g} m); at least {minimum} are needed to describe a place"
        )
    return ok


def require_varying_intensity(scan: Scan, valid: np.ndarray, where: str, why: str) -> None:
    """`ScanDataError` naming ``where`` and ``why`` unless the intensities of the ``valid`` points are finite and
    not all equal (a flat intensity carries nothing for a front end that reads it)."""
    inten = scan.intensity[valid]
    if not np.isfinite(inten).all() or float(inten.max()) == float(inten.min()):
        src = f"{scan.source}: " if scan.source else ""
        raise ScanDataError(
            f"{src}{where}: the intensity of the valid points is constant or not finite "
            f"({inten.min()}..{inten.max()}); {why}"
        )


def check_saved_params(path: str | Path, header: dict[str, Any], params: Params) -> None:
    """`ArtifactError` unless a saved database's header records exactly ``params`` (it was made with them).

    A field added since the database was saved is absent from its header; it takes its default (which is what
    the code did before the field existed), so a header that differs only by such fields at their defaults
    loads."""
    saved = (header.get("meta") or {}).get("params")
    recorded = type(params).without_runtime(saved)
    current = params.saved_dump()
    if recorded == current:
        return
    try:
        filled = type(params).model_validate(recorded).saved_dump() if isinstance(recorded, Mapping) else None
    except (ConfigError, ValidationError):
        filled = None
    if filled != current:
        raise ArtifactError(f"{path}: database was made with other parameters: {short_repr(saved, 200)}")


def params_key(name: str, params: Any) -> str:
    """A short stable hash of a front-end name and its parameters (a `Params` model or plain JSON data)."""
    if isinstance(params, Params):
        params = params.saved_dump()
    return f"{name}-{stable_hash({'name': name, 'params': params})}"


#: the parameters class of a recognizer
P = TypeVar("P", bound=Params)


class Recognizer(ABC, Generic[P]):
    """Base class of every place recognizer: implements ``add``/``query`` from the three primitives.

    Subclasses set ``name`` and ``Params`` and implement ``describe``, ``add_description``,
    ``query_description``, ``save`` and ``load``. ``Cls(params)`` takes a ``Params`` instance or a mapping
    (merged deeply into the defaults), plus keyword overrides; ``self.params`` holds the validated parameters.
    ``frontend_key`` defaults to a hash of all parameters; override it with the front end's own ones so that
    pipelines sharing a front end share descriptions. ``cache_descriptions`` = False keeps descriptions out of
    the on-disk cache (when they are as large as the scan itself).
    """

    name: ClassVar[str] = "recognizer"
    Params: ClassVar[type[Params]] = Params
    cache_descriptions: ClassVar[bool] = True
    params: P

    def __init__(self, params: P | Mapping[str, Any] | None = None, **overrides: Any) -> None:
        if isinstance(params, Params) and not isinstance(params, self.Params):
            raise ConfigError(
                f"{self.name}: params must be a {self.Params.__name__}, got {type(params).__name__}"
            )
        if isinstance(params, Params) and not overrides:
            resolved: Params = params
        else:
            base = params.model_dump() if isinstance(params, Params) else params
            resolved = resolve(self.Params, base, overrides, where=self.name)
        self.params = cast(P, resolved)

    @property
    def frontend_key(self) -> str:
        return params_key(self.name, self.params)

    @abstractmethod
    def describe(self, scan: Scan) -> Description: ...

    @abstractmethod
    def add_description(
        self, scan_id: int, description: Description, pose: np.ndarray | None = None
    ) -> None: ...

    @abstractmethod
    def query_description(
        self,
        description: Description,
        k: int = 1,
        max_id: int | None = None,
        query_id: int = -1,
        prior: MotionPrior | None = None,
    ) -> list[Candidate]: ...

    @abstractmethod
    def save(self, path: str | Path) -> None: ...

    @abstractmethod
    def load(self, path: str | Path) -> None: ...

    def add(self, scan_id: int, scan: Scan, pose: np.ndarray | None = None) -> None:
        _check_scan(
            f"{self.name}.add", scan, "add(scan_id, scan, pose=None)", swapped=isinstance(scan_id, Scan)
        )
        _check_integer(f"{self.name}.add", "scan_id", scan_id, ScanDataError)
        self.add_description(scan_id, self.describe(scan), pose)

    def query(self, scan: Scan, k: int = 1, max_id: int | None = None, query_id: int = -1) -> list[Candidate]:
        where = f"{self.name}.query"
        _check_scan(where, scan, "query(scan, k=1, max_id=None, query_id=-1)")
        _check_integer(where, "k", k, ConfigError)
        if max_id is not None:
            _check_integer(where, "max_id", max_id, ConfigError)
        _check_integer(where, "query_id", query_id, ConfigError)
        return self.query_description(self.describe(scan), k=k, max_id=max_id, query_id=query_id)


def _check_scan(where: str, scan: object, signature: str, swapped: bool = False) -> None:
    """`ScanDataError` naming the ``scan`` argument of ``where`` unless it is a `Scan`."""
    if not isinstance(scan, Scan):
        hint = "; the arguments look swapped" if swapped else ""
        raise ScanDataError(
            f"{where}: argument 'scan' must be a placerec.types.Scan (e.g. from placerec.io.read_scan), got "
            f"{type(scan).__name__} {short_repr(scan, 40)}{hint}; the call is {signature}"
        )


def _check_integer(where: str, name: str, value: object, error: type[Exception]) -> None:
    """``error`` naming argument ``name`` of ``where`` unless ``value`` is an integer (a numpy one too, not bool)."""
    if not isinstance(value, numbers.Integral) or isinstance(value, bool):
        raise error(
            f"{where}: argument {name!r} must be an integer, got {type(value).__name__} {short_repr(value, 40)}"
        )


#: The verification the global-localisation presets share (ISHOT paper Sec. V-C: one verification module for
#: every pipeline; the settings measured in docs/localization.md): every nearest neighbour paired, each candidate
#: verified as a local map of the entries within 15 m, ICP clouds cropped at 40 m, RANSAC from 3 inliers, accepted
#: by eps_ICP with at least 70 % of the query's voxels overlapping the local map; a candidate within 7.5 m (half
#: the local map's radius) of one already verified for the query is skipped; candidates are verified one at a time
#: in rank order and the first accepted answers (the paper examines further candidates only when one fails); when
#: voting ends without an accepted place, the voting pipelines verify the 30 most voted (their last resort).
LOCALIZE_VERIFY: dict[str, Any] = {
    "verify": {
        "tau_max": 1.0,
        "radius_m": 15.0,
        "separation_m": 7.5,
        "at_once": 1,
        "fallback_top_k": 30,
        "icp": {"max_range": 40.0},
        "ransac": {"min_inliers": 3},
        "score": {"min_fitness": 0.7},
    },
}


@dataclass(frozen=True)
class PipelineEntry:
    """A registered pipeline: its class (``"module:Class"``), parameter preset, a one-line summary and its
    operating ``threshold`` on the candidate score (what `LoopClosureDetector` accepts and the benchmark judges
    at), chosen once on the tuning split (docs/protocol.md); None where none was chosen. ``sensors``: its
    settings on the sensors whose own tuning cells chose others (`placerec.sensor_presets`)."""

    target: str
    summary: str
    preset: dict[str, Any] = field(default_factory=dict)
    threshold: float | None = None
    #: sensor model name (`placerec.sim.sensors.SENSORS`) -> operating threshold and parameters on its scans
    sensors: Mapping[str, SensorPreset] = field(default_factory=dict)

    def threshold_for(self, sensor: str | None, odometry: bool = False) -> float | None:
        """The operating threshold on ``sensor``'s scans: its own (``sensors``; with ``odometry``, the one chosen
        with the odometry gate where there is one), else ``threshold``."""
        own = self.sensors.get(sensor or "", SensorPreset()).with_odometry(odometry).threshold
        return self.threshold if own is None else own

    def params_for(self, sensor: str | None, odometry: bool = False) -> Mapping[str, Any]:
        """The parameter overrides on ``sensor``'s scans (``sensors``, with ``odometry`` as for `threshold_for`;
        none for another or no sensor)."""
        return self.sensors.get(sensor or "", SensorPreset()).with_odometry(odometry).params


#: Registered pipelines by short name. The loop pipelines' operating thresholds were picked by the tuning rule of
#: docs/protocol.md on the tuning matrix (town x 4 sensors, seed 0): `placerec bench configs/benchmark_tuning.yaml
#: --suggest`. 0.25 is the verification's min_score (no false closure scored above it on the tuning cells); Scan
#: Context's ICP-verified false closures reached 0.259, MapClosures' false ones 14 inliers. A sensor's own thresholds
#: come from the same rule on that sensor's tuning cells alone (`placerec bench ... --suggest` prints them per
#: sensor), with the settings chosen there (`placerec.sensor_presets`, docs/sensors.md).
PIPELINES: dict[str, PipelineEntry] = {
    "scan-context": PipelineEntry(
        "placerec.baselines.scan_context:ScanContext",
        "Scan Context (Kim & Kim 2018): polar max-height grid, ring-key search, column-shift distance",
        # the coarse ICP stage from its yaw-only guess on a 3 m query grid: same P / R / max F1 on the tuning
        # cells, a third less verification CPU (docs/verification.md)
        {"verify": {"icp_only_coarse_voxel_size": 3.0}},
        threshold=0.3,
        sensors=SENSOR_PRESETS["scan-context"],
    ),
    "map-closures": PipelineEntry(
        "placerec.baselines.map_closures_peer:MapClosuresPeer",
        "MapClosures peer (PRBonn): bird's-eye density-map ORB, HBST, RANSAC; fed single scans",
        threshold=15.0,
    ),
    "orb-hbst": PipelineEntry(
        "placerec.pipelines.visual:VisualHBST",
        "VPR paper: intensity image, ORB features, HBST retrieval; RANSAC + ICP verification",
        {"features": "orb", "hbst": {"threshold": 50}, "verify": {"top_k": 5, "icp_top_k": 2}},
        threshold=0.25,
        sensors=SENSOR_PRESETS["orb-hbst"],
    ),
    "brisk-hbst": PipelineEntry(
        "placerec.pipelines.visual:VisualHBST",
        "VPR paper: intensity image, FAST + BRISK features, HBST retrieval; RANSAC + ICP verification",
        {"features": "brisk", "hbst": {"threshold": 100}, "verify": {"top_k": 5, "icp_top_k": 2}},
        threshold=0.25,
        sensors=SENSOR_PRESETS["brisk-hbst"],
    ),
    "orb-dbow": PipelineEntry(
        "placerec.pipelines.dbow:VisualDBoW",
        "VPR paper: intensity image, ORB features, DBoW2 bag of words; RANSAC + ICP verification",
        {"features": "orb", "verify": {"top_k": 20, "icp_top_k": 2}},
        threshold=0.25,
        sensors=SENSOR_PRESETS["orb-dbow"],
    ),
    "surf-dbow": PipelineEntry(
        "placerec.pipelines.dbow:VisualDBoW",
        "VPR paper: intensity image, FAST + SURF features, DBoW2 bag of words; RANSAC + ICP verification",
        {"features": "fast-surf", "verify": {"top_k": 20, "icp_top_k": 2}},
        threshold=0.25,
        sensors=SENSOR_PRESETS["surf-dbow"],
    ),
    "superpoint-dbow": PipelineEntry(
        "placerec.pipelines.dbow:VisualDBoW",
        "VPR paper: intensity image, our SuperPoint (trained on simulated LiDAR), DBoW2; RANSAC + ICP verification",
        {"features": "superpoint", "verify": {"top_k": 20, "icp_top_k": 2}},
        threshold=0.25,
        sensors=SENSOR_PRESETS["superpoint-dbow"],
    ),
    "ishot-votes": PipelineEntry(
        "placerec.pipelines.keypoint_voting:KeypointVoting",
        "ISHOT paper: ISS-BR keypoints, ISHOT descriptors (geometry + intensity), ratio-tested NN votes",
        {"features": {"descriptor": "ishot"}},
    ),
    "shot-votes": PipelineEntry(
        "placerec.pipelines.keypoint_voting:KeypointVoting",
        "ISHOT paper's baseline: ISS-BR keypoints, SHOT descriptors, ratio-tested NN votes",
        {"features": {"descriptor": "shot"}},
    ),
    "ishot-prob": PipelineEntry(
        "placerec.pipelines.probabilistic_voting:ProbabilisticVoting",
        "ISHOT paper Sec. IV: probabilistic keypoint voting (batches of 16, stop at 15 %), verification + ICP",
        {"features": {"descriptor": "ishot"}, "search": {"index": "pca"}, **LOCALIZE_VERIFY},
    ),
    "shot-global": PipelineEntry(
        "placerec.pipelines.global_registration:GlobalRegistration",
        "ISHOT paper's baseline (a): SHOT global registration, K = 4 over every map keypoint, verification + ICP",
        {
            "features": {"descriptor": "shot"},
            **LOCALIZE_VERIFY,
            "verify": {**LOCALIZE_VERIFY["verify"], "top_k": 1},
        },
    ),
    "shot-gestalt-votes": PipelineEntry(
        "placerec.pipelines.gestalt_voting:GestaltVoting",
        "ISHOT paper's baseline (b) on SHOT: Bosse & Zlot voting (10 % rounds, K = 10, log-normal stop), verification",
        {"features": {"descriptor": "shot"}, **LOCALIZE_VERIFY},
    ),
    "delight": PipelineEntry(
        "placerec.pipelines.delight:Delight",
        "ISHOT paper's baseline (c): DELIGHT intensity histograms (2 spheres x 8 sectors, chi-squared) rank the "
        "places, then the shared verification on SHOT",
        # its 5 candidates verified together, the best answering: one at a time accepted a wrong pose on the
        # training queries (docs/localization.md)
        {
            "features": {"descriptor": "shot"},
            **LOCALIZE_VERIFY,
            "verify": {**LOCALIZE_VERIFY["verify"], "at_once": None},
        },
    ),
    "fpfh-votes": PipelineEntry(
        "placerec.pipelines.keypoint_voting:KeypointVoting",
        "ISHOT paper's baseline: ISS-BR keypoints, FPFH descriptors, ratio-tested NN votes",
        {"features": {"descriptor": "fpfh"}},
    ),
}

_PROTOCOL_METHODS = (
    "describe",
    "add_description",
    "query_description",
    "add",
    "query",
    "save",
    "load",
)


def pipeline_class(name: str) -> type[Any]:
    """The class of a registered pipeline, or of a ``"package.module:Class"`` path.

    A path imports its module (running that module's code: name trusted packages only); a module that fails to
    import is a `ConfigError` naming it. The path must name a class that implements `placerec.types.PlaceRecognizer` (a `Recognizer` subclass, or
    a class with every protocol method, ``name`` and ``frontend_key``); anything else is a `ConfigError`, raised
    before anything is called.
    """
    entry = PIPELINES.get(name)
    target = entry.target if entry else str(name)
    module_name, sep, attr = target.partition(":")
    if not sep or not module_name or not attr.isidentifier():
        raise ConfigError(
            f"unknown pipeline {name!r}; registered: {', '.join(PIPELINES)} (or 'package.module:Class')"
        )
    try:
        module = importlib.import_module(module_name)
    except Exception as exc:  # a plugin module may fail to import with any error (SyntaxError, its own)
        reason = short_repr(str(exc), 200)
        raise ConfigError(
            f"pipeline {name!r}: cannot import module {module_name!r} ({type(exc).__name__}: {reason})"
        ) from exc
    obj = inspect.getattr_static(module, attr, None)
    if not inspect.isclass(obj):
        kind = "nothing" if obj is None else f"a {type(obj).__name__}"
        raise ConfigError(
            f"pipeline {name!r}: {target} is {kind}, not a class implementing placerec.types.PlaceRecognizer"
        )
    if not issubclass(obj, Recognizer):
        missing = [m for m in _PROTOCOL_METHODS if not inspect.isfunction(getattr(obj, m, None))]
        missing += [a for a in ("name", "frontend_key") if not hasattr(obj, a)]
        if missing:
            raise ConfigError(
                f"pipeline {name!r}: class {target} does not implement placerec.types.PlaceRecognizer "
                f"(missing: {', '.join(missing)})"
            )
    return obj


def pipeline_params(
    name: str,
    params: Mapping[str, Any] | None = None,
    path: str = "",
    sensor: str | None = None,
    odometry: bool = False,
) -> Params:
    """The resolved parameters of a `Recognizer` pipeline: its defaults, the registry preset, its settings on
    ``sensor``'s scans (a sensor model name; `PipelineEntry.params_for`, those chosen with the odometry gate for a
    detector that has one when ``odometry``), then ``params``.

    ``path`` is where ``params`` sit in a config (e.g. ``pipelines[1].params``), for the error messages.
    """
    cls = pipeline_class(name)
    if not issubclass(cls, Recognizer):
        raise ConfigError(
            f"pipeline {name!r}: {cls.__name__} does not declare its parameters (not a Recognizer)"
        )
    entry = PIPELINES.get(name)
    preset, own = (entry.preset, entry.params_for(sensor, odometry)) if entry else (None, None)
    return resolve(cls.Params, preset, own, params, where=name, path=path or "params")


def make_pipeline(
    name: str,
    params: Mapping[str, Any] | None = None,
    path: str = "",
    sensor: str | None = None,
    odometry: bool = False,
) -> PlaceRecognizer:
    """Build a pipeline by registry name (or ``module:Class``) with parameter overrides from a config.

    A `Recognizer` gets its defaults, the registry preset, its settings on ``sensor``'s scans (a sensor model
    name, `PipelineEntry.params_for`; with ``odometry``, those chosen with the odometry gate, for a detector that
    has it) and ``params`` merged deeply and validated (`ConfigError` naming ``path.key`` and the allowed keys);
    any other protocol class is called with ``**params``.
    """
    cls = pipeline_class(name)
    if issubclass(cls, Recognizer):
        return cls(pipeline_params(name, params, path, sensor, odometry))
    if params is not None and not isinstance(params, Mapping):
        raise ConfigError(f"pipeline {name!r}: {path or 'params'} must be a mapping")
    return cls(**deep_merge({}, params))
