"""Experiment configuration: every section is a `placerec.params.Params` model (strict, ``extra="forbid"``,
immutable), loaded from YAML.

`load_config` is the one entry point: YAML file (or none) + ``key.path=value`` overrides -> validated
`ExperimentConfig`. Any unknown key or bad value raises `ConfigError` naming the dotted key path, what was wrong
and the allowed keys (`placerec.params.format_errors`). `dump_default_config` writes the defaults as YAML.
"""

from __future__ import annotations

import ipaddress
import re
from pathlib import Path
from typing import Any, Literal, TypeVar

import yaml
from pydantic import BaseModel, Field, field_validator, model_validator

from placerec.errors import ConfigError, short_repr
from placerec.eval.exclusion import ExclusionWindow
from placerec.keyframes import KeyframeParams
from placerec.loop_filter import LoopFilterParams
from placerec.odometry_gate import OdometryGateParams
from placerec.params import Params, resolve
from placerec.preprocess import PreprocessParams
from placerec.safe_yaml import load_yaml, load_yaml_file
from placerec.sim.odometry import OdometryDrift, slam_demo_drift
from placerec.types import PlaceRecognizer
from placerec.verify.ambiguity import AmbiguityParams

P = TypeVar("P", bound=Params)

__all__ = [
    "SimulatorConfig",
    "DatasetConfig",
    "experiment_preprocess",
    "PipelineSpec",
    "ExclusionConfig",
    "LocalizeConfig",
    "PoseTruthConfig",
    "EvaluationConfig",
    "OutputConfig",
    "ExecutionConfig",
    "ExperimentConfig",
    "load_config",
    "load_params_file",
    "read_config_file",
    "parse_config",
    "apply_overrides",
    "dump_default_config",
]


class SimulatorConfig(Params):
    """The built-in LiDAR simulator used as dataset (see `placerec.sim`)."""

    world: str = "town"
    sensor: str = "os1-64"
    n_scans: int | None = Field(None, ge=1, le=100_000, description="None = the whole route; at most 100,000")
    seed: int = 0
    world_seed: int | None = Field(
        None, description="the world's own seed (None: seed); keep it and change seed for a second session"
    )
    unit_seed: int | None = Field(None, description="the sensor unit's seed (None: seed)")
    route: str = "default"
    spacing: float = Field(1.0, gt=0, description="metres between scans (unless rate_hz is set)")
    rate_hz: float | None = Field(
        None, gt=0, le=1000, description="scans per second along the route's speed profile instead of spacing"
    )
    clutter: bool = True
    occluders: bool = False
    sweep_motion: bool = Field(
        False,
        description="render each ray from the sensor pose at its own time (motion distortion to de-skew)",
    )
    sensor_height: float | None = Field(None, gt=0)
    odometry_drift: float | None = Field(
        None,
        ge=0,
        le=1,
        description="drifting odometry_poses with this relative translation error (the simulator's OdometryDrift,"
        " its other errors scaled alike; keyframes use them as odometry); None: none",
    )


class DatasetConfig(Params):
    """Where scans and poses come from: the simulator (default) or a path readable by `placerec.io.open_sequence`."""

    source: Literal["simulator", "path"] = "simulator"
    path: str | None = None
    dataset: str | None = Field(
        None, description="dataset layout (kitti, mulran, newer-college, helipr, nclt, mcap); None = detected"
    )
    sequence: str | None = Field(None, description="kitti: the sequence of a dataset root, e.g. '00'")
    sensor: str | None = Field(None, description="helipr: Ouster, Velodyne, Aeva or Avia")
    topic: str | None = Field(None, description="rosbag / mcap: the PointCloud2 topic")
    format: str | None = None
    poses: str | None = None
    simulator: SimulatorConfig = Field(default_factory=SimulatorConfig)
    first: int = Field(0, ge=0, description="index of the first scan used")
    last: int | None = Field(None, description="index past the last scan used (None = to the end)")
    step: int = Field(1, ge=1, description="use every step-th scan")

    @model_validator(mode="after")
    def _path_needed(self) -> DatasetConfig:
        if self.source == "path" and not self.path:
            raise ValueError("dataset.source 'path' needs dataset.path")
        return self


def experiment_preprocess() -> PreprocessParams:
    """An experiment's preprocessing unless its config says otherwise (`placerec.preprocess.PreprocessParams`):
    returns nearer than 0.5 m dropped, the sensor's default intensity normalisation."""
    return PreprocessParams(min_range=0.5)


class PipelineSpec(Params):
    """One pipeline to run: a registry name (see ``placerec.recognizer.PIPELINES``) or ``module:Class``,
    a display label, parameter overrides validated by the pipeline itself, and the operating threshold the
    report judges it at (None: the registry preset's, chosen on the tuning split; docs/protocol.md)."""

    name: str
    label: str | None = None
    params: dict[str, Any] = Field(default_factory=dict)
    threshold: float | None = Field(
        None,
        allow_inf_nan=False,
        description="operating threshold on the candidate score (None: the preset's)",
    )
    loop_filter: LoopFilterParams | None = Field(
        None,
        description="loop mode: DLoopDetector's islands and temporal consistency on its candidates (None: off)",
    )

    @property
    def display_name(self) -> str:
        return self.label or self.name

    def threshold_for(self, sensor: str | None, odometry: bool = False) -> float | None:
        """The threshold the pipeline is judged at on ``sensor``'s scans (a sensor model name, None: unknown):
        ``threshold`` when given, else its preset's for that sensor, with the odometry gate when ``odometry``
        (`placerec.recognizer.PipelineEntry`)."""
        from placerec.recognizer import PIPELINES

        if self.threshold is not None:
            return self.threshold
        entry = PIPELINES.get(self.name)
        return None if entry is None else entry.threshold_for(sensor, odometry)


class ExclusionConfig(ExclusionWindow):
    """Loop mode: a database scan is eligible for a query only when it is older than EVERY limit set here —
    at least ``frames`` frames, ``seconds`` seconds (needs timestamps) and ``metres`` travelled (needs poses)
    before it; ``null`` = no limit of that kind. ``frames`` stays 120 (VPR paper) when the others are set: write
    ``frames: null`` to use only seconds or metres. The detector and the ground truth apply this one rule
    (`placerec.eval.exclusion.ExclusionWindow`, whose fields and checks these are). With ``keyframes`` set the
    places are keyframes: ``frames`` counts keyframes, ``seconds`` and ``metres`` apply to their timestamps and path
    (docs/keyframes.md)."""


class LocalizeConfig(Params):
    """Localize mode: a map sequence and a query sequence. ``condition`` picks a simulated query set
    (gator, pole, occlusion); ``map``/``queries`` give real sequences instead."""

    condition: Literal["gator", "pole", "occlusion"] = "gator"
    n_queries: int = Field(50, ge=1, le=100_000, description="simulated query scans (at most 100,000)")
    draw: int = Field(
        0,
        ge=0,
        description="simulated query draw (placerec.experiment.protocol): 2 the held-out test queries, 1 the"
        " training queries defaults were chosen on, 0 the development queries",
    )
    map: DatasetConfig | None = None
    queries: DatasetConfig | None = None
    success_distance: float = Field(3.0, gt=0)
    ambiguity: AmbiguityParams = Field(
        default_factory=AmbiguityParams,
        description="refuse an accepted answer another place nearly matches (placerec.verify.ambiguity; off)",
    )


class PoseTruthConfig(Params):
    """The pose ground truth (`placerec.eval.pose_truth`): a revisit overlaps an eligible scan by ``min_overlap``
    (voxels of ``voxel`` m), a closure is true when its relative pose is within ``max_translation`` /
    ``max_rotation_deg`` of the true one. Reported beside the distance-only figures in loop mode."""

    enabled: bool = True
    max_translation: float = Field(0.5, gt=0, allow_inf_nan=False, description="m")
    max_rotation_deg: float = Field(2.0, gt=0, allow_inf_nan=False, description="deg")
    min_overlap: float = Field(0.5, gt=0, le=1, description="fraction of the smaller scan's voxels")
    voxel: float = Field(1.0, gt=0, allow_inf_nan=False, description="m")


class OdometryGateConfig(Params):
    """Judge closures as a SLAM system with odometry does (`placerec.odometry_gate`): a closure that disagrees
    with the odometry by more than ``bounds`` is no answer, and the pipeline's next candidate that agrees is. The
    odometry is the dataset's true poses drifting as ``drift`` says (default configs/slam_demo.yaml's), drawn with
    ``seed`` (None: the simulator's seed, else 0), the odometry `placerec slam` runs on with that config."""

    bounds: OdometryGateParams = Field(default_factory=OdometryGateParams)
    drift: OdometryDrift = Field(default_factory=slam_demo_drift)
    seed: int | None = Field(None, description="the drift's seed (None: the simulator's seed, else 0)")


class EvaluationConfig(Params):
    """How pipelines are evaluated (loop: VPR paper protocol; localize: ISHOT paper protocol)."""

    mode: Literal["loop", "localize"] = "loop"
    exclusion: ExclusionConfig = Field(default_factory=ExclusionConfig)
    gt_distance: float = Field(
        5.0, gt=0, description="a revisit has an eligible scan within this distance (m)"
    )
    gt_yaw_deg: float | None = Field(None, gt=0, description="optional heading limit for a true match")
    top_n: int = Field(5, ge=1, le=1000, description="candidates requested per query (recall@N)")
    retrieval_distance: float = Field(
        25.0,
        gt=0,
        description="retrieval protocol: a candidate within this distance (m) is a hit (recall@1, @1%)",
    )
    reverse_yaw_deg: float = Field(
        90.0, gt=0, le=180, description="a revisit is reverse-direction beyond this heading difference (deg)"
    )
    pose_truth: PoseTruthConfig = Field(default_factory=PoseTruthConfig)
    gt_icp: bool = Field(
        False,
        description="VPR paper's ground truth: a revisit is near AND an ICP from the true pose succeeds (1 m, 20 deg)",
    )
    localize: LocalizeConfig = Field(default_factory=LocalizeConfig)
    odometry_gate: OdometryGateConfig | None = Field(
        None, description="loop mode: closures judged against a drifting odometry (None: appearance alone)"
    )


class OutputConfig(Params):
    """Where results go: ``dir/<name>_<timestamp>/`` with a ``latest`` link."""

    dir: str = "results"
    figures: bool = True
    cache_dir: str | None = Field(
        ".cache/descriptions", description="per-scan description cache (None = off)"
    )
    progress: bool = True
    evidence: bool = Field(
        True,
        description="per-closure evidence in the report (galleries, why candidates were rejected); needs"
        " figures",
    )
    evidence_per_gallery: int = Field(
        4, ge=1, le=100, description="closures shown per gallery (accepted, false, missed) and pipeline"
    )


#: Most worker processes any setting may ask for (a typo of a few zeros would start that many processes).
MAX_WORKERS = 1024
#: A Dask scheduler address: ``[protocol://]host:port``, an IPv6 host in brackets.
_SCHEDULER = re.compile(
    r"(?:(?P<protocol>tcp|tls|ws|wss|ucx)://)?"
    r"(?:\[(?P<ipv6>[^]/\s]{1,64})\]|(?P<host>[A-Za-z0-9](?:[A-Za-z0-9.-]{0,251}[A-Za-z0-9])?))"
    r":(?P<port>[0-9]{1,5})"
)


def scheduler_problem(address: str) -> str | None:
    """Why ``address`` is no Dask scheduler address (`_SCHEDULER`, a port in 1-65535, a valid IPv6 address in
    brackets); None when it is one."""
    m = _SCHEDULER.fullmatch(address)
    expected = "expected [tcp|tls|ws|wss|ucx://]host:port, e.g. tcp://10.0.0.5:8786 or tcp://[::1]:8786"
    if m is None:
        return f"{short_repr(address)} is not a Dask scheduler address; {expected}"
    if not 1 <= int(m["port"]) <= 65535:
        return f"{short_repr(address)}: port {m['port']} is not in 1-65535"
    if m["ipv6"] is not None:
        try:
            ipaddress.IPv6Address(m["ipv6"])
        except ValueError:
            return f"{short_repr(address)}: [{m['ipv6']}] is not an IPv6 address; {expected}"
    return None


class ExecutionConfig(Params):
    """Where scans are described: in the main process (``workers: 1``, local executor), in ``workers`` local
    processes, or on a Dask distributed cluster (``executor: dask``: a LocalCluster of ``workers`` processes, or
    the scheduler at ``scheduler``, e.g. ``tcp://10.0.0.5:8786``, whose workers must see the dataset and the
    cache folder at the same paths). Descriptions go to the on-disk cache (``output.cache_dir``, or a temporary
    folder for the run when it is off); the run then queries and inserts in scan order as usual, so results are
    those of a serial run."""

    workers: int = Field(
        1, ge=1, le=MAX_WORKERS, description="processes describing scans (1 = the main process; at most 1024)"
    )
    executor: Literal["local", "dask"] = "local"
    scheduler: str | None = Field(
        None, description="Dask scheduler address (tcp://host:port); None = LocalCluster"
    )
    chunk: int = Field(16, ge=1, le=100_000, description="scans per task")

    @field_validator("scheduler")
    @classmethod
    def _scheduler_address(cls, v: str | None) -> str | None:
        problem = None if v is None else scheduler_problem(v)
        if problem is not None:
            raise ValueError(problem)
        return v

    @model_validator(mode="after")
    def _scheduler_needs_dask(self) -> ExecutionConfig:
        if self.scheduler is not None and self.executor != "dask":
            raise ValueError("execution.scheduler needs execution.executor: dask")
        return self

    @property
    def parallel(self) -> bool:
        """Whether description runs outside the main process."""
        return self.executor == "dask" or self.workers > 1


class ExperimentConfig(Params):
    """The root of a placerec experiment config."""

    name: str = "experiment"
    dataset: DatasetConfig = Field(default_factory=DatasetConfig)
    preprocess: PreprocessParams = Field(default_factory=experiment_preprocess)
    pipelines: list[PipelineSpec] = Field(default_factory=lambda: [PipelineSpec(name="scan-context")])
    evaluation: EvaluationConfig = Field(default_factory=EvaluationConfig)
    output: OutputConfig = Field(default_factory=OutputConfig)
    execution: ExecutionConfig = Field(default_factory=ExecutionConfig)
    keyframes: KeyframeParams | None = Field(
        None,
        description="loop mode: pipelines see keyframes of the scans of each window (placerec.keyframes,"
        " docs/keyframes.md), e.g. {seconds: 0.5} or {metres: 5}; None: single scans",
    )

    @property
    def sensor(self) -> str | None:
        """The sensor model whose pipeline settings and thresholds apply (`placerec.sensor_presets`): the
        simulator's; None on recorded data (the presets')."""
        return self.dataset.simulator.sensor if self.dataset.source == "simulator" else None

    @property
    def with_odometry(self) -> bool:
        """Whether closures are judged with the odometry gate (``evaluation.odometry_gate``): the pipelines then
        run with their sensor's settings chosen with it (`placerec.sensor_presets`)."""
        return self.evaluation.odometry_gate is not None

    def make_pipeline(self, i: int) -> PlaceRecognizer:
        """Pipeline ``i`` of the config, built with its sensor's settings (those chosen with the odometry gate when
        the evaluation has it; `placerec.recognizer.make_pipeline`); errors name ``pipelines[i].params``."""
        from placerec.recognizer import make_pipeline

        spec = self.pipelines[i]
        return make_pipeline(
            spec.name,
            spec.params,
            path=f"pipelines[{i}].params",
            sensor=self.sensor,
            odometry=self.with_odometry,
        )

    def operating_threshold(self, spec: PipelineSpec) -> float | None:
        """``spec``'s operating threshold in this experiment: its sensor's (`PipelineSpec.threshold_for`), the one
        chosen with the odometry gate when the evaluation has it."""
        return spec.threshold_for(self.sensor, self.with_odometry)

    @model_validator(mode="after")
    def _keyframes_in_loop_mode(self) -> ExperimentConfig:
        if self.keyframes is not None and self.evaluation.mode != "loop":
            raise ValueError("keyframes: loop mode only (evaluation.mode: loop)")
        return self

    @model_validator(mode="after")
    def _unique_labels(self) -> ExperimentConfig:
        labels = [p.display_name for p in self.pipelines]
        dupes = sorted({x for x in labels if labels.count(x) > 1})
        if dupes:
            raise ValueError(
                f"pipeline labels must be unique; repeated: {dupes} (set 'label' to tell them apart)"
            )
        return self


def parse_config(data: dict[str, Any] | None, origin: str = "<config>") -> ExperimentConfig:
    """Validate a plain dict as an `ExperimentConfig`; raises `ConfigError`."""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{origin}: the top level of a config must be a mapping, got {type(data).__name__}")
    return resolve(ExperimentConfig, data, where=f"{origin}: invalid configuration")


def _item_name(item: Any) -> str:
    """How a list item is named in an error: a pipeline-like mapping by its label (else its name)."""
    if isinstance(item, dict):
        return str(item.get("label") or item.get("name") or "?")
    return short_repr(item, 40)


def _list_index(items: list[Any], part: str, key: str, item: str) -> int:
    """The index in ``items`` that the override key part ``part`` selects: a number, an item's label (or name, when
    no label is given), or a name only one item has; `ConfigError` naming ``key`` and listing the items otherwise."""
    if re.fullmatch(r"-?[0-9]+", part):
        index = int(part)
        if 0 <= index < len(items):
            return index
        why = f"no item {index}"
    else:
        dicts = [(i, x) for i, x in enumerate(items) if isinstance(x, dict)]
        for matches in (
            [i for i, x in dicts if (x.get("label") or x.get("name")) == part],
            [i for i, x in dicts if x.get("name") == part],
        ):
            if len(matches) == 1:
                return matches[0]
            if len(matches) > 1:
                why = f"{len(matches)} items are named {part!r}; use the index or a label"
                break
        else:
            why = f"no item labelled or named {part!r}"
    listing = ", ".join(f"{i}: {_item_name(x)}" for i, x in enumerate(items)) or "none"
    raise ConfigError(f"override {short_repr(item)}: '{key}': {why}; the list holds {listing}")


def apply_overrides(data: dict[str, Any], overrides: list[str]) -> dict[str, Any]:
    """Apply ``a.b.c=value`` overrides (value parsed as YAML) to a nested dict, in place; returns it.

    A part of the key inside a list picks an item: its index (``pipelines.0.params.nfeatures=500``), or its label,
    or its name when one item only has it (``pipelines.orb-hbst.threshold=0.3``). The values are validated where
    the data is (the config model; a pipeline's ``params`` by the pipeline, naming ``pipelines[N].params.key``)."""
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"override {item!r} must look like key.path=value")
        key, raw = item.split("=", 1)
        parts = [p for p in key.strip().split(".") if p]
        if not parts:
            raise ConfigError(f"override {item!r} has an empty key")
        value = load_yaml(raw, f"override {short_repr(item)}")
        node: dict[str, Any] | list[Any] = data
        for i, part in enumerate(parts):
            where = ".".join(parts[: i + 1])
            if isinstance(node, list):
                index = _list_index(node, part, where, item)
                if i == len(parts) - 1:
                    node[index] = value
                    break
                child = node[index]
            else:
                if i == len(parts) - 1:
                    node[part] = value
                    break
                child = node.get(part)
                if child is None:
                    child = node[part] = {}
            if not isinstance(child, dict | list):
                raise ConfigError(f"override {item!r}: '{where}' is not a section")
            node = child
    return data


def read_config_file(path: str | Path) -> dict[str, Any]:
    """The top-level mapping of a YAML config file (empty for an empty file), read with the limits of
    `placerec.safe_yaml`; `ConfigError` naming the file if it is missing, not YAML or not a mapping."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: config file not found")
    loaded = load_yaml_file(path)
    if loaded is not None and not isinstance(loaded, dict):
        raise ConfigError(f"{path}: the top level of a config must be a mapping, got {type(loaded).__name__}")
    return loaded or {}


def load_params_file(cls: type[P], path: str | Path | None, what: str, **overrides: Any) -> P:
    """A `Params` section ``cls`` from a YAML file (None = its defaults) with top-level ``overrides`` (None values
    ignored); `ConfigError` naming the file (or ``what``) on a bad key or value."""
    data = {} if path is None else read_config_file(path)
    data.update({k: v for k, v in overrides.items() if v is not None})
    return resolve(cls, data, where=str(path or what))


def load_config(path: str | Path | None = None, overrides: list[str] | None = None) -> ExperimentConfig:
    """Load a YAML config (None = all defaults), apply overrides, validate. Raises `ConfigError`."""
    data = {} if path is None else read_config_file(path)
    origin = "<defaults>" if path is None else str(path)
    if overrides:
        if "pipelines" not in data and any(o.strip().startswith("pipelines.") for o in overrides):
            data["pipelines"] = ExperimentConfig().model_dump(mode="json")["pipelines"]  # the default ones
        apply_overrides(data, overrides)
    return parse_config(data, origin)


def config_to_yaml(config: BaseModel) -> str:
    return yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False)


def dump_default_config(path: str | Path | None = None) -> str:
    """The default config as YAML; also written (atomically) to ``path`` when given."""
    text = "# placerec default configuration (placerec dump-config)\n" + config_to_yaml(ExperimentConfig())
    if path is not None:
        from placerec.io.atomic import atomic_write

        with atomic_write(path, "w") as fh:
            fh.write(text)
    return text
