"""What `run_experiment` leaves on disk: every candidate in the CSV, and ``latest`` only on a complete run."""

import csv

import numpy as np
import pytest

from placerec.baselines.scan_context import ScanContext
from placerec.config import load_config
from placerec.errors import ConfigError, ScanDataError, ScanFormatError
from placerec.eval import ExclusionWindow, loop_ground_truth
from placerec.experiment import run_experiment
from placerec.experiment.candidates import read_candidates, write_candidates
from placerec.experiment.report import recompute_loop_metrics
from placerec.io import read_poses, write_kitti_poses
from placerec.types import Candidate

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
    assert list(rows[0]) == ["query_id", "rank", "match_id", "score", "inliers"]
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
    q, m, s = read_candidates(path).top1()
    assert q.tolist() == [0, 1] and m.tolist() == [-1, 0] and np.isnan(s[0]) and s[1] == 0.75


@pytest.mark.parametrize(
    "text, message",
    [
        ("query_id,match_id\n0,1\n", "missing column"),
        ("query_id,rank,match_id,score,inliers\n0,2,1,0.5,\n", "rank 2 after 0"),
        ("query_id,rank,match_id,score,inliers\n0,1,x,0.5,\n", "line 2: match_id must be an integer"),
        ("query_id,rank,match_id,score,inliers\n0,1,-1,0.5,\n", "single row with -1"),
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
