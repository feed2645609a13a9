"""The friction a new user meets in the first hour (issue #32), each reproduced and checked fixed."""

from __future__ import annotations

import re

import pytest
import yaml
from typer.testing import CliRunner

from placerec.cli import app
from placerec.config import load_config
from placerec.errors import ConfigError

runner = CliRunner()

TWO_PIPELINES = {
    "name": "first-hour",
    "pipelines": [
        {"name": "scan-context"},
        {"name": "orb-hbst", "label": "orb"},
    ],
}


@pytest.fixture
def two_pipelines(tmp_path):
    path = tmp_path / "two.yaml"
    path.write_text(yaml.safe_dump(TWO_PIPELINES))
    return path


# --- 1. pipeline parameters from the command line ---------------------------------------------------------------


def test_set_pipeline_params_by_index_label_and_name(two_pipelines):
    cfg = load_config(
        two_pipelines,
        [
            "pipelines.0.params.num_rings=10",
            "pipelines.orb.params.feature_params.nfeatures=500",
            "pipelines.orb-hbst.threshold=0.25",
            "pipelines.scan-context.label=sc",
        ],
    )
    assert cfg.pipelines[0].params == {"num_rings": 10} and cfg.pipelines[0].label == "sc"
    assert cfg.pipelines[1].params == {"feature_params": {"nfeatures": 500}}
    assert cfg.pipelines[1].threshold == 0.25


def test_set_pipeline_params_on_the_default_pipelines():
    cfg = load_config(None, ["pipelines.0.params.num_rings=10"])
    assert [(p.name, p.params) for p in cfg.pipelines] == [("scan-context", {"num_rings": 10})]


@pytest.mark.parametrize(
    ("override", "message"),
    [
        (
            "pipelines.2.params.num_rings=10",
            r"'pipelines\.2': no item 2; the list holds 0: scan-context, 1: orb",
        ),
        ("pipelines.sift.params.x=1", r"'pipelines\.sift': no item labelled or named 'sift'.*1: orb"),
        ("pipelines.0.name.x=1", r"'pipelines\.0\.name' is not a section"),
    ],
)
def test_set_pipeline_bad_selector(two_pipelines, override, message):
    with pytest.raises(ConfigError, match=message):
        load_config(two_pipelines, [override])


def test_set_pipeline_same_name_twice_needs_index_or_label(tmp_path):
    path = tmp_path / "twice.yaml"
    path.write_text(
        yaml.safe_dump(
            {"pipelines": [{"name": "scan-context", "label": "a"}, {"name": "scan-context", "label": "b"}]}
        )
    )
    with pytest.raises(ConfigError, match="2 items are named 'scan-context'"):
        load_config(path, ["pipelines.scan-context.threshold=0.1"])
    assert load_config(path, ["pipelines.b.threshold=0.1"]).pipelines[1].threshold == 0.1


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("pipelines.0.params.nfeatures=500", r"pipelines\[0\]\.params\.nfeatures: unknown key; allowed keys"),
        (
            "pipelines.orb.params.feature_params.nfeatures=abc",
            r"pipelines\[1\]\.params\.feature_params\.nfeatures: .*integer",
        ),
        (
            "pipelines.orb.params.feature_params.nfeatures=-3",
            r"pipelines\[1\]\.params\.feature_params\.nfeatures: .*greater than 0",
        ),
    ],
)
def test_run_validates_pipeline_overrides_like_yaml(two_pipelines, tmp_path, override, message):
    out = tmp_path / "results"
    result = runner.invoke(app, ["run", str(two_pipelines), "--out", str(out), "--set", override])
    assert result.exit_code == 2, result.output
    assert result.output.startswith("error:") and len(result.output.strip().splitlines()) == 1
    assert re.search(message, result.output), result.output
    assert not out.exists()  # rejected before a results folder is made


def test_slam_pipeline_overrides_still_work():
    from placerec.slam_app.config import load_slam_config

    cfg = load_slam_config(
        None, ["loops.pipeline.params.feature_params.nfeatures=500", "loops.pipeline.threshold=0.2"]
    )
    assert cfg.loops.pipeline.params == {"feature_params": {"nfeatures": 500}}
    assert cfg.loops.pipeline.threshold == 0.2


# --- 2. Ctrl-C during `placerec run` ------------------------------------------------------------------------------


def _small_run(tmp_path):
    config = {
        "name": "ctrl-c",
        "dataset": {"simulator": {"world": "town", "sensor": "vlp16", "n_scans": 6}},
        "pipelines": [
            {"name": "scan-context", "label": "a"},
            {"name": "scan-context", "label": "b", "params": {"num_rings": 10}},
        ],
        "evaluation": {"exclusion": {"frames": 2}, "pose_truth": {"enabled": False}},
        "output": {"dir": str(tmp_path / "results"), "figures": False, "cache_dir": None, "progress": False},
    }
    path = tmp_path / "ctrl_c.yaml"
    path.write_text(yaml.safe_dump(config))
    return path, tmp_path / "results"


def test_ctrl_c_during_the_pipelines_leaves_no_folder(tmp_path, monkeypatch, warm_kernels):
    from placerec.baselines.scan_context import ScanContext

    calls = []
    describe = ScanContext.describe

    def interrupted(self, scan):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return describe(self, scan)

    monkeypatch.setattr(ScanContext, "describe", interrupted)
    config, results = _small_run(tmp_path)
    result = runner.invoke(app, ["run", str(config)])
    assert result.exit_code == 130, result.output
    assert result.output.strip().splitlines()[-1] == "interrupted"
    assert list(results.iterdir()) == []  # the folder holding only config.yaml is gone; no latest


def test_ctrl_c_after_some_results_marks_the_folder_incomplete(tmp_path, monkeypatch, warm_kernels):
    import placerec.experiment.report as report

    calls = []
    summary = report.loop_summary

    def interrupted(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:  # pipeline a reported, b's candidates written: interrupted while judging b
            raise KeyboardInterrupt
        return summary(*args, **kwargs)

    monkeypatch.setattr(report, "loop_summary", interrupted)
    config, results = _small_run(tmp_path)
    result = runner.invoke(app, ["run", str(config)])
    assert result.exit_code == 130, result.output
    assert result.output.strip().splitlines()[-1] == "interrupted"
    (run,) = results.iterdir()  # no latest link
    assert run.name.startswith("ctrl-c_")
    assert (run / "INCOMPLETE").read_text() == (
        "interrupted before the report was complete; pipelines with results: a, b; without: none\n"
    )
    assert not (run / "metrics.json").exists()


def test_an_interrupted_run_keeps_latest_where_it_was(tmp_path):
    from placerec.experiment.run_folder import INCOMPLETE, abandon_run, point_latest

    done, stopped, empty = (tmp_path / n for n in ("done", "stopped", "empty"))
    for run in (done, stopped, empty):
        run.mkdir()
        (run / "config.yaml").write_text("name: x\n")
    point_latest(done)
    (stopped / "candidates_a.csv").write_text("")
    assert abandon_run(stopped, ["a", "b c"]) == stopped / INCOMPLETE
    assert "with results: a; without: b c" in (stopped / INCOMPLETE).read_text()
    assert abandon_run(empty, ["a"]) is None and not empty.exists()
    assert abandon_run(done, ["a"]) is None and done.exists() and not (done / INCOMPLETE).exists()
    assert (tmp_path / "latest").resolve() == done.resolve()


# --- 3. the README says where `placerec` comes from ---------------------------------------------------------------


def test_readme_says_how_to_get_placerec_on_the_path():
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    readme = (root / "README.md").read_text()
    first_command = re.search(r"```bash\n(?:[^`]*\n)?placerec ", readme).start()  # the first block running it
    before = readme[:first_command]
    assert "source .venv/bin/activate" in before and ".venv/bin/placerec" in before
    pyproject = (root / "pyproject.toml").read_text()
    section = pyproject.split("[project.optional-dependencies]")[1].split("\n[")[0]
    extras = re.findall(r"^([a-z0-9-]+) = \[", section, flags=re.M)
    assert "slam" in extras and "dev" in extras
    install = before[before.index("pip install -e") :]
    for extra in extras:
        assert f"`{extra}`" in install or extra in install.split("]")[0], extra


# --- 4a. an unknown scan suffix names the command line's option too -----------------------------------------------


def test_unknown_suffix_names_the_option_and_the_keyword(tmp_path):
    path = tmp_path / "scan.xyz"
    path.write_text("1 2 3\n")
    result = runner.invoke(app, ["info", str(path)])
    assert result.exit_code == 2, result.output
    line = result.output.strip()
    assert "--format on the command line, format= in Python" in line
    assert ".pcap" in line and "'pcd'" in line


def test_bin_that_is_neither_format_names_the_option(tmp_path):
    import numpy as np

    path = tmp_path / "garbage.bin"
    rec = np.full((500, 4), 0.5, "<f4")
    rec[:, :3] = 3e6  # no LiDAR point, and no NCLT laser ids
    rec.tofile(path)
    result = runner.invoke(app, ["info", str(path)])
    assert result.exit_code == 2 and "--format kitti or --format nclt" in result.output


# --- 4b. swapped or wrong arguments to Recognizer.add / query -----------------------------------------------------


def _scan():
    import numpy as np

    from placerec.types import Scan

    rng = np.random.default_rng(0)
    return Scan((rng.normal(size=(2000, 3)) * 10).astype("f4"), rng.random(2000).astype("f4"))


@pytest.mark.parametrize(
    ("call", "error", "message"),
    [
        (
            lambda rec, s: rec.add(s, 0),
            "ScanDataError",
            r"scan-context\.add: argument 'scan' must be a placerec\.types\.Scan.*got int 0; the arguments look swapped",
        ),
        (
            lambda rec, s: rec.add(0, "scan.bin"),
            "ScanDataError",
            r"argument 'scan' must be a placerec\.types\.Scan.*got str",
        ),
        (
            lambda rec, s: rec.add(1.5, s),
            "ScanDataError",
            r"argument 'scan_id' must be an integer, got float 1\.5",
        ),
        (
            lambda rec, s: rec.query(0),
            "ScanDataError",
            r"scan-context\.query: argument 'scan' must be a placerec\.types\.Scan",
        ),
        (lambda rec, s: rec.query(s, k="3"), "ConfigError", r"argument 'k' must be an integer, got str"),
        (lambda rec, s: rec.query(s, max_id=2.0), "ConfigError", r"argument 'max_id' must be an integer"),
        (
            lambda rec, s: rec.query(s, query_id=None),
            "ConfigError",
            r"argument 'query_id' must be an integer",
        ),
    ],
)
def test_recognizer_entry_points_check_their_arguments(call, error, message):
    import placerec.errors
    from placerec.recognizer import make_pipeline

    rec = make_pipeline("scan-context")
    with pytest.raises(getattr(placerec.errors, error), match=message):
        call(rec, _scan())


def test_recognizer_entry_points_take_numpy_integers():
    import numpy as np

    from placerec.recognizer import make_pipeline

    rec, scan = make_pipeline("scan-context"), _scan()
    rec.add(np.int64(3), scan)
    (best,) = rec.query(scan, k=np.int64(1), max_id=np.int32(10))
    assert best.match_id == 3


# --- 4c. `placerec slam` with no loop closed ----------------------------------------------------------------------


def test_slam_table_prints_a_dash_for_no_loop_update(capsys):
    from placerec.eval.metrics import timing_summary
    from placerec.slam_app.report import _loop_rows, print_slam_table

    payload = {
        "pipeline": "orb-hbst",
        "odometry_source": "simulated drift",
        "trajectory": {},
        "loops": {"accepted": 0, "injected": 0, "median_translation_error": float("nan")},
        "time_ms": {
            "online_without_odometry": timing_summary([2.0, 4.0]),
            "online_with_odometry": timing_summary([3.0, 5.0]),
            "isam2_update": timing_summary([1.0, 1.0]),
            "isam2_loop_update": timing_summary([]),  # no loop closed: NaN statistics
        },
    }
    header, (row,) = _loop_rows(payload)
    cells = dict(zip(header, row, strict=True))
    assert cells["iSAM2 loop ms"] == "-" and cells["median t err [m]"] == "-"
    assert cells["iSAM2 ms"] == "1.000"
    print_slam_table(payload, "slam")
    assert "nan" not in capsys.readouterr().out.lower()
