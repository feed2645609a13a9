"""Open a run's ``index.html`` in a real headless browser and say what failed.

`check_report` loads the page from disk in Chromium (Debian's ``/usr/bin/chromium``, driven by Playwright; the
``browser`` extra installs Playwright, ``apt-get install chromium`` the browser) and returns a `ReportCheck`: the
console errors and uncaught exceptions, the images that did not load, the requests that failed, and how many
images and plotly figures the page holds and drew. The slow report test and ``tools/bench_viewer.py`` use it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

from placerec.errors import ConfigError, DependencyError

__all__ = ["CHROMIUM", "ReportCheck", "check_report"]

#: Debian's Chromium, the browser Playwright drives (its own browser download is not used)
CHROMIUM = "/usr/bin/chromium"

#: what the page reports once loaded: every image with whether it loaded, and the plotly figures placed / drawn
_INSPECT = """() => ({
  images: Array.from(document.images).map(i => [i.getAttribute('src'), i.complete && i.naturalWidth > 0]),
  plotDivs: document.querySelectorAll('.plotly-graph-div').length,
  plotsDrawn: Array.from(document.querySelectorAll('.plotly-graph-div'))
    .filter(d => d.querySelector('.main-svg') !== null).length,
})"""


@dataclass(frozen=True)
class ReportCheck:
    """What a browser saw of a report page: ``console_errors`` (console messages of type error),
    ``page_errors`` (uncaught exceptions), ``broken_images`` (the ``src`` of each image that did not load),
    ``failed_requests`` (url and reason), ``n_images``, ``n_plots`` (plotly figures on the page) and
    ``n_plots_drawn`` (those plotly drew), ``load_s`` (seconds until the page and its figures were loaded)."""

    path: Path
    console_errors: list[str] = field(default_factory=list)
    page_errors: list[str] = field(default_factory=list)
    broken_images: list[str] = field(default_factory=list)
    failed_requests: list[str] = field(default_factory=list)
    n_images: int = 0
    n_plots: int = 0
    n_plots_drawn: int = 0
    load_s: float = 0.0

    @property
    def problems(self) -> list[str]:
        """Every failure, one line each (empty when the page is fine)."""
        out = [f"console error: {e}" for e in self.console_errors]
        out += [f"uncaught exception: {e}" for e in self.page_errors]
        out += [f"image did not load: {src}" for src in self.broken_images]
        out += [f"request failed: {r}" for r in self.failed_requests]
        if self.n_plots_drawn < self.n_plots:
            out.append(f"{self.n_plots - self.n_plots_drawn} of {self.n_plots} plotly figures not drawn")
        return out

    @property
    def ok(self) -> bool:
        return not self.problems


def check_report(path: str | Path, chromium: str = CHROMIUM, timeout_s: float = 60.0) -> ReportCheck:
    """Load ``path`` (an HTML file, or a run folder: its ``index.html``) in headless ``chromium`` and return what
    failed (`ReportCheck`). `ConfigError` when there is no such page; `DependencyError` naming what to install
    when Playwright or Chromium is missing."""
    page_path = Path(path)
    if page_path.is_dir():
        page_path = page_path / "index.html"
    if not page_path.is_file():
        raise ConfigError(f"{page_path}: no report page to open")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError as exc:
        raise DependencyError(
            "checking a report in a browser needs Playwright: pip install 'placerec[browser]' (or pip install"
            " playwright); its browser is Debian's chromium (apt-get install chromium)"
        ) from exc
    if not Path(chromium).is_file():
        raise DependencyError(
            f"checking a report in a browser needs Chromium at {chromium}: apt-get install chromium"
        )
    console: list[str] = []
    exceptions: list[str] = []
    failed: list[str] = []
    t0 = time.perf_counter()
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=chromium, headless=True)
        try:
            page = browser.new_page()
            page.on("console", lambda m: console.append(m.text) if m.type == "error" else None)
            page.on("pageerror", lambda e: exceptions.append(str(e)))
            page.on("requestfailed", lambda r: failed.append(f"{r.url}: {r.failure}"))
            page.goto(page_path.resolve().as_uri(), wait_until="load", timeout=timeout_s * 1e3)
            seen = page.evaluate(_INSPECT)
        finally:
            browser.close()
    images = seen["images"]
    return ReportCheck(
        page_path,
        console,
        exceptions,
        [src for src, loaded in images if not loaded],
        failed,
        len(images),
        int(seen["plotDivs"]),
        int(seen["plotsDrawn"]),
        time.perf_counter() - t0,
    )
