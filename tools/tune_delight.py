"""Choose DELIGHT's sphere radii and histogram bins on the tuning split (docs/protocol: localisation draw 1).

The first stage of ``delight`` alone (`placerec.pipelines.delight`): every grid point's descriptors of the map
entries (``configs/localize.yaml``'s map, scans at least ``--spacing`` m apart, as the Table III rows use) and of
the tuning queries (`placerec.experiment.protocol.LOCALIZE_TUNING_DRAW`, the three conditions), preprocessed as
the runner does, then each query's entries ranked by `delight_distance`. A query is retrieved at k when one of
its k best entries lies within ``--radius`` m of its true position; the table gives that recall per condition at
k = 1, 5 (the verification's first chunk) and 30 (every entry the verification may reach), the share of queries
with any entry that close (the ceiling), and recall@5 within 10 m (the query spots' distance to the route).

Choice, fixed before running: the highest mean over the conditions of recall@5 within ``--radius``; ties go to
the higher mean recall@5 within 10 m, then recall@1, then the fewer bins and the smaller radii. The grid's outer
radius takes each of ``--outer`` with the inner one at half of it; ``sector_shifts`` off is measured beside the
chosen point (the heading is random at the queries).

``--test`` measures the stored defaults (`DelightParams`), and nothing else, on the test draw
(`LOCALIZE_TEST_DRAW`): a result to report, never a choice (no grid is accepted with it).

    python tools/tune_delight.py                         # 100 queries per condition, ~1 min on 2 cores
    python tools/tune_delight.py --n-queries 30 --outer 20,40 --bins 16,32
    python tools/tune_delight.py --test --n-queries 30   # the defaults on the held-out queries
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from placerec.config import load_config  # noqa: E402
from placerec.experiment.preprocessing import preprocessed_scan  # noqa: E402
from placerec.experiment.protocol import LOCALIZE_TEST_DRAW, LOCALIZE_TUNING_DRAW  # noqa: E402
from placerec.pipelines.delight import DelightParams, delight_distance, make_descriptor  # noqa: E402
from placerec.sim import make_localization_split  # noqa: E402
from placerec.three_d.entries import far_from_all  # noqa: E402

CONDITIONS = ("gator", "pole", "occlusion")
KS = (1, 5, 30)
WIDE_M = 10.0


def spaced_entries(positions: np.ndarray, spacing: float) -> np.ndarray:
    """Indices of the scans that become entries: each at least ``spacing`` from every earlier entry (the rule of
    `KeypointVoting`'s ``places.spacing_m``, `far_from_all`)."""
    kept: list[int] = []
    for i, p in enumerate(positions):
        if spacing <= 0 or far_from_all(positions[kept], p, spacing):
            kept.append(i)
    return np.asarray(kept, np.int64)


def describe_all(seq: Any, indices: Any, grid: list[DelightParams], preprocess: Any) -> list[np.ndarray]:
    """Per grid point, the (len(indices), 2, 8, bins) descriptors of the scans ``indices`` of ``seq``."""
    out: list[list[np.ndarray]] = [[] for _ in grid]
    for i in indices:
        scan, _ = preprocessed_scan(seq, int(i), preprocess)
        for g, params in enumerate(grid):
            out[g].append(make_descriptor(scan, params))
    return [np.stack(d) for d in out]


def recalls(
    map_desc: np.ndarray,
    map_xyz: np.ndarray,
    q_desc: np.ndarray,
    q_xyz: np.ndarray,
    radius: float,
    shifts: bool,
) -> dict[str, float]:
    """Recall@k within ``radius`` (and @5 within `WIDE_M`) of one condition's queries, and the ceiling."""
    hit = {k: [] for k in KS}
    wide, reachable = [], []
    for d, xyz in zip(q_desc, q_xyz, strict=True):
        dist, _ = delight_distance(d, map_desc, shifts)
        order = np.argsort(dist, kind="stable")
        gap = np.linalg.norm(map_xyz[order] - xyz, axis=1)
        for k in KS:
            hit[k].append(bool((gap[:k] <= radius).any()))
        wide.append(bool((gap[:5] <= WIDE_M).any()))
        reachable.append(bool((gap <= radius).any()))
    out = {f"r@{k}": float(np.mean(hit[k])) for k in KS}
    out["r@5_10m"] = float(np.mean(wide))
    out["ceiling"] = float(np.mean(reachable))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(ROOT / "configs" / "localize.yaml"))
    ap.add_argument("--n-queries", type=int, default=100, help="queries per condition")
    ap.add_argument("--outer", default=None, help="outer radii (m); the inner one is half (default 20,40,60)")
    ap.add_argument("--bins", default=None, help="histogram bins (default 16,32,64)")
    ap.add_argument("--spacing", type=float, default=2.5, help="m between map entries (places.spacing_m)")
    ap.add_argument("--radius", type=float, default=3.0, help="m; a retrieved entry this close is right")
    ap.add_argument("--test", action="store_true", help="measure the stored defaults on the test draw")
    args = ap.parse_args()
    if args.test and (args.outer or args.bins):
        ap.error("--test measures the stored defaults only: no --outer / --bins")
    draw = LOCALIZE_TEST_DRAW if args.test else LOCALIZE_TUNING_DRAW
    t0 = time.perf_counter()
    cfg = load_config(args.config)
    sim = cfg.dataset.simulator
    split = make_localization_split(
        sim.world, sim.sensor, sim.seed, n_queries=args.n_queries, n_map=sim.n_scans, draw=draw
    )
    if args.test:
        grid = [DelightParams()]
    else:
        outer, bins = (args.outer or "20,40,60").split(","), (args.bins or "16,32,64").split(",")
        grid = [DelightParams(outer_radius=float(o), inner_radius=float(o) / 2, bins=int(b))
                for o, b in itertools.product(outer, bins)]  # fmt: skip
    entries = spaced_entries(split.map.poses[:, :3, 3], args.spacing)
    map_xyz = split.map.poses[entries, :3, 3]
    map_desc = describe_all(split.map, entries, grid, cfg.preprocess)
    queries = {}
    for cond in CONDITIONS:
        seq = split.queries[cond]
        queries[cond] = (describe_all(seq, range(len(seq)), grid, cfg.preprocess), seq.poses[:, :3, 3])

    def row(g: int, shifts: bool) -> dict[str, Any]:
        per = {
            c: recalls(map_desc[g], map_xyz, qd[g], qxyz, args.radius, shifts)
            for c, (qd, qxyz) in queries.items()
        }
        mean = {m: float(np.mean([per[c][m] for c in CONDITIONS])) for m in per[CONDITIONS[0]]}
        p = grid[g]
        return {"outer_radius": p.outer_radius, "inner_radius": p.inner_radius, "bins": p.bins, "shifts": shifts,
                "conditions": per, "mean": mean}  # fmt: skip

    rows = [row(g, True) for g in range(len(grid))]
    best = max(
        range(len(rows)),
        key=lambda g: (rows[g]["mean"]["r@5"], rows[g]["mean"]["r@5_10m"], rows[g]["mean"]["r@1"],
                       -rows[g]["bins"], -rows[g]["outer_radius"]),
    )  # fmt: skip
    no_shift = row(best, False)
    from rich.console import Console
    from rich.table import Table

    title = (
        f"DELIGHT first stage, {'test' if args.test else 'tuning'} draw {draw}: {args.n_queries} queries per "
        f"condition, {len(entries)} entries {args.spacing} m apart, recall within {args.radius} m "
        "(r@5 10m: within 10 m)"
    )
    table = Table(title=title)
    for col in ("outer / inner m", "bins", "shifts", *CONDITIONS, "mean r@1", "mean r@5", "mean r@30",
                "mean r@5 10m", "ceiling"):  # fmt: skip
        table.add_column(col)
    for r in [*rows, no_shift]:
        cells = [
            f"{r['conditions'][c]['r@1']:.2f} / {r['conditions'][c]['r@5']:.2f} / {r['conditions'][c]['r@30']:.2f}"
            for c in CONDITIONS
        ]
        mark = " *" if r is rows[best] and not args.test else ""
        table.add_row(f"{r['outer_radius']:g} / {r['inner_radius']:g}{mark}", str(r["bins"]), str(r["shifts"]),
                      *cells, *(f"{r['mean'][m]:.3f}" for m in ("r@1", "r@5", "r@30", "r@5_10m", "ceiling")))  # fmt: skip
    Console(width=170).print(table)
    rule = "" if args.test else "; * = chosen (highest mean r@5, ties: r@5 within 10 m, r@1)"
    print(f"per condition: r@1 / r@5 / r@30{rule}")
    line = {
        "tool": "tune_delight",
        "draw": draw,
        "n_queries": args.n_queries,
        "entries": int(len(entries)),
        "spacing_m": args.spacing,
        "radius_m": args.radius,
        "grid": rows,
        "chosen": None if args.test else {k: rows[best][k] for k in ("outer_radius", "inner_radius", "bins")},
        "without_shifts": no_shift["mean"],
        "load_avg": round(os.getloadavg()[0], 2),
        "runtime_s": round(time.perf_counter() - t0, 1),
    }
    print(json.dumps(line))


if __name__ == "__main__":
    main()
