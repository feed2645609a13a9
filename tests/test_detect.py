"""`placerec detect`: loop closure on a sequence on disk in one command, with and without poses; bad input; Ctrl-C;
the real Ouster revisit pair."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from placerec.cli import app
from placerec.detect import CSV_COLUMNS, DEFAULT_PIPELINE
from placerec.experiment.candidates import xyzrpy_to_pose
from placerec.recognizer import PIPELINES
from placerec.sim import SimulatedSequence, write_kitti_sequence
from placerec.types import ListSequence, rigid_problem

PASS = 5  # scans a pass; the route is driven twice, 1 m spacing, so query i revisits scan i - PASS


@pytest.fixture(scope="module")
def folders(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The same 5 m of town street driven twice (one world, two noise seeds), OS1-64, written as KITTI folders:
    one with poses.txt, one without."""
    root = tmp_path_factory.mktemp("detect")
    passes = [SimulatedSequence("town", "os1-64", n_scans=PASS, seed=s, world_seed=0) for s in (1, 2)]
    scans = [p[i] for p in passes for i in range(PASS)]
    poses = np.concatenate([p.poses for p in passes])
    seq = ListSequence(scans, poses, np.arange(2 * PASS) * 0.1, name="revisit")
    with_poses = write_kitti_sequence(seq, root / "with_poses", progress=False)
    without = root / "without_poses"
    shutil.copytree(with_poses, without)
    (without / "poses.txt").unlink()
    return with_poses, without


def _detect(*args: str) -> tuple[int, str]:
    result = CliRunner().invoke(app, ["detect", *args])
    return result.exit_code, result.output


def _read(out: Path) -> tuple[list[dict[str, str]], dict]:
    with (out / "closures.csv").open() as fh:
        reader = csv.DictReader(fh)
        assert tuple(reader.fieldnames or ()) == CSV_COLUMNS
        rows = list(reader)
    return rows, json.loads((out / "closures.json").read_text())


def _check_closures(rows: list[dict[str, str]], closures: list[dict]) -> None:
    """The CSV and the JSON agree; every T_match_query is a rigid 4x4 that its x y z roll pitch yaw describe; the
    match is the scan the first pass took at the query's place (give or take one)."""
    assert len(rows) == len(closures) > 0
    for row, c in zip(rows, closures, strict=True):
        assert int(row["query_id"]) == c["query_id"] and int(row["match_id"]) == c["match_id"]
        assert c["query_file"] == f"{c['query_id']:06d}.bin" and row["match_file"] == c["match_file"]
        assert abs(c["query_id"] - PASS - c["match_id"]) <= 1
        T = np.array(c["T_match_query"])
        assert T.shape == (4, 4) and rigid_problem(T[None]) is None
        assert np.allclose(T[3], [0, 0, 0, 1]) and np.isclose(np.linalg.det(T[:3, :3]), 1.0)
        assert np.allclose(np.array([float(row[f"T{r}{k}"]) for r in range(4) for k in range(4)]), T.ravel())
        xyzrpy = [float(row[k]) for k in ("x", "y", "z", "roll", "pitch", "yaw")]
        assert np.allclose(xyzrpy_to_pose(xyzrpy), T, atol=1e-9)
        assert np.linalg.norm(T[:3, 3]) < 2.0  # the same place, one scan apart at most
        assert c["score"] >= PIPELINES[DEFAULT_PIPELINE].threshold  # type: ignore[operator]


def test_with_poses_the_revisits_are_found_drawn_and_scored(folders, tmp_path):
    code, output = _detect(str(folders[0]), "--exclusion-frames", str(PASS), "--out", str(tmp_path / "o"))
    assert code == 0, output
    rows, summary = _read(tmp_path / "o")
    _check_closures(rows, summary["closures"])
    assert all(row["true"] == "True" for row in rows)
    assert summary["pipeline"] == DEFAULT_PIPELINE and summary["poses"] == "ground truth"
    scored = summary["scored"]
    assert scored["precision"] == 1.0 and scored["n_revisits"] == PASS
    assert scored["revisits_found"] == len({r["query_id"] for r in summary["closures"]}) >= 3
    assert (tmp_path / "o" / "closures.png").stat().st_size > 0
    assert "precision 1.00" in output and f"revisits found {scored['revisits_found']} of {PASS}" in output
    assert all(len(line) <= 100 for line in output.splitlines() if not line.startswith("  /"))


def test_without_poses_closures_are_written_not_scored_and_drawn_by_scan_index(folders, tmp_path):
    code, output = _detect(str(folders[1]), "--exclusion-frames", str(PASS), "--out", str(tmp_path / "o"))
    assert code == 0, output
    rows, summary = _read(tmp_path / "o")
    _check_closures(rows, summary["closures"])
    assert all(row["true"] == "" for row in rows) and summary["scored"] is None
    assert (tmp_path / "o" / "closures.png").stat().st_size > 0  # (query, match) scan indices
    assert "closures not scored" in output


def test_kiss_icp_odometry_draws_the_closures_without_scoring_them(folders, tmp_path):
    out = tmp_path / "o"
    args = (
        "--exclusion-frames",
        str(PASS),
        "--odometry",
        "kiss-icp",
        "--pipeline",
        "orb-hbst",
        "--out",
        str(out),
    )
    code, output = _detect(str(folders[1]), *args)
    assert code == 0, output
    rows, summary = _read(out)
    assert rows and summary["poses"] == "kiss-icp" and summary["scored"] is None
    assert (out / "closures.png").stat().st_size > 0 and "closures.png" in output


def test_the_default_folder_and_window(folders, tmp_path, monkeypatch):
    """Default --out: results/detect_<sequence>_<timestamp>; the default window is 120 frames, or half the scans of
    a shorter sequence (here 10 scans: 5, so the second pass is queried against the first); a window longer than
    the sequence queries nothing and says so."""
    from placerec.detect import exclusion_frames

    assert (exclusion_frames(None, 2), exclusion_frames(None, 10), exclusion_frames(None, 10_000)) == (
        1,
        5,
        120,
    )
    assert exclusion_frames(0, 10) == 0
    monkeypatch.chdir(tmp_path)
    code, output = _detect(str(folders[1]), "--pipeline", "orb-hbst")
    assert code == 0, output
    (run,) = (tmp_path / "results").glob("detect_without_poses_*")
    summary = json.loads((run / "closures.json").read_text())
    assert summary["exclusion"]["frames"] == PASS and summary["n_closures"] >= PASS - 1
    code, output = _detect(str(folders[1]), "--exclusion-frames", "1000", "--out", str(tmp_path / "o"))
    assert code == 0 and "nothing queried" in output


@pytest.mark.parametrize(
    ("args", "named"),
    [
        (["--pipeline", "no-such"], "--pipeline"),
        (["--pipeline", "ishot-votes"], "--threshold"),
        (["--exclusion-frames", "-1"], "--exclusion-frames"),
        (["--odometry", "gps"], "--odometry"),
        (["--exclusion-metres", "5"], "--exclusion-metres"),
    ],
)
def test_bad_options_are_errors_naming_them(folders, tmp_path, monkeypatch, args, named):
    monkeypatch.chdir(tmp_path)
    code, output = _detect(str(folders[1]), *args)
    assert code == 2 and named in output, output
    assert not (tmp_path / "results").exists()  # checked before a results folder is made


def test_a_source_that_is_no_sequence_or_holds_no_scans_is_an_error_naming_it(folders, tmp_path):
    (tmp_path / "empty").mkdir()
    for source in (folders[1] / "velodyne" / "000000.bin", tmp_path / "empty", tmp_path / "missing"):
        code, output = _detect(str(source))
        assert code == 2 and output.startswith("error: SOURCE"), output


def test_ctrl_c_removes_the_unfinished_folder(folders, tmp_path, monkeypatch):
    from placerec.loop_closure import LoopClosureDetector

    def interrupt(self, *args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(LoopClosureDetector, "process", interrupt)
    monkeypatch.chdir(tmp_path)
    code, output = _detect(str(folders[1]), "--pipeline", "scan-context")
    assert code == 130 and "interrupted" in output
    assert list((tmp_path / "results").iterdir()) == []


def test_the_real_ouster_revisit_pair_in_one_command(real_data, tmp_path):
    """Two MulRan OS1-64 scans (read as KITTI-style x y z intensity), different sweeps: every verified pipeline and
    Scan Context close the pair (scores ~0.52), MapClosures does not (below its 15 inliers); the registration says
    the two were taken at (nearly) the same pose (~1.5 cm, < 0.1 deg)."""
    pair = real_data / "ouster_os1_64_revisit_pair"
    code, output = _detect(str(pair), "--out", str(tmp_path / "o"))  # no option: a 2-scan window of 1
    assert code == 0, output
    rows, summary = _read(tmp_path / "o")
    (c,) = summary["closures"]
    assert (c["query_id"], c["match_id"]) == (1, 0)
    assert (c["query_file"], c["match_file"]) == ("32line_2.bin", "32line_1.bin")
    T = np.array(c["T_match_query"])
    assert rigid_problem(T[None]) is None and np.linalg.norm(T[:3, 3]) < 0.1
    assert "1 closure" in output and "not scored" in output


def test_the_readme_api_snippet_runs_on_a_sequence_without_poses(folders: tuple[Path, Path]) -> None:
    """The README's Python API example, run as written on a folder without poses (#32: it crashed on
    ``seq.poses[i]``)."""
    import re

    readme = (Path(__file__).parent.parent / "README.md").read_text()
    api = readme[readme.index("## Python API") :]
    code = re.search(r"```python\n(.*?)```", api, re.S)
    assert code is not None
    snippet = code.group(1).replace('"path/to/sequence"', repr(str(folders[1])))
    assert "path/to/sequence" not in snippet and "seq.poses[i]" in snippet
    namespace: dict = {}
    exec(compile(snippet, "README.md", "exec"), namespace)  # noqa: S102 - our own README
    assert namespace["seq"].poses is None and namespace["detector"].n_processed == len(namespace["seq"])
