"""The SLAM application: ``placerec slam`` (a config in, poses, g2o, loop edges, ATE/RPE and figures out).

* `placerec.slam_app.config` — `SlamConfig`, `load_slam_config`: the dataset, the odometry source, the loop
  closure pipeline, the graph and the robustness test of a run;
* `placerec.slam_app.run` — `run_slam` / `slam_sequence`: the config's sequence through the back end's online
  loop (`placerec.slam.online.OnlineSlam`);
* `placerec.slam_app.report` — the results folder.

It sits beside `placerec.experiment` and uses its public helpers (datasets, run folder, tables); the back end
(`placerec.slam`: pose graph, online loop closure, odometry) needs none of it.
"""

from placerec._lazy import lazy_exports

_EXPORTS = {
    "SlamConfig": "config",
    "load_slam_config": "config",
    "run_slam": "run",
    "slam_sequence": "run",
}

__all__ = sorted(_EXPORTS)
__getattr__ = lazy_exports(__name__, _EXPORTS)
