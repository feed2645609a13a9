"""What `run_experiment` leaves on disk: every candidate in the CSV, and ``latest`` only on a complete run."""

import csv
import json
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from placerec.baselines.scan_context import ScanContext
from placerec.config import load_config
from placerec.errors import ConfigError, ScanDataError, ScanFormatError
from placerec.eval import ExclusionWindow, loop_ground_truth
from placerec.experiment import run_experiment
from placerec.experiment.candidates import CandidateTable, read_candidates, write_candidates
from placerec.experiment.report import recompute_loop_metrics, report_localize, report_loop
from placerec.experiment.run_folder import make_run_dir
from placerec.experiment.runner import STAGES, PipelineRecord
from placerec.experiment.tables import print_table, table_rows
from placerec.io import read_poses, write_kitti_poses
from placerec.loop_closure import split_verify_time
from placerec.types import Candidate, ListSequence, Scan, Verification, relative_pose

N_SCANS = 24


class FailingScanContext(ScanContext):
    """Scan Context that refuses its 10th query: a run that fails midway."""

    def query_description(self, description, k=1, max_id=None, query_id=-1):
        if query_id >= 10:
            raise ScanDataError("FailingScanContext refuses query 10")
        return super().query_description(description, k=k, max_id=max_id, query_id=query_id)


@pytest.fixture(scope="module")
def sequence_dir(tmp_path_factory):
    """A KITTI-layout folder: a 12-scan loop of random pillars driven twice, 5 m steps."""
    root = tmp_path_factory.mktemp("seq")
    (root / "velodyne").mkdir()
    rng = np.random.default_rng(0)
    world = np.c_[rng.uniform(-80, 80, (600, 2)), rng.uniform(1, 6, 600)]
    angle = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    xy = np.tile(np.c_[10 * np.cos(angle), 10 * np.sin(angle)], (2, 1))
    poses = np.tile(np.eye(4), (N_SCANS, 1, 1))
    poses[:, :2, 3] = xy
    for i, p in enumerate(xy):
        d = world[:, :2] - p
        near = np.linalg.norm(d, axis=1) < 50
        pts = np.concatenate([np.c_[d[near], world[near, 2] * k / 5 - 1.5] for k in range(6)])
        pts += rng.normal(0, 0.02, pts.shape)
        np.c_[pts, np.full(len(pts), 0.5)].astype(np.float32).tofile(root / "velodyne" / f"{i:06d}.bin")
    write_kitti_poses(root / "poses.txt", poses)
    return root


def config(
    sequence_dir, out, pipeline="scan-context", exclusion=("evaluation.exclusion.frames=6",), extra=()
):
    return load_config(
        None,
        [
            "name=tiny",
            "dataset.source=path",
            f"dataset.path={sequence_dir}",
            f"pipelines=[{{name: '{pipeline}'}}]",
            *exclusion,
            "evaluation.top_n=3",
            f"output.dir={out}",
            "output.cache_dir=null",
            "output.progress=false",
            "output.figures=false",
            *extra,
        ],
    )


def test_candidates_csv_holds_the_top_n_per_query_and_recomputes_recall_at_n(sequence_dir, tmp_path):
    run, payload = run_experiment(config(sequence_dir, tmp_path))
    with (run / "candidates_scan-context.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == [
        "query_id",
        "rank",
        "match_id",
        "score",
        "inliers",
        "x",
        "y",
        "z",
        "roll",
        "pitch",
        "yaw",
        "verified_score",
        "fitness",
        "rmse",
        "accepted",
    ]
    per_query = {}
    for r in rows:
        per_query.setdefault(int(r["query_id"]), []).append(r)
    assert sorted(per_query) == list(range(N_SCANS))
    for q, cands in per_query.items():
        eligible = max(0, q - 6 + 1)  # scans 0 .. q-6
        if eligible == 0:
            assert [(c["rank"], c["match_id"], c["score"]) for c in cands] == [("1", "-1", "")]
            continue
        assert [int(c["rank"]) for c in cands] == list(range(1, min(3, eligible) + 1))
        assert all(0 <= int(c["match_id"]) <= q - 6 for c in cands)
        scores = [float(c["score"]) for c in cands]
        assert scores == sorted(scores, reverse=True)
    m = payload["pipelines"]["scan-context"]
    assert m["n_revisits"] > 0
    again = recompute_loop_metrics(run, "scan-context")
    assert again["recall_at_n"] == pytest.approx(m["recall_at_n"])
    assert again["max_f1"] == pytest.approx(m["max_f1"])
    # the retrieval protocol and the direction split sit beside the loop protocol, recomputed alike
    assert set(m["retrieval"]) >= {"recall_at_1", "recall_at_1pct", "n_queries", "k_1pct_max"}
    assert m["retrieval"]["n_queries"] >= m["n_revisits"]  # 25 m finds at least the revisits within 5 m
    assert sum(m["directions"][d]["n_revisits"] for d in ("same", "reverse")) == m["n_revisits"]
    assert again["retrieval"] == m["retrieval"] and again["directions"] == m["directions"]


@pytest.mark.parametrize("frames", ["null", "2"])
def test_run_applies_the_configured_window_to_detector_and_ground_truth(sequence_dir, tmp_path, frames):
    """Metres and frames from the config reach both sides: no candidate inside the window, revisits counted alike."""
    settings = (f"evaluation.exclusion.frames={frames}", "evaluation.exclusion.metres=40")
    run, payload = run_experiment(config(sequence_dir, tmp_path, exclusion=settings))
    window = ExclusionWindow(None if frames == "null" else int(frames), None, 40.0)
    poses, _ = read_poses(run / "poses.txt")
    gt = loop_ground_truth(poses, exclusion=window)
    table = read_candidates(run / "candidates_scan-context.csv")
    bound = gt.max_eligible[table.query_ids]
    assert np.all(table.match_ids <= bound[:, None])
    assert np.array_equal(
        table.match_ids[:, 0] >= 0, bound >= 0
    )  # queried exactly when something was eligible
    assert payload["pipelines"]["scan-context"]["n_revisits"] == gt.n_revisits > 0


def test_candidates_round_trip_with_inliers(tmp_path):
    path = tmp_path / "c.csv"
    cands = [[], [Candidate(1, 0, 0.5, inliers=7), Candidate(1, 3, 0.25)]]
    write_candidates(path, [0, 1], cands)
    table = read_candidates(path)
    assert table.query_ids.tolist() == [0, 1]
    assert table.match_ids.tolist() == [[-1, -1], [0, 3]]
    assert np.isnan(table.scores[0]).all() and table.scores[1].tolist() == [0.5, 0.25]
    assert table.inliers.tolist() == [[-1, -1], [7, -1]]
    assert table.topn(3).tolist() == [[-1, -1, -1], [0, 3, -1]]


def test_top1_files_of_earlier_runs_still_read(tmp_path):
    path = tmp_path / "candidates_old.csv"
    path.write_text("query_id,match_id,score\n0,-1,\n1,0,0.75\n")
    table = read_candidates(path)
    q, m, s = table.top1()
    assert q.tolist() == [0, 1] and m.tolist() == [-1, 0] and np.isnan(s[0]) and s[1] == 0.75
    assert np.isnan(table.relative_poses).all() and table.accepted.tolist() == [[-1], [-1]]
    ranked = tmp_path / "candidates_ranked.csv"  # the five columns written before poses were added
    ranked.write_text("query_id,rank,match_id,score,inliers\n0,1,2,0.5,7\n0,2,1,0.25,\n")
    table = read_candidates(ranked)
    assert table.match_ids.tolist() == [[2, 1]] and table.inliers.tolist() == [[7, -1]]
    assert np.isnan(table.relative_poses).all() and np.isnan(table.fitness).all()


def _pose(xyz, rpy_deg):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", rpy_deg, degrees=True).as_matrix()
    T[:3, 3] = xyz
    return T


def test_candidates_round_trip_with_relative_poses_and_verification(tmp_path):
    T = _pose((1.5, -2.0, 0.25), (2.0, -3.0, 120.0))

    def verification(score, fitness, rmse, accepted):
        return Verification(T, score, accepted, 40, 50, fitness, rmse, 0.1)

    nan = float("nan")
    other = {"verify": "column shift"}  # a pipeline's own diagnostics: no verification statistics
    cands = [
        [
            Candidate(
                0, 4, 0.8, T, 40, accepted=True, verification=verification(0.8, 0.9, 0.05, True), verify_ms=3
            ),
            Candidate(
                0, 2, 0.0, np.eye(4), 3, accepted=False, verification=verification(0.0, nan, nan, False)
            ),
            Candidate(0, 1, 0.0, None, None, other),
        ]
    ]
    path = tmp_path / "c.csv"
    write_candidates(path, [0], cands)
    with path.open() as fh:
        rows = list(csv.DictReader(fh))
    assert [float(rows[0][k]) for k in ("x", "y", "z", "roll", "pitch", "yaw")] == pytest.approx(
        [1.5, -2.0, 0.25, 2.0, -3.0, 120.0]
    )
    assert (rows[0]["verified_score"], rows[0]["accepted"], rows[1]["fitness"], rows[1]["accepted"]) == (
        "0.8",
        "1",
        "",
        "0",
    )
    table = read_candidates(path)
    np.testing.assert_allclose(table.relative_poses[0, 0], T, atol=1e-12)
    np.testing.assert_allclose(table.relative_poses[0, 1], np.eye(4), atol=1e-12)
    assert np.isnan(table.relative_poses[0, 2]).all() and np.isnan(table.verified_scores[0, 2])
    assert table.verified_scores[0, :2].tolist() == [0.8, 0.0] and table.inliers.tolist() == [[40, 3, -1]]
    assert table.fitness[0, 0] == 0.9 and np.isnan(table.fitness[0, 1]) and table.rmse[0, 0] == 0.05
    assert table.accepted.tolist() == [[1, 0, -1]]
    again = CandidateTable.from_candidates([0], cands)  # what the run evaluates equals what the file holds
    np.testing.assert_allclose(again.relative_poses, table.relative_poses, atol=1e-12)
    assert again.accepted.tolist() == [[1, 0, -1]] and np.array_equal(again.rmse, table.rmse, equal_nan=True)


@pytest.mark.parametrize(
    "text, message",
    [
        ("query_id,match_id\n0,1\n", "missing column"),
        ("query_id,rank,match_id,score,inliers\n0,2,1,0.5,\n", "rank 2 after 0"),
        ("query_id,rank,match_id,score,inliers\n0,1,x,0.5,\n", "line 2: match_id must be an integer"),
        ("query_id,rank,match_id,score,inliers\n0,1,-1,0.5,\n", "single row with -1"),
        ("query_id,rank,match_id,score,x,y\n0,1,2,0.5,1.0,\n", "give all of x,y,z,roll,pitch,yaw or none"),
        ("query_id,rank,match_id,score,fitness\n0,1,2,0.5,high\n", "line 2: fitness must be a number"),
        ("query_id,rank,match_id,score,accepted\n0,1,2,0.5,yes\n", "accepted must be 1, 0 or empty"),
    ],
)
def test_malformed_candidates_file_names_file_and_line(tmp_path, text, message):
    path = tmp_path / "candidates_x.csv"
    path.write_text(text)
    with pytest.raises(ScanFormatError, match=message) as err:
        read_candidates(path)
    assert str(path) in str(err.value)


def test_failed_run_does_not_repoint_latest(sequence_dir, tmp_path):
    good, _ = run_experiment(config(sequence_dir, tmp_path))
    latest = tmp_path / "latest"
    assert latest.resolve() == good.resolve()
    with pytest.raises(ScanDataError, match="refuses query 10"):
        run_experiment(config(sequence_dir, tmp_path, f"{__name__}:FailingScanContext"))
    assert latest.resolve() == good.resolve()
    assert (
        len([p for p in tmp_path.iterdir() if p.name.startswith("tiny_")]) == 2
    )  # the failed run's folder stays
    again, _ = run_experiment(config(sequence_dir, tmp_path))
    assert latest.resolve() == again.resolve() != good.resolve()


@pytest.mark.parametrize(
    "pipeline, extra, message",
    [
        ("subprocess:run", (), "subprocess:run is a function, not a class"),
        ("no-such-pipeline", (), "unknown pipeline 'no-such-pipeline'"),
        ("placerec.no_such_module:X", (), "cannot import module 'placerec.no_such_module'"),
        (
            "scan-context",
            ("pipelines=[{name: scan-context, params: {rings: 0}}]",),
            r"pipelines\[0\]\.params\.rings",
        ),
        ("scan-context", ("pipelines=[{name: scan-context, params: {ringz: 20}}]",), "unknown key"),
        ("scan-context", ("evaluation.mode=localize",), "localize mode on a path dataset needs"),
    ],
)
def test_a_config_that_cannot_run_leaves_no_run_folder(sequence_dir, tmp_path, pipeline, extra, message):
    cfg = config(sequence_dir, tmp_path / "results", pipeline, extra=extra)
    with pytest.raises(ConfigError, match=message):
        run_experiment(cfg)
    assert not (tmp_path / "results").exists()


def test_a_dataset_without_poses_fails_before_the_run_folder_is_made(sequence_dir, tmp_path):
    bare = tmp_path / "bare"
    (bare / "velodyne").mkdir(parents=True)
    for i in range(3):
        (bare / "velodyne" / f"{i:06d}.bin").write_bytes(
            (sequence_dir / "velodyne" / f"{i:06d}.bin").read_bytes()
        )
    with pytest.raises(ConfigError, match="has no poses"):
        run_experiment(config(bare, tmp_path / "results"))
    assert not (tmp_path / "results").exists()


def test_a_results_root_that_is_a_file_is_a_config_error(sequence_dir, tmp_path):
    (tmp_path / "results").write_text("not a folder")
    with pytest.raises(ConfigError, match="output.dir: cannot make the results folder"):
        run_experiment(config(sequence_dir, tmp_path / "results"))


def _hand_run(tmp_path, mode="loop"):
    """Poses and a config for hand-made records: scans 0..4 100 m apart, 5..9 revisit scan i-5 from 1 m on with
    a 90 deg turn, 10, 11 far away (the world of tests/test_pose_metrics.py)."""
    x = np.r_[np.arange(5) * 100.0, np.arange(5) * 100.0 + 1.0, 1000.0, 2000.0]
    poses = np.stack([_pose((xi, 0, 0), (0, 0, 90.0 if i >= 5 else 0.0)) for i, xi in enumerate(x)])
    scans = [Scan(np.zeros((1, 3)), np.zeros(1)) for _ in x]
    cfg = load_config(
        None,
        [
            "name=hand",
            f"evaluation.mode={mode}",
            "evaluation.exclusion.frames=5",
            "evaluation.top_n=2",
            f"output.dir={tmp_path}",
            "output.cache_dir=null",
            "output.progress=false",
        ],
    )
    return cfg, ListSequence(scans, poses, name="hand"), poses


def _record(label, query_ids, candidates, verify_ms=0.0):
    record = PipelineRecord(label, "Hand", "hand", {}, list(query_ids), candidates)
    for stage in STAGES:
        record.timing_ms[stage] = [verify_ms if stage == "verify" else 1.0] * len(query_ids)
    return record


def _flat(d, prefix=""):
    out = {}
    for k, v in d.items():
        out.update(_flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
    return out


def test_loop_report_holds_pose_errors_extended_precision_and_recomputes_them(tmp_path, capsys):
    cfg, seq, P = _hand_run(tmp_path)
    rel = lambda m, q: relative_pose(P[m], P[q])  # noqa: E731
    top = {  # query: (match, score, relative pose); q5, q7, q9 true, q6, q10 false; max F1 at 0.5
        5: (0, 0.9, rel(0, 5) @ _pose((0.1, 0, 0), (0, 0, 0))),
        6: (0, 0.8, _pose((0.5, 0, 0), (0, 0, 90))),
        7: (2, 0.7, rel(2, 7) @ _pose((0, 0.3, 0), (0, 0, 2))),
        9: (4, 0.5, rel(4, 9)),
        10: (1, 0.1, None),
    }
    ids = list(range(12))
    verified = [[Candidate(q, *top[q], 30, verify_ms=2.0)] if q in top else [] for q in ids]
    yaw_only = [
        [Candidate(q, top[q][0], top[q][1], _pose((0, 0, 0), (0, 0, 90)))] if q in top else [] for q in ids
    ]
    records = [_record("verified", ids, verified, 2.0), _record("yaw-only", ids, yaw_only)]
    run = make_run_dir(cfg)
    payload = report_loop(cfg, run, seq, records)
    m = payload["pipelines"]["verified"]
    assert (m["max_f1"], m["threshold_at_max_f1"]) == (pytest.approx(2 / 3), 0.5)  # 3 TP, 1 FP, 5 revisits
    assert (m["recall_at_100_precision"], m["precision_at_min_recall"], m["extended_precision"]) == (
        0.2,
        1,
        0.6,
    )
    e = m["pose_error"]
    assert (e["n_tp"], e["n_tp_with_pose"], e["n_accepted"], e["n_accepted_with_pose"]) == (3, 3, 4, 4)
    assert e["tp_translation_m"] == pytest.approx({"median": 0.1, "p95": 0.28, "max": 0.3})
    assert e["tp_rotation_deg"] == pytest.approx({"median": 0.0, "p95": 1.8, "max": 2.0}, abs=1e-6)
    assert e["accepted_max_translation_m"] == pytest.approx(100.5)  # the false closure of q6
    on_disk = json.loads((run / "metrics.json").read_text())["pipelines"]
    assert on_disk["yaw-only"]["pose_error"]["tp_translation_m"] == {"median": None, "p95": None, "max": None}
    assert on_disk["yaw-only"]["pose_error"]["accepted_max_translation_m"] is None
    assert on_disk["verified"]["time_ms"]["stages"]["verify"]["mean"] == 2.0
    for label in ("verified", "yaw-only"):
        again = recompute_loop_metrics(run, label)  # the CSV carries the poses
        want = payload["pipelines"][label]["pose_error"]
        assert _flat(again["pose_error"]) == pytest.approx(_flat(want), nan_ok=True)
        assert again["extended_precision"] == payload["pipelines"][label]["extended_precision"]
    header, rows = table_rows(payload)
    row = dict(zip(header, rows[0], strict=False))
    assert (row["R@P100"], row["EP"], row["TP t err [m] median"], row["max accepted t err [m]"]) == (
        "0.200",
        "0.600",
        "0.100",
        "100.500",
    )
    assert (
        row["verify mean"] == "2.000"
        and dict(zip(header, rows[1], strict=False))["TP t err [m] median"] == "-"
    )
    page = (run / "index.html").read_text()
    assert "TP t err [m] median" in page and "100.500" in page
    print_table(payload, "hand [loop]", wide=True)
    printed = capsys.readouterr().out
    assert "hand [loop]" in printed and "[m]" in printed and "100.500" in printed  # units are no rich markup
    assert "retrieval within 25 m, same- / reverse-direction revisits" in printed and "R@1% 25 m" in page


def test_localize_counts_success_from_the_estimated_pose_and_labels_retrieval(tmp_path):
    cfg, seq, P = _hand_run(tmp_path, "localize")
    map_seq = ListSequence([seq[i] for i in range(5)], P[:5], name="map")
    query_seq = ListSequence([seq[i] for i in range(5, 9)], P[5:9], name="queries")  # 1 m from map scan i-5
    rel = lambda m, q: relative_pose(P[m], P[q + 5])  # noqa: E731
    posed = [
        [Candidate(0, 0, 1.0, rel(0, 0) @ _pose((0.2, 0, 0), (0, 0, 3)))],  # 0.2 m, 3 deg: fine
        [Candidate(1, 1, 1.0, rel(1, 1) @ _pose((0, 2.0, 0), (0, 0, 0)))],  # 2 m: success, not fine
        [Candidate(2, 2, 1.0, rel(2, 2) @ _pose((5.0, 0, 0), (0, 0, 0)))],  # the right place, but 5 m off
        [Candidate(3, 3, 1.0, None)],  # the right place without a pose: no estimate
    ]
    retrieval = [[Candidate(q, q, 1.0, _pose((0, 0, 0), (0, 0, 90)))] for q in range(4)]  # yaw only
    records = [_record("posed", range(4), posed), _record("retrieval", range(4), retrieval)]
    run = make_run_dir(cfg)
    payload = report_localize(cfg, run, map_seq, query_seq, records)
    p, r = payload["pipelines"]["posed"], payload["pipelines"]["retrieval"]
    assert (p["success_basis"], p["n_success"], p["n_no_estimate"], p["fine_success_rate"]) == (
        "pose",
        2,
        1,
        0.25,
    )
    assert p["median_error"] == pytest.approx(2.0)
    assert (r["success_basis"], r["n_success"], r["median_error"]) == ("retrieval", 4, pytest.approx(1.0))
    assert np.isnan(r["fine_success_rate"])
    header, rows = table_rows(payload)
    assert dict(zip(header, rows[1], strict=False))["basis"] == "retrieval"


def test_split_verify_time_moves_verification_out_of_the_query_stage():
    timing = {"query": 10.0}
    split_verify_time([Candidate(0, 1, 0.5, verify_ms=3.0), Candidate(0, 2, 0.4)], timing)
    assert timing == {"query": 7.0, "verify": 3.0}
    timing = {"query": 10.0}
    split_verify_time([Candidate(0, 1, 0.5)], timing)
    assert timing == {"query": 10.0}


class TimedScanContext(ScanContext):
    """Scan Context whose candidates say they took 1.5 ms of verification each."""

    def query_description(self, description, k=1, max_id=None, query_id=-1):
        cands = super().query_description(description, k=k, max_id=max_id, query_id=query_id)
        return [replace(c, verify_ms=1.5) for c in cands]


def test_the_run_reports_a_verify_stage(sequence_dir, tmp_path):
    run, payload = run_experiment(config(sequence_dir, tmp_path, f"{__name__}:TimedScanContext"))
    record = payload["pipelines"][f"{__name__}:TimedScanContext"]
    table = read_candidates(run / f"candidates_{__name__}_TimedScanContext.csv")
    per_scan = 1.5 * (table.match_ids >= 0).sum(axis=1)
    stages = record["time_ms"]["stages"]
    assert stages["verify"]["mean"] == pytest.approx(per_scan.mean())
    assert stages["verify"]["max"] == pytest.approx(per_scan.max())


def test_localisation_counts_only_accepted_answers():
    """A rejected top candidate is no answer, never a success, even when it lies next to the truth; an accepted
    one beyond the success distance is a wrong answer."""
    from placerec.eval import localization_metrics
    from placerec.experiment.report import localize_estimates

    map_poses = np.stack([np.eye(4)] * 3)
    map_poses[:, 0, 3] = [0.0, 10.0, 20.0]
    truth = np.stack([np.eye(4)] * 5)
    truth[:, 0, 3] = [0.5, 10.5, 0.5, 5.0, 0.5]
    near = np.eye(4)
    near[0, 3] = 0.5

    def cand(q, m, accepted, score):
        return Candidate(q, m, score, near, 20, accepted=accepted)

    rows = [
        [cand(0, 0, True, 0.9)],  # accepted, 0 m off: localised
        [cand(1, 1, False, 0.1)],  # rejected, though right: no answer
        [cand(2, 2, True, 0.8)],  # accepted, 20 m off: wrong
        [],  # nothing: no answer
        [cand(4, 0, None, 0.5)],  # a pipeline that verifies, this candidate unverified: no answer
    ]
    table = CandidateTable.from_candidates([0, 1, 2, 3, 4], rows)
    estimates, basis, rule = localize_estimates(table, map_poses)
    assert (basis, rule) == ("pose", "accepted")
    m = localization_metrics(estimates, truth, 3.0, basis=basis, answer_rule=rule)
    s = m.summary()
    assert (s["n_success"], s["n_no_estimate"], s["n_wrong"]) == (1, 3, 1)
    assert s["success_rate"] == 0.2 and s["no_answer_rate"] == 0.6 and s["wrong_rate"] == 0.2


def test_localisation_without_verification_answers_with_the_top_candidate():
    """No candidate carries an acceptance (retrieval only): the top candidate is the answer, scored on the
    matched map scan's position."""
    from placerec.eval import localization_metrics
    from placerec.experiment.report import localize_estimates

    map_poses = np.stack([np.eye(4)] * 2)
    map_poses[:, 0, 3] = [0.0, 10.0]
    truth = np.stack([np.eye(4)] * 3)
    truth[:, 0, 3] = [1.0, 1.0, 1.0]
    rows = [[Candidate(0, 0, 0.9)], [Candidate(1, 1, 0.9)], []]
    estimates, basis, rule = localize_estimates(CandidateTable.from_candidates([0, 1, 2], rows), map_poses)
    assert (basis, rule) == ("retrieval", "top")
    m = localization_metrics(estimates, truth, 3.0, basis=basis, answer_rule=rule)
    assert (m.n_success, m.n_wrong, m.n_no_estimate) == (1, 1, 1)


def test_localize_draws_the_configured_query_draw():
    """``evaluation.localize.draw`` reaches the simulator split (another draw, other query poses, the same map);
    with map/queries datasets it is an error, not ignored."""
    from placerec.experiment.runner import localize_sequences
    from placerec.sim import make_localization_split

    base = ["evaluation.mode=localize", "evaluation.localize.n_queries=3", "dataset.simulator.n_scans=40"]
    maps, queries = {}, {}
    for draw in (0, 2):
        maps[draw], queries[draw] = localize_sequences(
            load_config(None, [*base, f"evaluation.localize.draw={draw}"])
        )
    split = make_localization_split("town", "vlp16", 0, n_queries=3, n_map=40, conditions=("gator",), draw=2)
    np.testing.assert_array_equal(queries[2].poses, split.queries["gator"].poses)
    assert not np.allclose(queries[0].poses[:, :3, 3], queries[2].poses[:, :3, 3])
    np.testing.assert_array_equal(maps[0].poses, maps[2].poses)
    paths = [
        "evaluation.localize.map={source: path, path: x}",
        "evaluation.localize.queries={source: path, path: x}",
    ]
    with pytest.raises(ConfigError, match="evaluation.localize.draw"):
        localize_sequences(load_config(None, [*base, *paths, "evaluation.localize.draw=2"]))


@pytest.mark.filterwarnings("ignore:Gimbal lock")
def test_poses_to_xyzrpy_is_pose_to_xyzrpy_of_each():
    """The candidates file converts every pose at once: the same numbers as one pose at a time (and as SciPy's
    own per-pose conversion), gimbal lock and identity included."""
    from placerec.experiment.candidates import pose_to_xyzrpy, poses_to_xyzrpy

    rng = np.random.default_rng(3)
    P = np.tile(np.eye(4), (200, 1, 1))
    P[:, :3, :3] = Rotation.random(200, random_state=4).as_matrix()
    P[:, :3, 3] = rng.normal(0, 20, (200, 3))
    P[0, :3, :3] = np.eye(3)
    P[1, :3, :3] = Rotation.from_euler("xyz", [10, 90, 30], degrees=True).as_matrix()
    each = np.array(
        [np.r_[p[:3, 3], Rotation.from_matrix(p[:3, :3]).as_euler("xyz", degrees=True)] for p in P]
    )
    assert poses_to_xyzrpy(P).tobytes() == each.tobytes()
    assert pose_to_xyzrpy(P[5]).tobytes() == each[5].tobytes()
    assert poses_to_xyzrpy(np.zeros((0, 4, 4))).shape == (0, 6)


def test_the_odometry_gate_judges_a_runs_candidates_and_leaves_its_files_raw(sequence_dir, tmp_path):
    run, plain = run_experiment(config(sequence_dir, tmp_path / "plain"))
    gate = "evaluation.odometry_gate={bounds: {metres: 0.001, per_metre: 0, degrees: 0.001, degrees_per_metre: 0}}"
    run_default, default = run_experiment(
        config(sequence_dir, tmp_path / "d", extra=("evaluation.odometry_gate={}",))
    )
    run_tight, tight = run_experiment(config(sequence_dir, tmp_path / "t", extra=(gate,)))
    p, d, t = (x["pipelines"]["scan-context"] for x in (plain, default, tight))
    # the loop's true closures agree with the drifting odometry: only wrong lower-ranked candidates are refused
    assert "odometry_gate_refused" not in p and d["odometry_gate_refused"] > 0
    assert (d["recall_at_100_precision"], d["max_f1"]) == (p["recall_at_100_precision"], p["max_f1"])
    # bounds no closure can meet: every candidate with a pose refused, no answer left at the operating threshold
    assert p["operating"]["n_accepted"] > 0 and t["operating"]["n_accepted"] == 0
    assert t["operating"]["missed"]["below_threshold"] == p["operating"]["n_revisits"]
    again = recompute_loop_metrics(run_tight, "scan-context")  # from the folder alone, judged with its gate
    assert (
        again["operating"]["n_accepted"] == 0 and again["odometry_gate_refused"] == t["odometry_gate_refused"]
    )
    for folder in (run_default, run_tight):  # the candidates file is the run's, the gate only judges it
        name = "candidates_scan-context.csv"
        assert (folder / name).read_text() == (run / name).read_text()
