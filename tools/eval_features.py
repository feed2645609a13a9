"""Repeatability and matching score of the 2D feature extractors on intensity image pairs with known poses.

For each extractor (ORB, BRISK, FAST+SURF, SURF, SuperPoint) and each pair set the script reports repeatability,
matching score and precision of mutual nearest-neighbour matches (definitions: `placerec.eval.features`; a
keypoint pair coincides within 3 px of the ground-truth pixel or 0.3 m in 3D), and the keypoints per image:

* ``sim``: held-out simulator pairs, worlds town / campus / industrial with world seeds 200-203 (SuperPoint trains
  on seeds 100-109), sensor OS1-64: per sequence, anchors along the route with a partner 1-8 m further along it
  and revisit pairs (an anchor on a revisit segment of the route and the nearest scan of the earlier pass),
  drawn with a fixed seed. Rendered views are cached under ``.cache/eval_features``.
* ``os1``: the real OS1-64 revisit pair (MulRan, from the LiDAR-Iris demo); it has no poses, so the relative pose
  is estimated here: ISHOT keypoints + RANSAC + ICP (`placerec.verify.verify`), then point-to-plane ICP with
  0.25 m voxels and shrinking gates; the ICP fitness and RMSE are printed.
* ``kitti``: the real KITTI 00 pairs 94/95 and 198/199 with the ground-truth poses, converted to LiDAR poses
  ``inv(Tr) @ P @ Tr`` with the published sequence-00 ``Tr`` (velodyne -> camera 0); an ICP from that pose
  checks it (the correction it finds is printed). Images: uniform projection, 64 x 1024, field of view
  +3 / -25 degrees (the values RangeNet++ uses for KITTI), the same for both scans of a pair.
* ``real``: the three real pairs together.

It also times each extractor per 64 x 1024 image (the real OS1-64 image; a simulator one without the real
data) and per 128 x 2048 image (that image upscaled 2x): median of ``--repeats`` calls after a warm-up, with the
load average. SuperPoint is timed through both backends (``cv2``: ONNX through cv2.dnn; ``torch``).

SuperPoint uses ``--superpoint-weights`` (default: the shipped ``placerec/vocab/superpoint_lidar.npz``); when the
weights are absent it is skipped with a message. Scores of untrained (random) weights mean nothing.

The last line printed is one JSON object with the headline figures. Example::

    python tools/eval_features.py          # ~30 s on 2 cores (renders ~90 scans; ~20 s once they are cached)
    python tools/eval_features.py --superpoint-weights runs/superpoint/superpoint_lidar.npz --csv results/pairs.csv
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from placerec.errors import ArtifactError, DependencyError, PlacerecError
from placerec.eval.features import PairScores, PairTruth, View, evaluate_pair, mean_scores
from placerec.features import make_extractor
from placerec.image import ImageParams

TOOLS = Path(__file__).resolve().parent
REPO = TOOLS.parent
REAL = REPO.parent / "shared" / "data" / "real"
CACHE = REPO / ".cache" / "eval_features"
EXTRACTORS = ("orb", "brisk", "fast-surf", "surf", "superpoint")
WORLDS = ("town", "campus", "industrial")
#: KITTI odometry sequences 00-02: velodyne -> camera 0 (``Tr`` of their calib.txt)
KITTI_TR_00 = np.array(
    [
        [4.276802385584e-04, -9.999672484946e-01, -8.084491683471e-03, -1.198459927713e-02],
        [-7.210626507497e-03, 8.081198471645e-03, -9.999413164504e-01, -5.403984729748e-02],
        [9.999738645903e-01, 4.859485810390e-04, -7.206933692422e-03, -2.921968648686e-01],
        [0.0, 0.0, 0.0, 1.0],
    ]
)
KITTI_IMAGE = ImageParams(mode="uniform", width=1024, height=64, fov_up_deg=3.0, fov_down_deg=25.0)
_VIEW_KIND, _VIEW_VERSION = "eval_features_view", 1


@dataclass(frozen=True)
class Pair:
    """One evaluated image pair: the sets it counts in (e.g. ``("sim", "sim-revisit")``), a label and its ground
    truth."""

    sets: tuple[str, ...]
    label: str
    truth: PairTruth


#: the pair sets in the order they are reported
SETS = ("sim", "sim-ahead", "sim-revisit", "os1", "kitti", "real")


# -- views ---------------------------------------------------------------------------------------------------------


def _preprocess(scan: Any) -> Any:
    from placerec.config import experiment_preprocess
    from placerec.preprocess import preprocess_scan

    return preprocess_scan(scan, experiment_preprocess(), keep_organized=True)


def view_of(scan: Any, params: ImageParams | None = None) -> View:
    """The view of a raw scan, formed as the pipelines form it (min range 0.5 m, organised scans kept)."""
    return View.from_scan(_preprocess(scan), params)


def _cached_view(seq: Any, index: int, key: str, cache: Path | None) -> View:
    from placerec.io.atomic import load_artifact, save_artifact

    path = None if cache is None else cache / f"{key}_{index}.npz"
    if path is not None and path.is_file():
        try:
            arrays, _ = load_artifact(path, _VIEW_KIND, (_VIEW_VERSION,))
            return View(arrays["image"], arrays["points"])
        except (ArtifactError, KeyError):
            pass  # a stale or broken entry is made again
    view = view_of(seq[index])
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        save_artifact(path, _VIEW_KIND, _VIEW_VERSION, {"image": view.image, "points": view.points})
    return view


def _pose_pairs(
    seq: Any, rng: np.random.Generator, n_forward: int, n_revisit: int
) -> list[tuple[int, int, str]]:
    """(anchor, partner, kind) pairs of one simulated sequence: ``n_forward`` anchors spread along the route with a
    partner 1-8 m further along it, and ``n_revisit`` scans on revisit segments with the nearest scan of the
    earlier pass."""
    poses = np.asarray(seq.poses)
    xyz = poses[:, :3, 3]
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xyz, axis=0), axis=1))])
    out: list[tuple[int, int, str]] = []
    usable = np.flatnonzero(arc <= arc[-1] - 8.0)
    for chunk in np.array_split(usable, n_forward):
        if chunk.size == 0:
            continue
        a = int(rng.choice(chunk))
        ahead = float(rng.uniform(1.0, 8.0))
        b = a + 1 + int(np.argmin(np.abs(arc[a + 1 :] - arc[a] - ahead)))  # the scan nearest that far ahead
        out.append((a, b, f"ahead {arc[b] - arc[a]:.1f} m"))
    revisits = [r for r in seq.revisits if r.stop - r.start >= 1]
    for k in range(min(n_revisit, len(revisits))):
        r = revisits[int(rng.integers(len(revisits)))] if k else max(revisits, key=lambda r: r.stop - r.start)
        a = int(rng.integers(r.start, r.stop))
        ref = np.arange(r.ref_start, r.ref_stop)
        b = int(ref[np.argmin(np.linalg.norm(xyz[ref] - xyz[a], axis=1))])
        out.append((a, b, f"revisit {r.kind} {np.linalg.norm(xyz[b] - xyz[a]):.1f} m"))
    return out


def sim_pairs(
    worlds: list[str],
    seeds: list[int],
    sensors: list[str],
    n_forward: int,
    n_revisit: int,
    seed: int,
    cache: Path | None,
    progress: Any = None,
) -> list[Pair]:
    """The held-out simulator pairs (module docstring)."""
    from placerec.config import DatasetConfig
    from placerec.experiment.datasets import dataset_fingerprint, open_dataset
    from placerec.hashing import stable_hash

    pairs: list[Pair] = []
    specs = [(w, s, sensor) for sensor in sensors for w in worlds for s in seeds]
    task = progress.add_task("simulator pairs", total=len(specs)) if progress else None
    for k, (world, s, sensor) in enumerate(specs):
        cfg = DatasetConfig.model_validate({"simulator": {"world": world, "sensor": sensor, "seed": s}})
        seq = open_dataset(cfg)
        key = stable_hash([cfg.model_dump(mode="json"), dataset_fingerprint(cfg), "min_range=0.5"])[:16]
        rng = np.random.default_rng([seed, k])
        for a, b, kind in _pose_pairs(seq, rng, n_forward, n_revisit):
            va, vb = _cached_view(seq, a, key, cache), _cached_view(seq, b, key, cache)
            a_to_b = np.linalg.inv(seq.poses[b]) @ seq.poses[a]
            pairs.append(
                Pair(
                    ("sim", f"sim-{kind.split()[0]}"),
                    f"{world}/{sensor}/s{s} {a}-{b} ({kind})",
                    PairTruth.from_views(va, vb, a_to_b),
                )
            )
        if progress:
            progress.advance(task)
    return pairs


# -- real pairs ----------------------------------------------------------------------------------------------------


def _fine_icp(a: Any, b: Any, T0: np.ndarray) -> Any:
    """Point-to-plane ICP of scan ``a`` onto ``b`` from ``T0`` (0.25 m voxels, gates 1 -> 0.5 -> 0.25 m)."""
    from placerec.verify.icp import prepare_source, prepare_target, refine
    from placerec.verify.params import IcpParams

    p = IcpParams(voxel_size=0.25, source_voxel_size=0.25, max_iterations=50)
    src, dst = prepare_source(a, p), prepare_target(b, p)
    res = None
    for gate in (1.0, 0.5, 0.25):
        res = refine(src, dst, T0, p.model_copy(update={"max_correspondence_distance": gate}), 0.3)
        T0 = res.T
    return res


def _motion(T: np.ndarray) -> str:
    ang = np.degrees(np.arccos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1, 1)))
    return f"{np.linalg.norm(T[:3, 3]):.3f} m, {ang:.3f} deg"


def os1_pair(real: Path, log: list[str]) -> list[Pair]:
    """The real OS1-64 revisit pair with its relative pose estimated by global registration and ICP."""
    from placerec.io import read_scan
    from placerec.three_d.features import extract_features
    from placerec.verify.matching import mutual_nearest
    from placerec.verify.verify import verify

    folder = real / "ouster_os1_64_revisit_pair"
    scans = [
        read_scan(folder / n, organized=True, layout=(64, 1024, "column-major"))
        for n in ("32line_1.bin", "32line_2.bin")
    ]
    fa, fb = (extract_features(s) for s in scans)
    qi, mi, _ = mutual_nearest(fa.descriptors, fb.descriptors)
    glob = verify(scans[0], scans[1], fa.keypoints[qi], fb.keypoints[mi])
    icp = _fine_icp(scans[0], scans[1], glob.T_match_query)
    log.append(
        f"os1 pair: registration ISHOT+RANSAC {glob.inliers}/{glob.correspondences} inliers, then ICP fitness "
        f"{icp.fitness:.3f} (within 0.3 m), RMSE {icp.rmse:.3f} m; relative pose {_motion(icp.T)}"
    )
    truth = PairTruth.from_views(view_of(scans[0]), view_of(scans[1]), icp.T)
    return [Pair(("os1", "real"), "OS1-64 32line_1-32line_2", truth)]


def kitti_pairs(real: Path, log: list[str]) -> list[Pair]:
    """The real KITTI 00 pairs with ground-truth LiDAR poses, each checked by ICP."""
    from placerec.io import read_poses, read_scan

    folder = real / "kitti00_frames"
    P, _ = read_poses(folder / "poses_00.txt")
    Tr_inv = np.linalg.inv(KITTI_TR_00)
    out = []
    for i, j in ((94, 95), (198, 199)):
        a, b = (read_scan(folder / f"{k:06d}.bin") for k in (i, j))
        pa, pb = (Tr_inv @ P[k] @ KITTI_TR_00 for k in (i, j))
        a_to_b = np.linalg.inv(pb) @ pa
        icp = _fine_icp(a, b, a_to_b)
        log.append(
            f"kitti {i}/{j}: ground-truth relative pose {_motion(a_to_b)}; ICP from it: fitness {icp.fitness:.3f}, "
            f"RMSE {icp.rmse:.3f} m, correction {_motion(np.linalg.inv(a_to_b) @ icp.T)}"
        )
        truth = PairTruth.from_views(view_of(a, KITTI_IMAGE), view_of(b, KITTI_IMAGE), a_to_b)
        out.append(Pair(("kitti", "real"), f"KITTI 00 {i:06d}-{j:06d}", truth))
    return out


# -- extractors and timing -----------------------------------------------------------------------------------------


def make_extractors(names: list[str], sp_weights: str | None, log: list[str]) -> dict[str, Any]:
    """The extractors to evaluate; SuperPoint is left out with a message when its weights are absent."""
    out = {}
    for name in names:
        try:
            out[name] = (
                make_extractor(name, weights=sp_weights) if name == "superpoint" else make_extractor(name)
            )
        except ArtifactError as exc:
            log.append(f"superpoint skipped: {exc} (pass --superpoint-weights PATH)")
    return out


def timings(
    extractors: dict[str, Any], image: np.ndarray, sp_weights: str | None, repeats: int, log: list[str]
):
    """Median ms per image (64 x 1024 and 128 x 2048) for each extractor (`bench_features.timeit`: after two
    warm-up calls); SuperPoint through both backends."""
    if str(TOOLS) not in sys.path:
        sys.path.insert(0, str(TOOLS))
    from bench_features import timeit

    big = cv2.resize(image, (image.shape[1] * 2, image.shape[0] * 2), interpolation=cv2.INTER_LINEAR)
    images = {"64x1024": image, "128x2048": big}
    timed = {k: v for k, v in extractors.items() if k != "superpoint"}
    if "superpoint" in extractors:
        for backend in ("cv2", "torch"):
            try:
                timed[f"superpoint-{backend}"] = make_extractor(
                    "superpoint", weights=sp_weights, backend=backend
                )
            except (DependencyError, ImportError) as exc:
                log.append(f"superpoint-{backend} not timed: {exc}")
    out: dict[str, dict[str, float]] = {}
    for name, ex in timed.items():
        out[name] = {
            size: round(timeit(lambda ex=ex, im=im: ex.extract(im), repeats)[0], 2)
            for size, im in images.items()
        }
    return out


# -- report --------------------------------------------------------------------------------------------------------


def match_figure(pairs: list[Pair], extractors: dict[str, Any], path: Path) -> Path:
    """Mutual matches of ORB and SuperPoint (those present) on the first KITTI pair, else the first simulator
    revisit pair, else the first pair; correct ones green (`placerec.experiment.figures.plot_feature_matches`)."""
    from placerec.eval.features import judged_matches
    from placerec.experiment.figures import plot_feature_matches

    pair = next((p for s in ("kitti", "sim-revisit") for p in pairs if s in p.sets), pairs[0])
    shown = {n: ex for n, ex in extractors.items() if n in ("orb", "superpoint")} or dict(extractors)
    matches = {}
    for name, ex in shown.items():
        fa, fb = ex.extract(pair.truth.a.image), ex.extract(pair.truth.b.image)
        qi, mi, judged, correct = judged_matches(fa, fb, pair.truth)
        matches[name] = (fa.keypoints[qi[judged]], fb.keypoints[mi[judged]], correct[judged])
    path.parent.mkdir(parents=True, exist_ok=True)
    return plot_feature_matches(pair.truth.a.image, pair.truth.b.image, matches, path, pair.label)


def write_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    """One row per pair and extractor, written atomically."""
    import csv
    import io

    from placerec.io.atomic import atomic_write

    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(rows[0]) if rows else ["extractor"])
    writer.writeheader()
    writer.writerows(rows)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path, "w") as fh:
        fh.write(buf.getvalue())


def _json_num(x: float) -> float | None:
    """Rounded, None for NaN (JSON has no NaN)."""
    return round(float(x), 5) if np.isfinite(x) else None


def _fmt(x: float, pct: bool = True) -> str:
    if not np.isfinite(x):
        return "-"
    return f"{100 * x:.1f}%" if pct else f"{x:.0f}"


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--extractors", default=",".join(EXTRACTORS), help="comma-separated registry names")
    ap.add_argument("--superpoint-weights", default=None, help="weights .npz (default: the shipped ones)")
    ap.add_argument("--worlds", default=",".join(WORLDS))
    ap.add_argument("--world-seeds", default="200,201,202,203", help="held out: training uses 100-109")
    ap.add_argument("--sensors", default="os1-64", help="simulated sensors, e.g. os1-64,hdl64")
    ap.add_argument("--forward", type=int, default=2, help="anchor + 1-8 m ahead pairs per sequence")
    ap.add_argument("--revisit", type=int, default=2, help="revisit pairs per sequence")
    ap.add_argument("--seed", type=int, default=0, help="seed of the pair draw")
    ap.add_argument("--real", type=Path, default=REAL, help="folder of the real samples")
    ap.add_argument("--no-sim", action="store_true", help="real pairs only")
    ap.add_argument("--repeats", type=int, default=7, help="timed calls per extractor and image size")
    ap.add_argument("--no-cache", action="store_true", help="render the simulator views again")
    ap.add_argument(
        "--csv", type=Path, default=None, help="write the figures of every pair and extractor here"
    )
    ap.add_argument(
        "--record",
        action="store_true",
        help="also write SuperPoint's figures into its weights' provenance .json ('evaluation')",
    )
    ap.add_argument(
        "--figure",
        default="results/eval_features_matches.png",
        help="matches of ORB and SuperPoint on one pair, correct in green ('' = none)",
    )
    args = ap.parse_args(argv)

    from rich.console import Console
    from rich.progress import Progress
    from rich.table import Table

    console = Console(width=None if os.isatty(1) else 120)
    log: list[str] = []
    names = [n.strip() for n in args.extractors.split(",") if n.strip()]
    extractors = make_extractors(names, args.superpoint_weights, log)
    pairs: list[Pair] = []
    with Progress(console=console, transient=True) as progress:
        if not args.no_sim:
            pairs += sim_pairs(
                args.worlds.split(","),
                [int(s) for s in args.world_seeds.split(",")],
                args.sensors.split(","),
                args.forward,
                args.revisit,
                args.seed,
                None if args.no_cache else CACHE,
                progress,
            )
        if args.real.is_dir():
            for loader in (os1_pair, kitti_pairs):
                try:
                    pairs += loader(args.real, log)
                except (PlacerecError, OSError) as exc:
                    log.append(f"{loader.__name__} skipped: {exc}")
        else:
            log.append(f"real pairs skipped: no real sample data at {args.real}")
        if not pairs:
            raise SystemExit("eval_features: no pairs to evaluate (no simulator pairs and no real data)")
        task = progress.add_task("features", total=len(pairs) * len(extractors))
        scores: dict[str, dict[str, list[PairScores]]] = {n: {} for n in extractors}
        rows: list[dict[str, Any]] = []
        for pair in pairs:
            for name, ex in extractors.items():
                fa, fb = ex.extract(pair.truth.a.image), ex.extract(pair.truth.b.image)
                result = evaluate_pair(fa, fb, pair.truth)
                for s in pair.sets:
                    scores[name].setdefault(s, []).append(result)
                rows.append({"extractor": name, "set": pair.sets[0], "pair": pair.label,
                             "distance_m": float(np.linalg.norm(pair.truth.a_to_b[:3, 3])),
                             "overlap": pair.truth.overlap, **result.as_dict()})  # fmt: skip
                progress.advance(task)
    for line in log:
        console.print(line)
    if args.csv is not None:
        write_csv(args.csv, rows)
        console.print(f"per-pair figures: {args.csv}")
    if args.figure:  # '' asks for none (a Path('') would be '.', written as './.png')
        console.print(f"matches figure: {match_figure(pairs, extractors, Path(args.figure))}")
    sets = [s for s in SETS if any(s in p.sets for p in pairs)]
    overlap = {s: float(np.mean([p.truth.overlap for p in pairs if s in p.sets])) for s in sets}
    distance = {s: [float(np.linalg.norm(p.truth.a_to_b[:3, 3])) for p in pairs if s in p.sets] for s in sets}
    summary = {n: {s: mean_scores(v[s]) for s in sets if s in v} for n, v in scores.items()}

    table = Table(title="Feature repeatability and matching (3 px / 0.3 m); mean over pairs")
    for col in (
        "extractor",
        "set",
        "pairs",
        "keypoints",
        "in overlap",
        "repeatability",
        "(chance)",
        "matching score",
        "precision",
    ):
        table.add_column(col, justify="left" if col in ("extractor", "set") else "right")
    for name, per_set in summary.items():
        for s, m in per_set.items():
            table.add_row(
                name, s, f"{m['pairs']:.0f}", _fmt(m["keypoints"], False), _fmt(m["overlap_keypoints"], False),
                _fmt(m["repeatability"]), _fmt(m["chance_repeatability"]), _fmt(m["matching_score"]),
                _fmt(m["precision"]),
            )  # fmt: skip
    console.print(table)
    console.print("(chance): repeatability against the other image's keypoints turned half a revolution")
    console.print("pixel overlap (share of valid pixels with a ground-truth partner): "
                  + ", ".join(f"{s} {100 * v:.0f}%" for s, v in overlap.items()))  # fmt: skip
    console.print("distance between the scans of a pair, median (min-max): "
                  + ", ".join(f"{s} {np.median(d):.1f} m ({min(d):.1f}-{max(d):.1f})" for s, d in distance.items()))  # fmt: skip

    os1 = [p for p in pairs if "os1" in p.sets]
    timing_image, timing_source = (os1[0], "real OS1-64") if os1 else (pairs[0], pairs[0].label.split()[0])
    timing_image = timing_image.truth.a.image
    if timing_image.shape != (64, 1024):
        timing_image = cv2.resize(timing_image, (1024, 64), interpolation=cv2.INTER_AREA)
    load_before = os.getloadavg()
    n_log = len(log)
    ms = timings(extractors, timing_image, args.superpoint_weights, args.repeats, log)
    load = [round(x, 2) for x in os.getloadavg()]
    tt = Table(
        title=f"ms per image ({timing_source} image; 128x2048 = it upscaled 2x), median of {args.repeats}"
    )
    tt.add_column("extractor")
    tt.add_column("64x1024", justify="right")
    tt.add_column("128x2048", justify="right")
    for name, t in ms.items():
        tt.add_row(name, f"{t['64x1024']:.1f}", f"{t['128x2048']:.1f}")
    console.print(tt)
    console.print(
        f"load average before / after timing: {load_before[0]:.2f} / {load[0]:.2f} (cores: {os.cpu_count()})"
    )
    for line in log[n_log:]:
        console.print(line)

    def ratio(s: str) -> float | None:
        try:
            r = summary["superpoint"][s]["matching_score"] / summary["orb"][s]["matching_score"]
        except (KeyError, ZeroDivisionError):
            return None
        return round(r, 3) if np.isfinite(r) else None

    headline = {
        "tool": "eval_features",
        "px": 3.0,
        "max_dist_m": 0.3,
        "pairs": {s: sum(s in p.sets for p in pairs) for s in sets},
        "pair_distance_median_m": {s: round(float(np.median(d)), 2) for s, d in distance.items()},
        "superpoint_weights": args.superpoint_weights or ("shipped" if "superpoint" in extractors else None),
        "scores": {
            n: {s: {k: _json_num(v) for k, v in m.items() if k != "pairs"} for s, m in per_set.items()}
            for n, per_set in summary.items()
        },
        "matching_score_ratio_superpoint_orb": {s: ratio(s) for s in ("sim", "real", "kitti", "os1")},
        "ms_per_image": ms,
        "timing_image": timing_source,
        "loadavg": load,
    }
    if args.record and "superpoint" in summary:
        console.print(f"recorded in {record_provenance(args.superpoint_weights, headline)}")
    print(json.dumps(headline, separators=(",", ":")))
    return headline


def record_provenance(weights: str | None, headline: dict[str, Any]) -> Path:
    """Add SuperPoint's figures of this run (scores per pair set, ratios to ORB, ms per image, load) to the
    provenance ``.json`` beside its weights, under ``evaluation``."""
    from placerec.features.superpoint.weights import resolve_weights
    from placerec.io.atomic import atomic_write

    path = resolve_weights(weights).with_suffix(".json")
    provenance = json.loads(path.read_text()) if path.is_file() else {}
    provenance["evaluation"] = {
        "tool": "tools/eval_features.py",
        "pairs": headline["pairs"],
        "superpoint": headline["scores"]["superpoint"],
        "matching_score_ratio_superpoint_orb": headline["matching_score_ratio_superpoint_orb"],
        "ms_per_image": {k: v for k, v in headline["ms_per_image"].items() if k.startswith("superpoint")},
        "loadavg": headline["loadavg"],
    }
    with atomic_write(path, "w") as fh:
        json.dump(provenance, fh, indent=2)
    return path


if __name__ == "__main__":
    main()
