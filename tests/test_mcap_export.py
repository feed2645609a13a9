"""closures.mcap (`placerec.io.mcap_export`): written from a constructed trajectory and read back with the mcap
package (topics, schemas, counts, poses, quaternions, timestamps, loop edges), Foxglove's field layout, bad input,
and a real ``placerec slam`` run whose file holds exactly the run's loops.csv and poses."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from placerec.errors import ScanDataError
from placerec.io import read_poses
from placerec.io.mcap_export import (
    ACCEPTED_COLOR,
    REJECTED_COLOR,
    TOPICS,
    LoopEdge,
    write_closures_mcap,
)
from placerec.io.poses import matrix_to_quat, quat_to_matrix
from placerec.types import REJECTIONS

ROOT = Path(__file__).resolve().parents[1]


def read_mcap(
    path: Path,
) -> tuple[dict[str, Any], dict[str, list[tuple[int, dict[str, Any]]]], dict[str, str]]:
    """(channels: topic -> (schema name, schema encoding, message encoding, schema), messages: topic -> [(log
    time, decoded JSON)] in file order, the ``placerec`` metadata), read with the mcap package's reader."""
    from mcap.reader import make_reader

    with path.open("rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None
        channels = {
            ch.topic: (
                summary.schemas[ch.schema_id].name,
                summary.schemas[ch.schema_id].encoding,
                ch.message_encoding,
                json.loads(summary.schemas[ch.schema_id].data),
            )
            for ch in summary.channels.values()
        }
        messages: dict[str, list[tuple[int, dict[str, Any]]]] = {t: [] for t in channels}
        order = []
        for _, channel, message in reader.iter_messages(log_time_order=False):
            messages[channel.topic].append((message.log_time, json.loads(message.data)))
            order.append(message.log_time)
        assert order == sorted(order)  # written in time order
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    return channels, messages, meta["placerec"]


def random_poses(n: int, seed: int) -> np.ndarray:
    P = np.tile(np.eye(4), (n, 1, 1))
    P[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    P[:, :3, 3] = np.random.default_rng(seed).normal(0, 20, (n, 3))
    return P


def decoded_pose(pose: dict[str, Any]) -> np.ndarray:
    p, o = pose["position"], pose["orientation"]
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(np.array([[o["x"], o["y"], o["z"], o["w"]]]))[0]
    T[:3, 3] = p["x"], p["y"], p["z"]
    return T


N = 6
POSES = random_poses(N, 1)
TRUTH = random_poses(N, 2)
STAMPS = 1_700_000_000.0 + 0.1 * np.arange(N) + 0.0123  # Unix times, as a bag's header stamps
REL = random_poses(1, 3)[0]
EDGES = [
    LoopEdge(query=4, match=1, score=0.42, T_match_query=REL, inliers=37),
    LoopEdge(query=5, match=0, score=0.05, inliers=4, accepted=False, rejection="ransac"),
]


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    path = tmp_path_factory.mktemp("mcap") / "closures.mcap"
    out = write_closures_mcap(
        path, POSES, EDGES, timestamps=STAMPS, ground_truth=TRUTH, frame_id="odom", sensor_frame="velodyne"
    )
    assert out == path
    return read_mcap(path)


def test_topics_schemas_and_counts(written):
    channels, messages, meta = written
    assert {t: c[0] for t, c in channels.items()} == TOPICS
    assert all(c[1] == "jsonschema" and c[2] == "json" for c in channels.values())
    counts = {t: len(m) for t, m in messages.items()}
    assert counts == {"/placerec/pose": N, "/placerec/tf": N, "/placerec/trajectory": 1, "/placerec/ground_truth": 1,
                      "/placerec/loops": 1, "/placerec/loops_rejected": 1, "/placerec/loop_closures": 2}  # fmt: skip
    assert meta["frame_id"] == "odom" and meta["time_source"] == "scan timestamps" and "rate_hz" not in meta
    assert meta["poses"] == str(N) and meta["loops"] == "2"


def test_poses_and_timestamps_read_back(written):
    _, messages, _ = written
    ns = np.round(STAMPS * 1e9).astype(np.int64)
    for i, (t, msg) in enumerate(messages["/placerec/pose"]):
        assert t == ns[i] and msg["timestamp"] == {"sec": int(ns[i] // 10**9), "nsec": int(ns[i] % 10**9)}
        assert msg["frame_id"] == "odom"
        np.testing.assert_array_equal(decoded_pose(msg["pose"])[:3, 3], POSES[i, :3, 3])  # exact: JSON floats
        np.testing.assert_allclose(decoded_pose(msg["pose"]), POSES[i], atol=1e-12)
    for i, (t, tf) in enumerate(messages["/placerec/tf"]):
        assert t == ns[i] and (tf["parent_frame_id"], tf["child_frame_id"]) == ("odom", "velodyne")
        pose = decoded_pose({"position": tf["translation"], "orientation": tf["rotation"]})
        np.testing.assert_allclose(pose, POSES[i], atol=1e-12)
    for topic, expected in (("/placerec/trajectory", POSES), ("/placerec/ground_truth", TRUTH)):
        [(t, msg)] = messages[topic]
        assert t == ns[-1] and msg["frame_id"] == "odom"
        np.testing.assert_allclose(np.stack([decoded_pose(p) for p in msg["poses"]]), expected, atol=1e-12)


def test_loop_edges_read_back(written):
    _, messages, _ = written
    ns = np.round(STAMPS * 1e9).astype(np.int64)
    closures = messages["/placerec/loop_closures"]
    assert [t for t, _ in closures] == [ns[4], ns[5]]
    (_, a), (_, b) = closures
    assert (a["query_index"], a["match_index"], a["score"], a["inliers"]) == (4, 1, 0.42, 37)
    assert a["accepted"] and a["rejection"] is None and not a["injected"]
    np.testing.assert_array_equal(np.reshape(a["relative_pose"], (4, 4)), REL)
    assert (b["query_index"], b["match_index"], b["inliers"], b["relative_pose"]) == (5, 0, 4, None)
    assert not b["accepted"] and b["rejection"] == "ransac"
    for topic, edge, color in (("/placerec/loops", EDGES[0], ACCEPTED_COLOR),
                               ("/placerec/loops_rejected", EDGES[1], REJECTED_COLOR)):  # fmt: skip
        [(t, update)] = messages[topic]
        [entity] = update["entities"]
        assert t == ns[edge.query] and update["deletions"] == []
        assert entity["id"] == f"loop/{edge.query}-{edge.match}" and entity["lifetime"] == {
            "sec": 0,
            "nsec": 0,
        }
        [line] = entity["lines"]
        ends = [[p["x"], p["y"], p["z"]] for p in line["points"]]
        np.testing.assert_array_equal(ends, [POSES[edge.match, :3, 3], POSES[edge.query, :3, 3]])
        assert line["color"] == color and line["type"] == 2  # LINE_LIST
        meta = {kv["key"]: kv["value"] for kv in entity["metadata"]}
        assert meta["query"] == str(edge.query) and meta["accepted"] == str(edge.accepted).lower()


def test_the_fields_are_foxgloves(written):
    """The field names and nesting of Foxglove's schemas (docs.foxglove.dev message schemas), written out here
    apart from the module's schemas; and every message valid against the schema stored in the file."""
    channels, messages, _ = written
    time, vec, quat = {"sec", "nsec"}, {"x", "y", "z"}, {"x", "y", "z", "w"}
    _, pose = messages["/placerec/pose"][0]
    assert set(pose) == {"timestamp", "frame_id", "pose"} and set(pose["timestamp"]) == time
    assert set(pose["pose"]) == {"position", "orientation"}
    assert set(pose["pose"]["position"]) == vec and set(pose["pose"]["orientation"]) == quat
    _, poses = messages["/placerec/trajectory"][0]
    assert set(poses) == {"timestamp", "frame_id", "poses"}
    _, tf = messages["/placerec/tf"][0]
    assert set(tf) == {"timestamp", "parent_frame_id", "child_frame_id", "translation", "rotation"}
    _, update = messages["/placerec/loops"][0]
    assert set(update) == {"deletions", "entities"}
    entity = update["entities"][0]
    assert set(entity) == {"timestamp", "frame_id", "id", "lifetime", "frame_locked", "metadata", "arrows",
                           "cubes", "spheres", "cylinders", "lines", "triangles", "texts", "models"}  # fmt: skip
    assert set(entity["lines"][0]) == {"type", "pose", "thickness", "scale_invariant", "points", "color",
                                       "colors", "indices"}  # fmt: skip
    assert set(entity["lines"][0]["color"]) == {"r", "g", "b", "a"}
    jsonschema = pytest.importorskip("jsonschema")
    for topic, items in messages.items():
        schema = channels[topic][3]
        jsonschema.Draft7Validator.check_schema(schema)
        for _, msg in items:
            jsonschema.validate(msg, schema)


def test_quaternion_of_a_known_rotation():
    yaw90 = np.array([[[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]])  # 90 deg about z
    q = matrix_to_quat(yaw90)[0]
    assert np.allclose(q, [0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)]) or np.allclose(
        q, [0, 0, -np.sqrt(0.5), -np.sqrt(0.5)]
    )
    R = random_poses(50, 7)[:, :3, :3]
    np.testing.assert_allclose(quat_to_matrix(matrix_to_quat(R)), R, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(matrix_to_quat(R), axis=1), 1.0, atol=1e-12)
    assert matrix_to_quat(np.zeros((0, 3, 3))).shape == (0, 4)


def test_without_timestamps_times_are_index_over_rate(tmp_path):
    path = tmp_path / "c.mcap"
    write_closures_mcap(path, POSES, EDGES)
    channels, messages, meta = read_mcap(path)
    assert [t for t, _ in messages["/placerec/pose"]] == [i * 100_000_000 for i in range(N)]  # 10 Hz
    assert messages["/placerec/pose"][3][1]["timestamp"] == {"sec": 0, "nsec": 300_000_000}
    assert (
        meta["time_source"] == "index / rate_hz"
        and float(meta["rate_hz"]) == 10.0
        and meta["frame_id"] == "map"
    )
    assert "/placerec/ground_truth" not in channels and "/placerec/tf" not in channels
    write_closures_mcap(path, POSES, rate_hz=4.0)
    channels, messages, meta = read_mcap(path)
    assert [t for t, _ in messages["/placerec/pose"]] == [i * 250_000_000 for i in range(N)]
    assert float(meta["rate_hz"]) == 4.0 and "/placerec/loop_closures" not in channels


def test_scans_without_a_pose_and_a_map_to_match(tmp_path):
    """Relocalisation's shape: NaN rows for the scans without a fix (``valid``), matches index a map's poses."""
    poses = POSES.copy()
    poses[2] = np.nan
    valid = np.ones(N, bool)
    valid[2] = False
    keyframes = random_poses(3, 9)
    edges = [LoopEdge(query=4, match=2, score=0.9, inliers=50), LoopEdge(query=2, match=0, accepted=False)]
    path = tmp_path / "fix.mcap"
    write_closures_mcap(path, poses, edges, timestamps=STAMPS, valid=valid, match_poses=keyframes)
    _, messages, meta = read_mcap(path)
    assert len(messages["/placerec/pose"]) == N - 1 and meta["poses"] == str(N - 1)
    [(_, trajectory)] = messages["/placerec/trajectory"]
    assert len(trajectory["poses"]) == N - 1
    assert len(messages["/placerec/loop_closures"]) == 2 and "/placerec/loops_rejected" not in messages
    [(_, update)] = messages["/placerec/loops"]
    points = update["entities"][0]["lines"][0]["points"]
    np.testing.assert_array_equal([list(p.values()) for p in points], [keyframes[2, :3, 3], POSES[4, :3, 3]])


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (
            {"poses": np.where(np.arange(N)[:, None, None] == 2, np.nan, POSES)},
            "poses: pose 2 is no rigid motion",
        ),
        ({"poses": POSES[:, :3]}, "poses must have shape (N, 4, 4)"),
        ({"timestamps": STAMPS[:-1]}, "5 timestamps for 6 poses"),
        ({"timestamps": np.r_[STAMPS[:-1], np.nan]}, "timestamp 5 is nan"),
        ({"timestamps": STAMPS - 2e9}, "timestamp 0 is"),
        ({"ground_truth": TRUTH[:-1]}, "ground_truth: 5 poses for 6 scans"),
        ({"loops": [LoopEdge(6, 0)]}, "loop 0 (query 6, match 0): query index outside the 6 poses"),
        ({"loops": [LoopEdge(3, -1)]}, "match index outside"),
        ({"loops": [LoopEdge(3, 0, T_match_query=np.full((4, 4), np.nan))]}, "T_match_query contains NaN"),
        ({"loops": [LoopEdge(3, 0, rejection="fitness")]}, "accepted, yet rejected by 'fitness'"),
        ({"loops": [LoopEdge(3, 0, score=float("inf"))]}, "score is inf"),
        ({"valid": np.ones(N - 1, bool)}, "valid has 5 entries for 6 poses"),
        ({"rate_hz": 0.0}, "rate_hz must be a positive number"),
        ({"frame_id": ""}, "frame_id must be a non-empty string"),
    ],
)
def test_bad_input_names_what_is_wrong(tmp_path, change, message):
    path = tmp_path / "bad.mcap"
    args: dict[str, Any] = {"poses": POSES, "loops": EDGES, **change}
    with pytest.raises(ScanDataError) as err:
        write_closures_mcap(path, args.pop("poses"), args.pop("loops"), **args)
    assert message in str(err.value) and str(path) in str(err.value)
    assert list(tmp_path.iterdir()) == []  # nothing written, no temporary file left


def test_a_slam_run_writes_its_loops(tmp_path):
    """``placerec slam`` on 50 scans of the town's block driven twice (4 m apart: the second lap revisits the
    first from scan 43) with two injected false loops: closures.mcap holds loops.csv's edges exactly (the
    injected ones rejected by the back end), the candidates verification rejected, and the run's poses."""
    from placerec.cli import app
    from placerec.experiment.candidates import pose_to_xyzrpy

    result = CliRunner().invoke(
        app,
        ["slam", str(ROOT / "configs" / "slam_demo.yaml"), "--out", str(tmp_path / "res"),
         "--set", "dataset.simulator.route=loop", "--set", "dataset.simulator.spacing=4",
         "--set", "dataset.simulator.n_scans=50", "--set", "loops.exclusion.frames=20",
         "--set", "output.progress=false", "--set", "output.figures=false",
         "--set", "robustness.false_loops=2", "--set", "robustness.min_distance=20"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    run = tmp_path / "res" / "latest"
    channels, messages, meta = read_mcap(run / "closures.mcap")
    metrics = json.loads((run / "metrics.json").read_text())
    rows = list(csv.DictReader((run / "loops.csv").open()))
    assert metrics["loops"]["accepted"] >= 5 and metrics["loops"]["injected"] == 2

    closures = [m for _, m in messages["/placerec/loop_closures"]]
    graph = [c for c in closures if c["rejection"] in (None, "back-end")]
    key = {(int(r["query_id"]), int(r["match_id"])): r for r in rows}
    assert sorted(key) == sorted((c["query_index"], c["match_index"]) for c in graph)
    for c in graph:
        row = key[(c["query_index"], c["match_index"])]
        assert c["injected"] == (row["injected"] == "1")
        assert c["accepted"] == (float(row["weight"]) >= 0.5)
        if not c["injected"]:
            assert c["score"] == pytest.approx(float(row["score"]), rel=1e-5) and c["inliers"] > 0
        xyzrpy = pose_to_xyzrpy(np.reshape(c["relative_pose"], (4, 4)))
        expected = [float(row[k]) for k in ("x", "y", "z", "roll", "pitch", "yaw")]
        np.testing.assert_allclose(xyzrpy, expected, rtol=1e-5, atol=1e-5)
    real = [c for c in graph if not c["injected"]]
    assert (
        sum(c["accepted"] for c in real)
        == metrics["loops"]["accepted"] - metrics["loops"]["rejected_by_back_end"]
    )
    assert (
        sum(not c["accepted"] for c in graph if c["injected"])
        == metrics["loops"]["injected_rejected_by_back_end"]
    )
    assert len(messages["/placerec/loops"]) == sum(c["accepted"] for c in graph)
    rejected = [c for c in closures if c["rejection"] not in (None, "back-end")]
    assert rejected and all(c["rejection"] in REJECTIONS and not c["accepted"] for c in rejected)
    assert len(messages["/placerec/loops_rejected"]) == len(closures) - len(messages["/placerec/loops"])

    poses, _ = read_poses(run / "poses_kitti.txt")
    _, stamps = read_poses(run / "poses_tum.txt")
    truth, _ = read_poses(run / "ground_truth_kitti.txt")
    assert (
        len(messages["/placerec/pose"]) == metrics["n_scans"] == 50
        and meta["time_source"] == "scan timestamps"
    )
    np.testing.assert_allclose(np.stack([decoded_pose(m["pose"]) for _, m in messages["/placerec/pose"]]), poses,
                               atol=1e-9)  # fmt: skip
    np.testing.assert_allclose([t / 1e9 for t, _ in messages["/placerec/pose"]], stamps, atol=1e-9)
    [(_, gt)] = messages["/placerec/ground_truth"]
    np.testing.assert_allclose(np.stack([decoded_pose(p) for p in gt["poses"]]), truth, atol=1e-9)
