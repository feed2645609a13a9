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

from collections.abc import Sequence
from itertools import pairwise
from typing import Any

import numpy as np
from pydantic import Field

from placerec.params import Params
from placerec.types import Prediction

__all__ = [
    "ChainPrior",
    "LoopChain",
    "OdometryGateParams",
    "odometry_disagreement",
    "pose_disagreement",
]


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
        metres, degrees = self.bounds_at(path)
        ok = (t <= metres) & (r <= degrees)
        return ok | np.isnan(t) | np.isnan(r)

    def bounds_at(self, path_m: Any) -> tuple[Any, Any]:
        """(translation m, rotation deg) the gate admits over ``path_m`` metres of odometry path."""
        return self.metres + self.per_metre * path_m, self.degrees + self.degrees_per_metre * path_m


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
    Places are the caller's indices into its ``poses`` and ``path`` (the odometry and its cumulative path), which
    must not change for places already passed: one chain serves one odometry.

    The graph holds only the places with a closure (the stretches between them are single edges) and is searched by
    SciPy's compiled Dijkstra, limited to the odometry's own path: 0.1 ms a prediction with 100 closures, 0.8 ms with
    1,000 and 8 ms with 10,000 closures spread at random over a 100,000-place route (the worst case: every place in
    reach), one core (docs/protocol.md)."""

    def __init__(self) -> None:
        self._closures: list[tuple[int, int, np.ndarray]] = []  # (match, query, T_match_query)
        self._places: set[int] = set()
        self._graph: _ChainGraph | None = None  # built on demand, dropped when a closure is added

    def __len__(self) -> int:
        return len(self._closures)

    def add(self, match: int, query: int, T_match_query: np.ndarray) -> None:
        """Record an accepted closure; one without a finite pose, or of a place to itself, is not recorded."""
        T = np.asarray(T_match_query, dtype=np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all() or int(match) == int(query):
            return
        self._closures.append((int(match), int(query), T))
        self._places.update((int(match), int(query)))
        self._graph = None

    def graph(self, path: Sequence[float] | np.ndarray) -> _ChainGraph | None:
        """The graph of the places with a closure over the odometry ``path`` (None without closures), built on
        first use after a closure was added."""
        if not self._closures:
            return None
        if self._graph is None:
            self._graph = _ChainGraph.build(self._closures, sorted(self._places), path)
        return self._graph

    def predict(
        self,
        match: int,
        query: int,
        poses: Sequence[np.ndarray] | np.ndarray,
        path: Sequence[float] | np.ndarray,
    ) -> tuple[np.ndarray, float]:
        """(the predicted ``T_match_query``, the odometry path ``L`` it rests on) along the shortest chain."""
        from scipy.sparse.csgraph import dijkstra

        match, query = int(match), int(query)
        direct = abs(float(path[query]) - float(path[match]))
        odometry = np.linalg.solve(poses[match], poses[query]), direct
        g = self.graph(path)
        if g is None:
            return odometry
        sources, targets = g.attach(match, path), g.attach(query, path)
        dist, previous = dijkstra(
            g.matrix, directed=False, indices=[i for i, _ in sources], return_predecessors=True, limit=direct
        )
        best, pick = direct, None
        for row, (s, to_s) in enumerate(sources):
            for t, from_t in targets:
                total = to_s + dist[row, t] + from_t
                if total < best - 1e-9:
                    best, pick = total, (row, s, t)
        if pick is None:
            return odometry
        row, s, t = pick
        nodes = [t]
        while nodes[-1] != s:
            nodes.append(int(previous[row, nodes[-1]]))
        nodes.reverse()
        first, last = int(g.places[s]), int(g.places[t])
        T = np.linalg.solve(poses[match], poses[first])
        along = abs(float(path[first]) - float(path[match]))
        for u, v in pairwise(nodes):
            a, b = int(g.places[u]), int(g.places[v])
            k = g.closure_between(u, v)
            if k < 0:
                T = T @ np.linalg.solve(poses[a], poses[b])
                along += abs(float(path[b]) - float(path[a]))
            else:
                m, _, T_mq = self._closures[k]
                T = T @ (T_mq if a == m else np.linalg.inv(T_mq))
        T = T @ np.linalg.solve(poses[last], poses[query])
        return T, along + abs(float(path[query]) - float(path[last]))


def _within(chain: LoopChain, query: int, path: Sequence[float] | np.ndarray, limit: float) -> np.ndarray:
    """The places before ``query`` whose `LoopChain.predict` may rest on at most ``limit`` metres of odometry path:
    within ``limit`` along the odometry of the query itself, or of a place with a closure that the chain joins to
    the query over less than ``limit`` (with the rest of it left for the odometry from there). A superset of the
    places whose prediction rests on no more; ascending."""
    from scipy.sparse.csgraph import dijkstra

    along = np.asarray(path[: query + 1], dtype=np.float64)
    before, at = along[:query], float(along[query])
    near = np.abs(before - at) <= limit
    g = chain.graph(path)
    if g is not None and before.size:
        targets = g.attach(query, path)
        dist = dijkstra(g.matrix, directed=False, indices=[t for t, _ in targets], limit=limit)
        reach = np.min(dist + np.array([d for _, d in targets])[:, None], axis=0)
        for k in np.flatnonzero(reach <= limit):
            near |= np.abs(before - float(path[int(g.places[k])])) <= limit - reach[k]
    return np.flatnonzero(near)


class ChainPrior:
    """The gate's predictions for one query against the earlier places (`predict`; a `placerec.types.MotionPrior`),
    through the closures of ``chain`` (`LoopChain`, the odometry alone when it holds none) over the odometry
    ``poses`` / ``path`` indexed by place, with the gate's ``bounds`` over the path each rests on; a pipeline
    matches features within them (`placerec.verify.guided`). Recognizer ids are places plus ``offset`` (a prior
    map's entries come first and have no odometry: no prediction)."""

    def __init__(
        self,
        chain: LoopChain,
        query: int,
        poses: Sequence[np.ndarray] | np.ndarray,
        path: Sequence[float] | np.ndarray,
        bounds: OdometryGateParams,
        offset: int = 0,
    ) -> None:
        self.chain, self.query, self.poses, self.path = chain, int(query), poses, path
        self.bounds, self.offset = bounds, int(offset)

    def predict(self, match_id: int) -> Prediction | None:
        """The prediction for recognizer id ``match_id``; None for a place without odometry or not before the
        query."""
        place = int(match_id) - self.offset
        if place < 0 or place >= self.query:
            return None
        T, along = self.chain.predict(place, self.query, self.poses, self.path)
        metres, degrees = self.bounds.bounds_at(along)
        return Prediction(T, float(metres), float(np.radians(degrees)))

    def near(self, metres: float, reach: float) -> list[tuple[int, Prediction]]:
        """(recognizer id, `predict`) of the earlier places predicted within ``metres`` of the query whose
        prediction's translation bound is at most ``reach``, nearest first (ties: the earlier place first). Only
        the places a chain short enough for that bound joins to the query are predicted (`LoopChain.predict`
        for each), so the cost follows the places around the query's recent closures, not the map."""
        b = self.bounds
        if b.metres > reach:
            return []
        limit = (reach - b.metres) / b.per_metre if b.per_metre > 0 else float("inf")
        found = []
        for place in _within(self.chain, self.query, self.path, limit).tolist():
            prediction = self.predict(place + self.offset)
            if prediction is None or prediction.metres > reach:
                continue
            d = float(np.linalg.norm(prediction.T_match_query[:3, 3]))
            if d <= metres:
                found.append((d, place, prediction))
        found.sort(key=lambda x: (x[0], x[1]))
        return [(place + self.offset, prediction) for _, place, prediction in found]


#: The length of a closure's edge in the chain's search (a closure adds no odometry; a positive length keeps the
#: sparse graph's edge, and `LoopChain.predict` counts the path from the chain's odometry stretches alone).
_CLOSURE_EDGE_M = 1e-9


class _ChainGraph:
    """`LoopChain`'s graph over the places with a closure: ``matrix`` (sparse, symmetric lengths), ``places``
    (sorted), and per edge the closure it is (``keys``, ``owners``: -1 for an odometry stretch)."""

    def __init__(self, matrix: Any, places: np.ndarray, keys: np.ndarray, owners: np.ndarray) -> None:
        self.matrix, self.places, self.keys, self.owners = matrix, places, keys, owners

    @classmethod
    def build(
        cls,
        closures: list[tuple[int, int, np.ndarray]],
        places: list[int],
        path: Sequence[float] | np.ndarray,
    ) -> _ChainGraph:
        from scipy.sparse import csr_matrix

        nodes = np.asarray(places, dtype=np.int64)
        n = nodes.size
        along = np.array([float(path[p]) for p in places])
        ends = np.array([(m, q) for m, q, _ in closures], dtype=np.int64)
        i, j = np.searchsorted(nodes, ends[:, 0]), np.searchsorted(nodes, ends[:, 1])
        line = np.arange(n - 1)
        lo = np.concatenate([line, np.minimum(i, j)])
        hi = np.concatenate([line + 1, np.maximum(i, j)])
        length = np.concatenate([np.abs(np.diff(along)), np.full(len(closures), _CLOSURE_EDGE_M)])
        owner = np.concatenate([np.full(n - 1, -1), np.arange(len(closures))])
        key = lo * n + hi
        order = np.lexsort((length, key))  # per node pair its shortest edge first
        keys, first = np.unique(key[order], return_index=True)
        keep = order[first]
        matrix = csr_matrix((length[keep], (lo[keep], hi[keep])), shape=(n, n))
        return cls(matrix, nodes, keys, owner[keep])

    def attach(self, place: int, path: Sequence[float] | np.ndarray) -> list[tuple[int, float]]:
        """The graph's nodes a place reaches along the odometry, with the path to each: itself when it has a
        closure, else the places with one just before and just after it."""
        i = int(np.searchsorted(self.places, place))
        if i < self.places.size and self.places[i] == place:
            return [(i, 0.0)]
        at = float(path[place])
        return [
            (k, abs(float(path[int(self.places[k])]) - at)) for k in (i - 1, i) if 0 <= k < self.places.size
        ]

    def closure_between(self, u: int, v: int) -> int:
        """The closure the shortest edge between nodes ``u`` and ``v`` is, or -1 (an odometry stretch)."""
        key = min(u, v) * self.places.size + max(u, v)
        return int(self.owners[int(np.searchsorted(self.keys, key))])
