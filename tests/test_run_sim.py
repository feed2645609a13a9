"""End to end: `placerec run` on a tiny simulated sequence (the block loop driven twice, OS1-64, 2 m spacing)."""

import json

import pytest
from typer.testing import CliRunner

from placerec.cli import app
from placerec.experiment.report import recompute_loop_metrics

TINY = """
name: tiny
dataset:
  simulator: {world: town, sensor: os1-64, route: loop, spacing: 2.0, seed: 3}
pipelines:
  - name: scan-context
  - name: orb-hbst
evaluation:
  exclusion: {frames: 50}
output:
  cache_dir: null
  progress: false
"""


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("run")
    cfg = root / "tiny.yaml"
    cfg.write_text(TINY)
    result = CliRunner().invoke(app, ["run", str(cfg), "--out", str(root / "results")])
    assert result.exit_code == 0, result.output
    assert "scan-context" in result.output
    return root / "results" / "latest"


@pytest.mark.parametrize("pipeline", ["scan-context", "orb-hbst"])
def test_pipelines_find_the_revisits(run_dir, pipeline):
    metrics = json.loads((run_dir / "metrics.json").read_text())
    m = metrics["pipelines"][pipeline]
    assert m["n_revisits"] >= 60
    # chance: a random eligible scan is within 5 m of the query for ~5/(2*86) of the route
    assert m["max_f1"] > 0.5 and m["recall_at_1"] > 0.5


@pytest.mark.parametrize("pipeline", ["scan-context", "orb-hbst"])
def test_metrics_json_agrees_with_the_candidates_csv(run_dir, pipeline):
    metrics = json.loads((run_dir / "metrics.json").read_text())["pipelines"][pipeline]
    again = recompute_loop_metrics(run_dir, pipeline)
    for key in (
        "max_f1",
        "precision_at_max_f1",
        "recall_at_max_f1",
        "recall_at_1",
        "n_revisits",
        "n_queries",
    ):
        assert again[key] == pytest.approx(metrics[key]), key
    for name in ("pr_curves.png", f"trajectory_{pipeline}.png", "timing.png", "index.html", "poses.txt"):
        assert (run_dir / name).is_file()
