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
