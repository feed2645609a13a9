"""SLAM and localisation: odometry files that are not rigid motions (scaled, sheared, zero, mirrored, NaN) or
hold another count than the scans, drift applied to NaN poses, and a pose graph given NaN, zero or non-rigid
poses and loops (GTSAM must not be left to fail on an indeterminate system). The SLAM config keys themselves are
walked in `fuzz.configs`."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from fuzz.corpus import Case
from fuzz.datasets import DAMAGE, kitti
from placerec.errors import ConfigError, ScanDataError, ScanFormatError


def _odometry_layout(tmp: Path, rows: Callable[[list[np.ndarray]], list[np.ndarray]], name: str = "odom.txt") -> list[str]:  # fmt: skip
    """A 3-scan KITTI layout and an odometry file of its poses edited by ``rows``; the SLAM overrides using it."""
    root = kitti(tmp / "k", n=3)
    poses = [np.c_[np.eye(3), [1.5 * k, 0, 0]] for k in range(3)]
    path = tmp / name
    path.write_text("".join(" ".join(f"{v:.9g}" for v in P.ravel()) + "\n" for P in rows(poses)))
    return [
        "dataset.source=path",
        f"dataset.path={root}",
        "dataset.dataset=kitti",
        "dataset.sequence='00'",
        "odometry.source=file",
        f"odometry.path={path}",
    ]


def _odometry(overrides: list[str]) -> np.ndarray:
    from placerec.experiment.datasets import open_dataset
    from placerec.slam_app.config import load_slam_config
    from placerec.slam_app.run import odometry_source

    cfg = load_slam_config(None, overrides)
    seq = open_dataset(cfg.dataset)
    odo = odometry_source(cfg, seq)
    return np.stack([odo(i, None) for i in range(len(seq))])


def _rigid_poses(n: int) -> Callable[[Any, Any], None]:
    def check(args: Any, poses: Any) -> None:
        assert poses.shape == (n, 4, 4) and np.isfinite(poses).all()

    return check


def _rigid_estimates(n: int) -> Callable[[Any, Any], None]:
    def check(args: Any, poses: Any) -> None:
        _rigid_poses(n)(args, poses)
        R = poses[:, :3, :3]
        np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-6)
        assert (np.linalg.det(R) > 0).all()

    return check


def _graph(poses: list[np.ndarray], loop: np.ndarray | None = None) -> Any:
    from placerec.slam.graph import LoopFactor, PoseGraph

    g = PoseGraph()
    for P in poses:
        g.add_pose(P)
    if loop is not None:
        g.add_loop(LoopFactor(match_id=0, query_id=len(poses) - 1, T_match_query=loop, score=1.0))
    g.update()
    return np.stack([g.pose(i) for i in range(len(poses))])


def _path_poses(n: int) -> list[np.ndarray]:
    out = []
    for k in range(n):
        P = np.eye(4)
        P[0, 3] = 1.5 * k
        out.append(P)
    return out


def _damaged(name: str) -> np.ndarray:
    P = _path_poses(3)[2]
    out = np.eye(4)
    out[:3, :] = DAMAGE[name](P[:3, :])
    return out


def cases() -> list[Case]:
    out: list[Case] = []
    out.append(Case("slam", "odometry-file/valid", lambda t: _odometry_layout(t, lambda r: r), _odometry, "ok",
                    check=_rigid_poses(3), fast=True))  # fmt: skip
    for damage, fn in DAMAGE.items():

        def edit(rows: list[np.ndarray], fn: Callable[[np.ndarray], np.ndarray] = fn) -> list[np.ndarray]:
            return rows[:2] + [fn(rows[2])]

        out.append(Case("slam", f"odometry-file/{damage}", lambda t, e=edit: _odometry_layout(t, e), _odometry,
                        names="odom.txt", error=ScanFormatError))  # fmt: skip
    out.append(Case("slam", "odometry-file/one-pose-short", lambda t: _odometry_layout(t, lambda r: r[:2]), _odometry,
                    names="odometry.path", error=ConfigError))  # fmt: skip
    out.append(Case("slam", "odometry-file/empty", lambda t: _odometry_layout(t, lambda r: []), _odometry,
                    names="odom.txt"))  # fmt: skip
    out.append(
        Case(
            "slam",
            "odometry-file/missing",
            lambda t: (
                _odometry_layout(t, lambda r: r)[:-1] + [f"odometry.path={t / 'absent.txt'}"]
            ),  # fmt: skip
            _odometry,
            names="absent.txt",
        )
    )
    out.append(
        Case("slam", "odometry-file/tum-zero-quaternion", lambda t: _tum(t), _odometry, names="odom_tum.txt")
    )

    # drifting odometry made from true poses that are not finite
    def drift(poses: np.ndarray) -> Any:
        from placerec.sim.odometry import OdometryDrift, drift_poses

        return drift_poses(poses, OdometryDrift(), 0)

    nan_path = np.stack(_path_poses(4))
    nan_path[2, 0, 3] = np.nan
    out.append(Case("slam", "drift/nan-pose", lambda t: nan_path.copy(), drift, error=ScanDataError))
    out.append(Case("slam", "drift/empty", lambda t: np.zeros((0, 4, 4)), drift, "either", error=ScanDataError,
                    check=lambda a, r: np.asarray(r).shape == (0, 4, 4)))  # fmt: skip
    out.append(Case("slam", "drift/valid", lambda t: np.stack(_path_poses(4)), drift, "ok",
                    check=lambda a, r: _rigid_poses(4)(a, r)))  # fmt: skip

    # the pose graph (GTSAM) given poses and loops that are no rigid motions
    out.append(Case("slam", "graph/valid", lambda t: _path_poses(3), _graph, "ok", check=_rigid_poses(3)))
    # every damaged pose or loop transform is refused (`placerec.types.rigid_problem`), never projected onto SO(3)
    for damage in DAMAGE:
        expect = "error"
        out.append(Case("slam", f"graph/pose-{damage}", lambda t, d=damage: _path_poses(2) + [_damaged(d)], _graph,
                        expect, error=ScanDataError, check=_rigid_estimates(3)))  # fmt: skip
        out.append(Case("slam", f"graph/loop-{damage}", lambda t, d=damage: (_path_poses(3), _damaged(d)),
                        lambda a: _graph(*a), expect, error=ScanDataError, check=_rigid_estimates(3)))  # fmt: skip
    return out


def _tum(tmp: Path) -> list[str]:
    overrides = _odometry_layout(tmp, lambda r: r)
    path = tmp / "odom_tum.txt"
    path.write_text("0.0 0 0 0 0 0 0 1\n0.1 1.5 0 0 0 0 0 0\n0.2 3.0 0 0 0 0 0 1\n")
    return overrides[:-1] + [f"odometry.path={path}", "odometry.format=tum"]
