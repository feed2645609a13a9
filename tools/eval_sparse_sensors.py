"""Sparse spinning sensors (VLP-16, HDL-32E): features per image and repeatability of ORB, BRISK, SURF and
SuperPoint per image option (issue #28 item 3). TUNING data only: town seed 0 (the tuning cell) and the feature
evaluation's world seeds 200-203 (placerec.experiment.protocol); never a test seed.

Options (the images each extractor sees):

* ``scan``: one scan per pair member, 1 m spacing, taken at rest (the spinning cells' capture today), the
  pipelines' image (``auto``: per-beam, 16 / 32 rows) upsampled by rows before extraction (x8 / x4, the default);
* ``scan x1``: the same without row upsampling (``row_upsample: 1``);
* ``kf<M>m <odo> <image>``: keyframes of M metres (`placerec.keyframes.KeyframeSequence`) of scans taken at
  10 Hz while moving (``sweep_motion``), de-skewed and accumulated with the simulator's 1 %-drift odometry
  (``drift``, what the benchmark's capture uses) or the true poses (``true``), projected ``per-beam`` (rows
  upsampled as today) or ``spherical`` at a fixed pixel size (0.2 / 0.4 deg; ``fill_radius_px`` 1).

Pairs: at arc positions drawn once per sequence (the same places for every option), ``ahead`` pairs (a frame and
the frame 3-8 m further along the route) and ``revisit`` pairs (a frame on a later pass and the nearest frame of a
pass at least 120 m of path earlier, within 5 m: what loop closure has to match; ``same`` / ``reverse`` by
heading). Figures per pair (`placerec.eval.features.evaluate_pair`, as tools/eval_features.py): keypoints per
image, repeatability (3 px / 0.3 m) and its chance level, matching score, match precision and the correct mutual
matches per pair (what RANSAC's inlier count and so the verified score, docs/verification.md, depend on). Extractors are those of
the pipelines (orb-dbow's ORB, brisk-hbst's BRISK, surf-dbow's FAST+SURF, superpoint-dbow's SuperPoint) and ORB
and SuperPoint keeping 1000 features instead of 300 (``n1000``).

    .venv/bin/python tools/eval_sparse_sensors.py            # ~9 min on 2 shared cores (--pairs 8: ~12 min)
    .venv/bin/python tools/eval_sparse_sensors.py --quick    # ~1 min: town seed 0, VLP-16, fewer options

Prints a table per sensor (means over all pairs, and repeatability over revisit pairs) and ends with one JSON line.
"""

from __future__ import annotations

import argparse
import json
import time
from functools import partial
from typing import Any

import numpy as np

from placerec.config import DatasetConfig, experiment_preprocess
from placerec.eval.features import PairTruth, View, evaluate_pair, mean_scores
from placerec.experiment.datasets import open_dataset
from placerec.experiment.protocol import is_test_seed
from placerec.features import make_extractor
from placerec.image import ImageParams
from placerec.keyframes import KeyframeParams, KeyframeSequence
from placerec.preprocess import preprocess_scan
from placerec.recognizer import make_pipeline

EXCLUSION_M = 120.0
REVISIT_M = 5.0
AHEAD_M = (3.0, 8.0)
#: (world, seed): the tuning cell and the feature evaluation's seeds (protocol.py: 200-203)
DATASETS = (("town", 0), ("campus", 200))
QUICK_DATASETS = (("town", 0),)


def extractors() -> dict[str, tuple[str, dict]]:
    """label -> (registry name, params) of the pipelines' extractors."""
    out = {}
    for label, pipe in (
        ("orb", "orb-dbow"),
        ("brisk", "brisk-hbst"),
        ("surf", "surf-dbow"),
        ("superpoint", "superpoint-dbow"),
    ):
        p = make_pipeline(pipe).params
        out[label] = (p.features, p.feature_params.model_dump())
    for label in ("orb", "superpoint"):
        name, params = out[label]
        out[f"{label} n1000"] = (name, dict(params, nfeatures=1000))
    return out


class CachedSequence:
    """A sequence whose rendered scans are kept (keyframes of several windows and odometries share them)."""

    def __init__(self, seq: Any) -> None:
        self.seq = seq
        self._scans: dict[int, Any] = {}

    def __len__(self) -> int:
        return len(self.seq)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.seq, name)

    def __getitem__(self, i: int) -> Any:
        i = int(i)
        if i not in self._scans:
            self._scans[i] = self.seq[i]
        return self._scans[i]


def arc_length(poses: np.ndarray) -> np.ndarray:
    xyz = poses[:, :3, 3]
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xyz, axis=0), axis=1))])


def draw_places(arc_total: float, n: int, seed: int) -> np.ndarray:
    """``n`` arc positions, one drawn uniformly in each of ``n`` equal stretches of the route."""
    rng = np.random.default_rng(seed)
    edges = np.linspace(0.0, arc_total, n + 1)
    return np.array([rng.uniform(a, b) for a, b in zip(edges[:-1], edges[1:], strict=True)])


def pairs_of(
    poses: np.ndarray, places_ahead: np.ndarray, places_revisit: np.ndarray, seed: int
) -> list[tuple]:
    """(a, b, kind) frame pairs: ahead pairs at the arc positions ``places_ahead``, revisit pairs at the shares
    ``places_revisit`` (in [0, 1]) of the frames that have an earlier pass (module docstring)."""
    arc = arc_length(poses)
    xyz = poses[:, :3, 3]
    heading = poses[:, :3, 0]
    rng = np.random.default_rng(seed)
    out = []
    for s in places_ahead:
        a = int(np.argmin(np.abs(arc - s)))
        target = arc[a] + rng.uniform(*AHEAD_M)
        later = np.flatnonzero(arc > arc[a] + 1e-6)
        if later.size == 0:
            continue
        b = int(later[np.argmin(np.abs(arc[later] - target))])
        out.append((a, b, "ahead"))
    # frames with an earlier pass within REVISIT_M at least EXCLUSION_M of path before
    rev = []
    for i in range(len(poses)):
        earlier = np.flatnonzero(arc <= arc[i] - EXCLUSION_M)
        if earlier.size == 0:
            continue
        d = np.linalg.norm(xyz[earlier] - xyz[i], axis=1)
        j = int(np.argmin(d))
        if d[j] <= REVISIT_M:
            rev.append((i, int(earlier[j])))
    used = set()
    for u in places_revisit if rev else ():
        k = int(round(u * (len(rev) - 1)))  # the same share of the revisit stretch for every option
        if k in used:
            continue
        used.add(k)
        i, j = rev[k]
        kind = "same" if float(heading[i] @ heading[j]) > 0 else "reverse"
        out.append((i, j, kind))
    return out


def open_sim(world: str, sensor: str, seed: int, moving: bool) -> Any:
    sim: dict[str, Any] = {"world": world, "sensor": sensor, "seed": seed, "route": "default"}
    if moving:
        sim.update(rate_hz=10.0, sweep_motion=True, odometry_drift=0.01)
    return open_dataset(DatasetConfig.model_validate({"simulator": sim}))


def options(quick: bool) -> list[tuple[str, dict]]:
    """label -> option: source (scan / keyframes), metres, odometry, image params, row_upsample."""
    out: list[tuple[str, dict]] = [
        ("scan", {"kf": None, "image": {}, "row_upsample": None}),
        ("scan x1", {"kf": None, "image": {}, "row_upsample": 1}),
    ]
    metres = (5.0,) if quick else (3.0, 5.0)
    for m in metres:
        odos = ("drift",) if quick or m != 5.0 else ("drift", "true")
        for odo in odos:
            images = [("per-beam", {"mode": "per-beam"})]
            if odo == "drift":
                images += [
                    (f"sph {r:g}", {"mode": "spherical", "resolution_deg": r, "fill_radius_px": 1})
                    for r in ((0.2,) if quick else (0.2, 0.4))
                ]
            for name, image in images:
                out.append((f"kf{m:g}m {odo} {name}", {"kf": (m, odo), "image": image, "row_upsample": None}))
    return out


def run_dataset(world: str, sensor: str, seed: int, n_pairs: int, quick: bool, exts: dict, log: Any) -> dict:
    """{option: {extractor: [(kind, PairScores)]}} and the pair distances of one (world, sensor, seed)."""
    if is_test_seed(seed):
        raise SystemExit(f"seed {seed} is a test-split seed: not used here")
    prep = partial(preprocess_scan, params=experiment_preprocess())
    still = CachedSequence(open_sim(world, sensor, seed, moving=False))
    moving = CachedSequence(open_sim(world, sensor, seed, moving=True))
    total = float(arc_length(np.asarray(still.poses))[-1])
    places_ahead = draw_places(total, n_pairs, seed=1000 + seed)
    places_revisit = draw_places(1.0, n_pairs, seed=2000 + seed)
    keyframes: dict[tuple, KeyframeSequence] = {}
    views: dict[tuple, View] = {}
    results: dict[str, dict[str, list]] = {}
    info: dict[str, dict] = {}
    for label, opt in options(quick):
        if opt["kf"] is None:
            seq, frame = still, lambda i: prep(still[i])
        else:
            m, odo = opt["kf"]
            if (m, odo) not in keyframes:
                odometry = moving.odometry_poses if odo == "drift" else np.asarray(moving.poses)
                keyframes[(m, odo)] = KeyframeSequence(
                    moving, KeyframeParams(metres=m), odometry, prepare=prep
                )
            kseq = keyframes[(m, odo)]
            seq, frame = kseq, kseq.__getitem__
        poses = np.asarray(seq.poses)
        pairs = pairs_of(poses, places_ahead, places_revisit, seed)
        image = ImageParams(**opt["image"])
        t0 = time.perf_counter()

        def view(i: int, opt=opt, seq=seq, frame=frame, image=image) -> View:
            key = (id(seq), i, json.dumps(opt["image"], sort_keys=True))
            if key not in views:
                views[key] = View.from_scan(frame(i), image)
            return views[key]

        truths = []
        for a, b, kind in pairs:
            va, vb = view(a), view(b)
            truths.append((kind, PairTruth.from_views(va, vb, np.linalg.inv(poses[b]) @ poses[a])))
        t_views = time.perf_counter() - t0
        res: dict[str, list] = {}
        for ex_label, (name, params) in exts.items():
            p = dict(params)
            if opt["row_upsample"] is not None:
                p["row_upsample"] = opt["row_upsample"]
            ex = make_extractor(name, **p)
            scores = []
            for kind, truth in truths:
                fa, fb = (ex.extract(v.image) for v in (truth.a, truth.b))
                scores.append((kind, evaluate_pair(fa, fb, truth)))
            res[ex_label] = scores
        results[label] = res
        dist = [float(np.linalg.norm(poses[a, :3, 3] - poses[b, :3, 3])) for a, b, _ in pairs]
        shape = truths[0][1].a.image.shape if truths else (0, 0)
        info[label] = {
            "pairs": len(pairs),
            "revisit_pairs": sum(k != "ahead" for _, _, k in pairs),
            "mean_pair_m": round(float(np.mean(dist)), 2) if dist else None,
            "image": f"{shape[0]}x{shape[1]}",
            "scans_per_frame": (
                1.0
                if opt["kf"] is None
                else round(
                    float(np.mean([len(seq.scan_indices(i)) for i in {x for p in pairs for x in p[:2]}])), 1
                )
            ),
            "seconds": round(time.perf_counter() - t0, 1),
            "view_seconds": round(t_views, 1),
        }
        log(f"  {world} s{seed} {sensor} {label}: {info[label]}")
    return {"results": results, "info": info}


def summarise(runs: list[dict]) -> dict[str, dict[str, dict[str, float]]]:
    """{option: {extractor: figures}} over every dataset's pairs."""
    out: dict[str, dict[str, dict[str, float]]] = {}
    for label in runs[0]["results"]:
        for ex in runs[0]["results"][label]:
            scores = [s for r in runs for s in r["results"][label][ex]]
            allp = mean_scores([s for _, s in scores])
            rev = mean_scores([s for k, s in scores if k != "ahead"])
            out.setdefault(label, {})[ex] = {
                "keypoints": allp["keypoints"],
                "repeatability": allp["repeatability"],
                "chance": allp["chance_repeatability"],
                "matching_score": allp["matching_score"],
                "precision": allp["precision"],
                "correct": allp["correct"],
                "revisit_repeatability": rev["repeatability"],
                "revisit_matching_score": rev["matching_score"],
                "pairs": allp["pairs"],
            }
    return out


def _f(x: float, pct: bool = True) -> str:
    if x is None or not np.isfinite(x):
        return "-"
    return f"{100 * x:.1f}" if pct else f"{x:.0f}"


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sensors", nargs="+", default=None, help="default: vlp16 hdl32 (--quick: vlp16)")
    ap.add_argument("--pairs", type=int, default=None, help="ahead pairs (and revisit places) per sequence")
    ap.add_argument("--quick", action="store_true", help="town seed 0, VLP-16, fewer pairs and options")
    args = ap.parse_args(argv)
    sensors = args.sensors or (["vlp16"] if args.quick else ["vlp16", "hdl32"])
    n_pairs = args.pairs or 6
    datasets = QUICK_DATASETS if args.quick else DATASETS
    t0 = time.perf_counter()
    table: dict[str, Any] = {}
    info: dict[str, Any] = {}
    for sensor in sensors:
        exts = extractors()
        runs = []
        for world, seed in datasets:
            r = run_dataset(world, sensor, seed, n_pairs, args.quick, exts, lambda s: print(s, flush=True))
            runs.append(r)
            info[f"{sensor} {world} {seed}"] = r["info"]
        table[sensor] = summarise(runs)
        print(f"\n{sensor} (tuning: {', '.join(f'{w} s{s}' for w, s in datasets)}): keypoints per image, "
              "repeatability % (chance), matching score %, match precision %, correct matches per pair; revisit "
              "pairs' repeatability / matching score %")  # fmt: skip
        print(f"{'option':24} {'extractor':16} {'kp':>4} {'rep':>5} {'(ch)':>6} {'MS':>5} {'prec':>5} "
              f"{'corr':>5} {'rev rep':>7} {'rev MS':>6} {'pairs':>5}")  # fmt: skip
        for label, per_ex in table[sensor].items():
            for ex, f in per_ex.items():
                print(f"{label:24} {ex:16} {_f(f['keypoints'], False):>4} {_f(f['repeatability']):>5} "
                      f"({_f(f['chance']):>4}) {_f(f['matching_score']):>5} {_f(f['precision']):>5} "
                      f"{_f(f['correct'], False):>5} {_f(f['revisit_repeatability']):>7} "
                      f"{_f(f['revisit_matching_score']):>6} {f['pairs']:5.0f}")  # fmt: skip
    out = {
        "tool": "eval_sparse_sensors",
        "split": "tuning",
        "datasets": [f"{w} {s}" for w, s in datasets],
        "seconds": round(time.perf_counter() - t0),
        "figures": {
            s: {
                o: {
                    e: {k: (round(v, 4) if np.isfinite(v) else None) for k, v in f.items()}
                    for e, f in pe.items()
                }
                for o, pe in t.items()
            }
            for s, t in table.items()
        },
        "info": info,
    }
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
