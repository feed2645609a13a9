"""The runner, the loop-closure detector and the report on a synthetic 'pole world' (no simulator needed)."""

import json

import numpy as np
import pytest

from placerec.config import load_config
from placerec.errors import ScanDataError
from placerec.experiment.report import recompute_loop_metrics, report_loop
from placerec.experiment.run_folder import make_run_dir
from placerec.experiment.runner import run_loop
from placerec.loop_closure import LoopClosureDetector
from placerec.recognizer import make_pipeline
from placerec.types import ListSequence, Scan


def pole_world_sequence(n_loop=120, n_revisit=50, seed=0):
    """A circle driven once plus a partial second pass 1 m off; scans see random poles within 60 m."""
    rng = np.random.default_rng(seed)
    world = np.c_[rng.uniform(-150, 150, (3000, 2)), rng.uniform(0.5, 8, 3000)]
    t = np.linspace(0, 2 * np.pi, n_loop, endpoint=False)
    xy = np.c_[60 * np.cos(t), 60 * np.sin(t)]
    xy = np.r_[xy, xy[:n_revisit] + 1.0]
    poses = np.tile(np.eye(4), (len(xy), 1, 1))
    poses[:, :2, 3] = xy
    scans = []
    for p in poses:
        d = world[:, :2] - p[:2, 3]
        near = np.linalg.norm(d, axis=1) < 60
        xyz = np.concatenate([np.c_[d[near], world[near, 2] * k / 7 - 1.8] for k in range(8)])
        xyz += rng.normal(0, 0.05, xyz.shape)
        scans.append(Scan(xyz, np.ones(len(xyz))))
    return ListSequence(scans, poses, np.arange(len(scans)) * 0.1, name="poles")


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory):
    out = tmp_path_factory.mktemp("results")
    cfg = load_config(
        None,
        [
            f"output.dir={out}",
            "output.cache_dir=null",
            "output.progress=false",
            "evaluation.exclusion.frames=50",
            "evaluation.top_n=3",
        ],
    )
    seq, records = run_loop(cfg, pole_world_sequence())
    run = make_run_dir(cfg)
    payload = report_loop(cfg, run, seq, records)
    return run, payload


def test_outputs_exist(run_folder):
    run, _ = run_folder
    for name in (
        "config.yaml",
        "metrics.json",
        "candidates_scan-context.csv",
        "poses.txt",
        "pr_curves.png",
        "trajectory_scan-context.png",
        "timing.png",
        "index.html",
    ):
        assert (run / name).is_file(), name
    assert (run.parent / "latest").resolve() == run.resolve()


def test_scan_context_finds_revisits_and_metrics_recompute(run_folder):
    run, payload = run_folder
    m = payload["pipelines"]["scan-context"]
    assert m["n_revisits"] >= 40 and m["max_f1"] > 0.8
    for key in ("max_f1", "precision_at_max_f1", "recall_at_max_f1", "auc", "recall_at_1", "n_queries"):
        assert key in m
    assert set(m["time_ms"]) >= {"mean", "median", "p95"}
    again = recompute_loop_metrics(run, "scan-context")
    for key in ("max_f1", "precision_at_max_f1", "recall_at_max_f1", "recall_at_1", "n_revisits"):
        assert again[key] == pytest.approx(m[key])
    assert (
        json.loads((run / "metrics.json").read_text())["pipelines"]["scan-context"]["max_f1"] == m["max_f1"]
    )


def test_detector_exclusion_window_and_threshold():
    seq = pole_world_sequence(n_loop=60, n_revisit=20)
    det = LoopClosureDetector(make_pipeline("scan-context"), threshold=0.5, exclusion_frames=50)
    found = []
    for i in range(len(seq)):
        accepted = det.process(seq[i], pose=seq.poses[i])
        assert all(c.match_id <= i - 50 and c.score >= 0.5 for c in accepted)
        assert all(c.match_id <= i - 50 for c in det.last_candidates)
        found += accepted
    assert len(found) >= 10 and all(c.query_id >= 60 for c in found)
    assert all(c.relative_pose.shape == (4, 4) for c in found)


def test_detector_metres_and_seconds_windows_need_inputs():
    det = LoopClosureDetector(
        make_pipeline("scan-context"), threshold=0.0, exclusion_frames=0, exclusion_metres=10
    )
    scan = Scan(np.random.default_rng(0).normal(size=(100, 3)) * 10, np.ones(100))
    with pytest.raises(ScanDataError, match="pose"):
        det.process(scan)
    det = LoopClosureDetector(
        make_pipeline("scan-context"), threshold=0.0, exclusion_frames=0, exclusion_seconds=25, k=3
    )
    with pytest.raises(ScanDataError, match="timestamp"):
        det.process(scan)
    # 1 m steps, 10 s apart: with a 25 s window scan 3 may match scans 0 only
    for i in range(4):
        pose = np.eye(4)
        pose[0, 3] = i
        det.process(scan, pose=pose, timestamp=10.0 * i)
    assert {c.match_id for c in det.last_candidates} == {0}


def test_description_cache_key_follows_the_data(tmp_path):
    """Cached descriptions never outlive their data: the key changes with the files, the calibration table and
    the simulator's code, not only with the config."""
    from placerec.config import DatasetConfig
    from placerec.experiment.datasets import dataset_fingerprint
    from placerec.experiment.runner import _data_key

    folder = tmp_path / "scans"
    folder.mkdir()
    (folder / "000000.bin").write_bytes(np.zeros(8, np.float32).tobytes())
    cfg = load_config(None, ["dataset.source=path", f"dataset.path={folder}"])
    before = _data_key(cfg, cfg.dataset)
    assert _data_key(cfg, cfg.dataset) == before  # stable
    (folder / "000000.bin").write_bytes(np.ones(12, np.float32).tobytes())  # the scan was replaced
    after = _data_key(cfg, cfg.dataset)
    assert after != before
    table = tmp_path / "calib.npz"
    table.write_bytes(b"x")
    with_calib = load_config(
        None, ["dataset.source=path", f"dataset.path={folder}", f"preprocess.intensity.calibration={table}"]
    )
    key = _data_key(with_calib, with_calib.dataset)
    table.write_bytes(b"xy")
    assert _data_key(with_calib, with_calib.dataset) != key
    sim = dataset_fingerprint(DatasetConfig())
    assert {"render.py", "textures.py", "intensity.py", "routes.py"} <= {name for name, _ in sim}
