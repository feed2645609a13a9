"""The ``placerec slam`` configuration: strict `placerec.params.Params` sections, loaded like experiment configs
(`placerec.config.read_config_file` + ``key.path=value`` overrides, errors naming the dotted key).

The ``dataset`` and ``preprocess`` sections are the experiment config's (`placerec.config`); ``loops.pipeline``
is a `placerec.config.PipelineSpec` and ``loops.exclusion`` an `placerec.config.ExclusionConfig`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from pydantic import Field, model_validator

from placerec.config import (
    DatasetConfig,
    ExclusionConfig,
    PipelineSpec,
    apply_overrides,
    config_to_yaml,
    experiment_preprocess,
    read_config_file,
)
from placerec.keyframes import KeyframeParams
from placerec.odometry_gate import OdometryGateParams
from placerec.params import Params, resolve
from placerec.preprocess import PreprocessParams
from placerec.realtime import RealtimeParams
from placerec.sim.odometry import OdometryDrift
from placerec.slam.graph import GraphParams
from placerec.slam.odometry import KissIcpParams
from placerec.verify.ambiguity import AmbiguityParams

__all__ = [
    "DriftConfig",
    "OdometryConfig",
    "LoopsConfig",
    "SlamEvaluationConfig",
    "RobustnessConfig",
    "SlamOutputConfig",
    "SlamConfig",
    "load_slam_config",
    "dump_default_slam_config",
]


class DriftConfig(OdometryDrift):
    """Drifting odometry made from the dataset's true poses: `placerec.sim.odometry.OdometryDrift` (noise per
    metre, a heading bias, a scale error) and its seed."""

    seed: int | None = Field(None, description="noise seed (None: the simulator's seed, else 0)")
    scale_bias: float = Field(
        0.005,
        gt=-1,
        description="relative scale error (> -1: a scale of 0 or less stops or reverses the motion)",
    )


class OdometryConfig(Params):
    """Where the odometry poses come from.

    ``dataset``: the simulator's drifting odometry (``drift``) applied to the dataset's true poses;
    ``kiss-icp``: KISS-ICP on the scans (``kiss_icp``); ``file``: a KITTI or TUM poses file (``path``), one pose
    per scan of the dataset (after its first/last/step slice)."""

    source: Literal["dataset", "kiss-icp", "file"] = "dataset"
    drift: DriftConfig = Field(default_factory=DriftConfig)
    kiss_icp: KissIcpParams = Field(default_factory=KissIcpParams)
    path: str | None = Field(None, description="poses file for source 'file'")
    format: Literal["kitti", "tum"] | None = Field(None, description="poses file format (None: by columns)")

    @model_validator(mode="after")
    def _path_needed(self) -> OdometryConfig:
        if self.source == "file" and not self.path:
            raise ValueError("odometry.source 'file' needs odometry.path")
        return self


class LoopsConfig(Params):
    """Loop closures: a verified pipeline inside `placerec.loop_closure.LoopClosureDetector`."""

    pipeline: PipelineSpec = Field(default_factory=lambda: PipelineSpec(name="orb-hbst"))
    threshold: float = Field(
        0.25,
        description="accept a closure when its verified score >= threshold (the verification's min_score)",
    )
    exclusion: ExclusionConfig = Field(default_factory=ExclusionConfig)
    k: int = Field(1, ge=1, description="closures accepted per scan at most (best first)")
    realtime: RealtimeParams | None = Field(
        None,
        description="the detector's real-time mode ({budget_ms: 100, max_backlog: 3}: query and verification in a"
        " worker thread, closures a few scans late, the same ones); None: sequential",
    )
    odometry_gate: OdometryGateParams | None = Field(
        None,
        description="accept a closure only where it agrees with the odometry (placerec.odometry_gate: {} for the"
        " bounds chosen for the demo's drift); None: off, the robust back end alone judges",
    )
    keyframes: KeyframeParams | None = Field(
        None,
        description="places accumulated from consecutive scans (placerec.keyframes, docs/keyframes.md), e.g."
        " {seconds: 0.5, every_metres: 1.8} for a Livox-style or solid-state scanner; the graph keeps a pose a"
        " scan; exclusion.frames then counts keyframes. None: each scan a place",
    )


class SlamEvaluationConfig(Params):
    """Trajectory errors against the dataset's poses (when it has them) and the check of each loop edge."""

    rpe_delta: int = Field(10, ge=1, description="RPE over this many frames")
    false_loop_translation: float = Field(
        1.0, gt=0, description="a loop whose pose is off by more than this (m) is false"
    )
    false_loop_rotation_deg: float = Field(5.0, gt=0, description="... or by more than this (deg)")


class RobustnessConfig(Params):
    """False loop edges injected into the graph, to test the robust back end (0: none)."""

    false_loops: int = Field(
        0,
        ge=0,
        le=100_000,
        description="random scan pairs at least 30 m apart, given plausible poses (at most 100,000)",
    )
    seed: int = 0
    min_distance: float = Field(30.0, gt=0, description="the pair's true distance at least this (m)")


class SlamOutputConfig(Params):
    """Where results go: ``dir/<name>_<timestamp>/`` with a ``latest`` link."""

    dir: str = "results"
    figures: bool = True
    progress: bool = True
    map_ply: bool = Field(False, description="write the corrected map (map.ply; scans read a second time)")
    map_voxel: float = Field(0.5, gt=0, description="voxel of the corrected map (m)")
    save_map: str | None = Field(
        None,
        description="save a map folder here (placerec.maps: every scan a keyframe at its optimised pose, the"
        " pipeline's database, the graph) for placerec localize and --prior-map",
    )
    overwrite_map: bool = Field(False, description="replace an existing map at save_map")
    map_pipelines: list[str] = Field(
        default_factory=list,
        max_length=8,
        description="more pipelines whose databases the saved map holds besides loops.pipeline's (every scan"
        " described and added to each, at its preset's threshold for the sensor), e.g. scan-context for a later"
        " session's prior_map.join_pipelines; with --prior-map the prior map's own database of each is extended",
    )
    map_pipeline_params: dict[str, dict[str, Any]] = Field(
        default_factory=dict,
        description="parameters of map_pipelines by name (merged over the preset and the sensor's settings), e.g."
        " configs/map_cross_sensor.yaml's Scan Context for a later session with another sensor",
    )


class PriorMapConfig(Params):
    """A map of an earlier session (`placerec.maps`) the run joins (`placerec.slam.multisession`): its pipeline
    database answers the inter-session queries, the sessions are joined once ``min_join_loops`` closures agree."""

    path: str | None = Field(None, description="the prior map folder (None: a single-session run)")
    anchor: Literal["fixed", "anchored"] = Field(
        "fixed",
        description="fixed: the map's poses do not move; anchored: its own graph holds them and closures may move"
        " them within its covariance (needs a map saved by placerec slam)",
    )
    min_join_loops: int = Field(2, ge=2, le=1000, description="agreeing inter-session closures that join")
    join_translation_m: float = Field(1.0, gt=0, description="m; two closures agree within this")
    join_rotation_deg: float = Field(5.0, gt=0, description="deg; ... and this")
    allow_other_sensor: bool = Field(False, description="join a session from another sensor than the map's")
    join_pipelines: list[str] = Field(
        default_factory=list,
        max_length=8,
        description="more of the map's pipelines whose global search (placerec.maps.Localizer, query only, at the"
        " map's threshold for each unless join_threshold) adds inter-session closures for every scan, e.g."
        " scan-context for a session driven the other way than the map",
    )
    join_threshold: float | None = Field(
        None,
        description="join_pipelines' global fixes score at least this (None: the map's threshold for each)",
    )
    join_ambiguity: AmbiguityParams = Field(
        default_factory=AmbiguityParams,
        description="join_pipelines' global search refuses a fix another place nearly matches"
        " (placerec.verify.ambiguity; off)",
    )


class SlamConfig(Params):
    """The root of a ``placerec slam`` config."""

    name: str = "slam"
    dataset: DatasetConfig = Field(default_factory=DatasetConfig)
    preprocess: PreprocessParams = Field(default_factory=experiment_preprocess)
    odometry: OdometryConfig = Field(default_factory=OdometryConfig)
    loops: LoopsConfig = Field(default_factory=LoopsConfig)
    graph: GraphParams = Field(default_factory=GraphParams)
    evaluation: SlamEvaluationConfig = Field(default_factory=SlamEvaluationConfig)
    robustness: RobustnessConfig = Field(default_factory=RobustnessConfig)
    output: SlamOutputConfig = Field(default_factory=SlamOutputConfig)
    prior_map: PriorMapConfig = Field(default_factory=PriorMapConfig)

    @model_validator(mode="after")
    def _keyframes_join_with_the_loop_pipeline(self) -> SlamConfig:
        """``loops.keyframes``: the join pipelines' global search localises single scans, which hold too little of
        a place where keyframes are needed; the loop pipeline's keyframes join the session."""
        if self.loops.keyframes is not None and self.prior_map.join_pipelines:
            raise ValueError(
                "prior_map.join_pipelines: not with loops.keyframes (they localise single scans); the loop"
                " pipeline's keyframes join the session to the map"
            )
        return self

    @model_validator(mode="after")
    def _other_pipelines(self) -> SlamConfig:
        """``prior_map.join_pipelines`` and ``output.map_pipelines`` name pipelines besides loops.pipeline's."""
        loop = self.loops.pipeline.name
        for key, names in (
            ("prior_map.join_pipelines", self.prior_map.join_pipelines),
            ("output.map_pipelines", self.output.map_pipelines),
        ):
            if loop in names:
                raise ValueError(f"{key}: {loop!r} is loops.pipeline already; name other pipelines")
        unknown = sorted(set(self.output.map_pipeline_params) - set(self.output.map_pipelines))
        if unknown:
            raise ValueError(f"output.map_pipeline_params: {unknown} not in output.map_pipelines")
        if self.output.map_pipeline_params and self.prior_map.path is not None:
            raise ValueError(
                "output.map_pipeline_params: with prior_map.path the merged map extends the prior map's own "
                "databases, with their parameters"
            )
        return self


def load_slam_config(path: str | Path | None = None, overrides: list[str] | None = None) -> SlamConfig:
    """Load a SLAM YAML config (None = defaults), apply ``key.path=value`` overrides, validate (`ConfigError`)."""
    data = {} if path is None else read_config_file(path)
    origin = "<defaults>" if path is None else str(path)
    if overrides:
        apply_overrides(data, overrides)
    return resolve(SlamConfig, data, where=f"{origin}: invalid SLAM configuration")


def dump_default_slam_config() -> str:
    """The default SLAM config as YAML."""
    return "# placerec slam default configuration\n" + config_to_yaml(SlamConfig())
