"""Sequences too short to hold a revisit (0 to 3 scans, shorter than the exclusion window, with or without poses)
run through every registered pipeline and the whole report: no candidates, metrics that say so (``no_revisits``,
``null`` for what is undefined, strict JSON), figures drawn without warnings, never a bare exception."""

import json
import warnings

import pytest
from typer.testing import CliRunner

from placerec.cli import app
from placerec.config import load_config
from placerec.experiment.report import recompute_loop_metrics, report_localize, report_loop
from placerec.experiment.run_folder import make_run_dir
from placerec.experiment.runner import build_pipelines, run_localize, run_loop
from placerec.recognizer import PIPELINES
from placerec.sim import SimulatedSequence
from placerec.types import ListSequence

NAMES = sorted(PIPELINES)


@pytest.fixture(scope="module")
def sim():
    seq = SimulatedSequence(world="town", sensor="vlp16", n_scans=3, seed=5, clutter=False)
    return [seq[i] for i in range(3)], seq.poses


def _config(tmp_path, *overrides):
    pipelines = "[" + ", ".join(f"{{name: {n}}}" for n in NAMES) + "]"
    return load_config(
        None,
        [f"output.dir={tmp_path}", "output.cache_dir=null", "output.progress=false", f"pipelines={pipelines}"]
        + list(overrides),
    )


def _strict_json(path):
    def refuse(constant):
        raise AssertionError(f"{path.name} holds {constant}: not strict JSON")

    return json.loads(path.read_text(), parse_constant=refuse)


@pytest.mark.parametrize("n", [0, 1, 3])
def test_a_sequence_shorter_than_the_window_gives_no_candidates_and_says_no_revisits(tmp_path, sim, n):
    scans, poses = sim
    cfg = _config(tmp_path)  # the default window (frames) is longer than the sequence
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # figures of empty or one-point trajectories draw without a warning
        seq, records = run_loop(cfg, ListSequence(scans[:n], poses[:n], name=f"short{n}"))
        run = make_run_dir(cfg)
        report_loop(cfg, run, seq, records)
    assert [r.label for r in records] == NAMES
    assert all(r.query_ids == list(range(n)) and not any(r.candidates) for r in records)
    metrics = _strict_json(run / "metrics.json")
    for name in NAMES:
        m = metrics["pipelines"][name]
        assert (m["n_queries"], m["n_revisits"], m["n_candidates"], m["no_revisits"]) == (n, 0, 0, True)
        assert (m["max_f1"], m["recall_at_1"], m["auc"], m["threshold_at_max_f1"]) == (0.0, 0.0, 0.0, None)
        assert (run / f"trajectory_{name}.png").is_file()
        again = recompute_loop_metrics(run, name)  # from the folder alone, as for any run
        assert (again["n_queries"], again["no_revisits"], again["max_f1"]) == (n, True, 0.0)
    assert (run / "index.html").is_file() and (run / "timing.png").is_file()


@pytest.mark.parametrize("n_map, n_queries", [(0, 2), (2, 0), (0, 0)])
def test_localize_with_an_empty_map_or_no_queries_reports_what_it_can(tmp_path, sim, n_map, n_queries):
    scans, poses = sim
    cfg = _config(tmp_path, "evaluation.mode=localize")
    map_seq = ListSequence(scans[:n_map], poses[:n_map], name="map")
    queries = ListSequence(scans[3 - n_queries :], poses[3 - n_queries :], name="queries")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        a, b, records = run_localize(cfg, (map_seq, queries), build_pipelines(cfg))
        run = make_run_dir(cfg)
        report_localize(cfg, run, a, b, records)
    metrics = _strict_json(run / "metrics.json")
    for name in NAMES:
        m = metrics["pipelines"][name]
        assert (m["n_queries"], m["n_success"], m["n_no_estimate"]) == (n_queries, 0, n_queries)
        assert m["success_rate"] == 0.0 and m["mean_error"] is None and m["median_error"] is None


def test_placerec_run_on_a_three_scan_simulation(tmp_path):
    config = tmp_path / "three.yaml"
    config.write_text(
        "name: three\ndataset: {simulator: {n_scans: 3}}\n"
        "pipelines: [{name: scan-context}, {name: orb-hbst}]\noutput: {cache_dir: null, progress: false}\n"
    )
    result = CliRunner().invoke(app, ["run", str(config), "--out", str(tmp_path / "results")])
    assert result.exit_code == 0, result.output
    run = (tmp_path / "results" / "latest").resolve()
    metrics = _strict_json(run / "metrics.json")
    assert all(m["no_revisits"] and m["n_queries"] == 3 for m in metrics["pipelines"].values())
