"""The odometry gate as the evaluation applies it (`evaluation.odometry_gate`): the drifting odometry a run is judged
against, and one query's candidates judged through the closures accepted before it (`placerec.odometry_gate`).

`placerec.experiment.report.odometry_gated` judges a finished run's tables with them; `placerec.experiment.runner`
uses the same steps while a run goes, to give a guided pipeline (``verify.guided``) the motion prior a detector
with the gate would have (`placerec.odometry_gate.ChainPrior`)."""

from __future__ import annotations

import numpy as np

from placerec.config import ExperimentConfig
from placerec.experiment.candidates import rank_order
from placerec.odometry_gate import LoopChain, OdometryGateParams, pose_disagreement

__all__ = ["gate_odometry", "judge_through_loops"]


def gate_odometry(cfg: ExperimentConfig, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(odometry poses, cumulative odometry path) of ``evaluation.odometry_gate``: ``poses`` drifting as its
    ``drift`` says, drawn with its ``seed`` (None: the simulator's seed, else 0). The gate must be set."""
    from placerec.sim.odometry import drift_poses
    from placerec.types import path_length

    gate = cfg.evaluation.odometry_gate
    assert gate is not None
    seed = gate.seed
    if seed is None:
        seed = cfg.dataset.simulator.seed if cfg.dataset.source == "simulator" else 0
    odom = drift_poses(poses, gate.drift, seed)
    return odom, path_length(odom[:, :3, 3])


def judge_through_loops(
    chain: LoopChain,
    query: int,
    match_ids: np.ndarray,
    relative_poses: np.ndarray,
    scores: np.ndarray,
    accepted: np.ndarray,
    odom: np.ndarray,
    path: np.ndarray,
    bounds: OdometryGateParams,
    threshold: float,
) -> np.ndarray:
    """Which of one query's candidates (a table row: ``match_ids`` (N,) with -1 padding, ``relative_poses``
    (N, 4, 4), ``scores``, ``accepted`` 1 / 0 / -1) the gate refuses, predicting through ``chain``; the best one
    it admits enters ``chain`` when it scores at least ``threshold``, as a detector at that threshold accepts it."""
    refused = np.zeros(match_ids.shape, bool)
    ranks = np.nonzero(match_ids >= 0)[0]
    for r in ranks:
        predicted, along = chain.predict(int(match_ids[r]), query, odom, path)
        trans, rot = pose_disagreement(relative_poses[r], predicted)
        refused[r] = not bounds.admits(trans, rot, np.array([along]))[0]
    if ranks.size == 0:
        return refused
    kept = np.where(refused, 0.0, scores)
    top = int(rank_order(match_ids, kept, np.where(refused, np.int8(0), accepted))[0])
    if kept[top] >= threshold:
        chain.add(int(match_ids[top]), query, relative_poses[top])
    return refused
