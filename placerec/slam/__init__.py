"""SLAM back end: odometry + verified loop closures + a GTSAM pose graph, judged by trajectory error.

* `placerec.slam.online.OnlineSlam` — the online module: feed scans with odometry poses, get loop edges; the
  graph (`placerec.slam.graph.PoseGraph`: odometry and robust loop factors, iSAM2, final batch) stays current.
* `placerec.slam.multisession.MultiSessionSlam` — a new session against a prior map: inter-session closures kept
  pending until enough agree, then one graph in the map's frame (`MultiSessionResult`: joined, or kept separate).
* `placerec.slam.odometry.KissIcpOdometry` — KISS-ICP odometry on the scans (extra ``slam``).
* `placerec.slam.result.SlamResult` — what a run of the online loop produced.
* `placerec.eval.trajectory` — ATE (after rigid alignment) and RPE.

``placerec slam`` (config, run, report) is the application on top, `placerec.slam_app`. Names are imported on
first use, so ``import placerec.slam`` imports neither GTSAM nor the pipelines.
"""

from placerec._lazy import lazy_exports

_EXPORTS = {
    "OnlineSlam": "online",
    "MultiSessionSlam": "multisession",
    "MultiSessionResult": "multisession",
    "PoseGraph": "graph",
    "GraphParams": "graph",
    "LoopFactor": "graph",
    "KissIcpOdometry": "odometry",
    "KissIcpParams": "odometry",
    "SlamResult": "result",
    "trajectory_errors": "placerec.eval.trajectory",
}

#: names of the SLAM application, which lives above the back end (`placerec.slam_app`)
_APPLICATION = ("SlamConfig", "load_slam_config", "run_slam", "slam_sequence")

__all__ = sorted(_EXPORTS)
_exports = lazy_exports(__name__, _EXPORTS)


def __getattr__(name: str) -> object:
    if name in _APPLICATION:
        raise AttributeError(
            f"placerec.slam.{name} is the SLAM application's: import it from placerec.slam_app"
        )
    return _exports(name)
