"""The report's interactive figures (plotly): PR curves with each point's threshold, and per pipeline its
trajectory with the closures, every closure's query / match ids and score under the mouse.

plotly.js is written once into the run folder (`write_plotly_js`) and each figure is an HTML fragment that uses
it, so ``index.html`` opens from disk with no network; the static PNGs stay beside them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from placerec.eval import LoopMetrics
from placerec.experiment.evidence import decision_text
from placerec.io.atomic import atomic_write
from placerec.types import Candidate

__all__ = ["PLOTLY_JS", "write_plotly_js", "pr_curves_html", "trajectory_html"]

#: plotly.js in the run folder, loaded by ``index.html``
PLOTLY_JS = "plotly.min.js"
_LAYOUT = {"template": "plotly_white", "margin": {"l": 50, "r": 20, "t": 40, "b": 40}}


def write_plotly_js(run: Path) -> Path:
    """``run/plotly.min.js``: the plotly.js of the installed plotly, for the figures of `pr_curves_html` and
    `trajectory_html`."""
    from plotly.offline import get_plotlyjs

    path = run / PLOTLY_JS
    with atomic_write(path, "w") as fh:
        fh.write(get_plotlyjs())
    return path


def _fragment(fig: Any, div_id: str) -> str:
    """``fig`` as a ``<div>`` and the script that draws it with the page's plotly.js."""
    import plotly.io as pio

    return pio.to_html(
        fig, include_plotlyjs=False, full_html=False, div_id=div_id, config={"displaylogo": False}
    )


def pr_curves_html(curves: dict[str, dict[str, Any]], title: str) -> str:
    """Precision-recall curves (``curves``: label -> {"precision", "recall", "thresholds": arrays,
    "best": (recall, precision) at max F1}), the threshold of each point shown under the mouse."""
    import plotly.graph_objects as go

    fig = go.Figure()
    for label, c in curves.items():
        fig.add_trace(
            go.Scatter(
                x=np.asarray(c["recall"], float),
                y=np.asarray(c["precision"], float),
                customdata=np.asarray(c["thresholds"], float),
                mode="lines",
                name=f"{label} (max F1 {c['max_f1']:.3f})",
                legendgroup=label,
                hovertemplate=f"{label}<br>threshold %{{customdata:.4g}}<br>recall %{{x:.3f}}"
                "<br>precision %{y:.3f}<extra></extra>",
            )
        )
        if c.get("best") is not None:
            fig.add_trace(
                go.Scatter(
                    x=[c["best"][0]],
                    y=[c["best"][1]],
                    mode="markers",
                    legendgroup=label,
                    showlegend=False,
                    marker={"size": 8, "color": "black", "symbol": "circle-open"},
                    hovertemplate=f"{label}: max F1 {c['max_f1']:.3f}<extra></extra>",
                )
            )
    fig.update_layout(
        title=title,
        xaxis={"title": "recall", "range": [0, 1.02]},
        yaxis={"title": "precision", "range": [0, 1.02]},
        height=480,
        **_LAYOUT,
    )
    return _fragment(fig, "pr-curves")


def trajectory_html(
    positions: np.ndarray,
    metrics: LoopMetrics,
    candidates: list[list[Candidate]],
    threshold: float,
    label: str,
    div_id: str,
) -> str:
    """The trajectory (x, y) with the closures at ``threshold``: true ones green, false ones red (a line from
    the query to its match), missed revisits orange; under the mouse each scan's id, each closure's query / match
    ids and score, each missed revisit's decision (`placerec.experiment.evidence.decision_text` of its top
    candidate). ``candidates`` are aligned with ``metrics.query_ids``."""
    import plotly.graph_objects as go

    xy = np.asarray(positions, float)[:, :2]
    q, m, s = metrics.query_ids, metrics.match_ids, metrics.scores
    if metrics.n_candidates and np.isfinite(threshold):
        out = metrics.outcomes_at(threshold)
        tp, fp, accepted = out["tp"], out["fp"], out["accepted"]
    else:
        tp = fp = accepted = np.zeros(q.size, bool)
    missed = metrics.revisit & ~accepted
    fig = go.Figure()
    fig.add_trace(
        go.Scattergl(
            x=xy[:, 0],
            y=xy[:, 1],
            mode="lines",
            name="route",
            line={"color": "#999", "width": 1},
            hovertemplate="scan %{text}<extra></extra>",
            text=[str(i) for i in range(len(xy))],
        )
    )
    for mask, colour, name in ((tp, "#2ca02c", "true closure"), (fp, "#d62728", "false closure")):
        rows = np.flatnonzero(mask)
        if not rows.size:
            continue
        lx = np.full(3 * rows.size, np.nan)
        ly = np.full(3 * rows.size, np.nan)
        lx[0::3], lx[1::3] = xy[q[rows], 0], xy[m[rows], 0]
        ly[0::3], ly[1::3] = xy[q[rows], 1], xy[m[rows], 1]
        fig.add_trace(
            go.Scatter(
                x=lx,
                y=ly,
                mode="lines",
                line={"color": colour, "width": 1},
                hoverinfo="skip",
                showlegend=False,
            )
        )
        fig.add_trace(
            go.Scatter(
                x=xy[q[rows], 0],
                y=xy[q[rows], 1],
                mode="markers",
                marker={"color": colour, "size": 6},
                name=f"{name} ({rows.size})",
                text=[f"query {q[r]} -> match {m[r]}<br>score {s[r]:.4g}" for r in rows],
                hovertemplate="%{text}<extra>" + name + "</extra>",
            )
        )
    rows = np.flatnonzero(missed)
    if rows.size:
        text = []
        for r in rows:
            top = candidates[r][0] if candidates[r] else None
            found = "" if top is None else f"top candidate: match {top.match_id}, score {top.score:.4g}<br>"
            text.append(f"query {q[r]}: missed revisit<br>{found}{decision_text(top, threshold)}")
        fig.add_trace(
            go.Scatter(
                x=xy[q[rows], 0],
                y=xy[q[rows], 1],
                mode="markers",
                marker={"color": "#ff7f0e", "size": 7, "symbol": "x"},
                name=f"missed revisit ({rows.size})",
                text=text,
                hovertemplate="%{text}<extra></extra>",
            )
        )
    fig.update_layout(
        title=f"{label}: closures at max F1 (threshold {threshold:.3g})",
        xaxis={"title": "x [m]"},
        yaxis={"title": "y [m]", "scaleanchor": "x"},
        height=560,
        **_LAYOUT,
    )
    return _fragment(fig, div_id)
