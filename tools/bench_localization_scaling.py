"""Time per localisation against the number of places (the ISHOT paper's sub-linear claim, issue #13 item 6).

A larger map is made of several simulated towns (seeds 0, 1, 2, ...; the same VLP-16 unit), each cut into places
2.5 m apart (one sweep per place, ``placerec build-places --set window_m=0``) and laid side by side 5 km apart. The
first N places (town 0 first) form a map of N places; gator queries of town 0 within 10 m of its first
min(N) places (so that every map covers them) localise in it with probabilistic
voting (``ishot-prob``, the vote model of ``configs/localize.yaml``), with exhaustive matching (every keypoint
matched, ranked by the posterior), with plain vote counting (``ishot-votes``) and with probabilistic voting over an
approximate index (``index: ivf``: faiss IVF, sqrt(descriptors) lists, 16 searched; its build timed apart), and on
request (``--variants``) with the region stop test (``ishot-prob-region``: ``stop_radius_m`` 7.5, ``reject_weight``
0.02, docs/localization.md) and the paper's baselines ``shot-global`` and ``shot-gestalt-votes`` over SHOT places of the
same towns. Printed per N: median and mean
time per localisation (describe + query + verification), median matching time, keypoints consumed, success within
3 m, and the memory of the sparse and of the full posterior tables; then the growth rate: the slope of log(time)
against log(N) between the smallest and the largest map (1 = linear). The last line is one JSON object.

    python tools/bench_localization_scaling.py                   # 50, 200, 800 places; ~15 min the first time
    python tools/bench_localization_scaling.py --sizes 50,200 --n-queries 5
    python tools/bench_localization_scaling.py --sizes 121,800 --variants ishot-prob,shot-global,shot-gestalt-votes
    python tools/bench_localization_scaling.py --variants ishot-prob,ishot-prob-region
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from placerec.artifacts.places import build_places  # noqa: E402
from placerec.intensity import normalize_intensity  # noqa: E402
from placerec.pipelines.keypoint_voting import KeypointVoting  # noqa: E402
from placerec.pipelines.probabilistic_voting import ProbabilisticVoting  # noqa: E402
from placerec.recognizer import LOCALIZE_VERIFY, make_pipeline  # noqa: E402
from placerec.sim import SimulatedSequence, make_localization_split  # noqa: E402
from placerec.three_d.places import PlacesDatabase, PlacesParams  # noqa: E402
from placerec.three_d.posterior import PosteriorTable  # noqa: E402

OFFSET_M = 5000.0


def town_places(seed: int, cache: Path, descriptor: str = "ishot") -> PlacesDatabase:
    tag = "" if descriptor == "ishot" else f"_{descriptor}"
    path = cache / f"places_town_vlp16{tag}_s{seed}.npz"
    if seed == 0 and not tag and (cache / "places_town_vlp16_float32.npz").is_file():
        path = cache / "places_town_vlp16_float32.npz"  # configs/localize.yaml's float32 one
    if not path.is_file():
        seq = SimulatedSequence(world="town", sensor="vlp16", seed=seed, unit_seed=0)
        path.parent.mkdir(parents=True, exist_ok=True)
        params = PlacesParams(
            window_m=0.0, spacing_m=2.5, features={"descriptor": descriptor}, descriptor_store="float32"
        )  # the float32 descriptors its figures were measured with
        build_places(seq, params).save(path)
    return PlacesDatabase.load(path)


def fill(rec: KeypointVoting, dbs: list[PlacesDatabase], n: int) -> None:
    """Add the first ``n`` places of the towns ``dbs`` (town w shifted by w * OFFSET_M in x)."""
    from placerec.verify.candidates import scan_cloud

    added = 0
    for w, db in enumerate(dbs):
        for p in range(len(db)):
            if added == n:
                return
            kp, desc = db.place_features(p)
            pose = db.poses[p].copy()
            pose[0, 3] += w * OFFSET_M
            cloud = scan_cloud(db.clouds[p][0], rec.params.verify)
            rec.add_description(
                w * 100000 + int(db.ids[p]), {"keypoints": kp, "descriptors": desc, "cloud": cloud}, pose
            )
            added += 1


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="50,200,800")
    ap.add_argument("--n-queries", type=int, default=15)
    ap.add_argument("--cache", default=str(ROOT / ".cache" / "localize"))
    ap.add_argument("--vote-model", default=str(ROOT / ".cache" / "localize" / "votes_town_vlp16.npz"))
    ap.add_argument("--figure", default=str(ROOT / "docs" / "figures" / "localization_scaling.png"))
    ap.add_argument("--variants", default="ishot-prob,ishot-exhaustive,ishot-votes,ishot-prob-ivf")
    args = ap.parse_args()
    t_start = time.perf_counter()
    sizes = [int(s) for s in args.sizes.split(",")]
    cache = Path(args.cache)
    wanted = args.variants.split(",")
    dbs: list[PlacesDatabase] = []
    while sum(len(d) for d in dbs) < max(sizes):
        dbs.append(town_places(len(dbs), cache))
        print(f"town {len(dbs) - 1}: {len(dbs[-1])} places", flush=True)
    shot_dbs = (
        [town_places(w, cache, "shot") for w in range(len(dbs))]
        if any(v.startswith("shot") for v in wanted)
        else []
    )
    # gator queries of town 0 within 10 m of one of its first min(sizes) places, so every map size covers them
    split = make_localization_split("town", "vlp16", 0, n_queries=4 * args.n_queries, conditions=("gator",))
    queries = split.queries["gator"]
    first = dbs[0].poses[: min(sizes), :3, 3]
    near = np.linalg.norm(queries.poses[:, None, :2, 3] - first[None, :, :2], axis=2).min(axis=1) <= 10.0
    picked = np.flatnonzero(near)[: args.n_queries]
    model = {"vote_model": args.vote_model} if Path(args.vote_model).is_file() else {}
    same_verify = LOCALIZE_VERIFY  # ishot-votes verifies as the presets of the others do
    variants = {
        "ishot-prob": lambda: make_pipeline("ishot-prob", model),
        "ishot-exhaustive": lambda: make_pipeline("ishot-prob", {**model, "early_stop": False}),
        "ishot-votes": lambda: make_pipeline("ishot-votes", same_verify),
        "ishot-prob-ivf": lambda: make_pipeline("ishot-prob", {**model, "search": {"index": "ivf"}}),
        "ishot-prob-region": lambda: make_pipeline(
            "ishot-prob", {**model, "stop_radius_m": 7.5, "reject_weight": 0.02}
        ),
        "shot-global": lambda: make_pipeline("shot-global"),
        "shot-gestalt-votes": lambda: make_pipeline("shot-gestalt-votes"),
    }
    unknown = set(wanted) - set(variants)
    if unknown:
        raise SystemExit(f"unknown variants {sorted(unknown)}; known: {', '.join(variants)}")
    variants = {name: variants[name] for name in wanted}
    described: dict[str, tuple[list, list]] = {}  # descriptor -> (query descriptions, describe ms)
    for descriptor, describer in (
        ("ishot", make_pipeline("ishot-votes", same_verify)),
        ("shot", make_pipeline("shot-global")),
    ):
        if not any(v.startswith(descriptor + "-") for v in wanted):
            continue
        out: tuple[list, list] = ([], [])
        for q in picked:
            t0 = time.perf_counter()
            out[0].append(describer.describe(normalize_intensity(queries[int(q)])))
            out[1].append((time.perf_counter() - t0) * 1e3)
        described[descriptor] = out
    truth = queries.poses[picked, :3, 3]
    rows = []
    for n in sizes:
        row = {"places": n}
        for descriptor, (_, ms) in described.items():
            row[f"describe_ms_median_{descriptor}" if descriptor != "ishot" else "describe_ms_median"] = (
                round(float(np.median(ms)), 1)
            )
        for name, make in variants.items():
            descs, describe_ms = described["shot" if name.startswith("shot") else "ishot"]
            rec = make()
            fill(rec, shot_dbs if name.startswith("shot") else dbs, n)
            if isinstance(rec, ProbabilisticVoting):
                t0 = time.perf_counter()
                table = rec.posterior_table()
                row["table_build_ms"] = round((time.perf_counter() - t0) * 1e3, 1)
                row["sparse_table_mb"] = round(table.nbytes / 2**20, 3)
                if n <= 2000:
                    full = PosteriorTable(
                        rec.vote_model, np.asarray([T[:3, 3] for T in rec.entries.poses]), "full"
                    )
                    row["full_table_mb"] = round(full.nbytes / 2**20, 3)
            index = rec.params.search.index
            if index != "flat":  # the index is built on the first query: time it apart
                t0 = time.perf_counter()
                rec.search(descs[0]["descriptors"][:1], rec.entries.store.view())
                row[f"{name}_{index}_build_ms"] = round((time.perf_counter() - t0) * 1e3, 1)
            times, matched, ok = [], [], []
            for q, d in enumerate(descs):
                t0 = time.perf_counter()
                cands = rec.query_description(d, k=1, query_id=q)
                times.append(describe_ms[q] + (time.perf_counter() - t0) * 1e3)
                top = cands[0] if cands else None
                matched.append(top.extra.get("keypoints_consumed", top.extra.get("n_query")) if top else 0)
                est = None
                if top is not None and top.relative_pose is not None:
                    w, sid = divmod(top.match_id, 100000)
                    T = dbs[w].scan_poses[sid] @ top.relative_pose
                    est = T[:3, 3] if w == 0 else None  # a place of another town is a wrong answer
                ok.append(est is not None and float(np.linalg.norm(est - truth[q])) <= 3.0)
            row[name] = {
                "median_ms": round(float(np.median(times)), 1),
                "mean_ms": round(float(np.mean(times)), 1),
                "keypoints_consumed": round(float(np.mean(matched)), 1),
                "success_3m": round(float(np.mean(ok)), 3),
            }
            print(n, name, row[name], flush=True)
        rows.append(row)
    growth = {}
    if len(sizes) >= 2:
        for name in variants:
            t = np.array([r[name]["median_ms"] for r in rows])
            growth[name] = round(float(np.polyfit(np.log(sizes), np.log(t), 1)[0]), 3)
    if args.figure:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(5.5, 4), dpi=120)
        for name in variants:
            ax.plot(
                sizes, [r[name]["median_ms"] for r in rows], "o-", label=f"{name} (slope {growth.get(name)})"
            )
        if "describe_ms_median" in rows[0]:
            ax.plot(
                sizes,
                [rows[0]["describe_ms_median"]] * len(sizes),
                "k:",
                label="describe query (ISS + ISHOT)",
            )
        ax.set(
            xscale="log", yscale="log", xlabel="places in the map", ylabel="median time per localisation (ms)"
        )
        ax.set_title("time per localisation vs map size (log-log)", fontsize=9)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(args.figure)
    line = {
        "bench": "localization_scaling",
        "sizes": sizes,
        "n_queries": len(picked),
        "rows": rows,
        "loglog_slope": growth,
        "cores": os.cpu_count(),
        "load_avg": round(os.getloadavg()[0], 2),
        "runtime_s": round(time.perf_counter() - t_start, 1),
    }
    print(json.dumps(line))


if __name__ == "__main__":
    main()
