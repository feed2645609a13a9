"""Issue #32, "output that fits": the console tables of a run, a benchmark, ``slam`` and ``pipelines NAME`` fit a
100-column terminal (80 for ``pipelines NAME``) with no cut cell, carry a legend and notes, and the table and the
timing figure share one definition of the time per scan."""

from __future__ import annotations

from typer.testing import CliRunner

from placerec.cli import app

runner = CliRunner()


def _fits(text: str, width: int) -> None:
    assert "…" not in text
    too_long = [line for line in text.splitlines() if len(line) > width]
    assert not too_long, too_long


def test_pipeline_parameters_read_at_80_columns_in_few_lines():
    from placerec.params import param_rows
    from placerec.recognizer import pipeline_params

    result = runner.invoke(app, ["pipelines", "orb-dbow"], env={"COLUMNS": "80"})
    assert result.exit_code == 0, result.output
    _fits(result.output, 80)
    rows = param_rows(pipeline_params("orb-dbow"))
    lines = result.output.splitlines()
    assert len(lines) < 3 * len(rows)  # was a 4-column table of 866 lines, descriptions 7 characters wide
    first = next(i for i, line in enumerate(lines) if line.startswith("features = "))
    assert lines[first + 1].startswith("    feature extractor (placerec.features.EXTRACTORS; VPR paper")
    assert "operating threshold: 0.25" in result.output
