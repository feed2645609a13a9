"""Issue #32, "output that fits": the console tables of a run, a benchmark, ``slam`` and ``pipelines NAME`` fit a
100-column terminal (80 for ``pipelines NAME``) with no cut cell, carry a legend and notes, and the table and the
timing figure share one definition of the time per scan."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from typer.testing import CliRunner

from placerec.cli import app

runner = CliRunner()


def _fits(text: str, width: int) -> None:
    """No cut cell, no line over ``width`` (but the results folder's path), no ``nan``."""
    assert "…" not in text and not re.search(r"\bnan\b", text, re.IGNORECASE)
    too_long = [line for line in text.splitlines() if len(line) > width and not line.startswith("results: ")]
    assert not too_long, too_long


def test_pipeline_parameters_read_at_80_columns_in_few_lines():
    from placerec.params import param_rows
    from placerec.recognizer import pipeline_params

    result = runner.invoke(app, ["pipelines", "orb-dbow"], env={"COLUMNS": "80"})
    assert result.exit_code == 0, result.output
    _fits(result.output, 80)
    rows = param_rows(pipeline_params("orb-dbow"))
    lines = result.output.splitlines()
    end = next(i for i, line in enumerate(lines) if line.startswith("operating threshold: "))
    assert end < 3 * len(rows)  # was a 4-column table of 866 lines, descriptions 7 characters wide
    # then a few lines a sensor's own settings (those with the odometry gate: what they change on top)
    blocks = [i for i, line in enumerate(lines) if line.startswith("on ")]
    assert blocks and all(b - a <= 6 for a, b in zip(blocks, [*blocks[1:], len(lines)], strict=True))
    first = next(i for i, line in enumerate(lines) if line.startswith("features = "))
    assert lines[first + 1].startswith("    feature extractor (placerec.features.EXTRACTORS; VPR paper")
    assert "operating threshold: 0.25, e1r: 0.35" in result.output  # the preset's, then a sensor's own


# --- a run's tables: the demo's labels and notes, on hand-made records --------------------------------------------


def _hand_payload(tmp_path, monkeypatch):
    """A loop-mode report of records labelled as the demo's (the MapClosures local-map rows without a candidate),
    with the arguments `plot_timing` got."""
    from placerec.config import load_config
    from placerec.experiment import figures
    from placerec.experiment.report import report_loop
    from placerec.experiment.run_folder import make_run_dir
    from placerec.experiment.runner import STAGES, PipelineRecord
    from placerec.types import Candidate, ListSequence, Scan

    x = np.r_[np.arange(5) * 100.0, np.arange(5) * 100.0 + 1.0]
    poses = np.tile(np.eye(4), (x.size, 1, 1))
    poses[:, 0, 3] = x
    seq = ListSequence([Scan(np.zeros((1, 3)), np.zeros(1)) for _ in x], poses, name="hand")
    cfg = load_config(None, ["name=hand", "evaluation.exclusion.frames=5", f"output.dir={tmp_path}",
                             "output.cache_dir=null", "output.progress=false"])  # fmt: skip
    found = [[Candidate(q, q - 5, 0.9 - 0.1 * (q - 5))] if q >= 5 else [] for q in range(x.size)]
    local = {"local_map": True, "local_map_distance": 100.0}
    specs = [  # label, registry name, params, candidates, ms per stage
        ("scan-context", "scan-context", {}, found, 20.0),
        ("map-closures", "map-closures", {"local_map": False}, found, 5.0),
        ("map-closures-local", "map-closures", local, [[] for _ in x], 16.0),
        ("map-closures-local-gt", "map-closures", local, [[] for _ in x], 2.0),
        ("superpoint-dbow", "superpoint-dbow", {}, found, 1234.5678),
    ]
    records = []
    for label, name, params, candidates, ms in specs:
        record = PipelineRecord(label, "Hand", name, params, list(range(x.size)), candidates, threshold=0.5)
        for i, stage in enumerate(STAGES):
            record.timing_ms[stage] = [ms * (1 + i) + q for q in range(x.size)]
        records.append(record)
    got = {}
    plot = figures.plot_timing

    def spy(timing, path, *args, **kwargs):
        got.update(timing=timing, args=args, kwargs=kwargs)
        return plot(timing, path, *args, **kwargs)

    monkeypatch.setattr(figures, "plot_timing", spy)
    run = make_run_dir(cfg)
    return run, report_loop(cfg, run, seq, records), records, got


def test_the_run_table_fits_100_columns_with_a_legend_and_notes(tmp_path, monkeypatch, capsys):
    from placerec.experiment.tables import print_table

    run, payload, _, _ = _hand_payload(tmp_path, monkeypatch)
    monkeypatch.setenv("COLUMNS", "100")
    print_table(payload, "demo (loop mode)")
    out = capsys.readouterr().out
    _fits(out, 100)
    slowest = f"{payload['pipelines']['superpoint-dbow']['time_ms']['mean']:.3f}"
    for text in ("max F1", "P@thr", "R@thr", "R@1", "ms/scan", slowest):  # the headline columns, uncut
        assert text in out
    assert "EP" not in out  # the other columns only with --wide
    assert "ms/scan: mean ms per scan, describe + query + insert + verify; preprocessing" in out  # the legend
    assert "map-closures-local (1,2)" in out and "map-closures-local-gt (1,2)" in out
    assert "map-closures (1)" in out and "scan-context (" not in out
    assert "(2) closed no local map" in out and "100 m" in out and "docs/evaluation.md" in out
    assert "(1) non-deterministic peer: its poses vary between identical runs" in out
    assert payload["notes"]["map-closures-local"][0].startswith("closed no local map")
    assert "notes" in json.loads((run / "metrics.json").read_text())
    print_table(payload, "demo (loop mode)", wide=True)
    wide = capsys.readouterr().out
    assert (
        "…" not in wide and "EP: extended precision" in wide and "R@P100: recall at 100 % precision" in wide
    )


def test_the_html_report_has_the_legend_notes_and_links_to_the_data_files(tmp_path, monkeypatch):
    run, payload, _, _ = _hand_payload(tmp_path, monkeypatch)
    page = (run / "index.html").read_text()
    for name in ("candidates_map-closures-local-gt.csv", "pipelines.yaml", "metrics.json", "config.yaml"):
        assert f'<a href="{name}">' in page
    assert "EP: extended precision" in page and "R@P100: recall at 100 % precision" in page
    assert "(2) closed no local map" in page and "map-closures-local (1,2)" in page


def test_the_table_and_the_timing_figure_share_one_time_per_scan(tmp_path, monkeypatch):
    _, payload, records, got = _hand_payload(tmp_path, monkeypatch)
    for record in records:
        bars = got["timing"][record.label]
        assert "preprocess" not in bars  # shared by the pipelines: in neither
        assert sum(bars.values()) == pytest.approx(payload["pipelines"][record.label]["time_ms"]["mean"])
    assert got["args"][0] == pytest.approx(np.mean(records[0].timing_ms["preprocess"]))  # said, not stacked
    assert "preprocessing" in got["args"][1]


# --- the CLI: placerec run, bench and slam at 100 columns ---------------------------------------------------------


def test_placerec_run_fits_100_columns_and_wide_prints_every_column(tmp_path):
    import yaml

    config = {
        "name": "fits",
        "dataset": {"simulator": {"world": "town", "sensor": "vlp16", "n_scans": 8}},
        "pipelines": [{"name": "scan-context", "label": "scan-context-with-a-long-label"}],
        "evaluation": {"exclusion": {"frames": 2}, "pose_truth": {"enabled": False}},
        "output": {"dir": str(tmp_path / "results"), "figures": False, "cache_dir": None, "progress": False},
    }
    path = tmp_path / "fits.yaml"
    path.write_text(yaml.safe_dump(config))
    result = runner.invoke(app, ["run", str(path)], env={"COLUMNS": "100"})
    assert result.exit_code == 0, result.output
    _fits(result.output, 100)
    assert "scan-context-with-a-long-label" in result.output and "ms/scan:" in result.output
    result = runner.invoke(app, ["run", str(path), "--wide"], env={"COLUMNS": "100"})
    assert result.exit_code == 0, result.output
    assert "…" not in result.output and "EP:" in result.output and "R@1% 25 m" in result.output


def test_the_benchmark_table_fits_100_columns_by_default(monkeypatch, capsys):
    from placerec.experiment.benchmark_summary import rows
    from placerec.experiment.tables import print_rows

    figure = {"mean": 0.8123, "worst": float("nan"), "cells": {"a": 1, "b": 0}}
    entry = {
        "threshold": 0.25,
        "accepted_translation_m": {"p95": 0.0412},
        "figures": {k: figure for k in ("max_f1", "precision", "recall", "false_closures", "ms_per_scan")},
    }
    payload = {"pipelines": {f"{name}-hbst-long-label": entry for name in ("orb", "brisk", "superpoint")}}
    monkeypatch.setenv("COLUMNS", "100")
    print_rows(*rows(payload, wide=False), "benchmark (test split, 12 cells): matrix mean / worst")
    out = capsys.readouterr().out
    _fits(out, 100)
    assert "thr: operating threshold" in out and "P worst" not in out
    assert rows(payload)[0][-1] == "ms/scan" and "P worst" in rows(payload)[0]  # every column for the HTML


def test_the_slam_tables_fit_100_columns_with_no_nan(monkeypatch, capsys):
    from placerec.eval.metrics import timing_summary
    from placerec.slam_app.report import print_slam_table

    err = {
        "ate_rmse": 12.3456,
        "ate_max": 40.5,
        "rpe_translation_rmse": 0.1234,
        "rpe_rotation_rmse_deg": np.nan,
    }
    payload = {
        "pipeline": "superpoint-dbow",
        "odometry_source": "simulated drift",
        "trajectory": {"odometry": err, "online": err, "optimized": err},
        "loops": {
            "accepted": 120,
            "false_accepted": 0,
            "opposite_direction": 41,
            "injected": 10,
            "rejected_by_back_end": 2,
            "injected_rejected_by_back_end": 10,
            "median_translation_error": 0.0345,
        },  # fmt: skip
        "time_ms": {
            "online_without_odometry": timing_summary([212.0, 240.0]),
            "online_with_odometry": timing_summary([3000.0, 5000.0]),
            "isam2_update": timing_summary([1.0, 1.0]),
            "isam2_loop_update": timing_summary([]),
        },
    }
    monkeypatch.setenv("COLUMNS", "100")
    print_slam_table(payload, "slam_demo (slam, 380 scans)")
    out = capsys.readouterr().out
    _fits(out, 100)
    assert "2 / 10" in out and "5000.000" not in out and "4000.000" in out
    assert "ATE: absolute trajectory error" in out
