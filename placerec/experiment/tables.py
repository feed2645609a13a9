"""The tables of a run: rows of its figures for the console (rich) and for ``index.html``.

`table_rows` (the main figures), `protocol_rows` (retrieval and direction, loop mode), `operating_rows` (at the
fixed operating thresholds, loop mode); `print_rows` prints any of them, `write_html_page` puts them with every
figure of a run folder on one page.
"""

from __future__ import annotations

import html
from pathlib import Path
from typing import Any

import numpy as np

from placerec.config import ExperimentConfig
from placerec.io.atomic import atomic_write

__all__ = [
    "lookup",
    "operating_rows",
    "print_rows",
    "print_table",
    "protocol_rows",
    "table_rows",
    "write_html_page",
    "write_index_html",
]


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return "-" if np.isnan(value) else f"{value:.3f}"
    return "-" if value is None else str(value)


_LOOP_COLUMNS = (
    ("max F1", ("max_f1",)),
    ("P@maxF1", ("precision_at_max_f1",)),
    ("R@maxF1", ("recall_at_max_f1",)),
    ("AUC", ("auc",)),
    ("R@P100", ("recall_at_100_precision",)),
    ("EP", ("extended_precision",)),
    ("R@1", ("recall_at_1",)),
    ("TP t err [m] median", ("pose_error", "tp_translation_m", "median")),
    ("p95", ("pose_error", "tp_translation_m", "p95")),
    ("TP rot err [deg] median", ("pose_error", "tp_rotation_deg", "median")),
    ("p95", ("pose_error", "tp_rotation_deg", "p95")),
    ("max accepted t err [m]", ("pose_error", "accepted_max_translation_m")),
)
#: the protocols beside the loop protocol (`placerec.eval.retrieval`): a second table in loop mode
_PROTOCOL_COLUMNS = (
    ("R@1 25 m", ("retrieval", "recall_at_1")),
    ("R@1% 25 m", ("retrieval", "recall_at_1pct")),
    ("retrieval queries", ("retrieval", "n_queries")),
    ("same: revisits", ("directions", "same", "n_revisits")),
    ("R@1", ("directions", "same", "recall_at_1")),
    ("R@maxF1", ("directions", "same", "recall_at_max_f1")),
    ("reverse: revisits", ("directions", "reverse", "n_revisits")),
    ("R@1", ("directions", "reverse", "recall_at_1")),
    ("R@maxF1", ("directions", "reverse", "recall_at_max_f1")),
)
_LOCALIZE_COLUMNS = (
    ("basis", ("success_basis",)),
    ("answers", ("answer_rule",)),
    ("localised", ("success_rate",)),
    ("no answer", ("no_answer_rate",)),
    ("wrong", ("wrong_rate",)),
    ("success 1 m/5 deg", ("fine_success_rate",)),
    ("median err [m]", ("median_error",)),
    ("median rot err [deg]", ("median_rotation_error_deg",)),
)
_TIME_COLUMNS = (
    ("mean", ("time_ms", "mean")),
    ("median", ("time_ms", "median")),
    ("p95", ("time_ms", "p95")),
    ("verify mean", ("time_ms", "stages", "verify", "mean")),
)


def lookup(entry: dict[str, Any], path: tuple[str, ...]) -> Any:
    for key in path:
        if not isinstance(entry, dict) or key not in entry:
            return None
        entry = entry[key]
    return entry


def table_rows(payload: dict[str, Any]) -> tuple[list[str], list[list[str]]]:
    """Header and rows of the results table (shared by the console and the HTML report). Pose errors are those
    of the closures accepted at the max-F1 threshold; ``-`` marks a value that is undefined (no 6-DoF pose, no
    verification stage)."""
    loop = payload["mode"] == "loop"
    columns = (_LOOP_COLUMNS if loop else _LOCALIZE_COLUMNS) + tuple(
        (f"ms/{'scan' if loop else 'query'} {h}" if h == "mean" else h, k) for h, k in _TIME_COLUMNS
    )
    tail = ("revisits", ("n_revisits",)) if loop else ("queries", ("n_queries",))
    header = ["pipeline"] + [h for h, _ in columns] + [tail[0]]
    rows = [
        [label] + [_fmt(lookup(m, k)) for _, k in columns] + [_fmt(lookup(m, tail[1]))]
        for label, m in payload["pipelines"].items()
    ]
    return header, rows


def protocol_rows(payload: dict[str, Any]) -> tuple[list[str], list[list[str]]] | None:
    """Header and rows of the loop-mode table of retrieval recalls (25 m) and same- / reverse-direction revisits
    (None in localize mode)."""
    if payload["mode"] != "loop":
        return None
    return _column_rows(payload, _PROTOCOL_COLUMNS)


def _column_rows(payload: dict[str, Any], columns: Any) -> tuple[list[str], list[list[str]]]:
    """Header and one row per pipeline of ``columns`` ((heading, key path) pairs)."""
    header = ["pipeline"] + [h for h, _ in columns]
    rows = [[label] + [_fmt(lookup(m, k)) for _, k in columns] for label, m in payload["pipelines"].items()]
    return header, rows


_OPERATING_COLUMNS = (
    ("threshold", ("operating", "threshold")),
    ("P", ("operating", "precision")),
    ("R", ("operating", "recall")),
    ("pose truth: P", ("pose_truth", "operating", "precision")),
    ("R", ("pose_truth", "operating", "recall")),
    ("false", ("pose_truth", "operating", "fp")),
    ("revisits", ("pose_truth", "n_revisits")),
    ("t err p95 [m]", ("pose_truth", "operating", "translation_m", "p95")),
)


def operating_rows(payload: dict[str, Any]) -> tuple[list[str], list[list[str]]] | None:
    """Header and rows of the loop-mode table at each pipeline's fixed operating threshold, under the distance and
    the pose ground truths (None in localize mode or when no pipeline has a threshold)."""
    if payload["mode"] != "loop" or not any(m.get("operating") for m in payload["pipelines"].values()):
        return None
    return _column_rows(payload, _OPERATING_COLUMNS)


def print_table(payload: dict[str, Any], title: str) -> None:
    """The results as rich console tables: the main one, and in loop mode the retrieval / direction one and the
    one at the fixed operating thresholds."""
    print_rows(*table_rows(payload), title)
    protocols = protocol_rows(payload)
    if protocols is not None:
        print_rows(*protocols, f"{title}: retrieval within 25 m, same- / reverse-direction revisits")
    operating = operating_rows(payload)
    if operating is not None:
        print_rows(*operating, f"{title}: at the fixed operating thresholds (docs/protocol.md)")


def print_rows(header: list[str], rows: list[list[str]], title: str) -> None:
    """A rich console table: the first column left-aligned, bold and never cut, the others right-aligned."""
    from rich.console import Console
    from rich.measure import Measurement
    from rich.table import Table
    from rich.text import Text

    table = Table(title=Text(title))
    names = max((len(r[0]) for r in rows), default=0)
    for i, h in enumerate(header):  # Text: "[m]" is a unit, not rich markup
        first = i == 0
        table.add_column(
            Text(h),
            justify="left" if first else "right",
            style="bold" if first else None,
            no_wrap=first,
            min_width=names if first else None,
        )
    for row in rows:
        table.add_row(*(Text(c) for c in row))
    console = Console()
    if not console.is_terminal:  # logs and pipes: as wide as the table, so that no column is cut
        wide = Console(width=10_000)
        console = Console(width=Measurement.get(wide, wide.options, table).maximum)
    console.print(table)


def write_index_html(run: Path, cfg: ExperimentConfig, payload: dict[str, Any]) -> Path:
    """A single page with the tables and every figure of the run."""
    tables = [table_rows(payload)] + [
        t for t in [protocol_rows(payload), operating_rows(payload)] if t is not None
    ]
    return write_html_page(run, cfg.name, f"mode: {html.escape(payload['mode'])}", tables)


def write_html_page(
    run: Path,
    title: str,
    subtitle: str,
    tables: list[tuple[list[str], list[list[str]]]],
    first: tuple[str, ...] = ("pr_curves.png",),
    last: tuple[str, ...] = ("timing.png",),
) -> Path:
    """``run/index.html``: ``title``, ``subtitle`` (HTML) with links to metrics.json and config.yaml, the
    ``tables`` (header, rows) and every PNG of the folder (``first`` ones first, ``last`` ones last)."""
    body = ""
    for header, rows in tables:
        head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
        cells = "".join("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in r) + "</tr>" for r in rows)
        body += f"<table><tr>{head}</tr>{cells}</table>"
    images = sorted(p.name for p in run.glob("*.png"))
    order = {**{n: 0 for n in first}, **{n: 2 for n in last}}
    images.sort(key=lambda n: (order.get(n, 1), n))
    figs = "".join(
        f'<figure><img src="{html.escape(n)}"><figcaption>{html.escape(n)}</figcaption></figure>'
        for n in images
    )
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>body{{font-family:sans-serif;margin:2em}}table{{border-collapse:collapse;margin-bottom:1em}}td,th{{border:1px solid #ccc;padding:4px 8px;text-align:right}}
td:first-child{{text-align:left;font-weight:bold}}figure{{display:inline-block;margin:1em}}img{{max-width:560px}}</style></head><body>
<h1>{html.escape(title)}</h1><p>{subtitle} &middot; files: <a href="metrics.json">metrics.json</a>,
<a href="config.yaml">config.yaml</a></p>{body}{figs}</body></html>"""
    path = run / "index.html"
    with atomic_write(path, "w") as fh:
        fh.write(page)
    return path
