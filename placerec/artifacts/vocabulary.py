"""The DBoW vocabulary: intensity images of simulated (or recorded) sequences -> features -> tree, trained as a
config (`VocabTrainingConfig`) says and written by `build_vocabulary` (``placerec train-vocab``).

The images are formed exactly as the experiment runner does for the visual pipelines (the config's
``preprocess`` section, then `placerec.image.make_image` with ``image``, then the feature extractor), so the words
match what ORB-DBoW / SURF-DBoW see at run time. By default the simulator supplies campus, industrial and town
worlds with seeds 100-109, disjoint from the evaluation configs (town, seeds 0-9): no scan of a test sequence is
used for training (a warning is logged otherwise). ``n_images`` are spread evenly over all sequences and along
each route.

Outputs: the vocabulary (binary format, `placerec.retrieval.dbow.io`) and ``<output stem>.json`` beside it with
the provenance (worlds, sensors, seeds, n_images, n_descriptors, training time, placerec version, config).

Example config (``configs/vocab_orb.yaml``)::

    features: orb
    k: 10
    L: 5
    n_images: 3000
    simulator: {worlds: [campus, industrial, town], sensors: [os1-64], seeds: [100, 101, 102]}
    output: placerec/vocab/orb_k10L5.dbow
"""

from __future__ import annotations

import json
import logging
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field

from placerec.config import DatasetConfig, SimulatorConfig, experiment_preprocess, load_params_file
from placerec.errors import ArtifactError, ConfigError
from placerec.hashing import stable_hash
from placerec.io.npz import read_npz_arrays
from placerec.keyframes import KeyframeParams
from placerec.params import Params
from placerec.pipelines.visual import VisualFrontendParams
from placerec.preprocess import PreprocessParams
from placerec.retrieval.dbow.vocabulary import VocabularyParams

log = logging.getLogger(__name__)

__all__ = [
    "VocabTrainingConfig",
    "TrainingSimulator",
    "load_training_config",
    "collect_descriptors",
    "cached_descriptors",
    "descriptor_cache_key",
    "build_vocabulary",
]

#: Seeds of the town world used by the evaluation configs (never trained on by default).
EVALUATION_SEEDS = tuple(range(10))


class TrainingSimulator(Params):
    """Simulated sequences to draw training images from: every (world, sensor, seed) combination, each driven as
    the other settings say (`placerec.config.SimulatorConfig`'s fields of the same names)."""

    worlds: list[str] = Field(default_factory=lambda: ["campus", "industrial", "town"])
    sensors: list[str] = Field(default_factory=lambda: ["os1-64"])
    seeds: list[int] = Field(default_factory=lambda: list(range(100, 110)))
    route: str = "default"
    spacing: float = Field(1.0, gt=0, description="metres between scans (unless rate_hz is set)")
    clutter: bool = True
    rate_hz: float | None = Field(
        None, gt=0, le=1000, allow_inf_nan=False, description="scans per second instead of spacing"
    )
    sweep_motion: bool = Field(False, description="rays measured from the pose at their own time")
    odometry_drift: float | None = Field(
        None,
        ge=0,
        le=1,
        allow_inf_nan=False,
        description="the keyframes' odometry's relative translation error",
    )


class VocabTrainingConfig(VisualFrontendParams, VocabularyParams):
    """What ``placerec train-vocab`` trains (see the module docstring): the visual front end's ``features``,
    ``feature_params`` and ``image`` (`placerec.pipelines.visual.VisualFrontendParams`), the vocabulary's
    ``k``, ``L``, ``weighting``, ... (`placerec.retrieval.dbow.vocabulary.VocabularyParams`), and where the
    training images come from."""

    preprocess: PreprocessParams = Field(default_factory=experiment_preprocess)
    keyframes: KeyframeParams | None = Field(
        None,
        description="train on keyframes of these windows, as an experiment with the same keyframes sees them",
    )
    n_images: int = Field(3000, ge=1)
    simulator: TrainingSimulator | None = Field(default_factory=TrainingSimulator)
    datasets: list[DatasetConfig] = Field(default_factory=list, description="extra sequences (e.g. recorded)")
    centre_dtype: Literal["auto", "float32", "float16", "int8"] = "auto"
    compress: bool = Field(False, description="zlib-compress the vocabulary file's arrays")
    workers: int = Field(1, ge=1, le=1024, description="processes extracting features (at most 1024)")
    descriptor_cache: str | None = Field(
        None, description="folder caching the extracted descriptors (reused when the image settings match)"
    )
    output: str = "vocab/vocabulary.dbow"


def load_training_config(path: str | Path | None, **overrides: Any) -> VocabTrainingConfig:
    """Read a training config from YAML (None = defaults) with top-level overrides; `ConfigError` on bad keys."""
    return load_params_file(VocabTrainingConfig, path, "training config", **overrides)


def _sequences(cfg: VocabTrainingConfig) -> list[tuple[str, dict[str, Any]]]:
    """(label, spec) of every training sequence; spec is a DatasetConfig dump."""
    out = []
    sim = cfg.simulator
    if sim is not None:
        # every setting but the lists is the simulator's own, the same for each sequence
        drive = sim.model_dump(exclude={"worlds", "sensors", "seeds"})
        for world in sim.worlds:
            for sensor in sim.sensors:
                for seed in sim.seeds:
                    if world == "town" and seed in EVALUATION_SEEDS:
                        log.warning("training on town seed %d, which the evaluation configs use", seed)
                    spec = DatasetConfig(
                        source="simulator",
                        simulator=SimulatorConfig(world=world, sensor=sensor, seed=seed, **drive),
                    )
                    out.append((f"{world}/{sensor}/seed{seed}", spec.model_dump(mode="json")))
    for i, ds in enumerate(cfg.datasets):
        out.append((ds.path or f"dataset{i}", ds.model_dump(mode="json")))
    if not out:
        raise ConfigError("training config: no sequence (set 'simulator' or 'datasets')")
    return out


def _extract(job: tuple[dict[str, Any], int, dict[str, Any]]) -> list[np.ndarray]:
    """Descriptors of ``count`` evenly spaced scans (keyframes, with ``keyframes`` set) of one sequence (runs in a
    worker process)."""
    from placerec.experiment.datasets import keyframed, open_dataset
    from placerec.experiment.preprocessing import preprocessed_scan
    from placerec.features import make_extractor
    from placerec.image import make_image

    spec, count, c = job
    cfg = VocabTrainingConfig.model_validate(c)
    seq = keyframed(cfg.keyframes, cfg.preprocess, open_dataset(DatasetConfig.model_validate(spec)))
    extractor = make_extractor(cfg.features, cfg.feature_params)
    index = np.unique(np.linspace(0, len(seq) - 1, min(count, len(seq))).round().astype(int))
    out = []
    for i in index:
        scan, _ = preprocessed_scan(seq, int(i), cfg.preprocess)
        out.append(extractor.extract(make_image(scan, cfg.image).image).descriptors)
    return out


def collect_descriptors(
    cfg: VocabTrainingConfig, progress: bool = False
) -> tuple[list[np.ndarray], list[str]]:
    """Per-image descriptors of the training images and, per image, the label of its sequence
    (``world/sensor/seed<n>`` for simulated ones)."""
    seqs = _sequences(cfg)
    counts = np.diff(np.linspace(0, cfg.n_images, len(seqs) + 1).round().astype(int))
    jobs = [(label, spec, int(n)) for (label, spec), n in zip(seqs, counts, strict=True) if n]
    work = [(spec, n, cfg.model_dump(mode="json")) for _, spec, n in jobs]
    parts: list[np.ndarray] = []
    labels: list[str] = []
    with _Bar(progress, len(jobs), "features") as advance:
        if cfg.workers > 1 and len(jobs) > 1:
            with ProcessPoolExecutor(cfg.workers) as pool:
                results = pool.map(_extract, work)
                for (label, _, _), res in zip(jobs, results, strict=True):
                    parts.extend(res)
                    labels.extend([label] * len(res))
                    advance()
        else:
            for (label, _, _), job in zip(jobs, work, strict=True):
                res = _extract(job)
                parts.extend(res)
                labels.extend([label] * len(res))
                advance()
    return parts, labels


def descriptor_cache_key(cfg: VocabTrainingConfig) -> str:
    """Hash of every setting that changes the extracted descriptors, and of the data they come from (the
    simulator's code, the dataset files, the calibration table)."""
    from placerec.experiment.datasets import dataset_fingerprint, files_fingerprint

    keys = (
        "features",
        "feature_params",
        "image",
        "preprocess",
        "keyframes",
        "n_images",
        "simulator",
        "datasets",
    )
    sources = [DatasetConfig.model_validate(spec) for _, spec in _sequences(cfg)]
    data = (
        [dataset_fingerprint(ds) for ds in sources],
        files_fingerprint(cfg.preprocess.intensity.calibration),
    )
    return stable_hash([cfg.model_dump(mode="json", include=set(keys)), data])


def cached_descriptors(
    cfg: VocabTrainingConfig, progress: bool = False
) -> tuple[list[np.ndarray], list[str]]:
    """`collect_descriptors`, through ``cfg.descriptor_cache`` when set: the cache file is keyed by every setting
    that changes the descriptors (features, image, preprocessing, sequences and their data, n_images), not by k,
    L, etc."""
    if cfg.descriptor_cache is None:
        return collect_descriptors(cfg, progress)
    digest = descriptor_cache_key(cfg)
    path = Path(cfg.descriptor_cache) / f"descriptors_{cfg.features}_{digest}.npz"
    if path.is_file():
        try:
            z = read_npz_arrays(path, path, ArtifactError, "artifact", allow_deflate=False)
            counts, flat, labels = z["counts"], z["descriptors"], [str(v) for v in z["labels"]]
            if counts.ndim != 1 or len(labels) != counts.size or int(counts.sum()) != flat.shape[0]:
                raise ArtifactError(f"{path}: counts, descriptors and labels of the cache disagree")
            log.info("descriptors from the cache %s", path)
            return np.split(flat, np.cumsum(counts)[:-1]), labels
        except (ArtifactError, KeyError, IndexError) as exc:
            log.warning("ignoring unreadable descriptor cache %s (%s)", path, exc)
    parts, labels = collect_descriptors(cfg, progress)
    from placerec.io.atomic import atomic_write

    counts = np.array([p.shape[0] for p in parts], np.int64)
    with atomic_write(path) as fh:
        np.savez(fh, counts=counts, descriptors=np.concatenate(parts), labels=np.array(labels))
    return parts, labels


def build_vocabulary(
    config: VocabTrainingConfig, output: str | Path | None = None, progress: bool = False
) -> Path:
    """Train the vocabulary ``config`` describes (`load_training_config` reads one from YAML) and write it
    atomically (plus ``<stem>.json``) to ``output`` (default: the config's); returns the vocabulary path."""
    from placerec._version import __version__
    from placerec.retrieval.dbow.io import save_vocabulary
    from placerec.retrieval.dbow.vocabulary import train_vocabulary

    out = Path(output or config.output)
    t0 = time.perf_counter()
    parts, labels = cached_descriptors(config, progress)
    labels = list(dict.fromkeys(labels))
    t_features = time.perf_counter() - t0
    meta = {
        "features": config.features,
        "feature_params": config.feature_params.model_dump(mode="json"),
        "image": config.image.model_dump(mode="json"),
        "keyframes": None if config.keyframes is None else config.keyframes.model_dump(mode="json"),
        "sequences": labels,
        "simulator": None if config.simulator is None else config.simulator.model_dump(mode="json"),
        "placerec_version": __version__,
        "feature_seconds": round(t_features, 1),
    }
    voc = train_vocabulary(parts, config, progress=progress, meta=meta)
    centre_dtype = None if config.centre_dtype == "auto" else config.centre_dtype
    save_vocabulary(voc, out, None if voc.binary else centre_dtype, compress=config.compress)
    info = {
        **voc.meta,
        "k": voc.k,
        "L": voc.L,
        "n_nodes": voc.n_nodes,
        "n_words": voc.n_words,
        "file_bytes": out.stat().st_size,
        "fingerprint": voc.fingerprint,
        "config": config.model_dump(mode="json"),
    }
    from placerec.io.atomic import atomic_write

    with atomic_write(out.with_suffix(".json"), "w") as fh:
        fh.write(json.dumps(info, indent=2, default=str) + "\n")
    log.info("wrote %s (%d words, %.1f MB)", out, voc.n_words, info["file_bytes"] / 1e6)
    return out


class _Bar:
    def __init__(self, enabled: bool, total: int, label: str) -> None:
        self.enabled, self.total, self.label = enabled, total, label

    def __enter__(self):  # noqa: ANN204
        if not self.enabled:
            return lambda: None
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

        self._bar = Progress(
            TextColumn("{task.description:<20}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn()
        )
        self._bar.__enter__()
        task = self._bar.add_task(f"{self.label} (sequences)", total=self.total)
        return lambda: self._bar.update(task, advance=1)

    def __exit__(self, *exc: object) -> None:
        if self.enabled:
            self._bar.__exit__(*exc)
