"""The report opened in a real headless browser (Debian's Chromium through Playwright): `check_report` finds
broken images and console errors on a page made to have them, and a real run's page has none."""

from __future__ import annotations

from pathlib import Path

import pytest

from placerec.errors import ConfigError, DependencyError
from placerec.experiment.browser import CHROMIUM, check_report
from tests.test_run_sim import TINY as TINY_RUN


def _browser_or_skip() -> None:
    pytest.importorskip(
        "playwright.sync_api", reason="the browser checks need playwright (the browser extra)"
    )
    if not Path(CHROMIUM).is_file():
        pytest.skip(f"no Chromium at {CHROMIUM} (apt-get install chromium)")


def test_a_missing_page_or_browser_is_a_clear_error(tmp_path):
    with pytest.raises(ConfigError, match="no report page"):
        check_report(tmp_path)
    (tmp_path / "index.html").write_text("<html></html>")
    pytest.importorskip("playwright.sync_api")
    with pytest.raises(DependencyError, match="apt-get install chromium"):
        check_report(tmp_path, chromium=str(tmp_path / "no-chromium"))


def test_the_check_sees_a_broken_image_and_a_console_error(tmp_path):
    _browser_or_skip()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(1, 1))
    fig.savefig(tmp_path / "fine.png")
    plt.close(fig)
    (tmp_path / "page.html").write_text(
        '<!doctype html><html><body><img src="fine.png"><img src="missing.png">'
        "<script>console.error('boom')</script></body></html>"
    )
    check = check_report(tmp_path / "page.html")
    assert check.n_images == 2
    assert check.broken_images == ["missing.png"]
    assert check.console_errors and any("boom" in e for e in check.console_errors)
    assert any("missing.png" in r for r in check.failed_requests)
    assert not check.ok


#: the tiny run of tests/test_run_sim.py, 3 closures a gallery
TINY = TINY_RUN + "  evidence_per_gallery: 3\n"


@pytest.mark.slow
def test_a_real_runs_report_opens_with_every_image_and_plot(tmp_path):
    """`placerec run` end to end (its report rebuilds the image pipelines for their figures' keypoints), then
    the page in Chromium: no console error, every image loaded, every plotly figure drawn."""
    _browser_or_skip()
    from typer.testing import CliRunner

    from placerec.cli import app

    cfg = tmp_path / "tiny.yaml"
    cfg.write_text(TINY)
    result = CliRunner().invoke(app, ["run", str(cfg), "--out", str(tmp_path / "results")])
    assert result.exit_code == 0, result.output
    run = tmp_path / "results" / "latest"
    check = check_report(run)
    assert check.problems == []
    pngs = list(run.glob("*.png")) + list((run / "evidence").rglob("*.png"))
    assert check.n_images == len(pngs) > 4
    assert check.n_plots == check.n_plots_drawn == 3  # the PR curves and one trajectory per pipeline
