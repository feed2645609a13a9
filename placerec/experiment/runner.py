"""Run an experiment config: dataset -> preprocessing -> every pipeline -> per-query records.

Scans are read and preprocessed once and fed to all pipelines in lockstep; pipelines with the same front end
(`placerec.types.PlaceRecognizer.frontend_key`) share one description per scan, in memory and in the on-disk
cache. The describe time reported for a scan is the time its front end took to compute the description, stored
with it, so it does not depend on the cache or on which pipeline came first. A scan a pipeline cannot describe
(`ScanDataError`: blank, a few points) gets no candidates from it and is not added to its database.
"""

from __future__ import annotations

import logging
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from placerec.config import ExperimentConfig
from placerec.errors import ConfigError, ScanDataError
from placerec.experiment.cache import DescriptionCache, config_hash
from placerec.experiment.candidates import CandidateTable
from placerec.experiment.datasets import dataset_fingerprint, files_fingerprint, keyframed, open_dataset
from placerec.experiment.gate import gate_odometry, judge_through_loops
from placerec.experiment.preprocessing import preprocessed_scan
from placerec.loop_closure import LoopClosureDetector, split_verify_time
from placerec.loop_filter import LoopFilterParams
from placerec.odometry_gate import ChainPrior, LoopChain
from placerec.params import Params
from placerec.types import Candidate, Description, PlaceRecognizer, Scan, Sequence
from placerec.verify.guided import guides
from placerec.viewer import active

log = logging.getLogger(__name__)

__all__ = [
    "PipelineRecord",
    "build_pipelines",
    "loop_sequence",
    "localize_sequences",
    "run_loop",
    "run_localize",
    "progress_bars",
    "description_cache",
]

STAGES = ("preprocess", "describe", "query", "insert", "verify")
#: the stages a pipeline's time per scan sums (`PipelineRecord.per_scan_ms`): preprocessing is shared by every
#: pipeline of a run (one scan preprocessed once), so it is not a pipeline's own time
SCAN_STAGES = ("describe", "query", "insert", "verify")
#: what that time includes, in words (the legends of the console table, the HTML report and timing.png)
PER_SCAN_TIME = "describe + query + insert + verify; preprocessing (shared by all pipelines) excluded"


@dataclass
class PipelineRecord:
    """What one pipeline answered: top-N candidates per query and stage times (ms) per scan; ``pipeline`` is
    the registry name (or ``module:Class``), ``params`` the resolved parameters (presets and defaults applied),
    ``threshold`` the operating threshold it is judged at (the config's, else the registry preset's; None: none)."""

    label: str
    name: str
    pipeline: str = ""
    params: dict[str, Any] = field(default_factory=dict)
    query_ids: list[int] = field(default_factory=list)
    candidates: list[list[Candidate]] = field(default_factory=list)
    timing_ms: dict[str, list[float]] = field(default_factory=lambda: {s: [] for s in STAGES})
    threshold: float | None = None
    #: DLoopDetector's islands and temporal consistency over the candidates in loop mode (`placerec.loop_filter`)
    loop_filter: LoopFilterParams | None = None

    def table(self) -> CandidateTable:
        """The candidates as a `placerec.experiment.candidates.CandidateTable` (top-1, top-N, scores)."""
        return CandidateTable.from_candidates(self.query_ids, self.candidates)

    def per_scan_ms(self) -> np.ndarray:
        """Total pipeline time per processed scan: the sum of the `SCAN_STAGES` (describe + query + insert +
        verify; preprocessing, shared by every pipeline of a run, excluded). The one definition of "ms/scan":
        ``metrics.json``'s ``time_ms``, the console table and ``timing.png`` all use it."""
        stages = [self.timing_ms[s] for s in SCAN_STAGES]
        return np.sum(np.asarray(stages, dtype=np.float64).reshape(len(stages), -1), axis=0)

    def stage_means_ms(self) -> dict[str, float]:
        """Mean ms per scan of each of the `SCAN_STAGES` (0 when no scan): they sum to ``per_scan_ms().mean()``."""
        return {s: float(np.mean(self.timing_ms[s])) if self.timing_ms[s] else 0.0 for s in SCAN_STAGES}


@contextmanager
def progress_bars(enabled: bool) -> Iterator[Any]:
    """A rich progress display (or a silent stand-in) with one task per pipeline."""
    if not enabled:

        class _Silent:
            def add_task(self, *a: Any, **k: Any) -> int:
                return 0

            def advance(self, *a: Any, **k: Any) -> None:
                pass

        yield _Silent()
        return
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    with Progress(
        TextColumn("{task.description:<22}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
        transient=False,
    ) as progress:
        yield progress


class _Frontends:
    """Shares descriptions between pipelines with the same front end, for the current scan and on disk; each
    description comes with the milliseconds its front end took to compute it (stored with it in the cache)."""

    def __init__(self, cache: DescriptionCache) -> None:
        self.cache = cache
        self._current: dict[str, tuple[Description, float] | ScanDataError] = {}
        self._index = -1

    def describe(self, rec: PlaceRecognizer, index: int, scan: Scan) -> tuple[Description, float]:
        """(description, describe ms) of scan ``index`` by ``rec``'s front end; a `ScanDataError` from it is
        raised again for every pipeline sharing the front end, without describing the scan again."""
        if index != self._index:
            self._current.clear()
            self._index = index
        key = rec.frontend_key
        if key not in self._current:
            on_disk = getattr(rec, "cache_descriptions", True)
            hit = self.cache.get(key, index) if on_disk else None
            if hit is None:
                t0 = time.perf_counter()
                try:
                    desc = rec.describe(scan)
                except ScanDataError as exc:
                    self._current[key] = exc
                    raise
                hit = desc, (time.perf_counter() - t0) * 1e3
                if on_disk:
                    self.cache.put(key, index, *hit)
            self._current[key] = hit
        found = self._current[key]
        if isinstance(found, ScanDataError):
            raise found
        return found


Pipelines = list[tuple[PipelineRecord, PlaceRecognizer]]


def build_pipelines(cfg: ExperimentConfig) -> Pipelines:
    """Every pipeline of the config with an empty record holding its resolved parameters (`ConfigError` for an
    unknown name, a ``module:Class`` that is no recognizer, or a bad parameter)."""
    out = []
    for i, spec in enumerate(cfg.pipelines):
        rec = cfg.make_pipeline(i)
        params = getattr(rec, "params", None)
        resolved = params.model_dump(mode="json") if isinstance(params, Params) else dict(spec.params)
        threshold = cfg.operating_threshold(spec)
        out.append(
            (
                PipelineRecord(
                    spec.display_name,
                    type(rec).__name__,
                    spec.name,
                    resolved,
                    threshold=threshold,
                    loop_filter=spec.loop_filter,
                ),
                rec,
            )
        )
    return out


def _data_key(cfg: ExperimentConfig, dataset_cfg: Any) -> str:
    """Cache key of a dataset's preprocessed scans: the configs, the data itself (simulator code or file stats) and
    the calibration table's file; with ``keyframes`` set also its parameters (the cache then holds descriptions of
    keyframes, indexed by keyframe, which a run on single scans must never read, nor a run with other windows)."""
    parts: list[Any] = [
        dataset_cfg.model_dump(mode="json"),
        cfg.preprocess.model_dump(mode="json"),
        dataset_fingerprint(dataset_cfg),
        files_fingerprint(cfg.preprocess.intensity.calibration),
    ]
    if cfg.keyframes is not None:  # only then, so that the keys of single-scan runs stay what they were
        parts.append({"keyframes": cfg.keyframes.model_dump(mode="json")})
    return config_hash(*parts)


@contextmanager
def description_cache(
    cfg: ExperimentConfig, dataset_cfg: Any, n_scans: int, cache_dir: str | None, progress: Any
) -> Iterator[DescriptionCache]:
    """The description cache of a config dataset; with ``execution`` parallel, filled first by
    `placerec.experiment.parallel.describe_in_parallel` (into a temporary folder for the run when the cache is
    off, ``cache_dir`` None)."""
    key = _data_key(cfg, dataset_cfg)
    if not cfg.execution.parallel:
        yield DescriptionCache(cache_dir, key)
        return
    from placerec.experiment.parallel import describe_in_parallel

    with ExitStack() as stack:
        root = cache_dir or stack.enter_context(tempfile.TemporaryDirectory(prefix="placerec-descriptions-"))
        describe_in_parallel(cfg, dataset_cfg, n_scans, root, key, progress)
        yield DescriptionCache(root, key)


def loop_sequence(cfg: ExperimentConfig, seq: Sequence | None = None) -> Sequence:
    """The loop-mode sequence (``cfg.dataset`` unless ``seq`` is given), as keyframes when ``cfg.keyframes`` is set
    (`placerec.experiment.datasets.keyframed`: then every pipeline, the ground truth and the exclusion window work
    on keyframes, ``exclusion.frames`` counting keyframes), checked against the exclusion window: `ConfigError`
    when a limit in metres has no poses or one in seconds no timestamps to apply to."""
    seq = keyframed(cfg.keyframes, cfg.preprocess, open_dataset(cfg.dataset) if seq is None else seq)
    ex = cfg.evaluation.exclusion
    if ex.metres is not None and seq.poses is None:
        raise ConfigError("evaluation.exclusion.metres needs a dataset with poses")
    if ex.seconds is not None and seq.timestamps is None:
        raise ConfigError("evaluation.exclusion.seconds needs a dataset with timestamps")
    return seq


def run_loop(
    cfg: ExperimentConfig,
    seq: Sequence | None = None,
    pipelines: Pipelines | None = None,
    on_scan: Callable[[int, Scan], None] | None = None,
    opened: Sequence | None = None,
) -> tuple[Sequence, list[PipelineRecord]]:
    """Loop mode: every scan queries (exclusion window applied) and is then added, for every pipeline.

    ``seq`` defaults to the config's dataset, ``pipelines`` to `build_pipelines`. The on-disk description cache
    (``output.cache_dir``) is keyed by the config's dataset, so it is used only when ``seq`` is not given. A
    sequence with no scans, or one shorter than the exclusion window, gives every query no candidates.
    ``on_scan(index, scan)`` sees every preprocessed scan once, in order (e.g. `placerec.experiment.truth`).
    ``opened`` (when ``seq`` is not given): the config's dataset as `loop_sequence` already opened it, used instead
    of opening it again (keyframes with ``odometry: kiss-icp`` then register the scans once); the cache stays on."""
    pipelines = build_pipelines(cfg) if pipelines is None else pipelines
    own_data = seq is None
    cache_dir = cfg.output.cache_dir if own_data else None
    seq = opened if own_data and opened is not None else loop_sequence(cfg, seq)
    ex = cfg.evaluation.exclusion
    detectors = [
        LoopClosureDetector(
            rec,
            threshold=-np.inf,
            exclusion_frames=ex.frames,
            exclusion_seconds=ex.seconds,
            exclusion_metres=ex.metres,
            k=cfg.evaluation.top_n,
            loop_filter=record.loop_filter,
        )
        for record, rec in pipelines
    ]
    poses, stamps = seq.poses, seq.timestamps
    guides = _guides(cfg, pipelines, poses)
    viewer = active()
    with progress_bars(cfg.output.progress) as progress, ExitStack() as stack:
        if own_data and cfg.execution.parallel:
            cache = stack.enter_context(description_cache(cfg, cfg.dataset, len(seq), cache_dir, progress))
        else:
            cache = DescriptionCache(cache_dir, _data_key(cfg, cfg.dataset))
        frontends = _Frontends(cache)
        tasks = [progress.add_task(record.label, total=len(seq)) for record, _ in pipelines]
        if viewer is not None:
            for record, rec in pipelines:
                stack.enter_context(viewer.watching(record.label, rec))
            if poses is not None:
                viewer.trajectory("gt", poses, static=True)
        for i in range(len(seq)):
            scan, pre_ms = preprocessed_scan(seq, i, cfg.preprocess)
            if on_scan is not None:
                on_scan(i, scan)
            pose = None if poses is None else poses[i]
            stamp = None if stamps is None else float(stamps[i])
            if viewer is not None:
                viewer.scan(i, scan, pose, stamp)
            for (record, rec), det, task, guide in zip(pipelines, detectors, tasks, guides, strict=True):
                timing = {"preprocess": pre_ms}
                try:
                    desc, timing["describe"] = frontends.describe(rec, i, scan)
                except ScanDataError as exc:
                    log.warning("%s: scan %d gets no candidates: %s", record.label, i, exc)
                    det.skip(pose, stamp)  # keeps the detector's ids equal to scan indices
                else:
                    prior = None if guide is None else guide.prior(i)
                    det.process(None, pose=pose, timestamp=stamp, description=desc, prior=prior)
                    if guide is not None:
                        guide.judge(i, det.last_candidates)
                    timing.update({k: v for k, v in det.last_timing_ms.items() if k != "describe"})
                    if viewer is not None:
                        viewer.description(record.label, rec, scan, desc)
                for stage in STAGES:
                    record.timing_ms[stage].append(timing.get(stage, 0.0))
                record.query_ids.append(i)
                record.candidates.append(det.last_candidates)
                if viewer is not None:
                    viewer.candidates(record.label, det.last_candidates, record.threshold)
                progress.advance(task)
    return seq, [record for record, _ in pipelines]


class _Guide:
    """The motion prior a detector with the odometry gate gives a guided pipeline (``verify.guided``), made while
    a loop-mode run goes: the evaluation's odometry (`placerec.experiment.gate.gate_odometry`) and the closures the
    gate admits at the pipeline's operating threshold, each query's best one entering the chain as the evaluation
    judges it afterwards (`placerec.experiment.gate.judge_through_loops`)."""

    def __init__(self, cfg: ExperimentConfig, poses: np.ndarray, threshold: float) -> None:
        gate = cfg.evaluation.odometry_gate
        assert gate is not None
        self.bounds, self.threshold = gate.bounds, threshold
        self.odom, self.path = gate_odometry(cfg, poses)
        self.chain = LoopChain()

    def prior(self, query: int) -> ChainPrior:
        """The prior for ``query``: through the chain (empty without ``through_loops``: the odometry alone)."""
        return ChainPrior(self.chain, query, self.odom, self.path, self.bounds)

    def judge(self, query: int, candidates: list[Candidate]) -> None:
        """Add ``query``'s answer to the chain as the evaluation judges it (`judge_through_loops`)."""
        if not self.bounds.through_loops or not candidates:
            return
        row = CandidateTable.from_candidates([query], [candidates])
        judge_through_loops(
            self.chain,
            query,
            row.match_ids[0],
            row.relative_poses[0],
            row.scores[0],
            row.accepted[0],
            self.odom,
            self.path,
            self.bounds,
            self.threshold,
        )


def _guides(cfg: ExperimentConfig, pipelines: Pipelines, poses: np.ndarray | None) -> list[_Guide | None]:
    """Per pipeline its `_Guide` where it matches within a motion prior (``verify.guided.enabled``) and the
    evaluation has the odometry gate, with poses and an operating threshold to judge at; None elsewhere."""
    if cfg.evaluation.odometry_gate is None or poses is None:
        return [None] * len(pipelines)
    out: list[_Guide | None] = []
    for record, rec in pipelines:
        threshold = record.threshold
        if guides(getattr(rec, "params", None)) and threshold is not None:
            out.append(_Guide(cfg, np.asarray(poses), float(threshold)))
        else:
            out.append(None)
    return out


def localize_sequences(cfg: ExperimentConfig) -> tuple[Sequence, Sequence]:
    """(map, queries) of localize mode: ``evaluation.localize``'s datasets or a simulator split; `ConfigError`
    when they are incomplete or lack poses."""
    loc = cfg.evaluation.localize
    if loc.map is not None or loc.queries is not None:
        if loc.map is None or loc.queries is None:
            raise ConfigError("evaluation.localize needs both 'map' and 'queries' datasets (or neither)")
        if loc.draw:
            raise ConfigError(
                "evaluation.localize.draw: a simulated query draw, not used with map/queries datasets"
            )
        return _with_poses(open_dataset(loc.map), open_dataset(loc.queries))
    if cfg.dataset.source != "simulator":
        raise ConfigError("localize mode on a path dataset needs evaluation.localize.map and .queries")
    from placerec.sim import make_localization_split

    sim = cfg.dataset.simulator
    split = make_localization_split(
        preset=sim.world,
        sensor=sim.sensor,
        seed=sim.seed,
        n_queries=loc.n_queries,
        n_map=sim.n_scans,
        conditions=(loc.condition,),
        draw=loc.draw,
    )
    return _with_poses(split.map, split.queries[loc.condition])


def _with_poses(map_seq: Sequence, query_seq: Sequence) -> tuple[Sequence, Sequence]:
    for what, seq in (("map", map_seq), ("query", query_seq)):
        if seq.poses is None:
            raise ConfigError(f"localize mode needs poses: the {what} sequence {seq.name} has none")
    return map_seq, query_seq


def run_localize(
    cfg: ExperimentConfig,
    sequences: tuple[Sequence, Sequence] | None = None,
    pipelines: Pipelines | None = None,
) -> tuple[Sequence, Sequence, list[PipelineRecord]]:
    """Localize mode: build each pipeline's database from the map sequence, then query every query scan.

    ``sequences`` (map, queries) default to `localize_sequences`, ``pipelines`` to `build_pipelines`; the map's
    descriptions are cached on disk (``output.cache_dir``) only when ``sequences`` is not given. An empty map
    gives every query no candidates; no queries give records with no rows."""
    pipelines = build_pipelines(cfg) if pipelines is None else pipelines
    cache_dir = cfg.output.cache_dir if sequences is None else None
    map_seq, query_seq = localize_sequences(cfg) if sequences is None else _with_poses(*sequences)
    map_cfg = cfg.evaluation.localize.map or cfg.dataset
    query_front = _Frontends(DescriptionCache(None, "queries"))
    viewer = active()
    with progress_bars(cfg.output.progress) as progress, ExitStack() as stack:
        if sequences is None and cfg.execution.parallel and cfg.evaluation.localize.map is not None:
            cache = stack.enter_context(description_cache(cfg, map_cfg, len(map_seq), cache_dir, progress))
        else:
            cache = DescriptionCache(cache_dir, _data_key(cfg, map_cfg))
        map_front = _Frontends(cache)
        map_poses = map_seq.poses
        assert map_poses is not None  # localize_sequences and _with_poses require them
        if viewer is not None:
            viewer.matches_in = "map"
            viewer.trajectory("map", map_poses, static=True)
            for record, rec in pipelines:
                stack.enter_context(viewer.watching(record.label, rec))
        tasks = [progress.add_task(f"{record.label} (map)", total=len(map_seq)) for record, _ in pipelines]
        for i in range(len(map_seq)):
            scan, _ = preprocessed_scan(map_seq, i, cfg.preprocess)
            if viewer is not None:
                viewer.remember("map", i, scan, map_poses[i])
            for (record, rec), task in zip(pipelines, tasks, strict=True):
                try:
                    desc = map_front.describe(rec, i, scan)[0]
                    rec.add_description(i, desc, map_poses[i])
                except ScanDataError as exc:
                    log.warning("%s: map scan %d not added: %s", record.label, i, exc)
                else:
                    if viewer is not None:
                        viewer.description(record.label, rec, scan, desc, space="map", index=i)
                progress.advance(task)
        tasks = [
            progress.add_task(f"{record.label} (queries)", total=len(query_seq)) for record, _ in pipelines
        ]
        query_poses, query_stamps = query_seq.poses, query_seq.timestamps
        for q in range(len(query_seq)):
            scan, pre_ms = preprocessed_scan(query_seq, q, cfg.preprocess)
            if viewer is not None:
                stamp = None if query_stamps is None else float(query_stamps[q])
                viewer.scan(q, scan, None if query_poses is None else query_poses[q], stamp)
            for (record, rec), task in zip(pipelines, tasks, strict=True):
                timing = {"preprocess": pre_ms}
                cands: list[Candidate] = []
                try:
                    desc, timing["describe"] = query_front.describe(rec, q, scan)
                except ScanDataError as exc:
                    log.warning("%s: query %d gets no candidates: %s", record.label, q, exc)
                else:
                    t0 = time.perf_counter()
                    cands = rec.query_description(desc, k=cfg.evaluation.top_n, query_id=q)
                    timing["query"] = (time.perf_counter() - t0) * 1e3
                    split_verify_time(cands, timing)
                    if viewer is not None:
                        viewer.description(record.label, rec, scan, desc)
                for stage in STAGES:
                    record.timing_ms[stage].append(timing.get(stage, 0.0))
                record.query_ids.append(q)
                record.candidates.append(cands)
                if viewer is not None:
                    viewer.localized(record.label, cands, record.threshold)
                progress.advance(task)
    return map_seq, query_seq, [record for record, _ in pipelines]
