"""Building blocks for place recognizers: the describe/database split, and the pipeline registry.

Most recognizers have a *front end* that turns a scan into a description (an image with features, a Scan Context
matrix, ISHOT descriptors) and a *database* that stores and searches descriptions. `DescribingRecognizer`
makes that split explicit so the experiment runner can cache descriptions per scan and share them between
pipelines with the same front end (``frontend_key``). `DescriptorRecognizer` implements the
`placerec.types.PlaceRecognizer` protocol on top of the split, so a subclass only writes ``describe``,
``add_description`` and ``query_description``.

Pipelines are registered by name in `PIPELINES` (``name -> "module:Class"``); `make_pipeline` also accepts a
``"module:Class"`` path, so pipelines from other packages work without registration.
"""

from __future__ import annotations

import dataclasses
import importlib
from abc import ABC, abstractmethod
from pathlib import Path
from typing import Any, ClassVar, Protocol, runtime_checkable

import numpy as np

from placerec.errors import ConfigError
from placerec.hashing import stable_hash
from placerec.types import Candidate, Scan

__all__ = [
    "Description",
    "DescribingRecognizer",
    "DescriptorRecognizer",
    "PIPELINES",
    "PIPELINE_PRESETS",
    "pipeline_class",
    "make_pipeline",
    "params_key",
]

#: A scan's description: named NumPy arrays (so it can be cached as ``.npz``).
Description = dict[str, np.ndarray]


@runtime_checkable
class DescribingRecognizer(Protocol):
    """A place recognizer whose front end can be run (and cached) separately from its database.

    ``frontend_key`` identifies the front end *and its parameters*: two recognizers with the same key must
    return identical descriptions for the same scan.
    """

    name: str

    @property
    def frontend_key(self) -> str: ...

    def describe(self, scan: Scan) -> Description: ...

    def add_description(
        self, scan_id: int, description: Description, pose: np.ndarray | None = None
    ) -> None: ...

    def query_description(
        self, description: Description, k: int = 1, max_id: int | None = None, query_id: int = -1
    ) -> list[Candidate]: ...


def params_key(name: str, params: Any) -> str:
    """A short stable hash of a front-end name and its parameters (a dataclass or a mapping)."""
    if dataclasses.is_dataclass(params) and not isinstance(params, type):
        params = dataclasses.asdict(params)
    return f"{name}-{stable_hash({'name': name, 'params': params})}"


class DescriptorRecognizer(ABC):
    """Base class: implements ``add``/``query`` from ``describe`` + ``add_description`` + ``query_description``.

    Subclasses set ``name``, a frozen dataclass ``Params`` with the paper's defaults, and implement the three
    abstract methods plus ``save``/``load``. ``self.params`` holds the validated parameters.
    """

    name: ClassVar[str] = "recognizer"
    Params: ClassVar[type]

    def __init__(self, params: Any | None = None, **overrides: Any) -> None:
        self.params = coerce_params(type(self), params, overrides)

    @classmethod
    def from_params(cls, params: dict[str, Any] | None = None) -> DescriptorRecognizer:
        return cls(coerce_params(cls, None, params or {}))

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
        self, description: Description, k: int = 1, max_id: int | None = None, query_id: int = -1
    ) -> list[Candidate]: ...

    @abstractmethod
    def save(self, path: str | Path) -> None: ...

    @abstractmethod
    def load(self, path: str | Path) -> None: ...

    def add(self, scan_id: int, scan: Scan, pose: np.ndarray | None = None) -> None:
        self.add_description(scan_id, self.describe(scan), pose)

    def query(self, scan: Scan, k: int = 1, max_id: int | None = None, query_id: int = -1) -> list[Candidate]:
        return self.query_description(self.describe(scan), k=k, max_id=max_id, query_id=query_id)


def coerce_params(cls: type, params: Any | None, overrides: dict[str, Any]) -> Any:
    """Build ``cls.Params`` from an instance and/or keyword overrides, with a `ConfigError` naming bad keys."""
    params_cls = cls.Params
    if params is None:
        params = params_cls()
    elif not isinstance(params, params_cls):
        raise ConfigError(
            f"{cls.__name__}: params must be a {params_cls.__name__}, got {type(params).__name__}"
        )
    if not overrides:
        return params
    allowed = [f.name for f in dataclasses.fields(params_cls)]
    unknown = sorted(set(overrides) - set(allowed))
    if unknown:
        raise ConfigError(
            f"{getattr(cls, 'name', cls.__name__)}: unknown parameter(s) {unknown}; allowed: {', '.join(allowed)}"
        )
    try:
        from pydantic import TypeAdapter, ValidationError

        merged = {**dataclasses.asdict(params), **overrides}
        return TypeAdapter(params_cls).validate_python(merged)
    except ValidationError as exc:
        details = "; ".join(f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in exc.errors())
        raise ConfigError(
            f"{getattr(cls, 'name', cls.__name__)}: invalid parameter value ({details})"
        ) from None


#: Registered pipelines: short name -> "module:Class". Later modules add their entries here.
PIPELINES: dict[str, str] = {
    "scan-context": "placerec.baselines.scan_context:ScanContext",
    "map-closures": "placerec.baselines.map_closures_peer:MapClosuresPeer",
    "orb-hbst": "placerec.pipelines.visual:VisualHBST",
    "brisk-hbst": "placerec.pipelines.visual:VisualHBST",
    "ishot-votes": "placerec.pipelines.keypoint_voting:KeypointVoting",
    "shot-votes": "placerec.pipelines.keypoint_voting:KeypointVoting",
    "fpfh-votes": "placerec.pipelines.keypoint_voting:KeypointVoting",
    "orb-dbow": "placerec.pipelines.dbow:VisualDBoW",
    "surf-dbow": "placerec.pipelines.dbow:VisualDBoW",
}

#: Parameter presets of registered names (merged under the config's own ``params``).
PIPELINE_PRESETS: dict[str, dict[str, Any]] = {
    "orb-hbst": {"features": "orb"},
    "brisk-hbst": {"features": "brisk"},
    "ishot-votes": {"descriptor": "ishot"},
    "shot-votes": {"descriptor": "shot"},
    "fpfh-votes": {"descriptor": "fpfh"},
    "orb-dbow": {"features": "orb"},
    "surf-dbow": {"features": "fast-surf"},
}


def pipeline_class(name: str) -> type:
    """The class of a registered pipeline, or of a ``"package.module:Class"`` path."""
    target = PIPELINES.get(name, name)
    if ":" not in target:
        raise ConfigError(
            f"unknown pipeline {name!r}; registered: {', '.join(sorted(PIPELINES))} (or 'module:Class')"
        )
    module_name, _, attr = target.partition(":")
    try:
        module = importlib.import_module(module_name)
        return getattr(module, attr)
    except (ImportError, AttributeError) as exc:
        raise ConfigError(f"pipeline {name!r}: cannot load {target} ({exc})") from exc


def make_pipeline(name: str, params: dict[str, Any] | None = None) -> Any:
    """Build a pipeline by registry name (or ``module:Class``) with parameter overrides from a config."""
    cls = pipeline_class(name)
    merged = {**PIPELINE_PRESETS.get(name, {}), **(params or {})}
    if hasattr(cls, "from_params"):
        return cls.from_params(merged)
    return cls(**merged)
