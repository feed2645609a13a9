"""SLAM back end: odometry + verified loop closures + a GTSAM pose graph, judged by trajectory error.

* `placerec.slam.online.OnlineSlam` — the online module: feed scans with odometry poses, get loop edges; the
  graph (`placerec.slam.graph.PoseGraph`: odometry and robust loop factors, iSAM2, final batch) stays current.
* `placerec.slam.odometry.KissIcpOdometry` — KISS-ICP odometry on the scans (extra ``slam``).
* `placerec.slam.run.run_slam` / `slam_sequence` — ``placerec slam``: a config (`placerec.slam.config`) through
  the online loop; `placerec.slam.report` writes poses (KITTI, TUM), g2o, loop edges, ATE/RPE, figures.
* `placerec.eval.trajectory` — ATE (after rigid alignment) and RPE.

Names are imported on first use, so ``import placerec.slam`` imports neither GTSAM nor the pipelines.
"""

from placerec._lazy import lazy_exports

_EXPORTS = {
    "OnlineSlam": "online",
    "PoseGraph": "graph",
    "GraphParams": "graph",
    "LoopFactor": "graph",
    "KissIcpOdometry": "odometry",
    "KissIcpParams": "odometry",
    "SlamConfig": "config",
    "load_slam_config": "config",
    "run_slam": "run",
    "slam_sequence": "run",
    "SlamResult": "result",
    "trajectory_errors": "placerec.eval.trajectory",
}

__all__ = sorted(_EXPORTS)
__getattr__ = lazy_exports(__name__, _EXPORTS)
