"""Poses and loop-closure edges as an MCAP file that Foxglove shows over the user's own recording.

`write_closures_mcap` writes JSON messages (``jsonschema`` schema encoding) with Foxglove's standard schemas,
timestamped with the scans' own times, so the file lines up with the bag the sequence came from:

* ``/placerec/pose`` — ``foxglove.PoseInFrame``, one per scan with a pose: the estimate at the scan's time;
* ``/placerec/trajectory`` — ``foxglove.PosesInFrame``, once at the last scan's time: the final trajectory;
* ``/placerec/ground_truth`` — ``foxglove.PosesInFrame``, once at the last scan's time, when ground truth is given;
* ``/placerec/loops`` and ``/placerec/loops_rejected`` — ``foxglove.SceneUpdate`` at each query scan's time: one
  entity per edge (id ``loop/<query>-<match>``, kept until the end), a line from the match's position to the
  query's (accepted green, rejected red) with the edge's numbers as metadata; two topics, so either can be
  switched off in the 3D panel;
* ``/placerec/loop_closures`` — ``placerec.LoopClosure`` (`LOOP_CLOSURE_SCHEMA`), one per edge at its query scan's
  time, accepted or not: the edge exactly, for a user's own tools;
* ``/placerec/tf`` — ``foxglove.FrameTransform`` ``frame_id -> sensor_frame`` per scan, only when
  ``sensor_frame`` is given (e.g. the frame of the bag's point clouds, to see them placed by the estimate).

A sequence without timestamps gets ``index / rate_hz`` (default `DEFAULT_RATE_HZ`). The file's metadata record
``placerec`` holds ``frame_id``, ``time_source`` (``scan timestamps`` or ``index / rate_hz``, then also
``rate_hz``), the numbers of poses and loops and the placerec version. Written atomically (`atomic_write`).
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from placerec._version import __version__
from placerec.errors import ScanDataError
from placerec.io.atomic import atomic_write
from placerec.io.poses import matrix_to_quat
from placerec.types import as_pose, check_poses

__all__ = [
    "LoopEdge",
    "write_closures_mcap",
    "DEFAULT_RATE_HZ",
    "DEFAULT_FRAME",
    "TOPICS",
    "SCHEMAS",
    "LOOP_CLOSURE_SCHEMA",
]

#: scans per second assumed when a sequence has no timestamps (a spinning LiDAR's usual rate)
DEFAULT_RATE_HZ = 10.0
DEFAULT_FRAME = "map"
#: topic -> schema name
TOPICS = {
    "/placerec/pose": "foxglove.PoseInFrame",
    "/placerec/trajectory": "foxglove.PosesInFrame",
    "/placerec/ground_truth": "foxglove.PosesInFrame",
    "/placerec/loops": "foxglove.SceneUpdate",
    "/placerec/loops_rejected": "foxglove.SceneUpdate",
    "/placerec/loop_closures": "placerec.LoopClosure",
    "/placerec/tf": "foxglove.FrameTransform",
}
ACCEPTED_COLOR = {"r": 0.1, "g": 0.75, "b": 0.2, "a": 1.0}
REJECTED_COLOR = {"r": 0.9, "g": 0.15, "b": 0.15, "a": 0.8}
LINE_THICKNESS_PX = 3.0
_LINE_LIST = 2  # foxglove.LineType: individual segments 0-1, 2-3, ...


@dataclass(frozen=True, eq=False)
class LoopEdge:
    """One loop-closure edge: ``query`` and ``match`` index the poses (``match``: ``match_poses`` when given),
    ``T_match_query`` the estimated relative pose (4x4; None: none estimated), ``score`` (NaN: none),
    ``inliers`` (None: not counted), ``accepted``, ``rejection`` (why not, None when accepted: a key of
    `placerec.types.REJECTIONS` for verification's stages, ``"back-end"`` for a loop the pose graph's robust
    optimisation turned down, ``"threshold"`` for a score below the operating threshold, or a caller's own short
    text) and ``injected`` (a false loop added on purpose to test the back end)."""

    query: int
    match: int
    score: float = float("nan")
    T_match_query: np.ndarray | None = None
    inliers: int | None = None
    accepted: bool = True
    rejection: str | None = None
    injected: bool = False


# --- schemas: Foxglove's JSON schemas (https://docs.foxglove.dev/docs/visualization/message-schemas), the fields
# placerec writes; a SceneEntity's other primitive arrays (always empty here) are declared as arrays only.


def _object(title: str | None, properties: dict[str, Any], description: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {"type": "object"}
    if title:
        out["title"] = title
    if description:
        out["description"] = description
    out["properties"] = properties
    out["required"] = list(properties)
    return out


_NUMBER = {"type": "number"}
_STRING = {"type": "string"}
_TIME = {
    "type": "object",
    "title": "time",
    "properties": {
        "sec": {"type": "integer", "minimum": 0},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999},
    },
}
_DURATION = {
    "type": "object",
    "title": "duration",
    "properties": {
        "sec": {"type": "integer"},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999},
    },
}
_VECTOR3 = _object("foxglove.Vector3", {k: _NUMBER for k in "xyz"})
_POINT3 = _object("foxglove.Point3", {k: _NUMBER for k in "xyz"})
_QUATERNION = _object("foxglove.Quaternion", {k: _NUMBER for k in "xyzw"})
_POSE = _object("foxglove.Pose", {"position": _VECTOR3, "orientation": _QUATERNION})
_COLOR = _object("foxglove.Color", {k: _NUMBER for k in "rgba"})
_KEY_VALUE = _object("foxglove.KeyValuePair", {"key": _STRING, "value": _STRING})
_LINE_PRIMITIVE = _object(
    "foxglove.LinePrimitive",
    {
        "type": {
            "title": "foxglove.LineType",
            "oneOf": [
                {"title": "LINE_STRIP", "const": 0},
                {"title": "LINE_LOOP", "const": 1},
                {"title": "LINE_LIST", "const": 2},
            ],
        },
        "pose": _POSE,
        "thickness": _NUMBER,
        "scale_invariant": {"type": "boolean"},
        "points": {"type": "array", "items": _POINT3},
        "color": _COLOR,
        "colors": {"type": "array", "items": _COLOR},
        "indices": {"type": "array", "items": {"type": "integer", "minimum": 0}},
    },
)
_OTHER_PRIMITIVES = ("arrows", "cubes", "spheres", "cylinders", "triangles", "texts", "models")
_SCENE_ENTITY = _object(
    "foxglove.SceneEntity",
    {
        "timestamp": _TIME,
        "frame_id": _STRING,
        "id": _STRING,
        "lifetime": _DURATION,
        "frame_locked": {"type": "boolean"},
        "metadata": {"type": "array", "items": _KEY_VALUE},
        "lines": {"type": "array", "items": _LINE_PRIMITIVE},
        **{k: {"type": "array", "items": {"type": "object"}} for k in _OTHER_PRIMITIVES},
    },
)
_SCENE_ENTITY_DELETION = _object(
    "foxglove.SceneEntityDeletion",
    {
        "timestamp": _TIME,
        "type": {"oneOf": [{"title": "MATCHING_ID", "const": 0}, {"title": "ALL", "const": 1}]},
        "id": _STRING,
    },
)

#: schema name -> JSON schema
SCHEMAS: dict[str, dict[str, Any]] = {
    "foxglove.PoseInFrame": _object(
        "foxglove.PoseInFrame", {"timestamp": _TIME, "frame_id": _STRING, "pose": _POSE}
    ),
    "foxglove.PosesInFrame": _object(
        "foxglove.PosesInFrame",
        {"timestamp": _TIME, "frame_id": _STRING, "poses": {"type": "array", "items": _POSE}},
    ),
    "foxglove.FrameTransform": _object(
        "foxglove.FrameTransform",
        {
            "timestamp": _TIME,
            "parent_frame_id": _STRING,
            "child_frame_id": _STRING,
            "translation": _VECTOR3,
            "rotation": _QUATERNION,
        },
    ),
    "foxglove.SceneUpdate": _object(
        "foxglove.SceneUpdate",
        {
            "deletions": {"type": "array", "items": _SCENE_ENTITY_DELETION},
            "entities": {"type": "array", "items": _SCENE_ENTITY},
        },
    ),
}
#: placerec's own message: one loop-closure edge, exactly
LOOP_CLOSURE_SCHEMA = _object(
    "placerec.LoopClosure",
    {
        "timestamp": {**_TIME, "description": "the query scan's time"},
        "frame_id": {**_STRING, "description": "the frame of the poses the indices refer to"},
        "query_index": {"type": "integer", "minimum": 0, "description": "the query scan's index"},
        "match_index": {"type": "integer", "minimum": 0, "description": "the matched scan's (or keyframe's)"},
        "score": {"type": ["number", "null"], "description": "the recognizer's score (null: none)"},
        "inliers": {
            "type": ["integer", "null"],
            "description": "supporting correspondences (null: not counted)",
        },
        "relative_pose": {
            "type": ["array", "null"],
            "items": _NUMBER,
            "minItems": 16,
            "maxItems": 16,
            "description": "T_match_query, 4x4 row-major: the query's pose in the match's frame (null: none)",
        },
        "accepted": {"type": "boolean"},
        "rejection": {
            "type": ["string", "null"],
            "description": "why not accepted, null if accepted: a verification stage (placerec.types.REJECTIONS:"
            " grouping, ransac, rank, fitness, score, residual), back-end (turned down by the robust pose graph),"
            " threshold (score below the operating threshold) or another short text",
        },
        "injected": {"type": "boolean", "description": "a false loop added on purpose to test the back end"},
    },
    "A loop-closure edge between two scans",
)
SCHEMAS["placerec.LoopClosure"] = LOOP_CLOSURE_SCHEMA


# --- messages


def _time(ns: int) -> dict[str, int]:
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def _pose(T: np.ndarray, q: np.ndarray) -> dict[str, Any]:
    x, y, z = (float(v) for v in T[:3, 3])
    return {
        "position": {"x": x, "y": y, "z": z},
        "orientation": {"x": float(q[0]), "y": float(q[1]), "z": float(q[2]), "w": float(q[3])},
    }


def _point(T: np.ndarray) -> dict[str, float]:
    return {"x": float(T[0, 3]), "y": float(T[1, 3]), "z": float(T[2, 3])}


_IDENTITY = {
    "position": {"x": 0.0, "y": 0.0, "z": 0.0},
    "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
}


def _entity(
    edge: LoopEdge, stamp: dict[str, int], frame_id: str, a: np.ndarray, b: np.ndarray
) -> dict[str, Any]:
    """The scene entity of one edge: a line from the match's position ``a`` to the query's ``b``."""
    meta = {
        "query": str(edge.query),
        "match": str(edge.match),
        "score": "-" if math.isnan(edge.score) else f"{edge.score:.4g}",
        "inliers": "-" if edge.inliers is None else str(edge.inliers),
        "accepted": str(edge.accepted).lower(),
        "rejection": edge.rejection or "-",
        "injected": str(edge.injected).lower(),
    }
    line = {
        "type": _LINE_LIST,
        "pose": _IDENTITY,
        "thickness": LINE_THICKNESS_PX,
        "scale_invariant": True,
        "points": [_point(a), _point(b)],
        "color": ACCEPTED_COLOR if edge.accepted else REJECTED_COLOR,
        "colors": [],
        "indices": [],
    }
    return {
        "timestamp": stamp,
        "frame_id": frame_id,
        "id": f"loop/{edge.query}-{edge.match}",
        "lifetime": {"sec": 0, "nsec": 0},
        "frame_locked": False,
        "metadata": [{"key": k, "value": v} for k, v in meta.items()],
        "lines": [line],
        **{k: [] for k in _OTHER_PRIMITIVES},
    }


def _closure(edge: LoopEdge, stamp: dict[str, int], frame_id: str) -> dict[str, Any]:
    T = edge.T_match_query
    return {
        "timestamp": stamp,
        "frame_id": frame_id,
        "query_index": edge.query,
        "match_index": edge.match,
        "score": None if math.isnan(edge.score) else float(edge.score),
        "inliers": edge.inliers,
        "relative_pose": None if T is None else [float(v) for v in T.reshape(-1)],
        "accepted": edge.accepted,
        "rejection": edge.rejection,
        "injected": edge.injected,
    }


# --- input checks


def _stamps_ns(where: str, timestamps: np.ndarray | None, n: int, rate_hz: float) -> tuple[np.ndarray, str]:
    """Each scan's time in integer nanoseconds and where it came from."""
    if timestamps is None:
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise ScanDataError(f"{where}: rate_hz must be a positive number, got {rate_hz!r}")
        return np.round(np.arange(n) * (1e9 / rate_hz)).astype(np.int64), "index / rate_hz"
    t = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    if t.shape[0] != n:
        raise ScanDataError(f"{where}: {t.shape[0]} timestamps for {n} poses")
    bad = ~(np.isfinite(t) & (t >= 0) & (t < 2**63 / 1e9))
    if bad.any():
        i = int(np.argmax(bad))
        raise ScanDataError(f"{where}: timestamp {i} is {float(t[i])}; expected finite seconds >= 0")
    return np.round(t * 1e9).astype(np.int64), "scan timestamps"


def _check_edges(where: str, loops: Iterable[LoopEdge], n: int, n_match: int) -> list[LoopEdge]:
    """The edges with plain Python numbers (NumPy scalars do not serialise as JSON); `ScanDataError` naming the
    first bad one."""
    out = []
    for k, e in enumerate(loops):
        what = f"{where}: loop {k} (query {e.query}, match {e.match})"
        if not (0 <= e.query < n):
            raise ScanDataError(f"{what}: query index outside the {n} poses")
        if not (0 <= e.match < n_match):
            raise ScanDataError(f"{what}: match index outside the {n_match} match poses")
        if math.isinf(e.score):
            raise ScanDataError(f"{what}: score is {e.score}")
        if e.inliers is not None and e.inliers < 0:
            raise ScanDataError(f"{what}: {e.inliers} inliers")
        if e.accepted and e.rejection is not None:
            raise ScanDataError(f"{what}: accepted, yet rejected by {e.rejection!r}")
        T = None if e.T_match_query is None else as_pose(e.T_match_query, f"{what}: T_match_query")
        inliers = None if e.inliers is None else int(e.inliers)
        out.append(LoopEdge(int(e.query), int(e.match), float(e.score), T, inliers, bool(e.accepted),
                            None if e.rejection is None else str(e.rejection), bool(e.injected)))  # fmt: skip
    return out


def _known(where: str, poses: np.ndarray, valid: np.ndarray | None) -> np.ndarray:
    """The (N,) mask of poses to write; ``check_poses`` on those."""
    P = np.asarray(poses, dtype=np.float64)
    if P.ndim != 3 or P.shape[1:] != (4, 4):
        raise ScanDataError(f"{where}: poses must have shape (N, 4, 4), got {P.shape}")
    mask = np.ones(len(P), bool) if valid is None else np.asarray(valid, dtype=bool).reshape(-1)
    if mask.shape[0] != len(P):
        raise ScanDataError(f"{where}: valid has {mask.shape[0]} entries for {len(P)} poses")
    check_poses(np.where(mask[:, None, None], P, np.eye(4)), None, where)
    return mask


# --- the file


def write_closures_mcap(
    path: str | Path,
    poses: np.ndarray,
    loops: Iterable[LoopEdge] = (),
    *,
    timestamps: np.ndarray | None = None,
    ground_truth: np.ndarray | None = None,
    frame_id: str = DEFAULT_FRAME,
    rate_hz: float = DEFAULT_RATE_HZ,
    sensor_frame: str | None = None,
    valid: np.ndarray | None = None,
    match_poses: np.ndarray | None = None,
) -> Path:
    """Write ``poses`` ((N, 4, 4) ``T_frame_sensor``, the estimate of each scan) and ``loops`` as MCAP at ``path``
    (topics and schemas: the module docstring); returns the path.

    ``timestamps``: (N,) seconds (None: ``index / rate_hz``); ``ground_truth``: (N, 4, 4) or None; ``frame_id``:
    the frame the poses are in; ``sensor_frame``: also publish ``frame_id -> sensor_frame`` transforms.
    ``valid``: (N,) bool, the scans that have a pose (None: all); the others' rows are not read (may be NaN),
    get no pose message and are left out of the trajectory, and an edge touching one gets no line (its
    ``placerec.LoopClosure`` message is written). ``match_poses``: what the edges' match indices index when they
    are not ``poses`` (e.g. a map's keyframe poses for relocalisation), in the same frame.
    Bad input (not a rigid pose, NaN, mismatched lengths, an index out of range) is a `ScanDataError` naming it.
    """
    from mcap.well_known import MessageEncoding, SchemaEncoding
    from mcap.writer import Writer

    path = Path(path)
    where = str(path)
    if not isinstance(frame_id, str) or not frame_id:
        raise ScanDataError(f"{where}: frame_id must be a non-empty string, got {frame_id!r}")
    if sensor_frame is not None and (not isinstance(sensor_frame, str) or not sensor_frame):
        raise ScanDataError(f"{where}: sensor_frame must be a non-empty string or None, got {sensor_frame!r}")
    known = _known(f"{where}: poses", poses, valid)
    P = np.where(known[:, None, None], np.asarray(poses, dtype=np.float64), np.eye(4))
    n = len(P)
    M = P if match_poses is None else check_poses(match_poses, None, f"{where}: match_poses")
    gt = None if ground_truth is None else check_poses(ground_truth, n, f"{where}: ground_truth")
    ns, time_source = _stamps_ns(where, timestamps, n, rate_hz)
    edges = _check_edges(where, loops, n, len(M))
    q = matrix_to_quat(P[:, :3, :3])
    t_end = int(ns.max()) if n else 0  # the trajectories' time: the last scan's
    end = _time(t_end)

    # (time ns, order of writing, topic, message): sorted by time, so the file's messages are in time order
    messages: list[tuple[int, int, str, dict[str, Any]]] = []

    def add(t: int, topic: str, msg: dict[str, Any]) -> None:
        messages.append((t, len(messages), topic, msg))

    for i in np.flatnonzero(known):
        stamp = _time(int(ns[i]))
        pose = _pose(P[i], q[i])
        add(int(ns[i]), "/placerec/pose", {"timestamp": stamp, "frame_id": frame_id, "pose": pose})
        if sensor_frame is not None:
            tf = {"timestamp": stamp, "parent_frame_id": frame_id, "child_frame_id": sensor_frame,
                  "translation": pose["position"], "rotation": pose["orientation"]}  # fmt: skip
            add(int(ns[i]), "/placerec/tf", tf)
    for e in sorted(edges, key=lambda e: (e.query, e.match)):
        t = int(ns[e.query])
        add(t, "/placerec/loop_closures", _closure(e, _time(t), frame_id))
        match_known = match_poses is not None or known[e.match]
        if known[e.query] and match_known:
            entity = _entity(e, _time(t), frame_id, M[e.match], P[e.query])
            topic = "/placerec/loops" if e.accepted else "/placerec/loops_rejected"
            add(t, topic, {"deletions": [], "entities": [entity]})
    trajectory = [_pose(P[i], q[i]) for i in np.flatnonzero(known)]
    add(t_end, "/placerec/trajectory", {"timestamp": end, "frame_id": frame_id, "poses": trajectory})
    if gt is not None:
        qg = matrix_to_quat(gt[:, :3, :3])
        truth = [_pose(gt[i], qg[i]) for i in range(n)]
        add(t_end, "/placerec/ground_truth", {"timestamp": end, "frame_id": frame_id, "poses": truth})
    messages.sort(key=lambda m: (m[0], m[1]))

    with atomic_write(path, "wb") as fh:
        writer = Writer(fh)
        writer.start(profile="", library=f"placerec {__version__}")
        channels: dict[str, int] = {}
        schema_ids: dict[str, int] = {}
        for topic in dict.fromkeys(m[2] for m in messages):  # the topics written, in order of first use
            name = TOPICS[topic]
            if name not in schema_ids:
                data = json.dumps(SCHEMAS[name], separators=(",", ":")).encode()
                schema_ids[name] = writer.register_schema(name, SchemaEncoding.JSONSchema, data)
            channels[topic] = writer.register_channel(topic, MessageEncoding.JSON, schema_ids[name])
        for seq, (t, _, topic, msg) in enumerate(messages):
            data = json.dumps(msg, separators=(",", ":"), allow_nan=False).encode()
            writer.add_message(channels[topic], log_time=t, data=data, publish_time=t, sequence=seq)
        meta = {"frame_id": frame_id, "time_source": time_source, "poses": str(int(known.sum())),
                "loops": str(len(edges)), "placerec_version": __version__}  # fmt: skip
        if timestamps is None:
            meta["rate_hz"] = repr(float(rate_hz))
        writer.add_metadata("placerec", meta)
        writer.finish()
    return path
