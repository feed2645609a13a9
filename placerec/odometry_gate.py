"""An odometry gate for loop closures: a closure must agree with where the odometry says the query is.

A closure's relative pose ``T_match_query`` and the odometry's own ``T_odom = inv(O_match) @ O_query`` describe
the same motion; they differ by the odometry's drift over the path between the two places, plus the closure's own
error. A SLAM system that has odometry knows how far it can have drifted, so a closure that puts the query much
farther from where the odometry has it is a look-alike place (a repeated block, a second identical warehouse
aisle), however well its scans register: LIO-SAM searches loop candidates only within a radius of the current
estimate for the same reason. The gate admits a closure when

    |t(T_match_query) - t(T_odom)|       <= metres  + per_metre * L
    angle(inv(T_match_query) @ T_odom)  <= degrees + degrees_per_metre * L

where ``L`` is the odometry's path length (m) from the matched place to the query. With ``through_loops`` (the
default) the closures already accepted count too (`LoopChain`): once a closure has tied the query's stretch to an
earlier one, the odometry's drift since then is what is left, so the motion is predicted along the shortest chain
of odometry segments and accepted closures, and ``L`` is the odometry path along that chain (a closure adds none).
A look-alike place far along the odometry but near a stretch already closed is then judged over the few metres
driven since that closure, not over the whole way round. The bound is the odometry's, not the place recogniser's: ``per_metre`` and ``degrees_per_metre`` must cover the worst relative drift of the
odometry in use. The defaults were chosen on the tuning split (docs/protocol.md, "The odometry gate") for the
demo SLAM config's drift model (heading drift 2 deg / 100 m, 1 % translation noise per metre, 0.2 % scale error:
configs/slam_demo.yaml); an odometry that drifts more needs wider bounds.

A candidate without a 6-DoF relative pose carries nothing to check and is left to the threshold alone. A false
closure that passes both the threshold and the gate is in the chain from then on: the gate is only as good as the
closures it has accepted (the thresholds are chosen with it so that none does on the tuning split).
`placerec.loop_closure.LoopClosureDetector` (``odometry_gate``) applies the gate online to the poses given to
``process``; the evaluation (``evaluation.odometry_gate``) applies the same test to a run's candidates.
"""

from __future__ import annotations

import heapq
from collections.abc import Sequence

import numpy as np
from pydantic import Field

from placerec.params import Params

__all__ = ["LoopChain", "OdometryGateParams", "odometry_disagreement", "pose_disagreement"]


class OdometryGateParams(Params):
    """The bounds of the odometry gate (module docstring); defaults chosen on the tuning split."""

    metres: float = Field(1.0, ge=0, allow_inf_nan=False, description="translation bound at L = 0 (m)")
    per_metre: float = Field(
        0.04, ge=0, allow_inf_nan=False, description="translation bound per metre of odometry path"
    )
    degrees: float = Field(4.0, ge=0, allow_inf_nan=False, description="rotation bound at L = 0 (deg)")
    degrees_per_metre: float = Field(
        0.05, ge=0, allow_inf_nan=False, description="rotation bound per metre of odometry path (deg)"
    )
    through_loops: bool = Field(
        True,
        description="predict the motion along the shortest chain of odometry and closures already accepted, L its"
        " odometry path (`LoopChain`); False: the odometry alone (the sensors' thresholds with the gate,"
        " `placerec.sensor_presets`, were chosen through loops)",
    )

    def admits(self, translation_m: np.ndarray, rotation_deg: np.ndarray, path_m: np.ndarray) -> np.ndarray:
        """Where a disagreement (`odometry_disagreement`) over ``path_m`` metres of odometry is within the bounds;
        NaN (no pose to compare) is admitted."""
        t = np.asarray(translation_m, dtype=np.float64)
        r = np.asarray(rotation_deg, dtype=np.float64)
        path = np.abs(np.asarray(path_m, dtype=np.float64))
        ok = (t <= self.metres + self.per_metre * path) & (r <= self.degrees + self.degrees_per_metre * path)
        return ok | np.isnan(t) | np.isnan(r)


def pose_disagreement(T_a: np.ndarray, T_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(translation m, rotation deg) between two stacks of (N, 4, 4) relative poses (or single 4x4 ones); NaN where
    ``T_a`` is not finite (a closure without a pose)."""
    T = np.asarray(T_a, dtype=np.float64).reshape(-1, 4, 4)
    B = np.asarray(T_b, dtype=np.float64).reshape(-1, 4, 4)
    trans = np.linalg.norm(T[:, :3, 3] - B[:, :3, 3], axis=1)
    R = np.einsum("nji,njk->nik", T[:, :3, :3], B[:, :3, :3])  # inv(R_a) @ R_b
    cos = np.clip((np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    rot = np.degrees(np.arccos(cos))
    bad = ~np.isfinite(T).all(axis=(1, 2))
    trans[bad] = np.nan
    rot[bad] = np.nan
    return trans, rot


def odometry_disagreement(
    T_match_query: np.ndarray, odom_match: np.ndarray, odom_query: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(translation m, rotation deg) between each closure's ``T_match_query`` and the odometry's motion from the
    matched place to the query, for (N, 4, 4) stacks (or single 4x4 poses); NaN where a closure has no pose."""
    Om = np.asarray(odom_match, dtype=np.float64).reshape(-1, 4, 4)
    Oq = np.asarray(odom_query, dtype=np.float64).reshape(-1, 4, 4)
    return pose_disagreement(T_match_query, np.linalg.solve(Om, Oq))  # inv(O_match) @ O_query


class LoopChain:
    """The closures a gate has accepted, for predicting a candidate's motion through them (``through_loops``).

    The places form a graph: the odometry joins each place to the next (an edge as long as the path driven
    between them) and each accepted closure joins its two places (an edge of length 0: it measured their relative
    pose). `predict` takes the shortest chain from the matched place to the query and composes its relative poses
    (the odometry's ``inv(O_a) @ O_b`` along a stretch, a closure's ``T_match_query`` or its inverse), so ``L`` is
    the odometry path the prediction still rests on. Without closures it is the odometry's own motion and path.
    Places are the caller's indices into its ``poses`` and ``path`` (the odometry and its cumulative path)."""

    def __init__(self) -> None:
        self._closures: list[tuple[int, int, np.ndarray]] = []  # (match, query, T_match_query)
        self._partners: dict[int, list[int]] = {}  # place -> indices of its closures
        self._places = np.zeros(0, dtype=np.int64)  # sorted places with a closure

    def __len__(self) -> int:
        return len(self._closures)

    def add(self, match: int, query: int, T_match_query: np.ndarray) -> None:
        """Record an accepted closure; one without a finite pose, or of a place to itself, is not recorded."""
        T = np.asarray(T_match_query, dtype=np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all() or int(match) == int(query):
            return
        k = len(self._closures)
        self._closures.append((int(match), int(query), T))
        for place in (int(match), int(query)):
            self._partners.setdefault(place, []).append(k)
        self._places = np.array(sorted(self._partners), dtype=np.int64)

    def predict(
        self,
        match: int,
        query: int,
        poses: Sequence[np.ndarray] | np.ndarray,
        path: Sequence[float] | np.ndarray,
    ) -> tuple[np.ndarray, float]:
        """(the predicted ``T_match_query``, the odometry path ``L`` it rests on) along the shortest chain."""
        match, query = int(match), int(query)
        direct = abs(float(path[query]) - float(path[match]))
        if not self._closures:
            return np.linalg.solve(poses[match], poses[query]), direct
        nodes = np.union1d(self._places, [match, query])
        along = np.array([float(path[int(n)]) for n in nodes])
        where = {int(n): i for i, n in enumerate(nodes)}
        dist = {match: 0.0}
        back: dict[int, tuple[int, int]] = {}  # place -> (previous place, closure index or -1: odometry)
        heap = [(0.0, match)]
        bound = direct + 1e-6  # the odometry's own chain, whose stretches may sum a rounding above it
        while heap:
            d, u = heapq.heappop(heap)
            if u == query:
                break
            if d > dist.get(u, np.inf):
                continue
            i = where[u]
            steps = [
                (int(nodes[j]), abs(along[j] - along[i]), -1) for j in (i - 1, i + 1) if 0 <= j < nodes.size
            ]
            for k in self._partners.get(u, ()):
                a, b, _ = self._closures[k]
                steps.append((b if u == a else a, 0.0, k))
            for v, w, k in steps:
                nd = d + w
                if (
                    nd < dist.get(v, np.inf) and nd <= bound
                ):  # a chain longer than the odometry's is no better
                    dist[v] = nd
                    back[v] = (u, k)
                    heapq.heappush(heap, (nd, v))
        chain = []
        v = query
        while v != match:
            u, k = back[v]
            chain.append((u, v, k))
            v = u
        T = np.eye(4)
        for u, v, k in reversed(chain):
            if k < 0:
                T = T @ np.linalg.solve(poses[u], poses[v])
            else:
                a, _, T_ab = self._closures[k]
                T = T @ (T_ab if u == a else np.linalg.inv(T_ab))
        return T, dist[query]
