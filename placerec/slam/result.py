"""What a SLAM run produced (`placerec.slam_app.run.slam_sequence`), for the report and the benchmarks."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from placerec.slam.graph import LoopFactor, PoseGraph
from placerec.slam.multisession import MultiSessionResult

__all__ = ["SlamResult", "ONLINE_STAGES"]

#: Stages of the online loop timed per scan (wall-clock ms); ``timing_ms`` also holds "odometry" (reported apart:
#: the loop's cost with and without it) and "cpu": the process CPU time of the loop without odometry (all its
#: threads), which contention from other processes does not inflate as it does wall-clock time.
ONLINE_STAGES = ("preprocess", "describe", "query", "verify", "insert", "graph", "isam2")


@dataclass
class SlamResult:
    """What a SLAM run produced: trajectories (N, 4, 4), the loop edges, per-scan stage times (ms)."""

    name: str
    odometry: np.ndarray
    online: np.ndarray
    optimized: np.ndarray
    loops: list[LoopFactor]
    timing_ms: dict[str, list[float]]
    batch: dict[str, Any]
    graph: PoseGraph
    ground_truth: np.ndarray | None = None
    timestamps: np.ndarray | None = None
    isam2_ms: list[float] = field(default_factory=list)
    isam2_loop_ms: list[float] = field(default_factory=list)
    candidates: list[list[Any]] = field(default_factory=list)
    queried: list[bool] = field(default_factory=list)  # whether the scan had older scans to query
    #: a run against a prior map (``--prior-map``): the join's outcome; ``loops`` then holds the session's own
    #: loops in session scan ids, and ``graph_poses`` every pose of ``graph`` (the map's, then the session's)
    multisession: MultiSessionResult | None = None
    graph_poses: np.ndarray | None = None
    #: the detector's real-time counters (`placerec.realtime.RealtimeStats.as_dict`); None: sequential mode
    realtime: dict[str, Any] | None = None
    #: closures over the threshold the detector's odometry gate refused (``loops.odometry_gate``); None: no gate
    refused_by_gate: int | None = None
