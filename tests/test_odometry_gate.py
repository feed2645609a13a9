"""The odometry gate (placerec.odometry_gate): its formula, the detector's use of it and the evaluation's."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_loop_filter import _Echo
from test_pose_truth import _pose

from placerec.config import parse_config
from placerec.errors import ConfigError, ScanDataError
from placerec.experiment.benchmark import _cell_key
from placerec.experiment.candidates import CandidateTable
from placerec.experiment.report import odometry_gated
from placerec.loop_closure import LoopClosureDetector
from placerec.odometry_gate import LoopChain, OdometryGateParams, odometry_disagreement
from placerec.safe_yaml import load_yaml_file
from placerec.sim.odometry import OdometryDrift, drift_poses, slam_demo_drift
from placerec.types import Candidate

ROOT = Path(__file__).resolve().parents[1]


def test_disagreement_is_the_translation_and_angle_between_the_closure_and_the_odometrys_motion():
    # odometry: the query 10 m ahead of the match, turned 30 deg; the closure says 3 m to the side and 40 deg
    odom_m, odom_q = _pose(5.0, 2.0, 90.0), _pose(5.0, 2.0, 90.0) @ _pose(10.0, 0.0, 30.0)
    t, r = odometry_disagreement(_pose(10.0, 3.0, 40.0), odom_m, odom_q)
    assert t[0] == pytest.approx(3.0) and r[0] == pytest.approx(10.0)
    # the match's frame, not the world's: the same closure in another heading of the match disagrees as much
    t2, r2 = odometry_disagreement(_pose(10.0, 3.0, 40.0), np.eye(4), _pose(10.0, 0.0, 30.0))
    assert t2[0] == pytest.approx(3.0) and r2[0] == pytest.approx(10.0)
    nan_t, nan_r = odometry_disagreement(np.full((4, 4), np.nan), odom_m, odom_q)
    assert np.isnan(nan_t[0]) and np.isnan(nan_r[0])


def test_bounds_grow_with_the_path_and_a_closure_without_a_pose_passes():
    g = OdometryGateParams(metres=1.0, per_metre=0.04, degrees=4.0, degrees_per_metre=0.05)
    # at 100 m of path: 5 m and 9 deg
    ok = g.admits(
        np.array([4.9, 5.1, 0.0, 0.0, np.nan]), np.array([0.0, 0.0, 8.9, 9.1, 50.0]), np.full(5, 100.0)
    )
    assert ok.tolist() == [True, False, True, False, True]
    assert g.admits(np.array([1.0]), np.array([4.0]), np.array([0.0])).all()
    with pytest.raises(ConfigError, match="per_metre"):
        OdometryGateParams.model_validate({"per_metre": -0.1})


class _Posed(_Echo):
    """Answers each query with fixed (match id, relative pose) candidates, best first."""

    name = "posed"

    def query_description(self, description, k=1, max_id=None, query_id=-1):
        got = [(m, T) for m, T in self.answers.get(query_id, []) if m <= max_id]
        return [Candidate(query_id, m, 0.9 - 0.1 * r, relative_pose=T) for r, (m, T) in enumerate(got)][:k]


def test_the_detector_drops_a_closure_far_from_the_odometry_and_keeps_the_one_that_agrees():
    # a straight 1 m-spaced drive; place 150 is 150 m past place 0 by odometry, so its true closure onto place 0
    # would have to be 150 m long: none here. Its candidates: place 100 (true: 50 m back) and a look-alike
    # (place 10, whose closure claims the query sits 2 m ahead of it, 138 m from where the odometry has it)
    odom = [_pose(float(i)) for i in range(151)]
    answers = {150: [(10, _pose(2.0)), (100, _pose(50.3))]}
    det = LoopClosureDetector(
        _Posed(answers), threshold=0.5, exclusion_frames=20, k=2, odometry_gate=OdometryGateParams()
    )
    out = [det.process(None, pose=odom[i], description={"x": np.zeros(1)}) for i in range(151)]
    assert [c.match_id for c in out[150]] == [100] and det.last_status == "ok"
    assert [c.match_id for c in det.last_candidates] == [10, 100]  # every candidate is kept for the caller
    alone = LoopClosureDetector(
        _Posed({150: answers[150][:1]}),
        threshold=0.5,
        exclusion_frames=20,
        odometry_gate=OdometryGateParams(),
    )
    got = [alone.process(None, pose=odom[i], description={"x": np.zeros(1)}) for i in range(151)]
    assert got[150] == [] and alone.last_status == "odometry_gate"
    ungated = LoopClosureDetector(_Posed({150: answers[150][:1]}), threshold=0.5, exclusion_frames=20)
    got = [ungated.process(None, description={"x": np.zeros(1)}) for _ in range(151)]
    assert [c.match_id for c in got[150]] == [10]


def test_the_gated_detector_needs_each_places_pose_and_leaves_a_prior_maps_places_alone():
    det = LoopClosureDetector(_Posed({}), threshold=0.5, odometry_gate=OdometryGateParams())
    with pytest.raises(ScanDataError, match="odometry_gate"):
        det.process(None, description={"x": np.zeros(1)})
    assert det.n_processed == 0
    # a prior map of 5 places in its own frame: a closure onto place 2 is not the session odometry's to judge
    det = LoopClosureDetector(
        _Posed({5: [(2, _pose(400.0))]}), threshold=0.5, prior_entries=5, odometry_gate=OdometryGateParams()
    )
    assert [c.match_id for c in det.process(None, pose=np.eye(4), description={"x": np.zeros(1)})] == [2]


def _table(rows):
    """A CandidateTable of (match id, score, accepted, pose) rows per query (queries 0, 1, ...)."""
    q, n = len(rows), max(len(r) for r in rows)
    match = np.full((q, n), -1)
    score = np.full((q, n), np.nan)
    acc = np.full((q, n), -1, np.int8)
    poses = np.full((q, n, 4, 4), np.nan)
    for i, r in enumerate(rows):
        for j, (m, s, a, T) in enumerate(r):
            match[i, j], score[i, j], acc[i, j], poses[i, j] = m, s, a, T
    nan = np.full((q, n), np.nan)
    return CandidateTable(np.arange(q), match, score, np.full((q, n), -1), poses, nan, nan, nan, acc)


def test_a_refused_candidate_becomes_a_rejected_one_and_the_next_accepted_one_the_answer():
    t = _table(
        [
            [(7, 0.6, 1, _pose(1.0)), (8, 0.5, 1, _pose(2.0)), (9, 0.0, 0, _pose(3.0))],
            [(4, 0.4, 1, _pose(4.0))],
        ]
    )
    refused = np.array([[True, False, False], [False, False, False]])
    g = t.refused(refused)
    assert g.match_ids.tolist() == [[8, 7, 9], [4, -1, -1]]  # the refused one after the other rejected one
    assert g.scores[0].tolist() == [0.5, 0.0, 0.0] and g.accepted[0].tolist() == [1, 0, 0]
    assert g.relative_poses[0, 0, 0, 3] == 2.0 and g.relative_poses[0, 1, 0, 3] == 1.0
    assert np.isnan(g.scores[1, 1]) and g.match_ids[1, 1] == -1  # padding stays last
    same = t.refused(np.zeros_like(refused))
    assert (same.match_ids == t.match_ids).all() and np.array_equal(same.scores, t.scores, equal_nan=True)


def _cfg(gate=None, seed=3):
    ev = {"mode": "loop"} | ({} if gate is None else {"odometry_gate": gate})
    return parse_config(
        {"dataset": {"source": "simulator", "simulator": {"seed": seed}}, "pipelines": [{"name": "scan-context"}],
         "evaluation": ev}
    )  # fmt: skip


def test_the_evaluation_refuses_what_a_drifting_odometry_rules_out_and_nothing_without_the_gate():
    poses = np.stack([_pose(float(i)) for i in range(200)])  # a straight drive, 1 m apart
    # query 180: a true closure onto scan 20 (160 m back, as the truth says) and a look-alike 30 m off
    t = _table([[(20, 0.5, 1, np.linalg.inv(poses[20]) @ poses[180]), (20, 0.4, 1, _pose(190.0))]])
    t = CandidateTable(np.array([180]), *(getattr(t, f) for f in list(t.__dataclass_fields__)[1:]))
    assert not odometry_gated(_cfg(), [t], poses)[1][0].any()
    refused = odometry_gated(_cfg({}), [t], poses)[1][0]
    assert refused.tolist() == [[False, True]]
    # the drift is the demo's, drawn with the simulator's seed, so the same refusals follow from that odometry
    odom = drift_poses(poses, slam_demo_drift(), 3)
    tr, _ = odometry_disagreement(t.relative_poses[0, 1], odom[20], odom[180])
    assert tr[0] > 1.0 + 0.04 * 160


def test_the_demo_drift_is_configs_slam_demo_yamls():
    drift = load_yaml_file(ROOT / "configs" / "slam_demo.yaml")["odometry"]["drift"]
    assert OdometryDrift(**drift) == slam_demo_drift()


def test_a_benchmark_cells_stamp_leaves_out_the_odometry_gate_judged_from_its_files():
    assert _cell_key(_cfg()) == _cell_key(_cfg({"bounds": {"per_metre": 0.1}}))
    assert _cell_key(_cfg()) != _cell_key(_cfg(seed=4))


def test_the_status_of_a_gated_query_does_not_stay_for_the_next():
    odom = [_pose(float(i)) for i in range(152)]
    det = LoopClosureDetector(
        _Posed({150: [(10, _pose(2.0))], 151: [(101, _pose(50.0))]}),
        threshold=0.5,
        exclusion_frames=20,
        odometry_gate=OdometryGateParams(),
    )
    for i in range(151):
        det.process(None, pose=odom[i], description={"x": np.zeros(1)})
    assert det.last_status == "odometry_gate"
    assert [c.match_id for c in det.process(None, pose=odom[151], description={"x": np.zeros(1)})] == [101]
    assert det.last_status == "ok"


def test_the_real_time_detector_gates_the_same_closures_as_the_sequential_one():
    from placerec.realtime import RealtimeParams

    odom = [_pose(float(i)) for i in range(160)]
    answers = {
        150: [(10, _pose(2.0)), (100, _pose(50.3))],
        155: [(20, _pose(1.0))],
        158: [(108, _pose(50.0))],
    }
    got = {}
    for mode, realtime in (("sequential", None), ("real-time", RealtimeParams(budget_ms=100, max_backlog=3))):
        with LoopClosureDetector(
            _Posed(answers),
            0.5,
            exclusion_frames=20,
            k=2,
            odometry_gate=OdometryGateParams(),
            realtime=realtime,
        ) as det:
            out = [
                c for i in range(160) for c in det.process(None, pose=odom[i], description={"x": np.zeros(1)})
            ]
            out += det.flush()
        got[mode] = sorted((c.query_id, c.match_id) for c in out)
    assert got["sequential"] == got["real-time"] == [(150, 100), (158, 108)]


def _route(n):
    """Poses of a winding drive, one place a metre: heading turning by 1 deg a place, some height change."""
    poses, T = [], np.eye(4)
    for i in range(n):
        poses.append(T.copy())
        step = _pose(1.0, 0.0, 1.0)
        step[2, 3] = 0.02 * np.sin(i / 7.0)
        T = T @ step
    return np.stack(poses)


def test_the_chain_predicts_through_accepted_closures_in_either_direction_and_counts_only_odometry():
    poses = _route(201)
    path = np.arange(201, dtype=np.float64)
    chain = LoopChain()
    T, along = chain.predict(145, 200, poses, path)  # no closure: the odometry's motion and path
    assert np.allclose(T, np.linalg.solve(poses[145], poses[200])) and along == 55.0
    # two closures, each with a pose of its own (not the odometry's): 150 -> 50 and 40 -> 198
    c1, c2 = _pose(3.0, 1.0, 10.0), _pose(-2.0, 4.0, -25.0)
    chain.add(50, 150, c1)
    chain.add(40, 198, c2)
    chain.add(60, 61, np.full((4, 4), np.nan))  # no pose: nothing to predict through
    assert len(chain) == 2
    T, along = chain.predict(145, 200, poses, path)
    # 145 -> 150 by odometry, the first closure backwards to 50, 50 -> 40 by odometry, the second to 198, 198 -> 200
    odo = lambda a, b: np.linalg.solve(poses[a], poses[b])  # noqa: E731
    expected = odo(145, 150) @ np.linalg.inv(c1) @ odo(50, 40) @ c2 @ odo(198, 200)
    assert np.allclose(T, expected) and along == pytest.approx(5.0 + 10.0 + 2.0)
    # a closure's own place as the query
    T, along = chain.predict(145, 198, poses, path)
    assert np.allclose(T, odo(145, 150) @ np.linalg.inv(c1) @ odo(50, 40) @ c2) and along == pytest.approx(
        15.0
    )
    # a chain no shorter than the odometry's own is not taken
    T, along = chain.predict(147, 152, poses, path)
    assert np.allclose(T, odo(147, 152)) and along == 5.0
    # a closure between neighbouring places is taken over the odometry between them
    chain.add(150, 151, _pose(0.5, 0.2, 3.0))
    T, along = chain.predict(145, 151, poses, path)
    assert np.allclose(T, odo(145, 150) @ _pose(0.5, 0.2, 3.0)) and along == pytest.approx(5.0)


def _far_lookalike(poses, match, query, off):
    """A closure of ``query`` onto ``match`` ``off`` metres to the side of where the poses have it."""
    return np.linalg.solve(poses[match], poses[query]) @ _pose(0.0, off, 0.0)


def test_after_a_closure_the_detector_judges_a_lookalike_over_the_path_since_it():
    # 1 m a place: query 150 closes onto place 20 where the odometry has it (130 m of path). Query 160's
    # look-alike onto place 25 sits 4 m off: within 1 m + 0.04 x 135 m of odometry alone, but 15 m past a closure
    # that tied place 20 to place 150 (1 m + 0.04 x 15 m) it is not where the chain puts it
    odom = _route(170)
    answers = {
        150: [(20, np.linalg.solve(odom[20], odom[150]))],
        160: [(25, _far_lookalike(odom, 25, 160, 4.0))],
    }
    got = {}
    for through in (True, False):
        det = LoopClosureDetector(
            _Posed(answers),
            threshold=0.5,
            exclusion_frames=20,
            odometry_gate=OdometryGateParams(through_loops=through),
        )
        out = [c for i in range(170) for c in det.process(None, pose=odom[i], description={"x": np.zeros(1)})]
        got[through] = [(c.query_id, c.match_id) for c in out]
        got[through, "refused"] = [(c.query_id, c.match_id) for c in det.refused_by_gate]
    assert got[False] == [(150, 20), (160, 25)] and got[False, "refused"] == []
    assert got[True] == [(150, 20)] and got[True, "refused"] == [(160, 25)]


def test_the_slam_report_counts_the_closures_the_gate_refused(capsys):
    from placerec.eval.metrics import timing_summary
    from placerec.slam_app.report import _loop_rows, print_slam_table

    payload = {
        "pipeline": "orb-hbst",
        "odometry_source": "dataset",
        "trajectory": {},
        "loops": {"accepted": 80, "injected": 0, "refused_by_odometry_gate": 3},
        "time_ms": {k: timing_summary([2.0, 4.0]) for k in
                    ("online_without_odometry", "online_with_odometry", "isam2_update", "isam2_loop_update")},
    }  # fmt: skip
    header, (row,) = _loop_rows(payload)
    assert dict(zip(header, row, strict=True))["refused by gate"] == "3"
    print_slam_table(payload, "slam")
    loops_table, times_table = capsys.readouterr().out.split("slam, odometry: dataset: time")
    assert "refused" in loops_table and "iSAM2" in times_table and "per scan" in times_table
    del payload["loops"]["refused_by_odometry_gate"]  # no gate
    header, (row,) = _loop_rows(payload)
    assert dict(zip(header, row, strict=True))["refused by gate"] == "-"


def test_the_evaluation_predicts_through_the_answers_accepted_at_the_operating_threshold():
    poses = _route(170)
    still = {"drift": {"translation": 0, "rotation_deg": 0, "yaw_bias_deg_per_100m": 0, "scale_bias": 0}}
    true = np.linalg.solve(poses[20], poses[150])
    rows = [[(20, 0.5, 1, true)], [(25, 0.6, 1, _far_lookalike(poses, 25, 160, 4.0))]]
    t = _table(rows)
    t = CandidateTable(np.array([150, 160]), *(getattr(t, f) for f in list(t.__dataclass_fields__)[1:]))
    cfg = _cfg(still)
    assert odometry_gated(cfg, [t], poses)[1][0].tolist() == [
        [False],
        [False],
    ]  # no threshold: odometry alone
    assert odometry_gated(cfg, [t], poses, [0.4])[1][0].tolist() == [[False], [True]]
    # the first closure scores under a threshold of 0.55: not accepted there, so nothing to predict through
    assert odometry_gated(cfg, [t], poses, [0.55])[1][0].tolist() == [[False], [False]]
    plain = _cfg(still | {"bounds": {"through_loops": False}})
    assert odometry_gated(plain, [t], poses, [0.4])[1][0].tolist() == [[False], [False]]


def test_the_chains_benchmark_ends_with_one_json_line_of_its_figures():
    import json
    import subprocess
    import sys

    out = subprocess.run(
        [sys.executable, str(ROOT / "tools" / "bench_loop_chain.py"), "--places", "3000", "--closures", "10", "50",
         "--predictions", "5"],
        capture_output=True, text=True, check=True, cwd=ROOT,
    ).stdout.strip().splitlines()  # fmt: skip
    line = json.loads(out[-1])
    assert line["tool"] == "bench_loop_chain" and set(line["closures"]) == {"10", "50"}
    assert all(f["predict_ms_median"] > 0 for f in line["closures"].values())


def test_placerec_slam_reports_the_gates_refusals_only_with_a_gate(tmp_path):
    pytest.importorskip("gtsam")
    from placerec.slam_app.config import load_slam_config
    from placerec.slam_app.run import run_slam

    base = ["dataset.simulator.sensor=vlp16", "dataset.simulator.n_scans=12", "output.progress=false",
            "output.figures=false", "loops.exclusion.frames=3"]  # fmt: skip
    _, plain = run_slam(load_slam_config(ROOT / "configs" / "slam_demo.yaml", base), tmp_path / "plain")
    assert "refused_by_odometry_gate" not in plain["loops"]
    # bounds no closure can meet: every closure over the threshold is refused and counted
    tight = "loops.odometry_gate={metres: 0.001, per_metre: 0, degrees: 0.001, degrees_per_metre: 0}"
    _, gated = run_slam(
        load_slam_config(ROOT / "configs" / "slam_demo.yaml", [*base, tight]), tmp_path / "gated"
    )
    assert plain["loops"]["accepted"] > 0 and gated["loops"]["accepted"] == 0
    assert gated["loops"]["refused_by_odometry_gate"] >= plain["loops"]["accepted"]
