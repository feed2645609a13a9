"""Global localisation on the simulator, after the ISHOT paper's Table III (Sec. V-C).

Runs ``configs/localize.yaml`` (localize mode) once per query condition (gator, pole, occlusion) through the same
runner and report as ``placerec run`` (a results folder per condition), after building the places database and
fitting the vote model the ISHOT pipelines read, when their files are missing (``--rebuild`` forces both; the vote
model is fitted on another draw of simulated query scans of all three conditions, never on the evaluated ones).

Per condition and pipeline it prints and returns: success (estimated 6-DoF position within 3 m), success within
1 m and 5 degrees, median and mean time per localisation (describe + query + verification, ms), the query keypoints
matched against the whole database (probabilistic voting stops early; vote counting and exhaustive matching use
all), and the early-stop rate. The last line is one JSON object of those figures.

    python tools/eval_localization.py                       # 30 queries per condition, ~10 min on 2 cores
    python tools/eval_localization.py --conditions gator --n-queries 10
"""

from __future__ import annotations

import argparse
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
from placerec.experiment.report import make_run_dir, report_localize  # noqa: E402
from placerec.experiment.runner import PipelineRecord, build_pipelines, run_localize  # noqa: E402

CONDITIONS = ("gator", "pole", "occlusion")
#: m between places (docs/localization.md: 2.5 m localised more queries than 5 m with single-sweep places)
PLACE_SPACING = 2.5


def places_stores(cfg: Any) -> dict[str, str]:
    """The places databases the config's pipelines read, each with the descriptor store it is saved in: that of
    the first pipeline reading it (its ``descriptor_store``; `PlacesParams`'s default when not set)."""
    from placerec.three_d.places import PlacesParams

    out: dict[str, str] = {}
    for s in cfg.pipelines:
        if s.params.get("places_db") is not None:
            out.setdefault(
                s.params["places_db"], s.params.get("descriptor_store") or PlacesParams().descriptor_store
            )
    return out


def ensure_artifacts(cfg: Any, rebuild: bool, figure: Path | None) -> dict[str, Any]:
    """Build the places databases and fit the vote model named by the config's ISHOT pipelines when missing: the
    places are built once from the map in float32 and saved in each database's store (`places_stores`; clouds
    int16 unless the store is float32, `PlacesDatabase.stored_as`); the vote model is fitted on the first."""
    from placerec.pipelines.vote_fitting import fit_votes
    from placerec.sim import make_localization_split
    from placerec.three_d.places import PlacesDatabase, PlacesParams, build_places
    from placerec.three_d.vote_model import plot_vote_model

    places = places_stores(cfg)
    models = {s.params.get("vote_model") for s in cfg.pipelines} - {None}
    if len(models) > 1:
        raise SystemExit(f"one vote model expected, got {models}")
    info: dict[str, Any] = {}
    sim = cfg.dataset.simulator
    split = make_localization_split(sim.world, sim.sensor, sim.seed, n_queries=30, n_map=sim.n_scans, draw=1)
    if places:
        missing = [name for name in places if rebuild or not Path(name).is_file()]
        if missing:
            t0 = time.perf_counter()
            params = PlacesParams(
                window_m=0.0, place_spacing=PLACE_SPACING, descriptor_store="float32", cloud_store="float32"
            )
            full = build_places(split.map, params)
            for name in missing:
                Path(name).parent.mkdir(parents=True, exist_ok=True)
                clouds = "float32" if places[name] == "float32" else "int16"
                full.stored_as(places[name], clouds).save(name)
            info["build_places_s"] = round(time.perf_counter() - t0, 1)
        path = Path(next(iter(places)))
        db = PlacesDatabase.load(path)
        info["places"] = len(db)
        info["place_keypoints"] = int(db.kp_offsets[-1])
        info["place_bytes"] = {name: round(Path(name).stat().st_size / len(db)) for name in places}
        if models:
            mpath = Path(models.pop())
            if rebuild or not mpath.is_file():
                t0 = time.perf_counter()
                model = fit_votes(db, list(split.queries.values()), provenance={"places_file": str(path)})
                model.save(mpath)
                info["fit_votes_s"] = round(time.perf_counter() - t0, 1)
                if figure is not None:
                    plot_vote_model(
                        model, figure, f"vote model, {len(db)} simulated places ({model.taus.size} votes)"
                    )
            from placerec.three_d.vote_model import VoteModel

            info["vote_model"] = VoteModel.load(mpath).summary()
    return info


def query_figures(record: PipelineRecord) -> dict[str, Any]:
    """Keypoints consumed, early-stop rate, places verified and time per localisation of one pipeline's queries."""
    per_scan = record.per_scan_ms()
    consumed, stops, match, verified = [], [], [], []
    for cands in record.candidates:
        top = cands[0].extra if cands else {}
        if "keypoints_consumed" in top:
            consumed.append(top["keypoints_consumed"])
            if "early_stop" in top:  # pipelines that can stop early (not global registration)
                stops.append(bool(top["early_stop"]))
            match.append(float(top.get("match_ms", 0.0)))
            if "n_verified" in top:
                verified.append(top["n_verified"])
        elif "n_query" in top:  # vote counting: every keypoint matched against the database
            consumed.append(top["n_query"])
    return {
        "median_ms": round(float(np.median(per_scan)), 1) if per_scan.size else None,
        "mean_ms": round(float(np.mean(per_scan)), 1) if per_scan.size else None,
        "keypoints_consumed": round(float(np.mean(consumed)), 1) if consumed else None,
        "keypoints_consumed_median": round(float(np.median(consumed)), 1) if consumed else None,
        "early_stop_rate": round(float(np.mean(stops)), 3) if stops else None,
        "match_ms": round(float(np.mean(match)), 1) if match else None,
        "verified": round(float(np.mean(verified)), 2) if verified else None,
    }


def accepted_wrong(
    record: PipelineRecord, map_poses: np.ndarray, query_poses: np.ndarray, radius: float
) -> int:
    """Queries whose top candidate was accepted by the verification with a pose more than ``radius`` off: false
    localisations a user would act on."""
    n = 0
    for q, cands in zip(record.query_ids, record.candidates, strict=True):
        if cands and cands[0].extra.get("accepted") and cands[0].relative_pose is not None:
            T = map_poses[cands[0].match_id] @ cands[0].relative_pose
            n += int(np.linalg.norm(T[:3, 3] - query_poses[q][:3, 3]) > radius)
    return n


def run_condition(config: str, overrides: list[str], condition: str, out: Path) -> dict[str, Any]:
    c = load_config(config, [*overrides, f"evaluation.localize.condition={condition}"])
    c = load_config(
        config, [*overrides, f"evaluation.localize.condition={condition}", f"name={c.name}_{condition}"]
    )
    pipelines = build_pipelines(c)
    run = make_run_dir(c, out)
    map_seq, query_seq, records = run_localize(c, None, pipelines)
    payload = report_localize(c, run, map_seq, query_seq, records)
    rows = {}
    for record in records:
        m = payload["pipelines"][record.label]
        rows[record.label] = {
            "success_3m": m["success_rate"],
            "success_1m_5deg": m["fine_success_rate"],
            **query_figures(record),
            "accepted_wrong": accepted_wrong(
                record, map_seq.poses, query_seq.poses, c.evaluation.localize.success_distance
            ),
            "n_queries": m["n_queries"],
        }
    return {"run": str(run), "pipelines": rows}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(ROOT / "configs" / "localize.yaml"))
    ap.add_argument("--conditions", default=",".join(CONDITIONS))
    ap.add_argument("--n-queries", type=int, default=None, help="override evaluation.localize.n_queries")
    ap.add_argument("--out", default="results/localization")
    ap.add_argument("--rebuild", action="store_true", help="rebuild the places databases and the vote model")
    ap.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="config override (repeatable)"
    )
    ap.add_argument("--figure", default=str(ROOT / "docs" / "figures" / "vote_model_town.png"))
    args = ap.parse_args()
    t0 = time.perf_counter()
    overrides = [
        *args.set,
        *([] if args.n_queries is None else [f"evaluation.localize.n_queries={args.n_queries}"]),
    ]
    cfg = load_config(args.config, overrides)
    info = ensure_artifacts(cfg, args.rebuild, Path(args.figure) if args.figure else None)
    results = {}
    for cond in args.conditions.split(","):
        results[cond] = run_condition(args.config, overrides, cond, Path(args.out))
    from rich.console import Console
    from rich.table import Table

    table = Table(title="global localisation (simulated town, VLP-16)")
    for col in (
        "condition",
        "pipeline",
        "success 3 m",
        "1 m / 5 deg",
        "median ms",
        "mean ms",
        "keypoints",
        "early stop",
        "verified",
        "wrong accepted",
    ):
        table.add_column(col)
    fmt = lambda v, p="{:.1%}": "-" if v is None else p.format(v)  # noqa: E731
    for cond, res in results.items():
        for label, r in res["pipelines"].items():
            table.add_row(cond, label, fmt(r["success_3m"]), fmt(r["success_1m_5deg"]), fmt(r["median_ms"], "{:.0f}"),
                          fmt(r["mean_ms"], "{:.0f}"), fmt(r["keypoints_consumed"], "{:.1f}"),
                          fmt(r["early_stop_rate"]), fmt(r["verified"], "{:.1f}"), str(r["accepted_wrong"]))  # fmt: skip
    Console().print(table)
    reduction = {}
    for cond, res in results.items():
        e = res["pipelines"].get("ishot-exhaustive")
        for label in ("ishot-prob", "ishot-prob-region-stop"):
            p = res["pipelines"].get(label)
            if p and e and p["keypoints_consumed"] and p["match_ms"]:
                reduction.setdefault(label, {})[cond] = {
                    "keypoints_x": round(e["keypoints_consumed"] / p["keypoints_consumed"], 2),
                    "match_time_x": round(e["match_ms"] / p["match_ms"], 2),
                }
    line = {
        "tool": "eval_localization",
        "config": os.path.relpath(args.config, ROOT),
        **info,
        "conditions": {c: r["pipelines"] for c, r in results.items()},
        "matching_reduction_vs_exhaustive": reduction,
        "load_avg": round(os.getloadavg()[0], 2),
        "runtime_s": round(time.perf_counter() - t0, 1),
    }
    print(json.dumps(line))


if __name__ == "__main__":
    main()
