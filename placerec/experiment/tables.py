"""The tables of a run: rows of its figures for the console (rich) and for ``index.html``.

`table_rows` (the main figures), `protocol_rows` (retrieval and direction, loop mode), `operating_rows` (at the
fixed operating thresholds, loop mode); `print_rows` prints any of them, `write_html_page` puts them with every
figure of a run folder on one page.
"""

from __future__ import annotations

import html
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from placerec.config import ExperimentConfig
from placerec.experiment.interactive import PLOTLY_JS
from placerec.experiment.runner import PER_SCAN_TIME
from placerec.io.atomic import atomic_write

if TYPE_CHECKING:
    from placerec.experiment.evidence_figures import PipelineEvidence

__all__ = [
    "LEGEND",
    "legend",
    "lookup",
    "operating_rows",
    "print_rows",
    "print_table",
    "evidence_section",
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


#: the console's default table (`table_rows` with ``wide`` False): the headline figures; ``--wide`` prints them all
_COMPACT_LOOP_COLUMNS = (
    ("max F1", ("max_f1",)),
    ("P@thr", ("operating", "precision")),
    ("R@thr", ("operating", "recall")),
    ("R@1", ("recall_at_1",)),
    ("ms/scan", ("time_ms", "mean")),
)
_COMPACT_LOCALIZE_COLUMNS = (
    ("localised", ("success_rate",)),
    ("no answer", ("no_answer_rate",)),
    ("wrong", ("wrong_rate",)),
    ("median err [m]", ("median_error",)),
    ("ms/query", ("time_ms", "mean")),
)

#: what each abbreviation of a table's header means (`legend`): a header is explained by the longest key it equals
#: or starts with (followed by a space)
LEGEND = {
    "max F1": "best F1 over all score thresholds",
    "maxF1": "best F1 over all score thresholds",
    "P@thr": "precision at the pipeline's fixed operating threshold (docs/protocol.md)",
    "R@thr": "recall at that threshold",
    "P@maxF1": "precision at the max-F1 threshold",
    "R@maxF1": "recall at the max-F1 threshold",
    "AUC": "average precision (area under the PR curve)",
    "R@P100": "recall at 100 % precision (before the first false closure)",
    "EP": "extended precision, (precision at the top score + R@P100) / 2",
    "R@1": "top candidate correct (any threshold)",
    "R@1 25 m": "retrieval recall@1 within 25 m",
    "R@1% 25 m": "retrieval recall@1 % of the database within 25 m",
    "TP t err [m]": "translation error of the true closures accepted at max F1",
    "TP rot err [deg]": "their rotation error",
    "p95": "95th percentile",
    "max accepted t err [m]": "worst translation error of a closure accepted at max F1",
    "ms/scan": f"mean ms per scan, {PER_SCAN_TIME} (timing.png shows the same)",
    "ms/query": f"mean ms per query, {PER_SCAN_TIME}",
    "verify mean": "mean ms per scan of the verification stage",
    "thr": "operating threshold",
    "P": "precision at the operating threshold",
    "R": "recall there",
    "FP": "false closures accepted, all cells",
    "t p95 m": "95th percentile translation error [m] of the accepted closures",
    "ATE": "absolute trajectory error",
    "RPE": "relative pose error",
    "iSAM2": "incremental smoothing and mapping (GTSAM) update",
    "odom": "odometry",
}


def legend(header: list[str]) -> list[str]:
    """``"ABBR: meaning"`` for each abbreviation of ``header`` that `LEGEND` explains, in header order, once each."""
    out: list[str] = []
    for h in header[1:]:
        keys = [k for k in LEGEND if h == k or h.startswith(k + " ") or f" {k} " in f" {h} "]
        if keys:
            key = max(keys, key=len)
            line = f"{key}: {LEGEND[key]}"
            if line not in out:
                out.append(line)
    return out


def lookup(entry: dict[str, Any], path: tuple[str, ...]) -> Any:
    for key in path:
        if not isinstance(entry, dict) or key not in entry:
            return None
        entry = entry[key]
    return entry


def table_rows(payload: dict[str, Any], wide: bool = True) -> tuple[list[str], list[list[str]]]:
    """Header and rows of the results table (shared by the console and the HTML report): every column, or with
    ``wide`` False the headline ones the console prints by default (max F1, P / R at the fixed threshold, R@1,
    ms/scan; localize mode: localised, no answer, wrong, median error, ms/query). Pose errors are those of the
    closures accepted at the max-F1 threshold; ``-`` marks a value that is undefined (no 6-DoF pose, no
    verification stage)."""
    loop = payload["mode"] == "loop"
    if not wide:
        return _column_rows(payload, _COMPACT_LOOP_COLUMNS if loop else _COMPACT_LOCALIZE_COLUMNS)
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


def print_table(payload: dict[str, Any], title: str, wide: bool = False) -> None:
    """The results as rich console tables, each with the legend of its abbreviations under it: the headline
    columns (`table_rows` with ``wide`` False), or with ``wide`` every column, and in loop mode the retrieval /
    direction table and the one at the fixed operating thresholds. The main table carries the run's notes
    (``payload["notes"]``)."""
    notes = payload.get("notes") or {}
    print_rows(*table_rows(payload, wide), title, notes=notes)
    if not wide:
        return
    protocols = protocol_rows(payload)
    if protocols is not None:
        print_rows(*protocols, f"{title}: retrieval within 25 m, same- / reverse-direction revisits")
    operating = operating_rows(payload)
    if operating is not None:
        print_rows(*operating, f"{title}: at the fixed operating thresholds (docs/protocol.md)")


def _numbered(notes: dict[str, list[str]]) -> tuple[dict[str, list[int]], list[str]]:
    """Each label's note numbers and the distinct notes, numbered from 1 in order of appearance."""
    texts: list[str] = []
    marks: dict[str, list[int]] = {}
    for label, items in notes.items():
        for text in items:
            if text not in texts:
                texts.append(text)
            marks.setdefault(label, []).append(texts.index(text) + 1)
    marks = {label: sorted(numbers) for label, numbers in marks.items()}
    return marks, texts


def print_rows(
    header: list[str],
    rows: list[list[str]],
    title: str,
    notes: dict[str, list[str]] | None = None,
    show_legend: bool = True,
) -> None:
    """A rich console table: the first column left-aligned, bold and never cut, the others right-aligned; under it
    the legend of its abbreviations (`legend`) and ``notes`` (row label -> texts, marked ``(1)`` beside the row).

    The table takes the terminal's width (``COLUMNS`` when not a terminal), headers wrapping; one that cannot fit
    without cutting a cell is printed at its full width instead (long lines rather than ``…``)."""
    import shutil
    import textwrap

    from rich.console import Console
    from rich.measure import Measurement
    from rich.table import Table
    from rich.text import Text

    marks, texts = _numbered(notes or {})
    rows = [[r[0] + (f" ({','.join(map(str, marks[r[0]]))})" if r[0] in marks else ""), *r[1:]] for r in rows]
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
    wide = Console(width=10_000)  # a measurement is clamped to the console's width
    natural = Measurement.get(wide, wide.options, table).maximum
    if natural > console.width:  # headers wrap to fit; if a cell would be cut instead: as wide as the table
        if any("…" in seg.text for line in console.render_lines(table) for seg in line):
            console = Console(width=natural)
    console.print(table)
    width = max(40, min(shutil.get_terminal_size().columns, 100))
    lines = legend(header) if show_legend else []
    lines += [f"({i}) {text}" for i, text in enumerate(texts, 1)]
    for line in lines:
        print(textwrap.fill(line, width, subsequent_indent="    ", break_on_hyphens=False))


def write_index_html(
    run: Path,
    cfg: ExperimentConfig,
    payload: dict[str, Any],
    interactive: str = "",
    sections: list[str] | None = None,
) -> Path:
    """A single page with the tables and every figure of the run; ``interactive`` (HTML: the plotly figures,
    `placerec.experiment.interactive`, whose plotly.js the folder holds) goes after the tables, ``sections``
    (HTML, e.g. `evidence_section`) after the figures."""
    tables = [table_rows(payload)] + [
        t for t in [protocol_rows(payload), operating_rows(payload)] if t is not None
    ]
    notes = payload.get("notes") or {}
    scripts = (PLOTLY_JS,) if interactive else ()
    return write_html_page(
        run,
        cfg.name,
        f"mode: {html.escape(payload['mode'])}",
        tables,
        notes=notes,
        interactive=interactive,
        sections=sections or [],
        scripts=scripts,
    )


def _table_html(header: list[str], rows: list[list[str]]) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    cells = "".join("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{cells}</table>"


#: the headings of the evidence galleries per mode (`evidence_section`)
GALLERY_TITLES = {
    "loop": {
        "accepted": "Accepted true closures",
        "false": "False closures (accepted, wrong place)",
        "missed": "Missed revisits (the best candidate, or with none the revisited scan)",
    },
    "localize": {
        "accepted": "Localised queries (the answer)",
        "false": "Wrong answers (beyond the success distance)",
        "missed": "No answer (the best candidate, or with none the nearest map scan)",
    },
}


def evidence_section(evidence: PipelineEvidence, trajectory: str = "", mode: str = "loop") -> str:
    """A pipeline's part of ``index.html``: why its candidates ended as they did (every candidate, and the top
    candidate of each query), its interactive ``trajectory`` (HTML), and its galleries (`GALLERY_TITLES` of
    ``mode``: accepted, false and missed closures, or localised, wrong and unanswered queries;
    `placerec.experiment.evidence`), each figure with its decision under it."""
    from placerec.experiment.evidence import ACCEPTED, KINDS, REJECTED, UNVERIFIED
    from placerec.types import REJECTIONS

    words = {
        ACCEPTED: "accepted",
        REJECTED: "rejected (no reason given)",
        UNVERIFIED: "not verified (score only)",
    }
    counts = evidence.counts
    keys = list(counts.all) + [k for k in counts.top if k not in counts.all]
    rows = [
        [
            f"{k}: {REJECTIONS[k]}" if k in REJECTIONS else words.get(k, k),
            str(counts.all.get(k, 0)),
            str(counts.top.get(k, 0)),
        ]
        for k in keys
    ]
    name = html.escape(evidence.label)
    body = f'<section class="evidence" id="evidence-{name}"><h2>{name}</h2>'
    body += "<h3>Why candidates ended as they did</h3>"
    body += _table_html(["verification", "all candidates", "top candidate per query"], rows)
    body += trajectory
    titles = GALLERY_TITLES[mode]
    for kind in KINDS:
        shown = [
            (c, f, n)
            for c, f, n in zip(evidence.cases, evidence.figures, evidence.lines, strict=True)
            if c.kind == kind
        ]
        body += f"<h3>{titles[kind]} ({len(shown)} shown)</h3>"
        if not shown:
            body += '<p class="legend">none</p>'
        for case, figure, lines in shown:
            caption = f"query {case.query_id}, match {case.match_id}: {case.decision}"
            if lines is not None:
                caption += f"; {lines[0]} inlier pairs drawn of {lines[1]}"
            body += (
                f'<figure class="closure"><img src="{html.escape(figure)}" alt="{html.escape(caption)}">'
                f"<figcaption>{html.escape(caption)}</figcaption></figure>"
            )
    return body + "</section>"


def write_html_page(
    run: Path,
    title: str,
    subtitle: str,
    tables: list[tuple[list[str], list[list[str]]]],
    first: tuple[str, ...] = ("pr_curves.png",),
    last: tuple[str, ...] = ("timing.png",),
    notes: dict[str, list[str]] | None = None,
    interactive: str = "",
    sections: list[str] | None = None,
    scripts: tuple[str, ...] = (),
) -> Path:
    """``run/index.html``: ``title``, ``subtitle`` (HTML) with links to the folder's data files (metrics.json,
    config.yaml, pipelines.yaml, the CSVs, ...), the ``tables`` (header, rows) each with the legend of its
    abbreviations, the first one with ``notes`` (row label -> texts, numbered beside the rows), ``interactive``
    (HTML), every PNG of the folder (``first`` ones first, ``last`` ones last) and the ``sections`` (HTML);
    ``scripts``: files of the folder the page loads first (plotly.js)."""
    marks, texts = _numbered(notes or {})
    body = ""
    for n, (header, rows) in enumerate(tables):
        head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
        cells = ""
        for r in rows:
            mark = f" ({','.join(map(str, marks[r[0]]))})" if n == 0 and r[0] in marks else ""
            cells += "<tr>" + "".join(
                f"<td>{html.escape(c + (mark if i == 0 else ''))}</td>" for i, c in enumerate(r)
            )
            cells += "</tr>"
        body += f"<table><tr>{head}</tr>{cells}</table>"
        lines = [html.escape(line) for line in legend(header)]
        if n == 0:
            lines += [f"({i}) {html.escape(text)}" for i, text in enumerate(texts, 1)]
        if lines:
            body += '<p class="legend">' + "<br>".join(lines) + "</p>"
    images = sorted(p.name for p in run.glob("*.png"))
    order = {**{n: 0 for n in first}, **{n: 2 for n in last}}
    images.sort(key=lambda n: (order.get(n, 1), n))
    figs = "".join(
        f'<figure><img src="{html.escape(n)}"><figcaption>{html.escape(n)}</figcaption></figure>'
        for n in images
    )
    data = sorted(
        (p.name for p in run.iterdir() if p.is_file() and p.suffix in _DATA_SUFFIXES),
        key=lambda n: (_LINK_ORDER.index(n) if n in _LINK_ORDER else len(_LINK_ORDER), n),
    )
    links = ",\n".join(f'<a href="{html.escape(n)}">{html.escape(n)}</a>' for n in data)
    head = "".join(f'<script src="{html.escape(n)}"></script>' for n in scripts)
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>body{{font-family:sans-serif;margin:2em}}table{{border-collapse:collapse;margin-bottom:0.3em}}td,th{{border:1px solid #ccc;padding:4px 8px;text-align:right}}
td:first-child{{text-align:left;font-weight:bold}}.legend{{font-size:smaller;color:#444;margin-top:0}}figure{{display:inline-block;margin:1em}}img{{max-width:560px}}
figure.closure{{vertical-align:top}}figure.closure img{{max-width:640px}}section.evidence{{border-top:2px solid #888;margin-top:2em}}</style>
{head}</head><body>
<h1>{html.escape(title)}</h1><p>{subtitle} &middot; files: {links}</p>{body}{interactive}{figs}{"".join(sections or [])}
</body></html>"""
    path = run / "index.html"
    with atomic_write(path, "w") as fh:
        fh.write(page)
    return path


#: the files `write_html_page` links (by suffix), and the order of those it puts first
_DATA_SUFFIXES = (".json", ".yaml", ".csv", ".txt", ".g2o", ".ply")
_LINK_ORDER = ("metrics.json", "benchmark.json", "config.yaml", "pipelines.yaml")
