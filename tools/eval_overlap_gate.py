"""The overlap gate for the displacement (`placerec.verify.score`, ``min_fitness_ratio``) from a tuning run's files.

Reads the candidates of a finished `placerec bench` run of the tuning split (verified with a low floor, so that the
candidates below the 0.25 one carry their ICP statistics), judges every verified candidate by the pose truth
(`placerec.eval.pose_truth`: right when its ``T_match_query`` is within 0.5 m / 2 deg of the true one and the match
eligible), and prints

* the fitness of right and wrong candidates by the verified pose's displacement ``d`` (its translation);
* the curve ``expected_fitness * exp(-d / L)`` fitted to the right candidates' median fitness per displacement bin;
* for each ratio, the gate applied to the candidates as the verification would (a gated candidate is no answer),
  the threshold the tuning rule picks on those answers (above every false closure's score, rounded up to 0.05,
  never below ``--floor``) and the recall there, mean over the cells (the run's revisit set: a guide for choosing
  the ratio, which the tuning bench then confirms with the gate in place).

Refuses a test-split run: a default is never chosen on test data (docs/protocol.md).

    placerec bench configs/benchmark_tuning.yaml --set 'sensors=[vlp16]' --set 'worlds=[town, campus, industrial]' \\
        --set 'seeds=[0, 1]' --set pipelines.6.params.verify.score.min_score=0.05 --out runs/vlp16_floor
    .venv/bin/python tools/eval_overlap_gate.py runs/vlp16_floor --pipelines superpoint-dbow orb-dbow

Ends with one JSON line.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
from scipy.optimize import curve_fit

from placerec.errors import ConfigError
from placerec.eval.metrics import loop_metrics
from placerec.eval.pose_truth import PoseGroundTruth
from placerec.experiment.benchmark import load_benchmark_config, read_cell
from placerec.experiment.benchmark_summary import tuning_pick
from placerec.experiment.candidates import CandidateTable

BINS_M = (0, 1, 2, 3, 4, 6, 8, 12, 20, 40)
STEP = 0.05


def load_cells(
    run: Path, labels: list[str]
) -> list[tuple[str, dict[str, CandidateTable], dict[str, PoseGroundTruth]]]:
    """Each finished cell's candidate tables and pose truths (the run's own revisit set) for ``labels``."""
    bench = load_benchmark_config(run / "config.yaml")
    if bench.split != "tuning":
        raise ConfigError(f"{run}: a {bench.split}-split run; the gate is chosen on tuning cells only")
    out = []
    for cell in bench.cells():
        folder = run / "cells" / cell.name
        if not (folder / "cell.json").is_file():
            continue
        f = read_cell(bench, cell, folder)
        every = [p.display_name for p in f.cfg.pipelines]
        missing = [label for label in labels if label not in every]
        if missing:
            raise ConfigError(f"{folder}: no pipeline {missing[0]!r}; the run has {every}")
        at = {label: every.index(label) for label in labels}
        out.append(
            (cell.name, {k: f.tables[i] for k, i in at.items()}, {k: f.pose_gts[i] for k, i in at.items()})
        )
    if not out:
        raise ConfigError(f"{run}: no finished cell")
    return out


def displacement(table: CandidateTable) -> np.ndarray:
    """(Q, N) metres: the translation of each candidate's verified pose (NaN without one)."""
    return np.linalg.norm(table.relative_poses[:, :, :3, 3], axis=-1)


def right(table: CandidateTable, gt: PoseGroundTruth) -> np.ndarray:
    """(Q, N) whether each candidate's pose is right (pose truth)."""
    q = np.broadcast_to(table.query_ids[:, None], table.match_ids.shape)
    return gt.is_true_match(q, table.match_ids) & (table.match_ids >= 0)


def answers(table: CandidateTable, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per query the best-scored candidate among ``keep`` (match id -1 and NaN where none)."""
    s = np.where(keep & (table.scores > 0), table.scores, -np.inf)
    best = np.argmax(s, axis=1)
    rows = np.arange(len(best))
    has = np.isfinite(s[rows, best])
    return np.where(has, table.match_ids[rows, best], -1), np.where(has, table.scores[rows, best], np.nan)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", type=Path, help="a finished tuning-split `placerec bench` output folder")
    ap.add_argument("--pipelines", nargs="+", required=True, help="pipeline labels of the run")
    ap.add_argument("--ratios", nargs="+", type=float, default=[0.5, 0.6, 0.65, 0.7, 0.75, 0.8, 0.85])
    ap.add_argument("--floor", type=float, default=0.10, help="the verification's min_score with the gate")
    args = ap.parse_args(argv)
    cells = load_cells(args.run, args.pipelines)

    fit_d, fit_f = [], []  # right candidates with ICP statistics, every pipeline
    print(f"{args.run}: {len(cells)} cells")
    for label in args.pipelines:
        print(f"\n{label}: fitness by displacement (right: all; wrong: verified score >= 0.10)")
        print(
            f"{'d [m]':>8} {'right n':>8} {'q10':>5} {'median':>6} {'wrong n':>8} {'median':>6} {'best score':>10}"
        )
        rd, rf, wd, wf, ws = [], [], [], [], []
        for _, tables, gts in cells:
            t, gt = tables[label], gts[label]
            d, ok, has = displacement(t), right(t, gt), np.isfinite(t.fitness)
            rd.append(d[ok & has]), rf.append(t.fitness[ok & has])
            wrong = ~ok & has & (t.verified_scores >= 0.10)
            wd.append(d[wrong]), wf.append(t.fitness[wrong]), ws.append(t.verified_scores[wrong])
        rd, rf, wd, wf, ws = (np.concatenate(x) for x in (rd, rf, wd, wf, ws))
        fit_d.append(rd), fit_f.append(rf)
        for lo, hi in zip(BINS_M[:-1], BINS_M[1:], strict=True):
            r, w = (rd >= lo) & (rd < hi), (wd >= lo) & (wd < hi)
            rq = f"{np.percentile(rf[r], 10):5.2f} {np.median(rf[r]):6.2f}" if r.any() else f"{'':>5} {'':>6}"
            wq = f"{np.median(wf[w]):6.2f} {ws[w].max():10.3f}" if w.any() else f"{'':>6} {'':>10}"
            print(f"{lo:3d}-{hi:<4d} {int(r.sum()):8d} {rq} {int(w.sum()):8d} {wq}")

    d_all, f_all = np.concatenate(fit_d), np.concatenate(fit_f)
    xs, ys = [], []
    for lo, hi in zip(BINS_M[:-1], BINS_M[1:], strict=True):
        sel = (d_all >= lo) & (d_all < hi)
        if sel.sum() >= 10:
            xs.append(float(np.median(d_all[sel]))), ys.append(float(np.median(f_all[sel])))
    (f0, length), _ = curve_fit(lambda d, a, b: a * np.exp(-d / b), xs, ys, p0=(0.7, 20.0), maxfev=10_000)
    print(f"\ncurve fitted to the right candidates' median fitness: {f0:.3f} exp(-d / {length:.1f} m)")

    sweep: dict[str, dict[str, dict[str, float]]] = {}
    print(
        f"\nratio sweep (floor {args.floor:g}; ratio 0: no gate): threshold the tuning rule picks, recall there"
    )
    for ratio in dict.fromkeys([0.0, *args.ratios]):
        row = {}
        for label in args.pipelines:
            worst, recalls, per_cell = -math.inf, [], []
            for _, tables, gts in cells:
                t, gt = tables[label], gts[label]
                expected = f0 * np.exp(-np.nan_to_num(displacement(t), nan=np.inf) / length)
                keep = (t.accepted != 0) | (t.verified_scores >= args.floor)
                keep &= (ratio == 0) | (np.nan_to_num(t.fitness, nan=-1.0) >= ratio * expected)
                m, s = answers(t, keep)
                met = loop_metrics(t.query_ids, m, s, gt)
                wrong = (met.match_ids >= 0) & ~met.correct
                worst = max(worst, float(met.scores[wrong].max()) if wrong.any() else -math.inf)
                per_cell.append(met)
            pick = tuning_pick(worst, args.floor, STEP)
            for met in per_cell:
                acc = (met.match_ids >= 0) & (met.scores >= pick)
                recalls.append(float((acc & met.correct).sum()) / max(met.n_revisits, 1))
            row[label] = {"threshold": round(pick, 3), "recall": round(float(np.mean(recalls)), 4)}
        sweep[f"{ratio:g}"] = row
        print(
            f"  ratio {ratio:4.2f}: "
            + " | ".join(f"{k} {v['threshold']:.2f} R {v['recall']:.3f}" for k, v in row.items())
        )
    payload = {
        "tool": "eval_overlap_gate",
        "run": str(args.run),
        "cells": len(cells),
        "expected_fitness": round(float(f0), 3),
        "expected_fitness_length_m": round(float(length), 1),
        "sweep": sweep,
    }
    print(json.dumps(payload))
    return payload


if __name__ == "__main__":
    sys.exit(0 if main() else 1)
