"""Global localisation on the simulator, after the ISHOT paper's Table III (Sec. V-C).

Runs ``configs/localize.yaml`` (localize mode) once per query condition (gator, pole, occlusion) through the same
runner and report as ``placerec run`` (a results folder per condition), after building the places database and
fitting the vote model the ISHOT pipelines read, when their files are missing (``--rebuild`` forces both; the vote
model is fitted on another draw of simulated query scans of all three conditions, never on the evaluated ones).

Only an answer the pipeline accepted counts (`placerec.experiment.report`: a rejected top candidate is no answer;
a pipeline without verification answers with its top candidate). Per condition and pipeline it prints and returns
the share localised (``success_3m``: an accepted 6-DoF position within 3 m), within 1 m and 5 degrees, the queries
with no answer (nothing accepted) and those answered wrongly (accepted, beyond 3 m), median and mean time per
localisation (describe + query + verification, ms), the query keypoints matched against the whole database
(probabilistic voting stops early; vote counting and exhaustive matching use all), and the early-stop rate. The
last line is one JSON object of those figures.

Query draws (`placerec.experiment.protocol`): ``--draw 2`` (the default) is the held-out test draw, the figures to
report; ``--draw 1`` the training queries the vote model was fitted on and ``reject_weight``, the verification
settings and DELIGHT's radii were chosen on (the docs' training-query tables); draw 0 the queries evaluated after
every design change until the split was written down: development data, not a held-out result. The vote model is
fitted on town's draw 1 (30 queries per condition) and never on the evaluated draw, except for ``--draw 1``, whose
output says so (``vote_model_trained_on_evaluated_draw``).

``--world campus|industrial`` localises on that world's map (VLP-16, seed 0; its own places database, built when
missing) with the vote model fitted on town: whether the vote model transfers.

    python tools/eval_localization.py                       # the held-out query draw 2, 30 queries per condition
    python tools/eval_localization.py --draw 1              # the training queries (the docs' training tables)
    python tools/eval_localization.py --world campus --pipelines ishot-prob,delight   # town's vote model on campus
    python tools/eval_localization.py --conditions gator --n-queries 10
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import re
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from placerec.config import apply_overrides, parse_config, read_config_file  # noqa: E402
from placerec.experiment.protocol import LOCALIZE_TEST_DRAW, LOCALIZE_TUNING_DRAW  # noqa: E402
from placerec.experiment.report import report_localize  # noqa: E402
from placerec.experiment.run_folder import make_run_dir  # noqa: E402
from placerec.experiment.runner import PipelineRecord, build_pipelines, run_localize  # noqa: E402

CONDITIONS = ("gator", "pole", "occlusion")
WORLDS = ("town", "campus", "industrial")
#: the world the vote model is fitted on (its training draw: LOCALIZE_TUNING_DRAW)
VOTE_MODEL_WORLD = "town"
#: m between places (docs/localization.md: 2.5 m localised more queries than 5 m with single-sweep places)
PLACE_SPACING = 2.5


def places_stores(cfg: Any) -> dict[str, str]:
    """The places databases the config's pipelines read, each with the descriptor store it is saved in: that of
    the first pipeline reading it (its ``search.descriptor_store``; `PlacesParams`'s default when not set)."""
    from placerec.three_d.places import PlacesParams

    out: dict[str, str] = {}
    for s in cfg.pipelines:
        path = (s.params.get("places") or {}).get("database")
        if path is not None:
            out.setdefault(
                path,
                (s.params.get("search") or {}).get("descriptor_store") or PlacesParams().descriptor_store,
            )
    return out


def ensure_artifacts(cfg: Any, rebuild: bool, figure: Path | None, world: str = "town") -> dict[str, Any]:
    """Build the places databases and fit the vote model named by the config's ISHOT pipelines when missing: the
    places are built once from the map in float32 and saved in each database's store (`places_stores`; clouds
    int16 unless the store is float32, `PlacesDatabase.stored_as`); the vote model is fitted on the first."""
    from placerec.artifacts.places import build_places
    from placerec.artifacts.votes import fit_votes
    from placerec.sim import make_localization_split
    from placerec.three_d.places import PlacesDatabase, PlacesParams
    from placerec.three_d.vote_model import plot_vote_model

    places = places_stores(cfg)
    models = {s.params.get("vote_model") for s in cfg.pipelines} - {None}
    if len(models) > 1:
        raise SystemExit(f"one vote model expected, got {models}")
    info: dict[str, Any] = {}
    sim = cfg.dataset.simulator
    split = make_localization_split(
        sim.world, sim.sensor, sim.seed, n_queries=30, n_map=sim.n_scans, draw=LOCALIZE_TUNING_DRAW
    )
    if places:
        missing = [name for name in places if rebuild or not Path(name).is_file()]
        if missing:
            t0 = time.perf_counter()
            params = PlacesParams(
                window_m=0.0, spacing_m=PLACE_SPACING, descriptor_store="float32", cloud_store="float32"
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
            if world != VOTE_MODEL_WORLD and not mpath.is_file():
                raise SystemExit(f"{mpath}: the {VOTE_MODEL_WORLD} vote model is missing; run on {VOTE_MODEL_WORLD}"
                                 " first")  # fmt: skip
            if (rebuild and world == VOTE_MODEL_WORLD) or not mpath.is_file():
                t0 = time.perf_counter()
                prov = {"places_file": str(path), "training_draw": LOCALIZE_TUNING_DRAW}
                model = fit_votes(db, list(split.queries.values()), provenance=prov)
                model.save(mpath)
                info["fit_votes_s"] = round(time.perf_counter() - t0, 1)
                if figure is not None:
                    plot_vote_model(
                        model, figure, f"vote model, {len(db)} simulated places ({model.taus.size} votes)"
                    )
            from placerec.three_d.vote_model import VoteModel

            model = VoteModel.load(mpath)
            info["vote_model"] = model.summary()
            info["vote_model_training"] = sorted(model.provenance.get("training_sequences", []))
    return info


def training_draws(names: list[str]) -> set[int]:
    """The query draws of a vote model's training sequences, from their names
    (``sim-<world>-...-query-<condition>[-draw<N>]``, `placerec.sim.make_localization_split`)."""
    draws = set()
    for name in names:
        m = re.search(r"-query-[a-z]+(?:-draw(\d+))?$", name)
        if m is None:
            raise SystemExit(f"vote model trained on {name!r}: not a simulated localisation draw")
        draws.add(int(m.group(1) or 0))
    return draws


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


def vote_model_draw_check(training: list[str], draw: int, world: str) -> dict[str, Any]:
    """The vote model's training draws (from its ``training`` sequence names) and whether the evaluated ``draw`` is
    one of them; `SystemExit` when it is and ``draw`` is not the tuning draw (a result on the model's own
    training queries)."""
    draws = training_draws(training)
    on_training = draw in draws and world == VOTE_MODEL_WORLD
    if on_training and draw != LOCALIZE_TUNING_DRAW:
        raise SystemExit(
            f"the vote model was fitted on query draw {draw}: refit it on the tuning draw (--rebuild)"
        )
    return {"vote_model_draws": sorted(draws), "vote_model_trained_on_evaluated_draw": on_training}


def config_data(config: str, world: str, labels: list[str] | None) -> dict[str, Any]:
    """The config as data, on the map of ``world`` (its places databases named after it instead of town; the vote
    model stays the one fitted on town), keeping the pipelines whose label (or name) is in ``labels`` (all when
    None)."""
    data = read_config_file(config)
    data.setdefault("dataset", {}).setdefault("simulator", {})["world"] = world
    specs = data.get("pipelines", [])
    known = [spec.get("label", spec["name"]) for spec in specs]
    unknown = sorted(set(labels or ()) - set(known))
    if unknown:
        raise SystemExit(f"--pipelines: {unknown} not in {config} (its labels: {', '.join(known)})")
    kept = []
    for spec, label in zip(specs, known, strict=True):
        if labels is not None and label not in labels:
            continue
        places = (spec.get("params") or {}).get("places") or {}
        if world != VOTE_MODEL_WORLD and "database" in places:
            if f"_{VOTE_MODEL_WORLD}_" not in places["database"]:
                raise SystemExit(
                    f"{label}: places.database {places['database']} does not name {VOTE_MODEL_WORLD}"
                )
            places["database"] = places["database"].replace(f"_{VOTE_MODEL_WORLD}_", f"_{world}_")
        kept.append(spec)
    data["pipelines"] = kept
    return data


def run_condition(data: dict[str, Any], overrides: list[str], condition: str, out: Path) -> dict[str, Any]:
    raw = apply_overrides(copy.deepcopy(data), [*overrides, f"evaluation.localize.condition={condition}"])
    world, draw = raw["dataset"]["simulator"]["world"], raw["evaluation"]["localize"]["draw"]
    raw["name"] = f"{raw.get('name', 'localize')}_{world}_draw{draw}_{condition}"
    c = parse_config(raw, "localize config")
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
            "answer_rule": m["answer_rule"],
            "no_answer": m["n_no_estimate"],
            "accepted_wrong": m["n_wrong"],
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
    ap.add_argument(
        "--draw",
        type=int,
        default=LOCALIZE_TEST_DRAW,
        help=f"query draw: {LOCALIZE_TEST_DRAW} the held-out test queries (default), {LOCALIZE_TUNING_DRAW} the"
        " training queries the vote model and reject_weight were chosen on, 0 the development draw",
    )
    ap.add_argument(
        "--world", default="town", choices=WORLDS, help=f"map world; the vote model is {VOTE_MODEL_WORLD}'s"
    )
    ap.add_argument(
        "--pipelines",
        default=None,
        help="comma-separated labels of the config's pipelines to run (default: all)",
    )
    args = ap.parse_args()
    t0 = time.perf_counter()
    overrides = [
        *args.set,
        f"evaluation.localize.draw={args.draw}",
        *([] if args.n_queries is None else [f"evaluation.localize.n_queries={args.n_queries}"]),
    ]
    data = config_data(args.config, args.world, args.pipelines.split(",") if args.pipelines else None)
    cfg = parse_config(apply_overrides(copy.deepcopy(data), overrides), args.config)
    figure = Path(args.figure) if args.figure and args.world == VOTE_MODEL_WORLD else None
    info = ensure_artifacts(cfg, args.rebuild, figure, args.world)
    if "vote_model_training" in info:
        info.update(vote_model_draw_check(info["vote_model_training"], args.draw, args.world))
    results = {}
    for cond in args.conditions.split(","):
        results[cond] = run_condition(data, overrides, cond, Path(args.out))
    from rich.console import Console
    from rich.table import Table

    table = Table(
        title=f"global localisation (simulated {args.world}, VLP-16, query draw {args.draw}; accepted answers only)"
    )
    for col in (
        "condition",
        "pipeline",
        "localised 3 m",
        "1 m / 5 deg",
        "median ms",
        "mean ms",
        "keypoints",
        "early stop",
        "verified",
        "no answer",
        "wrong accepted",
    ):
        table.add_column(col)
    fmt = lambda v, p="{:.1%}": "-" if v is None else p.format(v)  # noqa: E731
    for cond, res in results.items():
        for label, r in res["pipelines"].items():
            table.add_row(cond, label, fmt(r["success_3m"]), fmt(r["success_1m_5deg"]), fmt(r["median_ms"], "{:.0f}"),
                          fmt(r["mean_ms"], "{:.0f}"), fmt(r["keypoints_consumed"], "{:.1f}"),
                          fmt(r["early_stop_rate"]), fmt(r["verified"], "{:.1f}"), str(r["no_answer"]),
                          str(r["accepted_wrong"]))  # fmt: skip
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
        "world": args.world,
        "draw": args.draw,
        **info,
        "conditions": {c: r["pipelines"] for c, r in results.items()},
        "matching_reduction_vs_exhaustive": reduction,
        "load_avg": round(os.getloadavg()[0], 2),
        "runtime_s": round(time.perf_counter() - t0, 1),
    }
    print(json.dumps(line))


if __name__ == "__main__":
    main()
