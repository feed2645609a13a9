"""The GTSAM pose graph of the SLAM back end (placerec.slam.graph) on a synthetic drive with drifting odometry:
loop closures reduce the trajectory error, injected false loops do not bend the map, g2o round-trips."""

import numpy as np
import pytest

from placerec.errors import ScanDataError
from placerec.eval.trajectory import trajectory_errors
from placerec.sim.geometry import euler_rotation
from placerec.sim.odometry import OdometryDrift, drift_poses
from placerec.slam.graph import GraphParams, LoopFactor, PoseGraph
from placerec.slam_app.config import SlamConfig
from placerec.slam_app.run import false_loops
from placerec.types import relative_pose


def _rectangle(w: float, h: float, lateral: float, reverse: bool) -> np.ndarray:
    """Poses every 1 m around a w x h rectangle (counter-clockwise, or clockwise when ``reverse``), ``lateral``
    metres inside it."""
    corners = np.array([[0, 0], [w, 0], [w, h], [0, h], [0, 0]], float)
    corners = corners + np.sign(np.array([w, h]) / 2 - corners) * lateral
    if reverse:
        corners = corners[::-1]
    pts, yaws = [], []
    for a, b in zip(corners[:-1], corners[1:], strict=True):
        d = b - a
        n = int(round(np.linalg.norm(d)))
        for k in range(n):
            pts.append(a + d * k / n)
            yaws.append(np.arctan2(d[1], d[0]))
    T = np.tile(np.eye(4), (len(pts), 1, 1))
    T[:, :3, :3] = euler_rotation(np.array(yaws), 0.0, 0.0)
    T[:, :2, 3] = pts
    T[:, 2, 3] = 1.8
    return T


@pytest.fixture(scope="module")
def drive():
    """A 160 m lap, the same lap again 2 m inside it, then the lap driven the other way: true poses, drifting
    odometry and the loops a verified recognizer would give (true relative poses + 2 cm / 0.05 deg noise) for
    every scan within 4 m of a scan at least 60 frames older."""
    gt = np.concatenate(
        [_rectangle(50, 30, 0, False), _rectangle(50, 30, 2, False), _rectangle(50, 30, 0, True)]
    )
    odo = drift_poses(
        gt,
        OdometryDrift(translation=0.02, rotation_deg=0.05, yaw_bias_deg_per_100m=2.0, scale_bias=0.0),
        seed=4,
    )
    rng = np.random.default_rng(1)
    loops = []
    pos = gt[:, :3, 3]
    for q in range(60, len(gt)):
        d = np.linalg.norm(pos[: q - 60] - pos[q], axis=1)
        if d.size and d.min() < 4.0:
            m = int(np.argmin(d))
            T = relative_pose(gt[m], gt[q])
            T[:3, 3] += rng.normal(0, 0.02, 3)
            T[:3, :3] = euler_rotation(rng.normal(0, np.radians(0.05)), 0.0, 0.0) @ T[:3, :3]
            loops.append(LoopFactor(m, q, T, 0.4))
    return gt, odo, loops


def _solve(odo, loops, params=None, extra=None, online=True):
    """Feed the graph scan by scan (iSAM2 after each with ``online``, else once at the end); optimise."""
    g = PoseGraph(params or GraphParams())
    by_query: dict[int, list[LoopFactor]] = {}
    for lp in loops:
        by_query.setdefault(lp.query_id, []).append(lp)
    for q, more in (extra or {}).items():
        by_query.setdefault(q, []).extend(more)
    for i, T in enumerate(odo):
        g.add_pose(T)
        for lp in by_query.get(i, []):
            g.add_loop(lp)
        if online:
            g.update()
    online = g.poses()
    optimized, info = g.optimize()
    return g, online, optimized, info


@pytest.fixture(scope="module")
def solved(drive):
    """The drive solved online with Cauchy loop factors (iSAM2 per scan) and a batch LM."""
    gt, odo, loops = drive
    return _solve(odo, loops, GraphParams(batch="lm"))


def test_loops_cut_the_drift(drive, solved):
    """Cauchy loop factors online, LM batch; the default GNC batch reaches the same from the odometry."""
    gt, odo, loops = drive
    assert len(loops) > 150
    opposite = [lp for lp in loops if relative_pose(gt[lp.match_id], gt[lp.query_id])[0, 0] < -0.7]
    assert len(opposite) > 50  # the third lap, driven the other way
    before = trajectory_errors(odo, gt).ate_rmse
    g, online, optimized, info = solved
    after = trajectory_errors(optimized, gt).ate_rmse
    assert before > 1.0
    assert after < before / 5, (before, after)
    assert trajectory_errors(online, gt).ate_rmse < before / 5  # iSAM2 online already has it
    assert info["method"] == "lm" and info["iterations"] >= 1
    assert g.loop_update_ms and g.update_ms  # updates with and without a loop are timed apart
    gnc, _, gnc_optimized, gnc_info = _solve(odo, loops, online=False)
    assert gnc_info["method"] == "gnc" and len(gnc_info["loop_weights"]) == len(loops)
    assert trajectory_errors(gnc_optimized, gt).ate_rmse == pytest.approx(after, rel=0.05)


@pytest.mark.parametrize("batch", ["lm", "gnc"])
def test_ten_false_loops_do_not_bend_the_map(drive, solved, batch):
    gt, odo, loops = drive
    params = GraphParams(batch=batch)
    online = (
        batch == "lm"
    )  # Cauchy factors in iSAM2, then LM; GNC is the batch step alone (no online updates)
    clean = trajectory_errors(
        (solved if online else _solve(odo, loops, params, online=False))[2], gt
    ).ate_rmse
    cfg = SlamConfig(robustness={"false_loops": 10, "seed": 2})
    injected = false_loops(cfg, gt, len(gt))
    assert sum(len(v) for v in injected.values()) == 10
    for q, lps in injected.items():
        for lp in lps:
            assert lp.injected and np.linalg.norm(gt[q, :3, 3] - gt[lp.match_id, :3, 3]) >= 30.0
    g, _, optimized, info = _solve(odo, loops, params, injected, online)
    dirty = trajectory_errors(optimized, gt).ate_rmse
    assert dirty <= 1.1 * clean, (clean, dirty)
    # the weights (GNC's, or the Cauchy kernel's at the final residual) single out the injected loops
    w = np.asarray(info["loop_weights"])
    is_injected = np.array([lp.injected for lp in g.loops])
    assert w[is_injected].max() < 0.5 and np.median(w[~is_injected]) > 0.5
    assert np.min(np.asarray(info["loop_residuals"])[is_injected]) > 10


def test_without_a_robust_kernel_false_loops_do_bend_the_map(drive):
    """The check above can fail: plain least squares is pulled off by the same false loops."""
    gt, odo, loops = drive
    params = GraphParams(robust="none", batch="lm")
    clean = trajectory_errors(_solve(odo, loops, params, online=False)[2], gt).ate_rmse
    injected = false_loops(SlamConfig(robustness={"false_loops": 10, "seed": 2}), gt, len(gt))
    dirty = trajectory_errors(_solve(odo, loops, params, injected, online=False)[2], gt).ate_rmse
    assert dirty > 2 * clean


def test_g2o_export_reads_back_in_gtsam(drive, tmp_path):
    import gtsam

    gt, odo, loops = drive
    g, _, optimized, _ = _solve(odo[:100], [lp for lp in loops if lp.query_id < 100][:5])
    path = g.write_g2o(tmp_path / "graph.g2o", optimized)
    graph, values = gtsam.readG2o(str(path), True)
    assert values.size() == 100
    assert graph.size() == 99 + len(g.loops)
    assert np.allclose(values.atPose3(57).matrix(), optimized[57], atol=1e-6)


def test_a_loop_to_a_missing_pose_is_refused():
    g = PoseGraph()
    g.add_pose(np.eye(4))
    with pytest.raises(ScanDataError, match="both poses must exist"):
        g.add_loop(LoopFactor(0, 3, np.eye(4)))


def test_large_drift_true_loops_are_not_taken_for_outliers(drive):
    """Odometry 5x worse (several metres off at the first closure): the default kernel (3 sigmas) and GNC still
    reach the least-squares solution of the clean loops, where a 1-sigma Cauchy kernel stays metres off."""
    gt, _, loops = drive
    odo = drift_poses(
        gt,
        OdometryDrift(translation=0.1, rotation_deg=0.25, yaw_bias_deg_per_100m=10.0, scale_bias=0.0),
        seed=4,
    )
    exact = trajectory_errors(_solve(odo, loops, GraphParams(robust="none", batch="lm"), online=False)[2], gt)
    default = trajectory_errors(_solve(odo, loops, online=False)[2], gt)
    narrow = trajectory_errors(_solve(odo, loops, GraphParams(robust_k=1.0, batch="lm"), online=False)[2], gt)
    assert trajectory_errors(odo, gt).ate_rmse > 5.0
    assert default.ate_rmse <= 1.05 * exact.ate_rmse
    assert narrow.ate_rmse > 2 * exact.ate_rmse


def test_rounded_poses_from_a_text_file_are_taken(drive):
    """Poses written with 4 decimals (rotations no longer orthonormal) enter the graph as the nearest rotations."""
    gt, odo, _ = drive
    rounded = np.round(odo[:50], 4)
    assert np.abs(np.einsum("nji,njk->nik", rounded[:, :3, :3], rounded[:, :3, :3]) - np.eye(3)).max() > 1e-5
    g = PoseGraph()
    for T in rounded:
        g.add_pose(T)
    g.add_loop(LoopFactor(0, 49, np.round(relative_pose(odo[0], odo[49]), 4)))
    g.update()
    assert np.allclose(g.poses()[:, :3, 3], odo[:50, :3, 3], atol=2e-3)


def test_missing_gtsam_says_what_to_install(monkeypatch):
    import sys

    from placerec.errors import DependencyError

    monkeypatch.setitem(sys.modules, "gtsam", None)  # what an environment without GTSAM gives
    with pytest.raises(DependencyError, match=r"placerec\[slam\]"):
        PoseGraph()


def test_degenerate_graphs_are_placerec_errors():
    """GTSAM's "Indeterminate linear system" (a RuntimeError) never reaches the user: sigma settings are bounded,
    a step's rotation sigma is capped at 180 deg, poses must be rigid, and what GTSAM still cannot solve is a
    ScanDataError naming the pose."""
    from placerec.errors import ConfigError
    from placerec.slam_app.config import load_slam_config

    for key, value in (
        ("odometry_sigma_translation", 1e300),
        ("odometry_min_sigma_translation", 1e6),
        ("loop_sigma_translation", 1e300),
        ("odometry_min_sigma_rotation_deg", 1e5),
        ("loop_sigma_translation", 0.0),
    ):
        with pytest.raises(ConfigError, match=rf"graph\.{key}: "):
            load_slam_config("configs/slam_demo.yaml", [f"graph.{key}={value}"])

    def run(xs: tuple[float, ...], **params: float) -> np.ndarray:
        g = PoseGraph(GraphParams(batch="lm", **params))
        for x in xs:
            g.add_pose(_at(x))
            g.update()
        g.add_loop(LoopFactor(0, len(xs) - 1, _at(xs[-1])))
        return g.optimize()[0]

    # 50 000 km steps: a rotation sigma of 5e6 deg, uncapped, made the system indeterminate
    np.testing.assert_allclose(run((0.0, 5e7, 1e8))[:, 0, 3], [0.0, 5e7, 1e8])
    with pytest.raises(
        ScanDataError, match=r"iSAM2 update failed near pose 1 \(an indeterminate linear system\)"
    ):
        run((0.0, 1e8, 1e8 - 1, 1e8, 0.0), odometry_sigma_translation=10.0)  # sigmas of 1e9 m
    g = PoseGraph()
    for x in (0.0, 1.0, 2.0):
        g.add_pose(_at(x))
    with pytest.raises(
        ScanDataError, match="odometry pose 3 is no rigid motion: rotation block is a reflection"
    ):
        g.add_pose(np.diag([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(
        ScanDataError, match="odometry pose 3 is no rigid motion: rotation block is not a rotation"
    ):
        g.add_pose(np.diag([0.0, 0.0, 0.0, 1.0]))
    with pytest.raises(ScanDataError, match="loop 0 -> 1 is no rigid motion"):
        g.add_loop(LoopFactor(0, 1, np.diag([2.0, 2.0, 2.0, 1.0])))
    assert g.n_poses == 3 and not g.loops


def _at(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T
