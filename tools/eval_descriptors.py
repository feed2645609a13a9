"""Table II of the ISHOT paper on simulated data: descriptor matching against a places database, PR over tau, AUC.

Protocol (Guo et al. 2019, Sec. V-B): a map sequence (simulated VLP-16, the paper's sensor) is cut into places
(`placerec.three_d.places.build_places`: ISS-BR keypoints, 7 m support, 0.4 m voxels, 40 m crop). Every keypoint
descriptor of every query scan (gator / pole / occlusion sets of `placerec.sim.make_localization_split`) is
matched to its two nearest database descriptors (exact L2); ``tau = d1 / d2`` (eq. 4). A match is a true
positive when the place of the 1st neighbour lies within 5 m (horizontal) of the query's ground-truth position;
every detected query keypoint is a positive. Sweeping the acceptance threshold ``tau < t`` for t in [0.5, 1]
gives precision = TP / accepted and recall = TP / keypoints; the AUC is the trapezoidal area under that
precision-recall curve (between the recalls at t = 0.5 and t = 1, no extrapolation). ``chance`` is the
precision of matching every keypoint to a random place. A paired bootstrap over the query scans gives 90% AUC
intervals and how often each link of the paper's ordering holds.

Places (``--window-m``): 0 (default) makes every place one map sweep (places every 5 m, overlapping extents),
which matches the density of the simulator's queries (one sweep each); 10 accumulates the sweeps within +-10 m of
travel as in Sec. IV-B (`PlacesParams` default), which the paper pairs with dense queries: with single-sweep
queries against accumulated places every descriptor falls to chance level here (docs/descriptors.md).

Descriptors: SHOT (352), ISHOT on raw intensity (linear, raw 100 -> 1, the sensor default), ISHOT-C on
intensity calibrated with `placerec.calibration` (Levinson & Thrun, fitted on the map sequence itself, without
ground truth), ISHOT-C* on the simulator's ground-truth inverse beam response (an *oracle* calibration, an upper
bound, not in the paper), FPFH (33). All use the same keypoints (intensity does not move them); calibrated
intensity is applied at every range (no 30 m cut-off), so the rows differ only by their intensity cue.

Queries (``--query-mode``): ``single`` (default) is the query set's scan, one VLP-16 sweep, as the simulator
renders it; ``actuated`` emulates the paper's actuated sensor (two rotations of a tilted spinning VLP-16, a dense
static scan): eight sweeps at the query pose with the sensor tilted 35 deg about axes 45 deg apart, merged in the
query frame (the simulator is not changed; only the query is composed from several of its sweeps).

Simulated scans are cached in memory and shared by all descriptors. Ends with exactly one JSON line.

    python tools/eval_descriptors.py [--world town] [--n-map 380] [--n-queries 30] [--window-m 0]
        [--query-mode single|actuated] [--descriptors shot,ishot,ishot-c,ishot-c-oracle,fpfh]
        [--figure docs/figures/descriptors_pr.png]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from placerec.artifacts.places import build_places
from placerec.intensity import normalize_intensity
from placerec.sim import make_localization_split
from placerec.three_d import FeatureParams, extract_features
from placerec.three_d.places import PlacesParams
from placerec.types import Scan

CONDITIONS = ("gator", "pole", "occlusion")
PAPER = {  # Table II, AUC (gator, pole)
    "fpfh": (0.0117, 0.0135),
    "shot": (0.0849, 0.0578),
    "ishot": (0.1454, 0.0883),
    "ishot-c": (0.1477, 0.0921),
}
LABELS = {
    "shot": "SHOT",
    "ishot": "ISHOT",
    "ishot-c": "ISHOT-C",
    "ishot-c-oracle": "ISHOT-C* (oracle)",
    "fpfh": "FPFH",
}


def _rot(axis: int, angle: float) -> np.ndarray:
    T = np.eye(4)
    a, b = [(1, 2), (2, 0), (0, 1)][axis]
    c, s = np.cos(angle), np.sin(angle)
    T[a, a], T[a, b], T[b, a], T[b, b] = c, -s, s, c
    return T


def actuated_scan(seq, i: int, n: int = 8, tilt_deg: float = 35.0) -> Scan:
    """``n`` sweeps at pose ``i`` with the sensor tilted ``tilt_deg`` about axes spread over 360 deg, merged in
    the pose's frame (an emulation of the paper's actuated, tilted VLP-16; rings keep their beam ids)."""
    T, t = seq.poses[i], float(seq.timestamps[i])
    xyz, inten, ring = [], [], []
    for k in range(n):
        R = _rot(2, 2 * np.pi * k / n) @ _rot(0, np.radians(tilt_deg))
        sweep = seq.scan_at(T @ R, timestamp=t, index=100_000 + n * i + k)
        xyz.append(sweep.xyz @ R[:3, :3].T.astype(np.float32))
        inten.append(sweep.intensity)
        ring.append(sweep.ring)
    return Scan(np.concatenate(xyz), np.concatenate(inten), ring=np.concatenate(ring), sensor=sweep.sensor)


class CachedSequence:
    """Renders each scan of a sequence once (the same scan feeds every descriptor); ``actuated`` composes
    queries with `actuated_scan`."""

    def __init__(self, seq, actuated: bool = False) -> None:
        self.seq = seq
        self.actuated = actuated
        self._cache: dict[int, Scan] = {}

    def __len__(self) -> int:
        return len(self.seq)

    def __getitem__(self, i: int) -> Scan:
        i = int(i)
        if i not in self._cache:
            self._cache[i] = actuated_scan(self.seq, i) if self.actuated else self.seq[i]
        return self._cache[i]

    @property
    def poses(self):
        return self.seq.poses

    @property
    def timestamps(self):
        return self.seq.timestamps

    @property
    def name(self) -> str:
        return self.seq.name


def oracle_calibration(response) -> Callable[[Scan], Scan]:
    """Ground-truth inverse of the simulated unit's per-beam response, clipped to [0, 1] (an oracle)."""

    def apply(scan: Scan) -> Scan:
        app = response.to_apparent(scan.intensity.astype(np.float64), scan.ring.astype(np.int64))
        return scan.with_intensity(np.clip(app, 0.0, 1.0).astype(np.float32))

    return apply


def real_calibration(map_seq, step: int) -> tuple[Callable[[Scan], Scan] | None, str]:
    """Levinson-Thrun calibration fitted on the map sequence (None and the reason if unavailable)."""
    try:
        from placerec.calibration import CalibrationParams, calibrate_sequence
    except ImportError as exc:
        return None, f"placerec.calibration not importable ({exc})"
    t0 = time.perf_counter()
    try:
        table = calibrate_sequence(map_seq, CalibrationParams(step=step))
    except Exception as exc:  # another component, still in progress: report and go on with the oracle
        return None, f"calibrate_sequence failed ({type(exc).__name__}: {exc})"
    print(f"calibration: Levinson-Thrun table fitted on {map_seq.name} (every {step}th scan) in "
          f"{time.perf_counter() - t0:.1f} s")  # fmt: skip
    return (lambda scan: table.apply(scan, max_range=None)), "levinson"


def pr_curve(tau: np.ndarray, tp: np.ndarray, n_pos: int, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Precision and recall of accepting matches with ``tau < t`` for every t of ``grid``."""
    order = np.argsort(tau)
    ts, cum_tp = tau[order], np.cumsum(tp[order])
    acc = np.searchsorted(ts, grid, side="left")
    tps = np.where(acc > 0, cum_tp[np.maximum(acc - 1, 0)], 0)
    prec = np.where(acc > 0, tps / np.maximum(acc, 1), 1.0)
    return prec, tps / max(n_pos, 1)


def auc(prec: np.ndarray, rec: np.ndarray) -> float:
    return float(np.sum(np.diff(rec) * (prec[1:] + prec[:-1]) / 2))


def evaluate(name, intensity, feats, map_seq, queries, places_params, gt_xy, grid):
    """Build the places database with ``feats``/``intensity``, match every query keypoint, return the results."""
    t0 = time.perf_counter()
    pp = places_params.model_copy(update={"features": feats})
    db = build_places(map_seq, pp, intensity=intensity, intensity_label=name)
    t_db = time.perf_counter() - t0
    place_xy = db.poses[:, :2, 3]
    row_place = db.row_place
    out = {"places": len(db), "db_descriptors": int(db.descriptors.shape[0]), "db_build_s": round(t_db, 1)}
    for cond, seq in queries.items():
        taus, tps, near, used, n_kp, t_scan = [], [], [], [], 0, []
        for q in range(len(seq)):
            t1 = time.perf_counter()
            lf = extract_features(intensity(seq[q]), feats)
            if len(lf) == 0:
                continue
            dist, idx = db.descriptors.view().knn2(lf.descriptors)
            t_scan.append(time.perf_counter() - t1)
            with np.errstate(divide="ignore", invalid="ignore"):
                tau = np.where(dist[:, 1] > 0, dist[:, 0] / dist[:, 1], 1.0)
            d = np.linalg.norm(place_xy[row_place[idx[:, 0]]] - gt_xy[cond][q], axis=1)
            taus.append(tau)
            tps.append(d <= 5.0)
            # a random place per match: the fraction of places within 5 m of the query (keypoint-weighted above)
            near.append(np.mean(np.linalg.norm(place_xy - gt_xy[cond][q], axis=1) <= 5.0))
            used.append(q)
            n_kp += len(lf)
        tau, tp = np.concatenate(taus), np.concatenate(tps)
        prec, rec = pr_curve(tau, tp, n_kp, grid)
        out[cond] = {
            "chance_precision": round(float(np.average(near, weights=[len(t) for t in taus])), 4),
            "auc": round(auc(prec, rec), 4),
            "keypoints": n_kp,
            "keypoints_per_scan": round(n_kp / len(seq), 1),
            "recall_at_1": round(float(rec[-1]), 4),
            "precision_at_1": round(float(prec[-1]), 4),
            "time_per_scan_s": round(float(np.mean(t_scan)), 3),
            "precision": prec.round(4).tolist(),
            "recall": rec.round(4).tolist(),
            "per_query": {q: (t, p) for q, t, p in zip(used, taus, tps, strict=True)},
        }
    return out


def bootstrap(results, conds, c_key, grid, reps: int, seed: int = 0):
    """Resample the query scans (paired across descriptors): 90% AUC intervals and how often each link of the
    ordering holds."""
    rng = np.random.default_rng(seed)
    out = {}
    for cond in conds:
        n = max(max(r[cond]["per_query"], default=-1) + 1 for r in results.values())
        aucs = {name: np.empty(reps) for name in results}
        for b in range(reps):
            sample = rng.integers(0, n, n)
            for name, r in results.items():
                pq = r[cond]["per_query"]
                parts = [pq[q] for q in sample if q in pq]
                tau = np.concatenate([t for t, _ in parts])
                tp = np.concatenate([p for _, p in parts])
                aucs[name][b] = auc(*pr_curve(tau, tp, tau.size, grid))
        ci = {name: [round(float(v), 4) for v in np.percentile(a, [5, 95])] for name, a in aucs.items()}
        links = {}
        if all(k in aucs for k in ("shot", "ishot", "fpfh", c_key)):
            links = {
                "ishot_c_ge_ishot": float(np.mean(aucs[c_key] >= aucs["ishot"])),
                "ishot_gt_shot": float(np.mean(aucs["ishot"] > aucs["shot"])),
                "shot_gt_fpfh": float(np.mean(aucs["shot"] > aucs["fpfh"])),
            }
        out[cond] = {"auc_ci90": ci, "link_frequency": links}
    return out


def ordering(aucs: dict[str, float], c_key: str) -> dict[str, bool]:
    """Each link of the paper's ordering ISHOT-C >= ISHOT > SHOT > FPFH."""
    return {
        "ishot_c_ge_ishot": aucs[c_key] >= aucs["ishot"],
        "ishot_gt_shot": aucs["ishot"] > aucs["shot"],
        "shot_gt_fpfh": aucs["shot"] > aucs["fpfh"],
    }


def figure(results, grid, path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    conds = [c for c in CONDITIONS if any(c in r for r in results.values())]
    fig, axes = plt.subplots(1, len(conds), figsize=(4.6 * len(conds), 4.0), squeeze=False)
    for ax, cond in zip(axes[0], conds, strict=True):
        for name, r in results.items():
            if cond in r:
                ax.plot(
                    r[cond]["recall"], r[cond]["precision"], label=f"{LABELS[name]} ({r[cond]['auc']:.3f})"
                )
        ax.set(title=f"{cond}", xlabel="recall", ylabel="precision", ylim=(0, 1.02))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--world", default="town")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--n-map", type=int, default=None, help="map scans (None: the route's ~380 at 1 m)")
    ap.add_argument("--n-queries", type=int, default=30, help="query scans per condition")
    ap.add_argument("--conditions", default=",".join(CONDITIONS))
    ap.add_argument("--descriptors", default="shot,ishot,ishot-c,ishot-c-oracle,fpfh")
    ap.add_argument("--place-spacing", type=float, default=PlacesParams.model_fields["spacing_m"].default)
    ap.add_argument(
        "--window-m", type=float, default=0.0, help="0: one sweep per place; 10: Sec. IV-B places"
    )
    ap.add_argument(
        "--member-spacing", type=float, default=PlacesParams.model_fields["member_spacing"].default
    )
    ap.add_argument("--bootstrap", type=int, default=300, help="query resamples for intervals (0: none)")
    ap.add_argument("--query-mode", choices=("single", "actuated"), default="single")
    ap.add_argument("--calibration-step", type=int, default=2, help="calibrate on every n-th map scan")
    ap.add_argument("--figure", type=Path, default=Path("docs/figures/descriptors_pr.png"))
    args = ap.parse_args()

    t_start = time.perf_counter()
    conds = tuple(c for c in args.conditions.split(",") if c)
    names = [d for d in args.descriptors.split(",") if d]
    split = make_localization_split(
        args.world, "vlp16", seed=args.seed, n_queries=args.n_queries, n_map=args.n_map, conditions=conds
    )
    map_seq = CachedSequence(split.map)
    queries = {c: CachedSequence(split.queries[c], args.query_mode == "actuated") for c in conds}
    gt_xy = {c: split.queries[c].poses[:, :2, 3] for c in conds}
    near = {c: split.nearest_map(c)[1] for c in conds}
    places_params = PlacesParams(
        spacing_m=args.place_spacing, window_m=args.window_m, member_spacing=args.member_spacing,
        store_clouds=False, descriptor_store="float32",  # the descriptors themselves, not their 8-bit codes
    )  # fmt: skip
    print(
        f"{os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}; map {split.map.name}: {len(split.map)} scans "
        f"(VLP-16); queries per condition: {args.n_queries}; places every {args.place_spacing} m, window "
        f"+-{args.window_m} m of travel, member scans every {args.member_spacing} m; queries: {args.query_mode}"
    )
    for c in conds:
        print(
            f"  {c}: distance to the nearest map scan median {np.median(near[c]):.1f} m, max {near[c].max():.1f} m"
        )

    intensity_fns: dict[str, Callable[[Scan], Scan]] = {
        "shot": normalize_intensity,
        "ishot": normalize_intensity,
        "fpfh": normalize_intensity,
        "ishot-c-oracle": oracle_calibration(split.map.beam_response),
    }
    calib_note = "not run"
    if "ishot-c" in names:
        fn, calib_note = real_calibration(map_seq, args.calibration_step)
        if fn is None:
            print(
                f"ISHOT-C: {calib_note}; ISHOT-C is SKIPPED, only the ORACLE calibration (ISHOT-C*) is reported"
            )
            names.remove("ishot-c")
        else:
            intensity_fns["ishot-c"] = fn
    grid = np.linspace(0.5, 1.0, 101)
    results = {}
    for name in names:
        desc = "ishot" if name.startswith("ishot") else name
        feats = FeatureParams(descriptor=desc)
        r = evaluate(name, intensity_fns[name], feats, map_seq, queries, places_params, gt_xy, grid)
        results[name] = r
        line = "  ".join(
            f"{c} AUC {r[c]['auc']:.4f} (R@1 {r[c]['recall_at_1']:.3f}, chance {r[c]['chance_precision']:.3f})"
            for c in conds
        )
        print(
            f"{LABELS[name]:<18} {r['places']} places / {r['db_descriptors']} descr ({r['db_build_s']} s): {line}"
        )

    print(
        f"\n{'descriptor':<18}"
        + "".join(f"{c + ' AUC':>14}{'rel.':>9}" for c in conds)
        + f"{'s/scan':>9}   paper (gator, pole)"
    )
    for name, r in results.items():
        row = f"{LABELS[name]:<18}"
        for c in conds:
            rel = (r[c]["auc"] / results["shot"][c]["auc"] - 1) * 100 if "shot" in results else float("nan")
            row += f"{r[c]['auc']:>14.4f}{rel:>+8.1f}%"
        t = np.mean([r[c]["time_per_scan_s"] for c in conds])
        paper = PAPER.get(name)
        row += f"{t:>9.2f}   " + (f"{paper[0]:.4f}, {paper[1]:.4f}" if paper else "-")
        print(row)

    c_key = "ishot-c" if "ishot-c" in results else "ishot-c-oracle"
    holds = {}
    if all(k in results for k in ("shot", "ishot", "fpfh", c_key)):
        for c in conds:
            links = ordering({k: results[k][c]["auc"] for k in results}, c_key)
            holds[c] = {**links, "all": all(links.values())}
            print(f"ordering ISHOT-C >= ISHOT > SHOT > FPFH on {c} (ISHOT-C = {LABELS[c_key]}): {holds[c]}")

    boot = bootstrap(results, conds, c_key, grid, args.bootstrap) if args.bootstrap else {}
    for c, b in boot.items():
        cis = ", ".join(f"{LABELS[k]} {v[0]:.4f}-{v[1]:.4f}" for k, v in b["auc_ci90"].items())
        print(f"bootstrap over {c} queries ({args.bootstrap}x): AUC 90% intervals {cis}")
        if b["link_frequency"]:
            print(f"  fraction of resamples in which each link holds: {b['link_frequency']}")

    extent = "one sweep each" if args.window_m == 0 else f"sweeps within +-{args.window_m} m of travel"
    title = (
        f"{split.map.name}: {results[names[0]]['places']} places (every {args.place_spacing} m, {extent}); "
        f"{args.query_mode}-sweep queries; tau 0.5..1; TP: place within 5 m"
    )
    figure(results, grid, args.figure, title)
    print(f"figure: {args.figure}")
    summary = {
        "tool": "eval_descriptors",
        "world": args.world,
        "sensor": "vlp16",
        "n_map": len(split.map),
        "n_queries": args.n_queries,
        "place_spacing": args.place_spacing,
        "window_m": args.window_m,
        "query_mode": args.query_mode,
        "calibration": calib_note,
        "ishot_c_row": c_key,
        "auc": {name: {c: r[c]["auc"] for c in conds} for name, r in results.items()},
        "recall_at_1": {name: {c: r[c]["recall_at_1"] for c in conds} for name, r in results.items()},
        "chance_precision": {c: results[names[0]][c]["chance_precision"] for c in conds},
        "places": results[names[0]]["places"],
        "keypoints_per_scan": {c: results[names[0]][c]["keypoints_per_scan"] for c in conds},
        "ordering_holds": {c: h["all"] for c, h in holds.items()},
        "ordering_links": {c: {k: v for k, v in h.items() if k != "all"} for c, h in holds.items()},
        "bootstrap": boot,
        "runtime_s": round(time.perf_counter() - t_start, 1),
    }
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
