"""Config-driven experiments: `run_experiment` runs every pipeline of a config and writes the results folder.

The experiment layer sits on top of the algorithms: it reads configs (`placerec.config`), opens data sources and
turns config sections into the algorithms' own parameter objects; no algorithm module imports it.

* `placerec.experiment.datasets` — a `DatasetConfig` as a sequence (simulator or recorded files), its fingerprint.
* `placerec.experiment.preprocessing` — the ``preprocess`` section as `placerec.preprocess.PreprocessParams`.
* `placerec.experiment.runner` — loop-closure and localisation runs over every pipeline.
* `placerec.experiment.cache` — the description cache shared by pipelines with the same front end.
* `placerec.experiment.report`, `.candidates`, `.figures` — the results folder: metrics, candidates, figures.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from placerec.config import ExperimentConfig

__all__ = ["run_experiment"]


def run_experiment(cfg: ExperimentConfig, out_dir: str | Path | None = None) -> tuple[Path, dict[str, Any]]:
    """Run ``cfg`` (loop or localize mode) and write its results folder; returns (folder, metrics dict).

    The pipelines are built and the datasets opened and checked (poses for the evaluation, what the exclusion
    window needs) before the results folder is made, so a config that cannot run leaves no folder behind. In loop
    mode the run uses the sequence opened for that check (`run_loop`'s ``opened``), in localize mode it opens the
    sequences again (the simulator and file sequences open in milliseconds once built); the description cache is
    keyed by the config's dataset either way. A run interrupted (Ctrl-C) leaves no folder, or one marked INCOMPLETE
    when some pipelines' results were written (`placerec.experiment.run_folder.abandon_run`)."""
    from placerec.experiment.report import report_localize, report_loop, require_poses
    from placerec.experiment.run_folder import interruptible, make_run_dir
    from placerec.experiment.runner import (
        build_pipelines,
        localize_sequences,
        loop_sequence,
        run_localize,
        run_loop,
    )

    pipelines = build_pipelines(cfg)
    labels = [record.label for record, _ in pipelines]
    if cfg.evaluation.mode == "loop":
        from placerec.experiment.truth import TruthClouds

        opened = loop_sequence(cfg)
        truth = TruthClouds(cfg.evaluation, require_poses(opened))
        run = make_run_dir(cfg, out_dir)
        with interruptible(run, labels):
            seq, records = run_loop(cfg, None, pipelines, on_scan=truth, opened=opened)
            recognizers = [rec for _, rec in pipelines]  # their front ends draw the evidence
            payload = report_loop(cfg, run, seq, records, truth, recognizers=recognizers)
    else:
        localize_sequences(cfg)
        run = make_run_dir(cfg, out_dir)
        with interruptible(run, labels):
            map_seq, query_seq, records = run_localize(cfg, None, pipelines)
            payload = report_localize(
                cfg, run, map_seq, query_seq, records, recognizers=[rec for _, rec in pipelines]
            )
    return run, payload
