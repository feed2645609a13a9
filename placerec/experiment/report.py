"""Turn pipeline records into results: metrics, CSVs, poses, figures, a console table and ``index.html``.

Output folder ``<output.dir>/<name>_<timestamp>/`` (and a ``latest`` link beside it):

* ``config.yaml`` — the resolved config;
* ``pipelines.yaml`` — per pipeline label: registry name, class and resolved parameters (defaults, the registry
  preset and the config's overrides merged);
* ``metrics.json`` — per pipeline: ``max_f1``, ``precision_at_max_f1``, ``recall_at_max_f1``, ``auc`` (average
  precision, see `placerec.eval.metrics`), ``recall_at_100_precision``, ``precision_at_min_recall``,
  ``extended_precision``, ``recall_at_1``, ``recall_at_n``, ``pose_error`` (the closures accepted at the max-F1
  threshold, `placerec.eval.pose_error`), ``success_rate``, ``success_basis`` and ``fine_success_rate``
  (localize mode), ``time_ms`` {mean, median, p95} per scan and per stage, ``n_queries``, ``n_revisits``; in loop
  mode also ``operating`` (the figures at the pipeline's fixed threshold, `operating_point`), ``max_false_score``,
  ``max_score``, ``min_score``, and ``pose_truth`` / ``icp_truth`` (the same under the pose ground truth and the
  ICP-confirmed one, docs/protocol.md); plus peak memory and, when a row needs one, ``notes`` (label -> texts,
  `pipeline_notes`: a local-map peer that closed no local map, a non-deterministic peer); per pipeline also
  ``rejections`` {``all``, ``top``: how verification ended for every candidate and for each query's top one,
  `placerec.experiment.evidence.rejection_counts`}. Strict JSON: a value that is undefined for the run is ``null`` (``threshold_at_max_f1`` with no
  candidate, ``mean_error`` with no estimate, times with no scan, pose errors with no 6-DoF pose). A sequence
  without revisits (too short, shorter than the exclusion window) has ``no_revisits: true`` and recalls, F1 and
  AUC of 0; no scans at all give ``n_queries: 0``;
* ``candidates_<label>.csv`` — every candidate, one row per (query, rank), with its relative pose and
  verification statistics (`placerec.experiment.candidates`);
* ``poses.txt`` — the ground-truth poses (KITTI format) the ids index into (localize mode: ``map_poses.txt`` and
  ``query_poses.txt``), so the metrics can be recomputed from the folder alone (`recompute_loop_metrics`);
* ``pr_curves.png``, ``trajectory_<label>.png`` (or ``localization_<label>.png``), ``timing.png``, ``index.html``;
* with ``output.evidence`` (and figures): ``evidence/<label>/<kind>_<query>_<match>.png``, a few accepted, false
  and missed closures per pipeline (localize mode: queries localised, answered wrongly, not answered;
  `placerec.experiment.evidence`), shown in ``index.html`` with the rejection counts; in loop mode also
  ``plotly.min.js``, which the page's interactive PR curves and trajectories use
  (`placerec.experiment.interactive`): the folder opens from disk with no network.

``latest`` is repointed only once every file of the report is written: a run that fails keeps its folder (for
inspection) but leaves ``latest`` on the last complete run.
"""

from __future__ import annotations

import json
import resource
import sys
from collections.abc import Iterable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from placerec.config import ExperimentConfig
from placerec.errors import ConfigError
from placerec.eval import (
    ExclusionWindow,
    LoopMetrics,
    closure_pose_errors,
    direction_summary,
    error_stats,
    evaluate_loop,
    full_pose_mask,
    localization_metrics,
    loop_ground_truth,
    loop_metrics,
    recall_by_direction,
    retrieval_metrics,
    timing_summary,
)
from placerec.eval.icp_truth import icp_ground_truth
from placerec.eval.pose_truth import (
    PoseGroundTruth,
    correct_candidates,
    overlap_directions,
    overlap_truth,
    with_candidates,
)
from placerec.experiment import figures
from placerec.experiment.candidates import CandidateTable, read_candidates, write_candidates
from placerec.experiment.evidence import rejection_counts
from placerec.experiment.gate import gate_odometry, judge_through_loops
from placerec.experiment.run_folder import finite_or_null, json_default, point_latest, slug
from placerec.experiment.runner import PER_SCAN_TIME, STAGES, PipelineRecord
from placerec.experiment.tables import lookup, write_index_html
from placerec.experiment.truth import TruthClouds
from placerec.io import read_poses, write_kitti_poses
from placerec.io.atomic import atomic_write
from placerec.io.mcap_export import LoopEdge, write_closures_mcap
from placerec.odometry_gate import LoopChain, OdometryGateParams, odometry_disagreement
from placerec.types import PlaceRecognizer, Sequence
from placerec.verify.ambiguity import AmbiguityParams, runner_up_ratio

__all__ = [
    "NONDETERMINISTIC",
    "loop_summary",
    "operating_point",
    "pipeline_notes",
    "pose_truths",
    "require_poses",
    "report_loop",
    "report_localize",
    "recompute_loop_metrics",
    "localize_estimates",
    "ambiguous_answers",
]


def _timing(record: PipelineRecord) -> dict[str, Any]:
    out: dict[str, Any] = timing_summary(record.per_scan_ms())
    out["stages"] = {s: timing_summary(record.timing_ms[s]) for s in STAGES if any(record.timing_ms[s])}
    return out


#: peers whose results differ between identical runs (registry name -> the note beside their rows)
NONDETERMINISTIC = {
    "map-closures": "non-deterministic peer: its poses vary between identical runs (docs/benchmarks.md,"
    " Structure refactor)",
}


def pipeline_notes(records: list[PipelineRecord]) -> dict[str, list[str]]:
    """The notes a reader needs beside a pipeline's row (label -> texts; ``metrics.json``'s ``notes``): a
    local-map peer that closed no local map (so every figure is 0), a non-deterministic peer."""
    notes: dict[str, list[str]] = {}
    for r in records:
        out = []
        if r.params.get("local_map") and not any(r.candidates):
            distance = r.params.get("local_map_distance")
            far = f"{distance:g} m" if isinstance(distance, int | float) else "local_map_distance"
            out.append(
                f"closed no local map, so no candidate and all 0: a map closes once the route is {far} from"
                " its first scan (docs/evaluation.md)"
            )
        if r.pipeline in NONDETERMINISTIC:
            out.append(NONDETERMINISTIC[r.pipeline])
        if out:
            notes[r.label] = out
    return notes


def _peak_memory_mb() -> float:
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1024 * 1024) if sys.platform == "darwin" else peak / 1024


def _gt_options(cfg: ExperimentConfig, timestamps: np.ndarray | None) -> dict[str, Any]:
    ev = cfg.evaluation
    return {
        "gt_distance": ev.gt_distance,
        "gt_yaw_deg": ev.gt_yaw_deg,
        "exclusion": ExclusionWindow(**ev.exclusion.model_dump()),
        "timestamps": timestamps,
    }


def recompute_loop_metrics(run_dir: str | Path, label: str) -> dict[str, Any]:
    """Recompute a pipeline's loop metrics (recall@N, the closures' pose errors and the figures at its operating
    threshold included) from the run folder alone (config, poses, candidates CSV): ``metrics.json``'s entry for
    ``label`` without the times and the other ground truths (judged with the run's odometry gate, if any)."""
    from placerec.config import load_config

    run_dir = Path(run_dir)
    cfg = load_config(run_dir / "config.yaml")
    poses = _read_or_empty(run_dir / "poses.txt", lambda p: read_poses(p)[0], (0, 4, 4))
    times = run_dir / "times.txt"
    stamps = _read_or_empty(times, lambda p: np.loadtxt(p, ndmin=1), (0,)) if times.is_file() else None
    spec = next((p for p in cfg.pipelines if p.display_name == label), None)
    threshold = None if spec is None else cfg.operating_threshold(spec)
    (table,), (refused,) = odometry_gated(
        cfg, [read_candidates(run_dir / f"candidates_{slug(label)}.csv")], poses, [threshold]
    )
    return loop_summary(cfg, table, poses, stamps, threshold, refused=refused)[1]


def operating_point(
    metrics: LoopMetrics,
    relative_poses: np.ndarray,
    poses: np.ndarray,
    threshold: float | None,
    nearest: np.ndarray | None = None,
) -> dict[str, Any] | None:
    """The figures of a pipeline at its fixed operating ``threshold`` (None when it has none): precision, recall,
    F1, the counts, the translation / rotation errors of every closure accepted there (true or false), and why
    revisits were missed (``missed``: no candidate, the top candidate below the threshold, i.e. rejected, or a
    wrong one accepted; with ``nearest``, the distance (m) from each query to its nearest eligible scan, the
    revisits and those found per band of that distance)."""
    if threshold is None:
        return None
    c = metrics.confusion_at(threshold)
    accepted = c["tp"] + c["fp"]
    p = c["tp"] / accepted if accepted else 1.0
    r = c["tp"] / metrics.n_revisits if metrics.n_revisits else 0.0
    errors = closure_pose_errors(metrics, relative_poses, poses, threshold)
    acc = errors.accepted
    masks = metrics.outcomes_at(threshold)
    fn, has = masks["fn"], metrics.match_ids >= 0
    missed: dict[str, Any] = {
        "no_candidate": int((fn & ~has).sum()),
        "below_threshold": int((fn & has & ~masks["accepted"]).sum()),
        "wrong_accepted": int((fn & masks["fp"]).sum()),
    }
    if nearest is not None:
        d = np.asarray(nearest, dtype=np.float64)
        for lo, hi in ((0.0, 5.0), (5.0, 10.0), (10.0, np.inf)):
            band = metrics.revisit & (d >= lo) & (d < hi)
            missed[f"nearest_{lo:g}-{hi:g}_m"] = [int(band.sum()), int((band & masks["tp"]).sum())]
    return {
        "threshold": float(threshold),
        "precision": p,
        "recall": r,
        "f1": 2 * p * r / (p + r) if p + r > 0 else 0.0,
        "n_accepted": accepted,
        "tp": c["tp"],
        "fp": c["fp"],
        "n_revisits": metrics.n_revisits,
        "translation_m": error_stats(errors.translation_m[acc]),
        "rotation_deg": error_stats(errors.rotation_deg[acc]),
        "accepted_translation_m": [round(float(v), 4) for v in errors.translation_m[acc] if np.isfinite(v)],
        "accepted_rotation_deg": [round(float(v), 3) for v in errors.rotation_deg[acc] if np.isfinite(v)],
        "missed": missed,
    }


def _min_score(params: dict[str, Any]) -> float | None:
    """The verification's ``min_score`` of a pipeline's resolved parameters when it accepts by score (a candidate
    scoring below it was rejected), else None."""
    score = lookup(params, ("verify", "score"))
    if isinstance(score, dict) and score.get("acceptance", "score") == "score":
        return score.get("min_score")
    return None


def max_false_score(metrics: LoopMetrics) -> float:
    """The score of the best-scored false closure (NaN when every candidate is true or there is none): a
    threshold above it accepts no false closure."""
    wrong = (metrics.match_ids >= 0) & ~metrics.correct
    return float(metrics.scores[wrong].max()) if wrong.any() else float("nan")


def _other_truth_summary(
    metrics: LoopMetrics,
    relative_poses: np.ndarray,
    poses: np.ndarray,
    threshold: float | None,
    nearest: np.ndarray | None = None,
) -> dict[str, Any]:
    """``metrics.json``'s entry for a ground truth beside the distance one: its PR figures and operating point."""
    return {
        "n_revisits": metrics.n_revisits,
        "max_f1": metrics.max_f1,
        "precision_at_max_f1": metrics.precision_at_max_f1,
        "recall_at_max_f1": metrics.recall_at_max_f1,
        "recall_at_100_precision": metrics.recall_at_100_precision,
        "max_false_score": max_false_score(metrics),
        "operating": operating_point(metrics, relative_poses, poses, threshold, nearest),
    }


def loop_summary(
    cfg: ExperimentConfig,
    table: CandidateTable,
    poses: np.ndarray,
    stamps: np.ndarray | None,
    threshold: float | None = None,
    truth: TruthClouds | None = None,
    pose_truth: PoseGroundTruth | None = None,
    refused: np.ndarray | None = None,
) -> tuple[LoopMetrics, dict[str, Any]]:
    """A pipeline's loop metrics and their ``metrics.json`` entry (without times): PR metrics of the top
    candidates, recall@N, the pose errors of the closures accepted at the max-F1 threshold, the figures at the
    operating ``threshold`` (``operating``), the same under ``pose_truth`` (`pose_truths`) and, with ``truth``'s
    clouds (``evaluation.gt_icp``), under the VPR paper's ICP-confirmed ground truth (``icp_truth``); with
    ``evaluation.odometry_gate``, how many candidates it ``refused`` (`odometry_gated`, which ``table`` is after)."""
    q, m, s = table.top1()
    ev = cfg.evaluation
    options = _gt_options(cfg, stamps)
    topn = table.topn(ev.top_n)
    metrics, gt = evaluate_loop(q, m, s, poses, topn, **options)
    rel = table.relative_poses[:, 0]
    summary = metrics.summary()
    nearest = gt.nearest_distance[metrics.query_ids]
    summary["operating"] = operating_point(metrics, rel, poses, threshold, nearest)
    summary["max_false_score"] = max_false_score(metrics)
    summary["max_score"] = float(np.nanmax(s)) if np.isfinite(s).any() else float("nan")
    if pose_truth is not None:
        pose_metrics = loop_metrics(q, m, s, pose_truth, topn)
        summary["pose_truth"] = _other_truth_summary(pose_metrics, rel, poses, threshold, nearest)
        if pose_truth.direction is not None:  # the same / reverse split of the pose truth's revisits
            summary["pose_truth"]["directions"] = recall_by_direction(
                pose_metrics, pose_truth.direction[pose_metrics.query_ids], threshold
            )
    if truth is not None and truth.icp_truth and len(truth.clouds) == poses.shape[0]:
        igt = icp_ground_truth(gt, truth.clouds, poses, truth.icp_settings)
        summary["icp_truth"] = _other_truth_summary(
            loop_metrics(q, m, s, igt, topn), rel, poses, threshold, nearest
        )
    summary["auc"] = summary.pop("average_precision")
    summary["directions"] = direction_summary(metrics, gt, ev.reverse_yaw_deg, threshold)
    retrieval_gt = loop_ground_truth(
        poses, **{**options, "gt_distance": ev.retrieval_distance, "gt_yaw_deg": None}
    )
    summary["retrieval"] = retrieval_metrics(metrics.query_ids, topn, retrieval_gt).summary()
    summary["pose_error"] = closure_pose_errors(metrics, rel, poses).summary()
    if cfg.evaluation.odometry_gate is not None and refused is not None:
        summary["odometry_gate_refused"] = int(refused.sum())
    return metrics, summary


def odometry_gated(
    cfg: ExperimentConfig,
    tables: list[CandidateTable],
    poses: np.ndarray,
    thresholds: list[float | None] | None = None,
) -> tuple[list[CandidateTable], list[np.ndarray]]:
    """The tables as the evaluation judges them, and per table the (Q, N) candidates ``evaluation.odometry_gate``
    refused: each candidate's relative pose against the drifting odometry made from ``poses``
    (`OdometryGateConfig`) over the odometry's path between the two places (`placerec.odometry_gate`), a refused
    one turned into a rejected one (`CandidateTable.refused`). Without the gate the tables as given, none refused.

    With the gate's ``through_loops`` the closures a table's pipeline accepted before count as well
    (`placerec.odometry_gate.LoopChain`): the queries are judged in order, and a query's answer (its best candidate
    the gate admits) enters the chain when it scores at least the table's operating threshold in ``thresholds``
    (None, or no ``thresholds``: the odometry alone), as a detector at that threshold would have accepted it."""
    gate = cfg.evaluation.odometry_gate
    if gate is None:
        return tables, [np.zeros(t.match_ids.shape, bool) for t in tables]
    odom, path = gate_odometry(cfg, poses)
    given = thresholds if thresholds is not None else [None] * len(tables)
    refusals = []
    for t, threshold in zip(tables, given, strict=True):
        if gate.bounds.through_loops and threshold is not None:
            refusals.append(_refused_through_loops(t, odom, path, gate.bounds, threshold))
        else:
            refusals.append(_refused_by_odometry(t, odom, path, gate.bounds))
    return [t.refused(r) for t, r in zip(tables, refusals, strict=True)], refusals


def _refused_by_odometry(
    t: CandidateTable, odom: np.ndarray, path: np.ndarray, bounds: OdometryGateParams
) -> np.ndarray:
    """The (Q, N) candidates of ``t`` the gate refuses against the odometry alone."""
    refused = np.zeros(t.match_ids.shape, bool)
    qi, rank = np.nonzero(t.match_ids >= 0)
    if qi.size:
        q, m = t.query_ids[qi], t.match_ids[qi, rank]
        trans, rot = odometry_disagreement(t.relative_poses[qi, rank], odom[m], odom[q])
        refused[qi, rank] = ~bounds.admits(trans, rot, path[q] - path[m])
    return refused


def _refused_through_loops(
    t: CandidateTable, odom: np.ndarray, path: np.ndarray, bounds: OdometryGateParams, threshold: float
) -> np.ndarray:
    """The (Q, N) candidates of ``t`` the gate refuses, predicting through the answers accepted at ``threshold``
    by the queries before (`odometry_gated`)."""
    chain = LoopChain()
    refused = np.zeros(t.match_ids.shape, bool)
    for i in np.argsort(t.query_ids, kind="stable"):
        refused[i] = judge_through_loops(
            chain,
            int(t.query_ids[i]),
            t.match_ids[i],
            t.relative_poses[i],
            t.scores[i],
            t.accepted[i],
            odom,
            path,
            bounds,
            threshold,
        )
    return refused


def pose_truths(
    cfg: ExperimentConfig,
    tables: list[CandidateTable],
    poses: np.ndarray,
    stamps: np.ndarray | None,
    truth: TruthClouds | None,
) -> list[PoseGroundTruth | None]:
    """The pose ground truth of each pipeline's candidates (`placerec.eval.pose_truth`), sharing one revisit set:
    the overlap's plus every query some pipeline of the run closed with a correct pose (None each when ``truth``
    holds no voxels: pose truth off, or not collected)."""
    if truth is None or not truth.pose_truth or len(truth.voxels) != poses.shape[0]:
        return [None] * len(tables)
    exclusion = _gt_options(cfg, stamps)["exclusion"]
    base = overlap_truth(truth.voxels, poses, exclusion, stamps, truth.settings, truth.overlap)
    truth.overlap = (base.is_revisit, base.best_overlap)
    keys = []
    for table in tables:
        width = min(cfg.evaluation.top_n, table.match_ids.shape[1])
        keys.append(
            correct_candidates(
                base, poses, table.query_ids, table.match_ids[:, :width], table.relative_poses[:, :width]
            )
        )
    n = max(len(base), 1)
    closed = np.zeros(len(base), dtype=bool)
    closed_by: dict[int, int] = {}
    for k in keys:
        closed[k // n] = True
        for key in k[::-1].tolist():  # per query its lowest match id last, so it is the one kept
            closed_by[key // n] = key % n
    shared = with_candidates(base, np.zeros(0, dtype=np.int64), closed)
    direction = overlap_directions(truth.voxels, poses, shared, cfg.evaluation.reverse_yaw_deg, closed_by)
    return [replace(with_candidates(base, k, closed), direction=direction) for k in keys]


def _read_or_empty(path: Path, read: Any, empty_shape: tuple[int, ...]) -> np.ndarray:
    """``read(path)``, or an empty array for the empty file a run of no scans writes."""
    if path.is_file() and path.stat().st_size == 0:
        return np.zeros(empty_shape)
    return read(path)


def report_loop(
    cfg: ExperimentConfig,
    run: Path,
    seq: Sequence,
    records: list[PipelineRecord],
    truth: TruthClouds | None = None,
    link_latest: bool = True,
    recognizers: Iterable[PlaceRecognizer] | None = None,
) -> dict[str, Any]:
    """Loop-mode metrics and all outputs; returns the metrics dict written to ``metrics.json``. ``truth`` (the
    scans' voxels collected by the run) adds the pose and ICP ground truths' figures; ``link_latest`` False leaves
    ``latest`` alone (a benchmark's cells). With ``output.evidence`` (and figures) the page gets each pipeline's
    evidence (`placerec.experiment.evidence_figures.draw_evidence`), for which ``recognizers`` (the run's, aligned
    with ``records``) describe the scans the figures show again; without them those pipelines are built again."""
    poses = require_poses(seq)
    write_kitti_poses(run / "poses.txt", poses)
    if seq.timestamps is not None:
        with atomic_write(run / "times.txt", "w") as fh:
            np.savetxt(fh, seq.timestamps, fmt="%.6f")
    results: dict[str, Any] = {}
    curves: dict[str, dict[str, Any]] = {}
    tables, refusals = odometry_gated(
        cfg, [record.table() for record in records], poses, [record.threshold for record in records]
    )
    pose_gts = pose_truths(cfg, tables, poses, seq.timestamps, truth)
    all_metrics = []
    for record, table, pose_gt, refused in zip(records, tables, pose_gts, refusals, strict=True):
        write_candidates(run / f"candidates_{slug(record.label)}.csv", record.query_ids, record.candidates)
        metrics, summary = loop_summary(
            cfg, table, poses, seq.timestamps, record.threshold, truth, pose_gt, refused
        )
        all_metrics.append(metrics)
        q, m = metrics.query_ids, metrics.match_ids
        summary["time_ms"] = _timing(record)
        summary["min_score"] = _min_score(record.params)
        summary["rejections"] = rejection_counts(record.candidates).as_dict()
        results[record.label] = summary
        curves[record.label] = {
            "precision": metrics.precision,
            "recall": metrics.recall,
            "thresholds": metrics.thresholds,
            "max_f1": metrics.max_f1,
            "best": (metrics.recall_at_max_f1, metrics.precision_at_max_f1),
        }
        accepted = (
            metrics.outcomes_at(metrics.threshold_at_max_f1)["accepted"]
            if metrics.n_candidates
            else np.zeros(q.size, bool)
        )
        write_closures_mcap(
            run / f"closures_{slug(record.label)}.mcap",
            poses,
            loop_edges(record, accepted, refused[:, 0] if refused.size else None),
            timestamps=seq.timestamps,
        )
        if cfg.output.figures:
            figures.plot_trajectory_closures(
                poses[:, :3, 3],
                q,
                m,
                metrics.correct,
                accepted,
                metrics.revisit,
                run / f"trajectory_{slug(record.label)}.png",
                f"{record.label}: closures at max F1 (threshold {metrics.threshold_at_max_f1:.3g})",
            )
    payload = {
        "mode": "loop",
        "dataset": seq.name,
        "n_scans": len(seq),
        "pipelines": results,
        "peak_memory_mb": _peak_memory_mb(),
    }
    notes = pipeline_notes(records)
    if notes:
        payload["notes"] = notes
    page = None
    if cfg.output.figures and cfg.output.evidence:
        page = _evidence_page(cfg, run, seq, records, all_metrics, curves, recognizers)
    _finish(cfg, run, payload, curves, records, link_latest, page)
    return payload


def loop_edges(
    record: PipelineRecord, accepted: np.ndarray, refused_top: np.ndarray | None = None
) -> list[LoopEdge]:
    """Each query's top candidate as a `LoopEdge` for ``closures_<label>.mcap``: accepted where ``accepted`` (the
    query's answer at the report's threshold, aligned with ``record.query_ids``) holds and verification did not
    reject it; a rejected one names verification's reason, ``odometry_gate`` where ``refused_top`` (the
    evaluation's odometry gate refused it), or ``threshold`` for a score below it."""
    edges = []
    refused = np.zeros(len(record.query_ids), bool) if refused_top is None else refused_top
    for q, ok, cands, gated in zip(record.query_ids, accepted, record.candidates, refused, strict=True):
        if not cands:
            continue
        c = cands[0]
        why = c.rejection or ("odometry_gate" if gated else None) or (None if ok else "threshold")
        edges.append(LoopEdge(q, c.match_id, c.score, c.relative_pose, c.inliers, why is None, why))
    return edges


def _evidence_page(
    cfg: ExperimentConfig,
    run: Path,
    seq: Sequence,
    records: list[PipelineRecord],
    metrics: list[LoopMetrics],
    curves: dict[str, dict[str, Any]],
    recognizers: Iterable[PlaceRecognizer] | None,
) -> tuple[str, list[str]]:
    """The interactive figures (plotly.js written into ``run``) and one evidence section per pipeline of
    ``index.html`` (`write_index_html`'s ``interactive`` and ``sections``), the evidence figures drawn."""
    from placerec.experiment import interactive
    from placerec.experiment.evidence import select_cases
    from placerec.experiment.evidence_figures import CaseScans, draw_evidence
    from placerec.experiment.tables import evidence_section

    poses = require_poses(seq)
    gt = loop_ground_truth(poses, **_gt_options(cfg, seq.timestamps))
    per = cfg.output.evidence_per_gallery
    cases = [select_cases(r, m, gt, poses, per) for r, m in zip(records, metrics, strict=True)]
    recs = None if recognizers is None else list(recognizers)
    evidence = draw_evidence(cfg, run, records, cases, CaseScans(seq, seq), recs)
    interactive.write_plotly_js(run)
    pr = interactive.pr_curves_html(curves, f"{cfg.name}: precision-recall (threshold under the mouse)")
    sections = []
    for k, (record, m, ev) in enumerate(zip(records, metrics, evidence, strict=True)):
        trajectory = interactive.trajectory_html(
            poses[:, :3, 3], m, record.candidates, m.threshold_at_max_f1, record.label, f"trajectory-{k}"
        )
        sections.append(evidence_section(ev, trajectory))
    return pr, sections


def report_localize(
    cfg: ExperimentConfig,
    run: Path,
    map_seq: Sequence,
    query_seq: Sequence,
    records: list[PipelineRecord],
    recognizers: Iterable[PlaceRecognizer] | None = None,
) -> dict[str, Any]:
    """Localize-mode metrics (success within ``success_distance``) and outputs; with ``output.evidence`` (and
    figures) the page gets each pipeline's evidence: queries localised, answered wrongly and not answered
    (`placerec.experiment.evidence.select_localize_cases`), ``recognizers`` as in `report_loop`."""
    map_poses, query_poses = map_seq.poses, query_seq.poses
    assert map_poses is not None and query_poses is not None  # localize mode checks them before it runs
    write_kitti_poses(run / "map_poses.txt", map_poses)
    write_kitti_poses(run / "query_poses.txt", query_poses)
    success_distance = cfg.evaluation.localize.success_distance
    results: dict[str, Any] = {}
    all_metrics = []
    for record in records:
        write_candidates(run / f"candidates_{slug(record.label)}.csv", record.query_ids, record.candidates)
        estimates, basis, rule = localize_estimates(
            record.table(), map_poses, cfg.evaluation.localize.ambiguity
        )
        metrics = localization_metrics(
            estimates,
            query_poses[np.asarray(record.query_ids, dtype=np.int64)],
            success_distance,
            basis=basis,
            answer_rule=rule,
        )
        all_metrics.append(metrics)
        summary = metrics.summary()
        summary["time_ms"] = _timing(record)
        summary["rejections"] = rejection_counts(record.candidates).as_dict()
        results[record.label] = summary
        if cfg.output.figures:
            figures.plot_localization(
                map_poses[:, :3, 3],
                query_poses[:, :3, 3],
                np.where(np.isfinite(estimates[:, :3, 3]), estimates[:, :3, 3], query_poses[:, :3, 3]),
                metrics.success,
                run / f"localization_{slug(record.label)}.png",
                f"{record.label}\nlocalised {metrics.success_rate:.1%} ({rule} answers within {success_distance} m,"
                f" {basis})",
                answered=metrics.answered,
            )
    payload = {
        "mode": "localize",
        "map": map_seq.name,
        "queries": query_seq.name,
        "n_map_scans": len(map_seq),
        "n_queries": len(query_seq),
        "pipelines": results,
        "peak_memory_mb": _peak_memory_mb(),
    }
    notes = pipeline_notes(records)
    if notes:
        payload["notes"] = notes
    page = None
    if cfg.output.figures and cfg.output.evidence:
        from placerec.experiment.evidence import select_localize_cases
        from placerec.experiment.evidence_figures import CaseScans, draw_evidence
        from placerec.experiment.tables import evidence_section

        per = cfg.output.evidence_per_gallery
        cases = [
            select_localize_cases(r, m, map_poses, query_poses, per)
            for r, m in zip(records, all_metrics, strict=True)
        ]
        recs = None if recognizers is None else list(recognizers)
        evidence = draw_evidence(cfg, run, records, cases, CaseScans(query_seq, map_seq), recs)
        page = ("", [evidence_section(ev, mode="localize") for ev in evidence])
    _finish(cfg, run, payload, {}, records, page=page)
    return payload


def localize_estimates(
    table: CandidateTable, map_poses: np.ndarray, ambiguity: AmbiguityParams | None = None
) -> tuple[np.ndarray, str, str]:
    """(Q, 4, 4) estimated query poses from the top candidates (NaN: no answer), their basis and the answer rule.

    Basis: ``"pose"`` (``T_world_match @ T_match_query``) when any top candidate carries a 6-DoF relative pose, a
    top candidate without one then giving no answer; else ``"retrieval"``, the matched map scan's pose.

    Answer rule: ``"accepted"`` when the pipeline verifies (any of its candidates carries ``accepted``): only a top
    candidate its verification accepted is an answer, a rejected one is no answer, never a hit (verification ranks
    the accepted candidates first, so a rejected top candidate means none was accepted). ``"top"`` for a pipeline
    that does not verify (no candidate carries ``accepted``): its top candidate is its answer. With
    ``ambiguity.max_ratio`` (`placerec.verify.ambiguity`) an accepted answer that another accepted candidate,
    placing the query more than ``ambiguity.separation_m`` away, nearly matches is no answer either, as a
    rejected one is."""
    top, rel = table.match_ids[:, 0], table.relative_poses[:, 0]
    answered, basis, rule = _answers(table)
    if rule == "accepted" and ambiguity is not None and ambiguity.max_ratio is not None:
        answered = answered & ~_ambiguous(table, map_poses, answered, basis, ambiguity)
    estimates = np.full((top.size, 4, 4), np.nan)
    estimates[answered] = _placed(map_poses, top[answered], rel[answered], basis)
    return estimates, basis, rule


def _answers(table: CandidateTable) -> tuple[np.ndarray, str, str]:
    """(Q,) which queries have an answer, the basis and the answer rule (`localize_estimates`)."""
    top, rel = table.match_ids[:, 0], table.relative_poses[:, 0]
    verifies = bool((table.accepted >= 0).any())
    answered = (top >= 0) & (table.accepted[:, 0] == 1) if verifies else top >= 0
    posed = full_pose_mask(rel)
    basis = "pose" if (posed & (top >= 0)).any() else "retrieval"
    if basis == "pose":
        answered = answered & posed
    return answered, basis, "accepted" if verifies else "top"


def ambiguous_answers(table: CandidateTable, map_poses: np.ndarray, ambiguity: AmbiguityParams) -> np.ndarray:
    """(Q,) the queries whose accepted answer the ambiguity rule refuses (`localize_estimates`'s rule), the
    candidates placed with ``map_poses`` (the poses of the scans the match ids index: a map's). None refused when
    the pipeline does not verify or ``ambiguity.max_ratio`` is None. Loop mode across two drives applies it with
    the first drive as the map (tools/eval_cross_sensor.py), as a session joining a prior map does
    (``prior_map.join_ambiguity``)."""
    answered, basis, rule = _answers(table)
    if rule != "accepted" or ambiguity.max_ratio is None:
        return np.zeros(answered.shape, bool)
    return answered & _ambiguous(table, map_poses, answered, basis, ambiguity)


def _placed(
    map_poses: np.ndarray, match_ids: np.ndarray, relative_poses: np.ndarray, basis: str
) -> np.ndarray:
    """(K, 4, 4) where candidates place their queries: the matched map scans' poses, composed with the candidates'
    relative poses on the ``"pose"`` basis (`localize_estimates`)."""
    T = map_poses[match_ids]
    return T @ relative_poses if basis == "pose" else T


def _ambiguous(
    table: CandidateTable, map_poses: np.ndarray, answered: np.ndarray, basis: str, params: AmbiguityParams
) -> np.ndarray:
    """(Q,) True where an answered query's accepted candidates make its answer ambiguous (`localize_estimates`)."""
    out = np.zeros(answered.shape, bool)
    for q in np.flatnonzero(answered):
        ok = (table.match_ids[q] >= 0) & (table.accepted[q] == 1)
        if basis == "pose":
            ok &= full_pose_mask(table.relative_poses[q])
        ranks = np.flatnonzero(ok)  # the top candidate first: it is answered, so accepted (and posed)
        where = _placed(map_poses, table.match_ids[q, ranks], table.relative_poses[q, ranks], basis)[:, :3, 3]
        out[q] = params.refuses(runner_up_ratio(table.scores[q, ranks], where, params.separation_m))
    return out


def require_poses(seq: Sequence) -> np.ndarray:
    """The poses of ``seq``, or `ConfigError` when it has none: loop-mode evaluation needs ground-truth poses."""
    if seq.poses is None:
        raise ConfigError(f"dataset {seq.name} has no poses: loop-mode evaluation needs ground-truth poses")
    return seq.poses


def _finish(
    cfg: ExperimentConfig,
    run: Path,
    payload: dict[str, Any],
    curves: dict[str, Any],
    records: list[PipelineRecord],
    link_latest: bool = True,
    page: tuple[str, list[str]] | None = None,
) -> None:
    """Write ``metrics.json``, ``pipelines.yaml``, the run's figures and ``index.html`` (with ``page``'s
    interactive figures and sections, `_evidence_page`), then point ``latest`` at the run."""
    with atomic_write(run / "metrics.json", "w") as fh:
        json.dump(finite_or_null(payload), fh, indent=2, default=json_default, allow_nan=False)
    with atomic_write(run / "pipelines.yaml", "w") as fh:  # resolved parameters: presets and defaults applied
        resolved = {r.label: {"pipeline": r.pipeline, "class": r.name, "params": r.params} for r in records}
        yaml.safe_dump(resolved, fh, sort_keys=False)
    if cfg.output.figures:
        if curves:
            figures.plot_pr_curves(curves, run / "pr_curves.png", f"{cfg.name}: precision-recall")
        means = {
            r.label: r.stage_means_ms() for r in records
        }  # they sum to time_ms.mean, the table's ms/scan
        shared = [float(np.mean(r.timing_ms["preprocess"])) for r in records if r.timing_ms["preprocess"]]
        figures.plot_timing(
            means, run / "timing.png", shared[0] if shared else None, PER_SCAN_TIME.replace("; ", "\n")
        )
        interactive, sections = page if page is not None else ("", [])
        write_index_html(run, cfg, payload, interactive, sections)
    if link_latest:
        point_latest(run)  # last: a run that failed before this point leaves latest where it was
