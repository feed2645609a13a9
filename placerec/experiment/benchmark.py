"""``placerec bench``: every loop pipeline over a matrix of simulated worlds x sensors x seeds, judged at fixed
operating thresholds.

A benchmark config (``configs/benchmark.yaml``) names a split of `placerec.experiment.protocol` (``test``: the
held-out matrix; ``tuning``: the matrix the presets' thresholds are chosen on), optionally a subset of its worlds,
sensors and seeds, the pipelines and the evaluation. Each cell (world, sensor, seed) is one loop-mode run of the
simulator's ``route`` through `placerec.experiment.runner.run_loop` and `placerec.experiment.report.report_loop`
(the pose and distance ground truths), written to ``<out>/cells/<cell>/`` with a ``cell.json`` stamp of its
config: a rerun (or an interrupted benchmark started again) skips the cells already done with the same config, and
descriptions are cached on disk (``output.cache_dir``). Cells run in ``execution.workers`` local processes or on a
Dask cluster (``execution.executor: dask``).

Per pipeline and cell, and over the matrix (mean and worst): max F1 (distance ground truth, as the VPR paper),
precision / recall / F1 at the pipeline's fixed operating threshold under the pose ground truth (the benchmark's
headline: what a pose graph would receive) and the distance one, recall at 100 % precision, the accepted closures'
translation / rotation errors (median, p95, max over the whole matrix), describe / query / verify ms per scan.
Outputs: ``benchmark.json``, ``cells.csv``, heatmaps (pipeline x cell), ``index.html``, a console table and one
JSON line (`bench_line`).
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from placerec.config import (
    EvaluationConfig,
    ExclusionConfig,
    ExecutionConfig,
    ExperimentConfig,
    PipelineSpec,
    apply_overrides,
    experiment_preprocess,
    read_config_file,
)
from placerec.errors import ArtifactError, ConfigError
from placerec.experiment import protocol
from placerec.experiment.benchmark_summary import BENCH_VERSION, summarise, write_outputs
from placerec.experiment.run_folder import json_default
from placerec.hashing import stable_hash
from placerec.io.atomic import atomic_write
from placerec.keyframes import KeyframeParams
from placerec.params import Params, resolve
from placerec.preprocess import PreprocessParams

__all__ = [
    "BenchmarkConfig",
    "CaptureParams",
    "Cell",
    "load_benchmark_config",
    "run_cell",
    "run_benchmark",
    "read_benchmark",
]

log = logging.getLogger(__name__)


class BenchOutputConfig(Params):
    """Where the benchmark goes: ``dir/<name>/`` (a fixed folder, so a rerun resumes), the description cache."""

    dir: str = "results"
    cache_dir: str | None = Field(
        ".cache/descriptions", description="per-scan description cache (None = off)"
    )
    figures: bool = True
    progress: bool = True


class CaptureParams(Params):
    """How a benchmark drives one sensor, when not as a spinning sensor's one scan per ``spacing`` metres.

    ``rate_hz``: scans per second along the route's speed profile; ``sweep_motion``: each ray measured from the
    pose at its own time (scans taken while moving, left un-deskewed as a driver delivers them);
    ``odometry_drift``: the relative translation error of the odometry that de-skews and places keyframes (None:
    the true poses); ``keyframes``: the pipelines see keyframes of these windows; ``exclusion``: the loop
    exclusion window of this sensor's cells (keyframes are metres apart, so a window counted in frames would
    mean something else). Overrides of the registry's settings for the sensor (`placerec.sensor_presets`, chosen
    on its tuning cells), for trying others: ``feature_params``, extractor settings of this sensor's visual
    pipelines; ``verify_score``, the verification's score and acceptance settings (`placerec.verify.ScoreParams`)
    of its pipelines that verify with a score; ``thresholds``, operating thresholds per pipeline label. A
    pipeline's own ``params:`` and ``threshold:`` in the config still win."""

    rate_hz: float | None = Field(None, gt=0, le=1000, allow_inf_nan=False, description="scans per second")
    sweep_motion: bool = Field(False, description="rays measured from the pose at their own time")
    odometry_drift: float | None = Field(None, ge=0, le=1, allow_inf_nan=False, description="relative error")
    keyframes: KeyframeParams | None = None
    exclusion: ExclusionConfig | None = None
    feature_params: dict[str, Any] = Field(
        default_factory=dict,
        description="overrides of the feature extractor's parameters in every pipeline of this sensor's cells that "
        "has an intensity-image front end (e.g. {nfeatures: 1000} for 16- and 32-row images: "
        "docs/intensity_images.md, 'Sparse spinning sensors')",
    )
    verify_score: dict[str, Any] = Field(
        default_factory=dict,
        description="overrides of the verification's score and acceptance settings (verify.score) in every "
        "pipeline of this sensor's cells that verifies with a score (e.g. the VLP-16's overlap gate for its "
        "displacement: docs/sensors.md)",
    )
    thresholds: dict[str, Annotated[float, Field(ge=0, allow_inf_nan=False)]] = Field(
        default_factory=dict, description="operating threshold per pipeline label in this sensor's cells"
    )

    @field_validator("verify_score")
    @classmethod
    def _valid_score_settings(cls, v: dict[str, Any]) -> dict[str, Any]:
        from placerec.verify.params import ScoreParams

        resolve(ScoreParams, v)  # unknown keys, bad values: named
        return v


def _default_capture() -> dict[str, CaptureParams]:
    return {name: CaptureParams(**values) for name, values in protocol.CAPTURE.items()}


class BenchmarkConfig(Params):
    """The root of a benchmark config (module docstring). ``worlds`` / ``sensors`` / ``seeds`` default to the
    split's (`placerec.experiment.protocol`); a tuning benchmark may not name a test-split seed."""

    name: str = "benchmark"
    split: Literal["test", "tuning"] = "test"
    worlds: list[str] | None = None
    sensors: list[str] | None = None
    seeds: list[int] | None = None
    route: str = "default"
    n_scans: int | None = Field(None, ge=1, le=100_000, description="scans per cell (None: the whole route)")
    spacing: float = Field(1.0, gt=0, allow_inf_nan=False, description="metres between scans")
    preprocess: PreprocessParams = Field(default_factory=experiment_preprocess)
    pipelines: list[PipelineSpec] = Field(min_length=1)
    evaluation: EvaluationConfig = Field(default_factory=EvaluationConfig)
    output: BenchOutputConfig = Field(default_factory=BenchOutputConfig)
    execution: ExecutionConfig = Field(default_factory=ExecutionConfig)
    capture: dict[str, CaptureParams] = Field(
        default_factory=_default_capture,
        description="per sensor: how it is driven (default placerec.experiment.protocol.CAPTURE)",
    )

    @field_validator("worlds")
    @classmethod
    def _known_worlds(cls, v: list[str] | None) -> list[str] | None:
        from placerec.sim.presets import preset_names

        return _known("world", v, preset_names())

    @field_validator("sensors")
    @classmethod
    def _known_sensors(cls, v: list[str] | None) -> list[str] | None:
        from placerec.sim.sensors import sensor_names

        return _known("sensor", v, sensor_names())

    @field_validator("capture")
    @classmethod
    def _known_capture_sensors(cls, v: dict[str, CaptureParams]) -> dict[str, CaptureParams]:
        from placerec.sim.sensors import sensor_names

        _known("sensor", list(v), sensor_names())
        return v

    @model_validator(mode="after")
    def _split_rules(self) -> BenchmarkConfig:
        if self.split == "tuning":
            bad = [s for s in self.seeds or [] if protocol.is_test_seed(s)]
            if bad:
                raise ValueError(
                    f"seeds: {bad[0]} is a test-split seed; a tuning benchmark may not use it (docs/protocol.md)"
                )
        if self.evaluation.mode != "loop":
            raise ValueError("evaluation.mode: a benchmark evaluates loop closure ('loop')")
        labels = [p.display_name for p in self.pipelines]
        dupes = sorted({x for x in labels if labels.count(x) > 1})
        if dupes:
            raise ValueError(f"pipeline labels must be unique; repeated: {dupes}")
        return self

    def cells(self) -> list[Cell]:
        """The matrix: the split's worlds x sensors x seeds, or the config's subsets."""
        test = self.split == "test"
        worlds = self.worlds or list(protocol.TEST_WORLDS if test else protocol.TUNING_WORLDS)
        sensors = self.sensors or list(protocol.TEST_SENSORS if test else protocol.TUNING_SENSORS)
        seeds = self.seeds or list(protocol.TEST_SEEDS if test else protocol.TUNING_SEEDS)
        return [Cell(w, s, int(seed)) for w in worlds for s in sensors for seed in seeds]

    def cell_config(self, cell: Cell) -> ExperimentConfig:
        """The loop-mode experiment config of one cell (with its sensor's `CaptureParams`, if any)."""
        simulator: dict[str, Any] = {
            "world": cell.world,
            "sensor": cell.sensor,
            "seed": cell.seed,
            "route": self.route,
            "n_scans": self.n_scans,
            "spacing": self.spacing,
        }
        evaluation = self.evaluation.model_dump(mode="json")
        extra: dict[str, Any] = {}
        capture = self.capture.get(cell.sensor)
        if capture is not None:
            for key in ("rate_hz", "sweep_motion", "odometry_drift"):
                if getattr(capture, key) not in (None, False):
                    simulator[key] = getattr(capture, key)
            if capture.keyframes is not None:
                extra["keyframes"] = capture.keyframes.model_dump(mode="json")
            if capture.exclusion is not None:
                evaluation["exclusion"] = capture.exclusion.model_dump(mode="json")
        odometry = self.evaluation.odometry_gate is not None
        pipelines = [_cell_spec(p, cell.sensor, capture, odometry) for p in self.pipelines]
        data = {
            "name": f"{self.name}-{cell.name}",
            "dataset": {"source": "simulator", "simulator": simulator},
            **extra,
            "preprocess": self.preprocess.model_dump(mode="json"),
            "pipelines": pipelines,
            "evaluation": evaluation,
            "output": {
                "dir": self.output.dir,
                "cache_dir": self.output.cache_dir,
                "figures": False,
                "progress": False,
            },  # fmt: skip
        }
        return resolve(ExperimentConfig, data, where=f"benchmark cell {cell.name}")


def _cell_spec(
    spec: PipelineSpec, sensor: str, capture: CaptureParams | None, odometry: bool = False
) -> dict[str, Any]:
    """A pipeline spec (JSON) in a cell of ``sensor``: its parameters on that sensor (the registry's,
    `placerec.sensor_presets`, those chosen with the odometry gate when ``odometry``, then the capture's
    overrides) under its own, which win, so a cell's config shows
    every setting it ran with; the capture's threshold for it when it gives none (else the registry's for the
    sensor applies, `ExperimentConfig.operating_threshold`)."""
    from placerec.params import deep_merge
    from placerec.recognizer import PIPELINES

    out = spec.model_dump(mode="json")
    entry = PIPELINES.get(spec.name)
    own = entry.params_for(sensor, odometry) if entry is not None else {}
    given = _capture_params(spec.name, capture) if capture is not None else {}
    if own or given:
        out["params"] = deep_merge(own, given, out.get("params") or {})
    if capture is not None and out.get("threshold") is None and spec.display_name in capture.thresholds:
        out["threshold"] = capture.thresholds[spec.display_name]
    return out


def _capture_params(name: str, capture: CaptureParams) -> dict[str, Any]:
    """The capture's parameter overrides for pipeline ``name``: ``feature_params`` when it has an intensity-image
    front end (its parameters have ``feature_params``), ``verify_score`` when it verifies with a score (its
    parameters have ``verify.score``); none for other pipelines."""
    cls = _recognizer_class(name)
    if cls is None:
        return {}
    fields = cls.Params.model_fields
    verify = fields["verify"].annotation if "verify" in fields else None
    out: dict[str, Any] = {}
    if capture.feature_params and "feature_params" in fields:
        out["feature_params"] = capture.feature_params
    if capture.verify_score and "score" in getattr(verify, "model_fields", {}):
        out["verify"] = {"score": capture.verify_score}
    return out


def _recognizer_class(name: str) -> Any:
    """The class of pipeline ``name`` when it is a `Recognizer` (it declares its parameters), else None."""
    from placerec.recognizer import Recognizer, pipeline_class

    cls = pipeline_class(name)
    return cls if isinstance(cls, type) and issubclass(cls, Recognizer) else None


@dataclass(frozen=True)
class Cell:
    """One cell of the matrix."""

    world: str
    sensor: str
    seed: int

    @property
    def name(self) -> str:
        return f"{self.world}_{self.sensor}_{self.seed}"


def _known(kind: str, names: list[str] | None, known: list[str]) -> list[str] | None:
    """``names`` when every one is ``known``; a `ValueError` naming the first unknown one otherwise."""
    bad = [n for n in names or [] if n not in known]
    if bad:
        raise ValueError(f"unknown {kind} {bad[0]!r}; known: {', '.join(known)}")
    return names


def load_benchmark_config(path: str | Path, overrides: list[str] | None = None) -> BenchmarkConfig:
    """A benchmark YAML with ``key.path=value`` overrides, validated; `ConfigError` naming the key."""
    data = read_config_file(path)
    if overrides:
        apply_overrides(data, overrides)
    return resolve(BenchmarkConfig, data, where=f"{path}: invalid benchmark configuration")


def _cell_key(cfg: ExperimentConfig) -> str:
    """The stamp of a cell's result: its config, each pipeline's resolved parameters (a registry preset changed
    since makes the cell run again) and the placerec version (not the thresholds: the figures at a threshold are
    recomputed from the cell's files, `cell_metrics`, and so is the odometry gate; nor the localisation settings).
    A pipeline that matches within the gate's motion prior (``verify.guided``) answers what it does because of the
    gate and the closures accepted at its operating threshold while the cell ran: then both are in the stamp."""
    from placerec._version import __version__
    from placerec.recognizer import pipeline_params
    from placerec.verify.guided import guides

    data = cfg.model_dump(mode="json")
    data["evaluation"].pop("localize", None)  # localisation settings: no part of a loop-mode cell
    gate = data["evaluation"].pop("odometry_gate", None)  # judged from the cell's files, as the thresholds
    guided = False
    for spec, given in zip(data["pipelines"], cfg.pipelines, strict=True):
        spec.pop("threshold", None)
        if _recognizer_class(given.name) is not None:
            resolved = pipeline_params(
                given.name, given.params, sensor=cfg.sensor, odometry=cfg.with_odometry
            )
            spec["resolved"] = resolved.model_dump(mode="json")
            if gate is not None and guides(resolved):
                spec["guided_at"] = cfg.operating_threshold(given)
                guided = True
    if guided:
        data["evaluation"]["odometry_gate"] = gate
    return stable_hash({"config": data, "placerec": __version__, "v": BENCH_VERSION})


def run_cell(cell_cfg_json: dict[str, Any], folder: str) -> dict[str, Any]:
    """Run one cell (a loop-mode config as JSON) into ``folder``; returns ``{"cell", "seconds", "metrics"}`` and
    writes it as ``folder/cell.json`` last, so a cell with a ``cell.json`` is complete. Runs in a worker process."""
    from placerec.config import parse_config
    from placerec.experiment.report import report_loop, require_poses
    from placerec.experiment.run_folder import finite_or_null
    from placerec.experiment.runner import build_pipelines, loop_sequence, run_loop
    from placerec.experiment.truth import TruthClouds

    cfg = parse_config(cell_cfg_json)
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    seq = loop_sequence(cfg)
    truth = TruthClouds(cfg.evaluation, require_poses(seq))
    seq, records = run_loop(cfg, None, build_pipelines(cfg), on_scan=truth, opened=seq)
    payload = report_loop(cfg, out, seq, records, truth, link_latest=False)
    offsets = np.cumsum([0] + [v.size for v in truth.voxels])
    with atomic_write(out / "truth.npz", "wb") as fh:
        overlap = truth.overlap or (np.zeros(0, bool), np.zeros(0))
        np.savez_compressed(
            fh,
            keys=np.concatenate(truth.voxels or [np.zeros(0, np.int64)]),
            offsets=offsets,
            revisit=overlap[0],
            best_overlap=overlap[1],
        )
    result = {
        "version": BENCH_VERSION,
        "key": _cell_key(cfg),
        "cell": out.name,
        "seconds": time.perf_counter() - t0,
        "n_scans": payload["n_scans"],
        "metrics": finite_or_null(payload["pipelines"]),
    }
    with atomic_write(out / "cell.json", "w") as fh:
        json.dump(result, fh, allow_nan=False, default=json_default)
    return result


def _done_cell(folder: Path, key: str) -> dict[str, Any] | None:
    """The result of a finished cell made with the same config, else None (a damaged stamp is redone)."""
    path = folder / "cell.json"
    if not path.is_file():
        return None
    try:
        found = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        log.warning("%s: unreadable (%s); the cell is run again", path, exc)
        return None
    if not isinstance(found, dict) or found.get("version") != BENCH_VERSION or found.get("key") != key:
        return None
    return found


def run_benchmark(
    bench: BenchmarkConfig, out_dir: str | Path | None = None, fresh: bool = False
) -> tuple[Path, dict[str, Any]]:
    """Run every cell not done yet (all with ``fresh``), then summarise; returns (folder, ``benchmark.json``).

    A cell is done when its ``cell.json`` stamp holds the key of its config and of the placerec version: after
    changing placerec's code without changing its version, run with ``fresh`` (``--fresh``)."""
    from placerec.experiment.parallel import task_pool
    from placerec.experiment.runner import build_pipelines, progress_bars

    cells = bench.cells()
    build_pipelines(bench.cell_config(cells[0]))  # every pipeline and parameter checked before any cell runs
    root = Path(out_dir) if out_dir is not None else Path(bench.output.dir) / bench.name
    try:
        (root / "cells").mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(
            f"output.dir: cannot make the benchmark folder {root}: {exc.strerror or exc}"
        ) from None
    t0 = time.perf_counter()
    results: dict[str, dict[str, Any]] = {}
    todo = []
    for cell in cells:
        cfg = bench.cell_config(cell)
        folder = root / "cells" / cell.name
        done = None if fresh else _done_cell(folder, _cell_key(cfg))
        if done is not None:
            results[cell.name] = done
        else:
            todo.append((cfg, folder))
    log.info("benchmark %s: %d cells, %d cached, %d to run", bench.name, len(cells), len(results), len(todo))

    with progress_bars(bench.output.progress) as progress:
        task = progress.add_task(f"cells ({len(results)} cached)", total=len(todo))

        def finished(result: dict[str, Any]) -> None:
            progress.advance(task)

        args = [(cfg.model_dump(mode="json"), str(folder)) for cfg, folder in todo]
        if todo and bench.execution.workers == 1 and bench.execution.executor == "local":
            ran = []
            for a in args:
                ran.append(run_cell(*a))
                finished(ran[-1])
        elif todo:
            with task_pool(bench.execution) as submit:
                ran = submit(run_cell, args, finished)
        else:
            ran = []
    results.update({r["cell"]: r for r in ran})
    ordered = {}
    for c in cells:
        found = results[c.name]
        ordered[c.name] = {
            **found,
            "metrics": cell_metrics(bench, c, root / "cells" / c.name, found["metrics"]),
        }
    payload = summarise(bench, ordered)
    payload["seconds"] = time.perf_counter() - t0
    payload["cells_run"] = len(todo)
    write_outputs(bench, root, payload)
    return root, payload


@dataclass(frozen=True)
class CellFiles:
    """A finished cell read back: its config (with its sensor's settings), poses, scan times, the truth clouds of
    the run, and per pipeline (in the config's order) its candidate table (after the odometry gate, if the
    evaluation has one), pose ground truth and the candidates the gate refused."""

    cfg: ExperimentConfig
    poses: np.ndarray
    stamps: np.ndarray | None
    truth: Any
    tables: list[Any]
    pose_gts: list[Any]
    refused: list[np.ndarray]


def read_cell(
    bench: BenchmarkConfig, cell: Cell, folder: Path, thresholds: Mapping[str, float] | None = None
) -> CellFiles:
    """A finished cell's files (poses, candidates, the scans' voxels in ``truth.npz``) with its pose truths made
    from them, the run's overlap search not made again, judged at the operating thresholds in force or at
    ``thresholds`` (by pipeline label) where given (they decide which closures an odometry gate through loops
    predicts through: `placerec.experiment.report.odometry_gated`); `ArtifactError` naming the file when one is
    missing or damaged."""
    from placerec.experiment.candidates import read_candidates
    from placerec.experiment.report import odometry_gated, pose_truths
    from placerec.experiment.run_folder import slug
    from placerec.experiment.truth import TruthClouds
    from placerec.io import read_poses

    cfg = bench.cell_config(cell)
    poses = read_poses(folder / "poses.txt")[0]
    stamps = np.loadtxt(folder / "times.txt", ndmin=1) if (folder / "times.txt").is_file() else None
    try:
        with np.load(folder / "truth.npz") as z:
            keys, offsets = z["keys"], z["offsets"]
            overlap = (z["revisit"], z["best_overlap"]) if "revisit" in z.files else None
    except (OSError, ValueError, KeyError) as exc:
        raise ArtifactError(
            f"{folder / 'truth.npz'}: missing or damaged ({exc}); run the cell again (--fresh)"
        ) from None
    truth = TruthClouds(cfg.evaluation, poses)
    truth.voxels = [keys[a:b] for a, b in zip(offsets[:-1], offsets[1:], strict=True)]
    truth.overlap = overlap  # the overlap search of the run, not made again
    raw = [read_candidates(folder / f"candidates_{slug(p.display_name)}.csv") for p in cfg.pipelines]
    tables, refused = odometry_gated(
        cfg, raw, poses, [judged_at(cfg, spec, thresholds) for spec in cfg.pipelines]
    )
    return CellFiles(
        cfg, poses, stamps, truth, tables, pose_truths(cfg, tables, poses, stamps, truth), refused
    )


def judged_at(
    cfg: ExperimentConfig, spec: PipelineSpec, thresholds: Mapping[str, float] | None
) -> float | None:
    """The threshold a cell's pipeline is judged at: ``thresholds``' entry for its label, else its operating one."""
    if thresholds is not None and spec.display_name in thresholds:
        return thresholds[spec.display_name]
    return cfg.operating_threshold(spec)


def cell_metrics(
    bench: BenchmarkConfig,
    cell: Cell,
    folder: Path,
    stored: dict[str, Any],
    thresholds: Mapping[str, float] | None = None,
) -> dict[str, Any]:
    """A finished cell's metrics per pipeline label with the figures at the operating thresholds recomputed from
    its files (`read_cell`) at the thresholds in force now, or at ``thresholds`` (by label) where given; the
    stored entries give the rest (times)."""
    from placerec.experiment.report import loop_summary
    from placerec.experiment.run_folder import finite_or_null

    f = read_cell(bench, cell, folder, thresholds)
    out = {}
    for spec, table, pose_gt, refused in zip(f.cfg.pipelines, f.tables, f.pose_gts, f.refused, strict=True):
        label = spec.display_name  # the cell's spec: with its sensor's thresholds
        threshold = judged_at(f.cfg, spec, thresholds)
        _, summary = loop_summary(f.cfg, table, f.poses, f.stamps, threshold, f.truth, pose_gt, refused)
        kept = stored.get(label, {})
        out[label] = {**kept, **finite_or_null(summary)}
    return out


#: The most thresholds `suggestions` tries per pipeline with an odometry gate through loops.
_MAX_TRIED = 40


def suggestions(
    bench: BenchmarkConfig, root: Path, cells: dict[str, dict[str, Any]], step: float = 0.05
) -> tuple[dict[str, float | None], dict[str, dict[str, float | None]]]:
    """The operating thresholds the tuning rule picks over the whole matrix and over each sensor's cells alone
    (`suggest_thresholds`, `suggest_by_sensor`), from the finished cells under ``root`` (``cells``: their
    ``cell.json``). With an odometry gate through loops (`placerec.odometry_gate.LoopChain`) the closures accepted
    at a threshold change which candidates the gate refuses, so a threshold is judged with the closures accepted
    at it: the rule's grid is walked up from the verification's floor, every cell judged again from its files at
    each threshold tried, and a pipeline's pick is the first threshold at which no false closure scores as high."""
    from placerec.experiment.benchmark_summary import suggest_by_sensor, suggest_thresholds

    gate = bench.evaluation.odometry_gate
    if gate is None or not gate.bounds.through_loops:
        return suggest_thresholds(bench, cells, step), suggest_by_sensor(bench, cells, step)
    by_name = {c.name: c for c in bench.cells()}
    sensors = dict.fromkeys(by_name[name].sensor for name in cells)
    overall = _walk_thresholds(bench, root, by_name, cells, step)
    per_sensor = {
        sensor: _walk_thresholds(
            bench, root, by_name, {n: c for n, c in cells.items() if by_name[n].sensor == sensor}, step
        )
        for sensor in sensors
    }
    return overall, per_sensor


def _walk_thresholds(
    bench: BenchmarkConfig,
    root: Path,
    by_name: dict[str, Cell],
    cells: dict[str, dict[str, Any]],
    step: float,
) -> dict[str, float | None]:
    """`suggestions`' walk over ``cells`` (``by_name``: the matrix's cells by name): per pipeline the first
    threshold of the grid the rule accepts when the cells are judged at it."""
    from placerec.experiment.benchmark_summary import rule_inputs, tuning_pick

    units: dict[str, float] = {}
    trying: dict[str, float] = {}
    picked: dict[str, float | None] = {}
    for label, inputs in rule_inputs(bench, cells, step).items():
        if inputs is None:
            picked[label] = None
            continue
        _, floor, unit = inputs
        units[label] = unit
        trying[label] = tuning_pick(-math.inf, floor, unit) or unit  # a threshold of 0 accepts every answer
    for _ in range(_MAX_TRIED):
        if not trying:
            break
        judged = {
            name: {
                **c,
                "metrics": cell_metrics(bench, by_name[name], root / "cells" / name, c["metrics"], trying),
            }
            for name, c in cells.items()
        }
        rule = rule_inputs(bench, judged, step)
        for label in list(trying):
            inputs = rule[label]
            if inputs is None:  # no score left to judge
                picked[label] = None
                del trying[label]
            elif tuning_pick(*inputs) <= trying[label] + 1e-9:  # no false closure scores as high
                picked[label] = trying.pop(label)
            else:
                trying[label] = round(trying[label] + units[label], 6)
    picked.update(dict.fromkeys(trying))  # none within the tries: no pick
    return {spec.display_name: picked.get(spec.display_name) for spec in bench.pipelines}


def read_benchmark(path: str | Path) -> dict[str, Any]:
    """A ``benchmark.json`` back; `ArtifactError` naming the file when it is not one of this version."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ArtifactError(f"{path}: not a readable benchmark.json ({exc})") from None
    if not isinstance(data, dict) or data.get("version") != BENCH_VERSION or "pipelines" not in data:
        raise ArtifactError(f"{path}: not a benchmark.json of version {BENCH_VERSION}")
    return data
