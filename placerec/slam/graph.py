"""The pose graph of the SLAM back end, in GTSAM: odometry and loop-closure factors, iSAM2 online, a final batch.

* Pose ``i`` is the key ``i`` (a ``gtsam.Pose3`` = ``T_world_sensor`` of scan ``i``); pose 0 has a tight prior.
* **Several sessions** (`placerec.slam.multisession`): `add_free_pose` adds a pose with an initial value only
  (optionally a tight prior), `add_odometry` a known-inlier odometry factor between any two poses, and
  `add_graph` appends another graph's poses under the next keys (its factors shifted, its estimate moved into
  this graph's frame, its odometry chain continued by `add_pose`). Keys stay 0, 1, ..., ``n_poses - 1``.
* **Odometry**: ``BetweenFactorPose3(i - 1, i, T_{i-1,i})`` with a diagonal covariance that grows with the step:
  sigma = max(floor, per-metre sigma x step length), translation and rotation separately.
* **Loops**: ``BetweenFactorPose3(match, query, T_match_query)`` (the verified relative pose of
  `placerec.types.Candidate`) with a diagonal covariance wrapped in a robust kernel (``robust``: Cauchy, Huber,
  Geman-McClure, DCS, or ``none``), so that a wrong loop's residual is down-weighted instead of bending the map.
* **Online**: `PoseGraph.update` hands the factors and initial values added since the last update to iSAM2;
  an update that holds a loop factor gets ``loop_iterations`` more iSAM2 passes (relinearisation at each).
* **Batch**: `PoseGraph.optimize` re-solves the whole graph from the iSAM2 estimate with Levenberg-Marquardt
  (robust loop factors) or graduated non-convexity (``batch: gnc``: GTSAM's GNC with a truncated quadratic loss on
  the loop factors, odometry and prior marked as known inliers; Yang et al. 2020).

GTSAM orders a Pose3 tangent as (rotation, translation); the g2o export (`write_g2o`) writes the information
matrix in g2o's (translation, rotation) order.

The sigma settings are bounded (`GraphParams`: translation at most `MAX_SIGMA_M`, rotation at most 180 deg),
poses, steps and loop transforms must be rigid motions (`placerec.types.rigid_problem`), and a system GTSAM still
cannot solve ("Indeterminate linear system", e.g. 100 000 km steps) is a `ScanDataError` naming the pose near which
it failed and the graph settings, never GTSAM's RuntimeError.
"""

from __future__ import annotations

import re
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field

from placerec.errors import DependencyError, ScanDataError
from placerec.io.atomic import atomic_write
from placerec.io.poses import matrix_to_quat
from placerec.params import Params
from placerec.types import as_pose

__all__ = ["GraphParams", "PoseGraph", "LoopFactor", "import_gtsam", "write_g2o"]


def import_gtsam() -> Any:
    """The ``gtsam`` module, or `DependencyError` saying how to install it."""
    try:
        import gtsam
    except ImportError as exc:
        raise DependencyError(
            f"the SLAM back end needs GTSAM: pip install 'placerec[slam]' (or gtsam>=4.2) ({exc})"
        ) from None
    return gtsam


#: Largest translation sigma (m) of any factor: against pose 0's 1e-6 prior, GTSAM's Cholesky solve stays
#: determinate up to ~1e6 m (measured); 1e4 m leaves a margin and is beyond any LiDAR odometry's error.
MAX_SIGMA_M = 1e4
#: GTSAM's message for a system it cannot solve names the variable: "... near variable 12 (Symbol: 12)".
_NEAR_VARIABLE = re.compile(r"near variable (\d+)")


class GraphParams(Params):
    """Noise models, robust kernel and optimisers of the pose graph (`placerec.slam.graph`)."""

    odometry_sigma_translation: float = Field(
        0.02, gt=0, le=10, description="odometry translation sigma per metre travelled (m/m; at most 10)"
    )
    odometry_sigma_rotation_deg: float = Field(
        0.1, gt=0, le=180, description="odometry rotation sigma per metre travelled (deg/m; at most 180)"
    )
    odometry_min_sigma_translation: float = Field(
        0.005, gt=0, le=MAX_SIGMA_M, description="floor of the translation sigma (m; at most 1e4)"
    )
    odometry_min_sigma_rotation_deg: float = Field(
        0.02, gt=0, le=180, description="floor of the rotation sigma (deg; at most 180)"
    )
    loop_sigma_translation: float = Field(
        0.1, gt=0, le=MAX_SIGMA_M, description="loop-closure translation sigma (m; at most 1e4)"
    )
    loop_sigma_rotation_deg: float = Field(
        1.0, gt=0, le=180, description="loop-closure rotation sigma (deg; at most 180)"
    )
    robust: Literal["cauchy", "huber", "geman-mcclure", "dcs", "none"] = Field(
        "cauchy", description="robust kernel of the loop factors"
    )
    robust_k: float = Field(
        3.0, gt=0, description="kernel width, in sigmas of the loop noise (measured: docs/slam.md)"
    )
    loop_iterations: int = Field(2, ge=0, description="extra iSAM2 passes after an update holding a loop")
    relinearize_threshold: float = Field(0.01, gt=0, description="iSAM2 relinearisation threshold")
    batch: Literal["lm", "gnc", "none"] = Field(
        "gnc", description="final batch optimisation: GNC, Levenberg-Marquardt, or none (keep iSAM2's)"
    )
    gnc_inlier_probability: float = Field(
        0.99,
        gt=0,
        lt=1,
        description="GNC: a loop factor beyond this chi-square quantile of its error is an outlier",
    )
    max_iterations: int = Field(100, ge=1, description="batch optimiser iterations")


@dataclass(frozen=True)
class LoopFactor:
    """A loop edge of the graph: ``T_match_query`` between poses ``match_id`` and ``query_id``."""

    match_id: int
    query_id: int
    T_match_query: np.ndarray
    score: float = float("nan")
    injected: bool = False


_KERNELS = {"cauchy": "Cauchy", "huber": "Huber", "geman-mcclure": "GemanMcClure", "dcs": "DCS"}


def _rigid(T: np.ndarray) -> np.ndarray:
    """``T`` (4x4) with its rotation projected onto SO(3) (poses read from text files are rounded)."""
    P = as_pose(T).copy()
    U, _, Vt = np.linalg.svd(P[:3, :3])
    P[:3, :3] = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    return P


@dataclass
class PoseGraph:
    """An incrementally built pose graph (see the module docstring); poses are added in order 0, 1, 2, ..."""

    params: GraphParams = field(default_factory=GraphParams)

    def __post_init__(self) -> None:
        gtsam = self._gtsam = import_gtsam()
        isam_params = gtsam.ISAM2Params()
        isam_params.setRelinearizeThreshold(self.params.relinearize_threshold)
        isam_params.relinearizeSkip = 1
        self._isam = gtsam.ISAM2(isam_params)
        self._new = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        self._new_has_loop = False
        self._estimate = gtsam.Values()
        self.odometry: list[tuple[int, int, np.ndarray, np.ndarray]] = []  # (i, j, T_ij, sigmas rot+trans)
        self.loops: list[LoopFactor] = []
        self.priors: list[tuple[int, np.ndarray]] = []  # (i, T_world_i): tight priors (sigma 1e-6)
        self._n = 0
        self.update_ms: list[float] = []
        self.loop_update_ms: list[float] = []
        self._last_pose: np.ndarray | None = None

    @property
    def n_poses(self) -> int:
        return self._n

    @property
    def prior(self) -> np.ndarray | None:
        """The prior on pose 0 (a single-session graph's anchor), None when pose 0 has none."""
        return next((T for i, T in self.priors if i == 0), None)

    def _sigmas(self, step: float) -> np.ndarray:
        p = self.params
        # at most 180 deg: a wider rotation sigma means nothing on SO(3), and GTSAM cannot solve 1e5 rad (measured)
        rot = np.radians(
            min(max(p.odometry_min_sigma_rotation_deg, p.odometry_sigma_rotation_deg * step), 180.0)
        )
        trans = max(p.odometry_min_sigma_translation, p.odometry_sigma_translation * step)
        return np.array([rot] * 3 + [trans] * 3)

    @contextmanager
    def _solving(self, what: str) -> Iterator[None]:
        """Run a GTSAM solve (``what``); its RuntimeError (an indeterminate linear system, a missing key) becomes
        a `ScanDataError` naming the pose it was near and the settings that shape the system."""
        try:
            yield
        except RuntimeError as exc:
            text = " ".join(str(exc).split())
            m = _NEAR_VARIABLE.search(text)
            near = f" near pose {m.group(1)}" if m else ""
            why = "an indeterminate linear system" if "ndeterminat" in text else f"GTSAM: {text[:200]}"
            raise ScanDataError(
                f"pose graph: {what} failed{near} ({why}); the graph's noise settings (graph.odometry_sigma_*, "
                f"graph.loop_sigma_*) or the odometry or loop poses{near} are degenerate"
            ) from exc

    def _checked(self, T: np.ndarray, what: str) -> np.ndarray:
        """``T`` as a rigid 4x4 (`_rigid`) if it is one (`as_pose`); `ScanDataError` naming ``what``."""
        return _rigid(as_pose(T, f"pose graph: {what}"))

    def _loop_noise(self, robust: bool = True) -> Any:
        gtsam, p = self._gtsam, self.params
        sig = np.array([np.radians(p.loop_sigma_rotation_deg)] * 3 + [p.loop_sigma_translation] * 3)
        base = gtsam.noiseModel.Diagonal.Sigmas(sig)
        if not robust or p.robust == "none":
            return base
        kernel = getattr(gtsam.noiseModel.mEstimator, _KERNELS[p.robust]).Create(p.robust_k)
        return gtsam.noiseModel.Robust.Create(kernel, base)

    def add_pose(self, odometry_pose: np.ndarray, step_pose: np.ndarray | None = None) -> int:
        """Add the next pose from its odometry pose ``T_world_sensor``; returns its id. The odometry factor is
        the motion since the previous odometry pose (``step_pose`` gives it directly instead); the first pose gets
        a tight prior at its odometry pose."""
        i = self.n_poses
        T = self._checked(odometry_pose, f"odometry pose {i}")
        if i == 0:
            self._insert(T, prior=True)
        else:
            assert self._last_pose is not None  # every earlier add_pose (or add_graph) set it
            step = np.linalg.solve(self._last_pose, T) if step_pose is None else step_pose
            rel = self._checked(step, f"odometry step {i - 1} -> {i}")
            self._odometry_factor(i - 1, i, rel, self._sigmas(float(np.linalg.norm(rel[:3, 3]))))
            self._insert(self.pose(i - 1) @ rel)
        self._last_pose = T
        return i

    def add_free_pose(self, initial: np.ndarray, prior: bool = False) -> int:
        """Add the next pose with ``initial`` (``T_world_sensor``) as its initial value and no factor (the caller
        adds them: `add_odometry`, `add_loop`), or with a tight prior there (``prior``); returns its id. The
        odometry chain of `add_pose` does not pass through it."""
        return self._insert(self._checked(initial, f"pose {self.n_poses}"), prior)

    def _insert(self, T: np.ndarray, prior: bool = False) -> int:
        """Pose ``n_poses`` with initial value ``T`` (already `_checked`), and a tight prior there (``prior``)."""
        gtsam = self._gtsam
        i = self.n_poses
        if prior:
            self.priors.append((i, T))
            noise = gtsam.noiseModel.Diagonal.Sigmas(np.full(6, 1e-6))
            self._new.add(gtsam.PriorFactorPose3(i, gtsam.Pose3(T), noise))
        self._new_values.insert(i, gtsam.Pose3(T))
        self._n += 1
        return i

    def add_odometry(self, i: int, j: int, T_ij: np.ndarray, sigmas: np.ndarray | None = None) -> None:
        """Add an odometry factor ``T_ij`` (pose ``j`` in the frame of pose ``i``) between two poses in the graph,
        with ``sigmas`` (6, rotation (rad) then translation (m)) or, by default, the step noise of `GraphParams`.
        Odometry factors are known inliers of the GNC batch."""
        n = self.n_poses
        if not (0 <= i < n and 0 <= j < n) or i == j:
            raise ScanDataError(f"odometry factor {i} -> {j}: both poses must exist and differ ({n} poses)")
        rel = self._checked(T_ij, f"odometry factor {i} -> {j}")
        if sigmas is None:
            sig = self._sigmas(float(np.linalg.norm(rel[:3, 3])))
        else:
            sig = np.asarray(sigmas, dtype=np.float64).reshape(-1)
            if sig.shape != (6,) or not np.all(np.isfinite(sig)) or np.any(sig <= 0):
                raise ScanDataError(
                    f"odometry factor {i} -> {j}: sigmas must be 6 finite values > 0 (rotation rad, then "
                    f"translation m), got {np.asarray(sigmas).tolist()}"
                )
        self._odometry_factor(i, j, rel, sig)

    def _odometry_factor(self, i: int, j: int, rel: np.ndarray, sig: np.ndarray) -> None:
        gtsam = self._gtsam
        self.odometry.append((i, j, rel, sig))
        self._new.add(gtsam.BetweenFactorPose3(i, j, gtsam.Pose3(rel), gtsam.noiseModel.Diagonal.Sigmas(sig)))

    def add_graph(self, other: PoseGraph, transform: np.ndarray | None = None, priors: bool = True) -> int:
        """Append ``other``'s poses under the next keys (``offset`` = this graph's `n_poses` before the call;
        returns it): initial values at ``transform @`` other's current estimate (``transform`` maps other's frame
        into this graph's: ``T_this_other``; identity by default), its odometry and loop factors with ids shifted by
        ``offset``, its priors (moved by ``transform``) only with ``priors``. `add_pose` then continues other's
        odometry chain: the next pose's odometry factor steps from other's last pose."""
        offset = self.n_poses
        A = np.eye(4) if transform is None else self._checked(transform, "transform of the appended graph")
        anchored = {i for i, _ in other.priors}
        for i, T in enumerate(other.poses()):
            self.add_free_pose(A @ T, prior=priors and i in anchored)
        for i, j, rel, sig in other.odometry:
            self.add_odometry(offset + i, offset + j, rel, sig)
        for lp in other.loops:
            self.add_loop(replace(lp, match_id=offset + lp.match_id, query_id=offset + lp.query_id))
        self._last_pose = other._last_pose
        return offset

    def add_loop(self, loop: LoopFactor) -> None:
        """Add a robust loop factor between two poses already in the graph."""
        n = self.n_poses
        if not (0 <= loop.match_id < n and 0 <= loop.query_id < n) or loop.match_id == loop.query_id:
            raise ScanDataError(
                f"loop {loop.match_id} -> {loop.query_id}: both poses must exist and differ ({n} poses)"
            )
        T = self._checked(loop.T_match_query, f"loop {loop.match_id} -> {loop.query_id}")
        loop = replace(loop, T_match_query=T)
        self.loops.append(loop)
        self._new.add(
            self._gtsam.BetweenFactorPose3(
                loop.match_id,
                loop.query_id,
                self._gtsam.Pose3(loop.T_match_query),
                self._loop_noise(),
            )
        )
        self._new_has_loop = True

    def pose(self, i: int) -> np.ndarray:
        """The current estimate of pose ``i`` (iSAM2's, or its initial value if not yet updated)."""
        if self._new_values.exists(i):
            return self._new_values.atPose3(i).matrix()
        return self._estimate.atPose3(i).matrix()

    def update(self) -> float:
        """Run iSAM2 on what was added since the last update; returns its time (ms)."""
        if self._new.size() == 0 and self._new_values.size() == 0:
            return 0.0
        t0 = time.perf_counter()
        with self._solving("iSAM2 update"):
            self._isam.update(self._new, self._new_values)
            if self._new_has_loop:
                for _ in range(self.params.loop_iterations):
                    self._isam.update()
            self._estimate = self._isam.calculateEstimate()
        ms = (time.perf_counter() - t0) * 1e3
        (self.loop_update_ms if self._new_has_loop else self.update_ms).append(ms)
        self._new = self._gtsam.NonlinearFactorGraph()
        self._new_values = self._gtsam.Values()
        self._new_has_loop = False
        return ms

    def poses(self) -> np.ndarray:
        """(N, 4, 4) current estimates (iSAM2's after `update`)."""
        return np.stack([self.pose(i) for i in range(self.n_poses)]) if self.n_poses else np.zeros((0, 4, 4))

    def _graph(self, robust: bool) -> Any:
        gtsam = self._gtsam
        g = gtsam.NonlinearFactorGraph()
        for i, T in self.priors:
            g.add(
                gtsam.PriorFactorPose3(i, gtsam.Pose3(T), gtsam.noiseModel.Diagonal.Sigmas(np.full(6, 1e-6)))
            )
        for i, j, rel, sig in self.odometry:
            g.add(gtsam.BetweenFactorPose3(i, j, gtsam.Pose3(rel), gtsam.noiseModel.Diagonal.Sigmas(sig)))
        noise = self._loop_noise(robust)
        for loop in self.loops:
            g.add(
                gtsam.BetweenFactorPose3(loop.match_id, loop.query_id, gtsam.Pose3(loop.T_match_query), noise)
            )
        return g

    def optimize(self) -> tuple[np.ndarray, dict[str, Any]]:
        """The final batch solution (N, 4, 4) from the current estimate, and what it did: method, iterations
        (LM), time, ``loop_residuals`` (each loop factor's error at the solution, in sigmas) and ``loop_weights``
        (GNC's weights, or the kernel's weight at that error: near 0 for a loop the back end rejected)."""
        gtsam, p = self._gtsam, self.params
        self.update()
        info: dict[str, Any] = {"method": p.batch}
        if p.batch == "none" or self.n_poses == 0:
            return self.poses(), info
        t0 = time.perf_counter()
        initial = self._estimate
        if p.batch == "lm":
            lm = gtsam.LevenbergMarquardtParams()
            lm.setMaxIterations(p.max_iterations)
            opt = gtsam.LevenbergMarquardtOptimizer(self._graph(robust=True), initial, lm)
            with self._solving("Levenberg-Marquardt batch"):
                result = opt.optimize()
            info["iterations"] = int(opt.iterations())
        else:
            graph = self._graph(robust=False)
            lm = gtsam.LevenbergMarquardtParams()
            lm.setMaxIterations(p.max_iterations)
            gnc = gtsam.GncLMParams(lm)
            gnc.setLossType(gtsam.GncLossType.TLS)
            known = len(self.priors) + len(self.odometry)
            gnc.setKnownInliers(list(range(known)))  # the priors and every odometry factor
            opt = gtsam.GncLMOptimizer(graph, initial, gnc)
            opt.setInlierCostThresholdsAtProbability(p.gnc_inlier_probability)
            with self._solving("GNC batch"):
                result = opt.optimize()
            gnc_weights = np.asarray(opt.getWeights())[known:]
        info["time_ms"] = (time.perf_counter() - t0) * 1e3
        residuals = self._loop_residuals(result)
        info["loop_residuals"] = residuals.tolist()
        if p.batch == "gnc":
            info["loop_weights"] = gnc_weights.tolist()
        else:
            kernel = self._loop_noise()
            weight = kernel.robust().weight if p.robust != "none" else (lambda r: 1.0)
            info["loop_weights"] = [float(weight(r)) for r in residuals]
        return np.stack([result.atPose3(i).matrix() for i in range(self.n_poses)]), info

    def _loop_residuals(self, values: Any) -> np.ndarray:
        """(L,) whitened error norm of every loop factor (in sigmas of the loop noise) at ``values``."""
        gtsam = self._gtsam
        noise = self._loop_noise(robust=False)
        return np.array(
            [
                np.linalg.norm(
                    gtsam.BetweenFactorPose3(
                        lp.match_id, lp.query_id, gtsam.Pose3(lp.T_match_query), noise
                    ).whitenedError(values)
                )
                for lp in self.loops
            ]
        )

    def write_g2o(self, path: str | Path, poses: np.ndarray | None = None) -> Path:
        """The graph as g2o text (``VERTEX_SE3:QUAT`` at ``poses`` (default: the current estimate), then every
        ``EDGE_SE3:QUAT`` with its information matrix; a robust kernel is not part of g2o's format), atomically."""
        p = self.params
        loop_sig = np.array([np.radians(p.loop_sigma_rotation_deg)] * 3 + [p.loop_sigma_translation] * 3)
        P = self.poses() if poses is None else np.asarray(poses, dtype=np.float64)
        return write_g2o(path, P, self.odometry, self.loops, loop_sig)


def write_g2o(
    path: str | Path,
    poses: np.ndarray,
    odometry: list[tuple[int, int, np.ndarray, np.ndarray]],
    loops: list[LoopFactor],
    loop_sigmas: np.ndarray,
) -> Path:
    """A pose graph as g2o text, atomically: a ``VERTEX_SE3:QUAT`` per pose, an ``EDGE_SE3:QUAT`` per odometry
    factor ``(i, j, T_ij, sigmas)`` and per loop (``loop_sigmas``), sigmas in GTSAM's order (rotation rad x3, then
    translation m x3) turned into g2o's information matrix (translation first, upper triangle), and ``FIX 0``."""

    def se3(T: np.ndarray) -> str:
        q = matrix_to_quat(T[None, :3, :3])[0]
        return " ".join(f"{v:.9g}" for v in (*T[:3, 3], *q))

    lines = [f"VERTEX_SE3:QUAT {i} {se3(T)}" for i, T in enumerate(poses)]
    edges = [(i, j, rel, sig) for i, j, rel, sig in odometry]
    edges += [(lp.match_id, lp.query_id, lp.T_match_query, loop_sigmas) for lp in loops]
    iu = np.triu_indices(6)
    for i, j, rel, sig in edges:
        info = np.diag(1.0 / np.square(np.r_[sig[3:], sig[:3]]))[iu]
        lines.append(f"EDGE_SE3:QUAT {i} {j} {se3(rel)} " + " ".join(f"{v:.9g}" for v in info))
    if len(poses):
        lines.append("FIX 0")
    with atomic_write(path, "w") as fh:
        fh.write("\n".join(lines) + "\n")
    return Path(path)
