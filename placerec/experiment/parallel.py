"""Describing a dataset's scans outside the main process, into the on-disk description cache.

`describe_in_parallel` splits the scans into chunks of ``execution.chunk``; each task (`describe_chunk`) opens the
dataset and builds the pipelines' front ends once per worker process, then preprocesses and describes its scans
with every front end whose description is not cached yet and stores them in the `DescriptionCache`, describe time
included. The run that follows finds every description in the cache, so its candidates are those of a serial
run. Executors: local processes (``concurrent.futures``, spawned) or Dask distributed (a LocalCluster, or the
scheduler of ``execution.scheduler``).
"""

from __future__ import annotations

import logging
import multiprocessing
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

from placerec.config import DatasetConfig, ExecutionConfig, ExperimentConfig, parse_config
from placerec.errors import ConfigError, DependencyError, ScanDataError, short_repr
from placerec.experiment.cache import DescriptionCache
from placerec.experiment.datasets import keyframed, open_dataset
from placerec.experiment.preprocessing import preprocessed_scan
from placerec.hashing import stable_hash
from placerec.types import PlaceRecognizer, Sequence

__all__ = ["ChunkResult", "describe_chunk", "describe_in_parallel", "task_pool"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ChunkResult:
    """What one task did: scans described by at least one front end, descriptions computed, found cached, and
    scans a front end could not describe."""

    scans: int
    described: int
    cached: int
    failed: int
    seconds: float


# per worker process: (dataset, front ends) by the task's config, so a worker opens the dataset once
_OPENED: dict[str, tuple[Sequence, list[PlaceRecognizer]]] = {}


def _frontends(cfg: ExperimentConfig) -> list[PlaceRecognizer]:
    """One recognizer per distinct cached front end of the config's pipelines."""
    seen: dict[str, PlaceRecognizer] = {}
    for i in range(len(cfg.pipelines)):
        rec = cfg.make_pipeline(i)
        if getattr(rec, "cache_descriptions", True):
            seen.setdefault(rec.frontend_key, rec)
    return list(seen.values())


def _opened(cfg_json: dict[str, Any], dataset_json: dict[str, Any]) -> tuple[Sequence, list[PlaceRecognizer]]:
    key = stable_hash([cfg_json, dataset_json])
    if key not in _OPENED:
        cfg = parse_config(cfg_json)
        seq = keyframed(
            cfg.keyframes, cfg.preprocess, open_dataset(DatasetConfig.model_validate(dataset_json))
        )
        _OPENED[key] = (seq, _frontends(cfg))
    return _OPENED[key]


def describe_chunk(
    cfg_json: dict[str, Any], dataset_json: dict[str, Any], cache_root: str, data_key: str, indices: list[int]
) -> ChunkResult:
    """Describe scans ``indices`` of the dataset ``dataset_json`` with every front end of ``cfg_json`` into the cache
    ``cache_root/data_key`` (skipping cached ones). Runs in a worker; arguments are plain JSON-able values."""
    t0 = time.perf_counter()
    seq, fronts = _opened(cfg_json, dataset_json)
    cfg = parse_config(cfg_json)
    cache = DescriptionCache(cache_root, data_key)
    described = cached = failed = 0
    for i in indices:
        todo = [rec for rec in fronts if not cache.has(rec.frontend_key, i)]
        cached += len(fronts) - len(todo)
        if not todo:
            continue
        scan, _ = preprocessed_scan(seq, i, cfg.preprocess)
        for rec in todo:
            t1 = time.perf_counter()
            try:
                desc = rec.describe(scan)
            except ScanDataError:
                failed += 1  # the run describes it again and reports the error
                continue
            cache.put(rec.frontend_key, i, desc, (time.perf_counter() - t1) * 1e3)
            described += 1
    return ChunkResult(len(indices), described, cached, failed, time.perf_counter() - t0)


def _gather(
    futures: list[Any], completed: Callable[[list[Any]], Any], done: Callable[[Any], None]
) -> list[Any]:
    """The futures' results in the order they complete (``completed``: the executor's ``as_completed``), each
    passed to ``done`` as it arrives."""
    out = []
    for fut in completed(futures):
        out.append(fut.result())
        done(out[-1])
    return out


@contextmanager
def _local_pool(workers: int) -> Iterator[Callable[..., list[Any]]]:
    with ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn")) as pool:

        def submit(
            fn: Callable[..., Any], args: list[tuple[Any, ...]], done: Callable[[Any], None]
        ) -> list[Any]:
            return _gather([pool.submit(fn, *a) for a in args], as_completed, done)

        yield submit


@contextmanager
def _dask_pool(workers: int, scheduler: str | None) -> Iterator[Callable[..., list[Any]]]:
    try:
        from distributed import Client, LocalCluster
        from distributed import as_completed as dask_completed
    except ImportError as exc:
        raise DependencyError(
            f"execution.executor: dask needs dask and distributed ({exc}); install them with: pip install "
            "placerec[dask]"
        ) from exc
    cluster = None
    if scheduler is None:
        cluster = LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None
        )
    try:
        try:
            client = Client(cluster if cluster is not None else scheduler, timeout="20s")
        except (OSError, ValueError, TypeError) as exc:  # distributed's own errors for a bad or dead address
            where = (
                "a local Dask cluster" if scheduler is None else f"the Dask scheduler {short_repr(scheduler)}"
            )
            raise ConfigError(
                f"execution.scheduler: cannot reach {where} ({type(exc).__name__}: {exc})"
            ) from exc
        with client:

            def submit(
                fn: Callable[..., Any], args: list[tuple[Any, ...]], done: Callable[[Any], None]
            ) -> list[Any]:
                return _gather([client.submit(fn, *a, pure=False) for a in args], dask_completed, done)

            yield submit
    finally:
        if cluster is not None:
            cluster.close()


def task_pool(execution: ExecutionConfig) -> Any:
    """A context manager giving ``submit(fn, args, done)`` on ``execution``'s executor: local spawned processes or
    Dask (a LocalCluster of ``workers``, or the scheduler at ``scheduler``); ``submit`` runs ``fn(*a)`` for every
    ``a`` in ``args``, calls ``done`` with each result as it completes and returns the results (completion order)."""
    if execution.executor == "dask":
        return _dask_pool(execution.workers, execution.scheduler)
    return _local_pool(execution.workers)


def describe_in_parallel(
    cfg: ExperimentConfig,
    dataset: DatasetConfig,
    n_scans: int,
    cache_root: str,
    data_key: str,
    progress: Any = None,
) -> list[ChunkResult]:
    """Describe scans 0..``n_scans - 1`` of ``dataset`` with every cached front end of ``cfg``'s pipelines into
    ``cache_root/data_key``, on the executor of ``cfg.execution``; ``progress`` (a rich Progress) shows the tasks."""
    ex = cfg.execution
    chunks = [list(range(a, min(a + ex.chunk, n_scans))) for a in range(0, n_scans, ex.chunk)]
    cfg_json, ds_json = cfg.model_dump(mode="json"), dataset.model_dump(mode="json")
    args = [(cfg_json, ds_json, str(cache_root), data_key, c) for c in chunks]
    task = progress.add_task(f"describe ({ex.executor} x{ex.workers})", total=n_scans) if progress else None

    def done(result: ChunkResult) -> None:
        if progress is not None:
            progress.advance(task, result.scans)

    t0 = time.perf_counter()
    with task_pool(ex) as submit:
        results = submit(describe_chunk, args, done)
    log.info(
        "described %d scans in %.1f s on %s (%d workers): %d descriptions computed, %d cached",
        n_scans,
        time.perf_counter() - t0,
        ex.executor,
        ex.workers,
        sum(r.described for r in results),
        sum(r.cached for r in results),
    )
    return results
