"""Cross-sensor maps (issue #28): a map built with one LiDAR, queried with another, against each sensor's
same-sensor baseline, with raw, normalised and calibrated intensity.

Data (`placerec.sim.SimulatedSequence`): map and queries drive the **same world** (``world_seed``) with different
drives (``seed``: the route's small motions and the noise) and different sensor units (``unit_seed``: the per-beam
response curves; the map role's unit is 700, the query role's 701, for every sensor). Splits
(`placerec.experiment.protocol`):

* ``test`` (default; the figures reported): town, world seed 4601, map drive seed 4601, query drive seed 4602
  (TEST_SEEDS); nothing is chosen on it.
* ``tuning``: town, world seed 0, map drive seed 0 (the tuning cell), query drive seed 1.

``--worlds`` runs the splits in more of the benchmark's worlds (town, campus, industrial; the same seeds): the
tuning split's campus and industrial drives (world seed 0, drive seeds 0 / 1) are the sensor benchmark's tuning
worlds (`configs/benchmark_sensors_tuning.yaml`), never a test seed.

Every fitted quantity comes from the tuning world only: each unit's per-beam Levinson table
(`placerec.calibration.calibrate_sequence`) is fitted on its own drive through the tuning world (world seed 0, drive
seed 0 for the map unit, 1 for the query unit, 60 scans 3 m apart), and so is the common-scale mapping below.
Operating thresholds are the presets' (`PIPELINES[name].threshold`, chosen on the tuning split by others).

Capture: spinning sensors one scan every ``--map-spacing`` m (map, default 4: ~96 scans of the ~380 m town route)
/ ``--query-spacing`` m (queries, default 8: ~48) at rest; the
Livox-style ``avia`` as the benchmark captures it (`protocol.CAPTURE`: 10 Hz frames taken while moving, 1 %-drift
odometry, `placerec.keyframes.KeyframeSequence` of 0.5 s), every k-th keyframe kept to about the same spacing.

Intensity (the scans' intensity is replaced before preprocessing, whose own normalisation is then ``raw``, the
identity; geometry is the same in every mode):

* ``raw``: the values the sensor reports (VLP-16 / HDL-64 / Avia 8 bit, Ouster 16 bit);
* ``normalised``: the sensor's default normaliser (`placerec.intensity.default_intensity_spec`: VLP-16 raw/100,
  HDL-64 and OS1 the 99th percentile of each scan, others the 99th percentile);
* ``calibrated``: the unit's per-beam table (all ranges: no 30 m cut-off, so that geometry is unchanged), then a
  per-unit monotone map to a **common reflectance scale**. A table alone is not such a scale: its gauge is "the
  unit's average beam" divided by the unit's saturation (docs/calibration.md), so an HDL-64 (response gamma 0.5)
  stays compressive (asphalt ~0.3 of full scale) and an OS1-64 is scaled by its 99th percentile. The common scale
  is the calibrated VLP-16 map unit's (its mean response is ~100 x, so its calibrated value is ~ the apparent
  reflectance): on the tuning world every unit's calibrated readings are averaged per 0.5 m world cell (within
  30 m), and the map is the binned-median, non-decreasing relation between the unit's cell values and the
  reference's on the cells both saw. The tool checks both against the simulator's ground truth (apparent
  reflectance from `BeamResponse.to_apparent`) on the tuning drives and prints it.

Modes, per pipeline (ishot-prob, scan-context, orb-dbow, superpoint-dbow; presets' thresholds):

* ``localise``: the map scans in a database, every query localised (`placerec.experiment.runner.run_localize`);
  success as `placerec.experiment.report` counts it: only an *accepted* top candidate is an answer (a rejected
  one is no answer), and it succeeds within 3 m (scan-context, which does not verify, answers with its top one);
  ``R@P1`` = the success rate when no accepted answer was wrong (farther than 3 m), else 0. The 3D voting
  pipelines (``ishot-prob`` ...) run in this mode only: they have no loop-closure threshold, an answer counts
  when their verification accepted it;
* ``loop``: the map sequence followed by the query sequence as one sequence (`ConcatSequence`; the queries' clock
  starts 1e6 s after the map's and the exclusion window is 5e5 s, so a query can close a loop onto the map part
  only), run in loop mode (`run_loop`), judged with the benchmark's pose ground truth (`loop_summary`,
  `pose_truths`) at a fixed threshold (the preset's; ``--loop-threshold PIPELINE=VALUE`` another): recall and
  precision there, and ``R@P1`` = that recall when the precision is 1.00, else 0. ``--loop-ambiguity RATIO``
  applies localisation's ambiguity rule to the loop answers, the map drive's true poses placing the candidates:
  the first drive plays a map with known poses (as in localise mode), as a second session joining a prior map does
  (``prior_map.join_ambiguity``; the odometry of a single drive is not such a map). An ambiguous query has no
  answer (`placerec.experiment.report.ambiguous_answers`).

Ratios: cross / same R@P1, where "same" is the query sensor's same-sensor baseline (its own map unit and query
unit).

Crop (``--crop``, default ``common``): every scan of every sensor is cropped to the elevation band all the run's
sensors see (`preprocess.elevation_deg`; +2 / -15 deg for the issue's pairs: the HDL-64 sees no higher than +2 deg,
the VLP-16 no lower than -15), so that map and queries hold the same part of the scene. Chosen on the tuning split
(HDL-64 -> VLP-16, ``--quick``: ISHOT 0 -> 88 % localised, Scan Context's loop recall 0 -> 75 %, ORB-DBoW 0 -> 46 %);
``--crop none`` keeps every point, as the runs before it did.
Descriptions are shared in memory within one run between the localise and loop runs of the same scans (by the
scans' content); raw scans are kept in a temporary folder for the run; the calibration tables and the common-scale
maps are kept in ``--cache-dir`` (default ``.cache/cross_sensor``).

    .venv/bin/python tools/eval_cross_sensor.py            # test split, every pair: 17 min measured on 2 cores
                                                           # (a test suite beside it), 1 of it calibrating
    .venv/bin/python tools/eval_cross_sensor.py --quick    # HDL-64 -> VLP-16 and both baselines, ISHOT-prob,
                                                           # ORB-DBoW and Scan Context
    .venv/bin/python tools/eval_cross_sensor.py --splits tuning --pairs hdl64:vlp16 --image common

``--image common`` (an exploration, run on the tuning split): the 2D pipelines' images on one spherical grid for
every sensor of the run (0.4 deg a pixel over the vertical field of view they all see) instead of each sensor's own
per-beam image. The first run of a cache folder fits the calibrations (~6 min for the eight units, HDL-64 most).
    .venv/bin/python tools/eval_cross_sensor.py --splits tuning test

Prints a table per split and ends with one JSON line.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import pickle
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from placerec.calibration import CalibrationParams, CalibrationTable, calibrate_points, gather_points
from placerec.calibration.table import load_calibration
from placerec.config import ExperimentConfig, apply_overrides, parse_config
from placerec.eval import localization_metrics
from placerec.experiment import protocol
from placerec.experiment.datasets import SlicedSequence
from placerec.experiment.report import ambiguous_answers, localize_estimates, loop_summary, pose_truths
from placerec.experiment.runner import PipelineRecord, build_pipelines, run_localize, run_loop
from placerec.experiment.truth import TruthClouds
from placerec.hashing import stable_hash
from placerec.intensity import normalize_intensity
from placerec.keyframes import KeyframeParams, KeyframeSequence
from placerec.params import deep_merge
from placerec.preprocess import preprocess_scan
from placerec.recognizer import PIPELINES, make_pipeline
from placerec.sim import SimulatedSequence
from placerec.sim.sensors import get_sensor, sensor_names
from placerec.types import Scan
from placerec.verify.ambiguity import AmbiguityParams

log = logging.getLogger("eval_cross_sensor")

LIVOX = "avia"
#: map sensor -> query sensor
CROSS_PAIRS = (("hdl64", "vlp16"), ("hdl64", "os1-64"), ("hdl64", LIVOX), ("os1-64", "vlp16"))
QUICK_PAIRS = (("hdl64", "vlp16"),)
PIPELINE_NAMES = ("ishot-prob", "scan-context", "orb-dbow", "superpoint-dbow")
QUICK_PIPELINES = ("ishot-prob", "scan-context", "orb-dbow")
INTENSITIES = ("raw", "normalised", "calibrated")
SPLITS: dict[str, dict[str, Any]] = {
    "tuning": {"world": "town", "world_seed": 0, "map_seed": 0, "query_seed": 1},
    "test": {"world": "town", "world_seed": protocol.TEST_SEEDS[0], "map_seed": protocol.TEST_SEEDS[0],
             "query_seed": protocol.TEST_SEEDS[1]},
}  # fmt: skip


def world_splits(splits: list[str], worlds: list[str]) -> dict[str, dict[str, Any]]:
    """The runs of ``splits`` in each of ``worlds`` (each split's seeds in any of the benchmark's worlds): key
    ``split`` for town, ``split-world`` for the others."""
    out = {}
    for split in splits:
        for world in worlds:
            out[split if world == "town" else f"{split}-{world}"] = {**SPLITS[split], "world": world}
    return out


#: sensor units (per-beam response draws) of the two roles, the same in every split
UNITS = {"map": 700, "query": 701}
#: the tuning drive each unit is calibrated on (world seed 0), and the reference of the common scale
CAL_SEEDS = {"map": 0, "query": 1}
CAL_SPACING = 3.0
REFERENCE = ("vlp16", "map")
COMMON_VOXEL = 0.5
COMMON_BINS = 48
#: the queries' clock starts this long after the map's; the loop exclusion window is half of it
GAP_S = 1.0e6
SUCCESS_M = 3.0


# -- sequences ------------------------------------------------------------------------------------------------------
class ScanStore:
    """A sequence whose rendered scans are pickled into a folder the first time they are read (raw scans: every
    intensity mode and both evaluation modes read the same ones)."""

    def __init__(self, seq: Any, folder: Path) -> None:
        self.seq = seq
        self.folder = folder
        folder.mkdir(parents=True, exist_ok=True)

    def __len__(self) -> int:
        return len(self.seq)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.seq, name)

    def __getitem__(self, i: int) -> Scan:
        path = self.folder / f"{int(i)}.pkl"
        if path.is_file():
            with open(path, "rb") as fh:
                scan: Scan = pickle.load(fh)
            return scan
        scan = self.seq[int(i)]
        with open(path, "wb") as fh:
            pickle.dump(scan, fh, protocol=pickle.HIGHEST_PROTOCOL)
        return scan


class IntensityView:
    """A sequence whose scans' intensity is replaced by ``fn(scan)``."""

    def __init__(self, seq: Any, fn: Callable[[Scan], Scan], tag: str) -> None:
        self.seq = seq
        self.fn = fn
        self.tag = tag

    def __len__(self) -> int:
        return len(self.seq)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.seq, name)

    def __getitem__(self, i: int) -> Scan:
        return self.fn(self.seq[int(i)])

    @property
    def name(self) -> str:
        return f"{self.seq.name}-{self.tag}"


class ConcatSequence:
    """``first`` followed by ``second`` as one sequence: poses concatenated, ``second``'s timestamps shifted to start
    ``gap_s`` after ``first``'s last one."""

    def __init__(self, first: Any, second: Any, gap_s: float = GAP_S) -> None:
        self.first, self.second = first, second
        self.n_first = len(first)
        t1 = np.asarray(first.timestamps, dtype=np.float64)
        t2 = np.asarray(second.timestamps, dtype=np.float64)
        for part, t in (("first", t1), ("second", t2)):
            if t.size and t[-1] - t[0] >= gap_s / 2:
                raise ValueError(f"ConcatSequence: the {part} part spans more than gap_s / 2 = {gap_s / 2} s")
        self._stamps = np.concatenate(
            [t1, t2 - (t2[0] if t2.size else 0.0) + (t1[-1] if t1.size else 0.0) + gap_s]
        )
        self._poses = np.concatenate([np.asarray(first.poses), np.asarray(second.poses)])

    def __len__(self) -> int:
        return self.n_first + len(self.second)

    def __getitem__(self, i: int) -> Scan:
        i = int(i)
        if i < 0:
            i += len(self)
        if not 0 <= i < len(self):
            raise IndexError(f"scan index {i} out of range for {len(self)} scans")
        return self.first[i] if i < self.n_first else self.second[i - self.n_first]

    @property
    def poses(self) -> np.ndarray:
        return self._poses

    @property
    def timestamps(self) -> np.ndarray:
        return self._stamps

    @property
    def name(self) -> str:
        return f"{self.first.name}+{self.second.name}"


def is_spinning(sensor: str) -> bool:
    return get_sensor(sensor).pattern == "spinning"


def base_sequence(world: str, world_seed: int, sensor: str, seed: int, unit: int, spacing: float) -> Any:
    """The raw drive: spinning sensors one scan every ``spacing`` m at rest; others 10 Hz frames while moving
    (`protocol.CAPTURE`)."""
    name = f"xs-{world}{world_seed}-{sensor}-s{seed}-u{unit}"
    if is_spinning(sensor):
        return SimulatedSequence(world=world, world_seed=world_seed, sensor=sensor, seed=seed, unit_seed=unit,
                                 spacing=spacing, name=f"{name}-{spacing:g}m")  # fmt: skip
    cap = protocol.CAPTURE[sensor]
    return SimulatedSequence(world=world, world_seed=world_seed, sensor=sensor, seed=seed, unit_seed=unit,
                             rate_hz=cap["rate_hz"], sweep_motion=cap["sweep_motion"],
                             odometry_drift=cap["odometry_drift"], name=name)  # fmt: skip


def places(base: Any, sensor: str, view: Callable[[Any], Any], spacing: float, cfg: ExperimentConfig) -> Any:
    """What the pipelines see of a drive: its scans (spinning) or every k-th keyframe, k chosen so that the
    keyframes are about ``spacing`` m apart (other sensors), with the intensity ``view`` applied to the raw
    scans."""
    seq = view(base)
    if is_spinning(sensor):
        return seq
    seconds = protocol.CAPTURE[sensor]["keyframes"]["seconds"]
    kf = KeyframeSequence(seq, KeyframeParams(seconds=seconds), base.odometry_poses,
                          prepare=lambda s: preprocess_scan(s, cfg.preprocess))  # fmt: skip
    p = np.asarray(kf.poses)[:, :3, 3]
    step_m = float(np.median(np.linalg.norm(np.diff(p, axis=0), axis=1))) if len(p) > 1 else spacing
    step = max(1, int(round(spacing / max(step_m, 1e-6))))
    return SlicedSequence(kf, 0, None, step)


# -- calibration and the common scale -------------------------------------------------------------------------------
def _cell_keys(xyz: np.ndarray, voxel: float) -> np.ndarray:
    c = np.floor(xyz / voxel).astype(np.int64) + (1 << 20)
    return (c[:, 0] << 42) | (c[:, 1] << 21) | c[:, 2]


def cell_means(keys: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(unique cell keys, mean value per cell)."""
    u, inv = np.unique(keys, return_inverse=True)
    return u, np.bincount(inv, values) / np.bincount(inv)


def fit_monotone(x: np.ndarray, y: np.ndarray, bins: int = COMMON_BINS) -> tuple[np.ndarray, np.ndarray]:
    """Knots (xs, ys) of a non-decreasing map y ~ f(x) on [0, 1]: the medians of x and y in ``bins`` quantile bins
    of x, made non-decreasing, with (0, 0) and (1, 1) as end points."""
    order = np.argsort(x)
    xs, ys = [0.0], [0.0]
    for part in np.array_split(order, bins):
        if part.size:
            xs.append(float(np.median(x[part])))
            ys.append(float(np.median(y[part])))
    xs.append(1.0)
    ys.append(1.0)
    kx, ky = np.asarray(xs), np.maximum.accumulate(np.clip(ys, 0.0, 1.0))
    keep = np.r_[True, np.diff(kx) > 1e-9]
    return kx[keep], ky[keep]


class Calibration:
    """A unit's per-beam table and its map to the common scale (knots; identity for the reference unit)."""

    def __init__(self, table: CalibrationTable, knots: tuple[np.ndarray, np.ndarray], check: dict[str, Any]):
        self.table = table
        self.knots = knots
        self.check = check

    def calibrated(self, scan: Scan) -> np.ndarray:
        return self.table.lookup(scan.intensity, scan.ring)

    def common(self, values: np.ndarray) -> np.ndarray:
        return np.interp(values, *self.knots).astype(np.float32)

    def apply(self, scan: Scan) -> Scan:
        out = self.common(self.calibrated(scan))
        if scan.shape is not None:  # organised scans: no-return points keep intensity 0
            out = np.where(np.any(scan.xyz != 0.0, axis=1), out, np.float32(0.0))
        return scan.with_intensity(out)


def _truth_check(seq: SimulatedSequence, pts: Any, values: dict[str, np.ndarray], n: int = 200_000) -> dict:
    """Correlation and MAE of each intensity with the true apparent reflectance of the drive's points (simulator
    ground truth), on at most ``n`` points."""
    rng = np.random.default_rng(0)
    idx = rng.choice(len(pts), size=min(n, len(pts)), replace=False)
    truth = np.asarray(seq.beam_response.to_apparent(pts.raw[idx], pts.beam[idx]), dtype=np.float64)
    ok = np.isfinite(truth) & (truth <= 1.0)
    out = {}
    for label, v in values.items():
        a = np.asarray(v[idx], dtype=np.float64)[ok]
        t = truth[ok]
        out[label] = {
            "corr": round(float(np.corrcoef(a, t)[0, 1]), 4),
            "mae": round(float(np.mean(np.abs(a - t))), 4),
        }
    return out


def calibrations(
    sensors_roles: list[tuple[str, str]], n_scans: int, cache_dir: Path, say: Callable[[str], None]
) -> dict[tuple[str, str], Calibration]:
    """The `Calibration` of every (sensor, role), fitted on the tuning world (module docstring); cached."""
    params = CalibrationParams(max_scans=n_scans)
    cache_dir.mkdir(parents=True, exist_ok=True)
    out: dict[tuple[str, str], Calibration] = {}
    ref_cells: tuple[np.ndarray, np.ndarray] | None = None
    from placerec import __version__

    for sensor, role in [REFERENCE] + [sr for sr in sensors_roles if sr != REFERENCE]:
        key = stable_hash({"sensor": sensor, "role": role, "unit": UNITS[role], "seed": CAL_SEEDS[role],
                           "spacing": CAL_SPACING, "params": params.model_dump(mode="json"), "ref": REFERENCE,
                           "voxel": COMMON_VOXEL, "bins": COMMON_BINS, "v": __version__})  # fmt: skip
        stem = cache_dir / f"{sensor}-{role}-{key}"
        tpath, kpath, cpath = (Path(f"{stem}{x}") for x in (".npz", ".json", ".cells.npz"))
        if tpath.is_file() and kpath.is_file() and ((sensor, role) != REFERENCE or cpath.is_file()):
            meta = json.loads(kpath.read_text())
            out[(sensor, role)] = Calibration(
                load_calibration(tpath), (np.asarray(meta["xs"]), np.asarray(meta["ys"])), meta["check"]
            )
            if (sensor, role) == REFERENCE:
                with np.load(cpath) as z:
                    ref_cells = (z["keys"], z["means"])
            say(f"  calibration {sensor} {role} unit {UNITS[role]}: cached ({tpath.name})")
            continue
        t0 = time.perf_counter()
        seq = SimulatedSequence(world="town", world_seed=0, sensor=sensor, seed=CAL_SEEDS[role], unit_seed=UNITS[role],
                                spacing=CAL_SPACING)  # fmt: skip
        pts = gather_points(seq, params)
        table = calibrate_points(pts, params)
        cal = table.lookup(pts.raw, pts.beam)
        keys, means = cell_means(_cell_keys(pts.xyz, COMMON_VOXEL), cal.astype(np.float64))
        if (sensor, role) == REFERENCE:
            ref_cells = (keys, means)
            np.savez(cpath, keys=keys, means=means)
            knots = (np.array([0.0, 1.0]), np.array([0.0, 1.0]))
            shared = len(keys)
        else:
            assert ref_cells is not None
            _, ia, ib = np.intersect1d(keys, ref_cells[0], assume_unique=True, return_indices=True)
            knots = fit_monotone(means[ia], ref_cells[1][ib])
            shared = int(ia.size)
        c = Calibration(table, knots, {})
        sat = float(table.meta.get("saturation", 1.0))
        c.check = {
            "cells_shared_with_reference": shared,
            "saturation": sat,
            "truth": _truth_check(
                seq,
                pts,
                {
                    "raw/saturation": np.clip(pts.raw / sat, 0, None),
                    "calibrated": cal,
                    "common": c.common(cal),
                },
            ),  # fmt: skip
        }
        table.save(tpath)
        kpath.write_text(json.dumps({"xs": knots[0].tolist(), "ys": knots[1].tolist(), "check": c.check}))
        out[(sensor, role)] = c
        say(
            f"  calibration {sensor} {role} unit {UNITS[role]}: {min(len(seq), n_scans)} scans, "
            f"{time.perf_counter() - t0:.0f} s"
        )
    return out


def intensity_fn(mode: str, sensor: str, cal: Calibration | None) -> Callable[[Scan], Scan]:
    if mode == "raw":
        return lambda s: s
    if mode == "normalised":
        return lambda s: normalize_intensity(s)  # the sensor's default spec
    assert cal is not None
    return cal.apply


# -- running --------------------------------------------------------------------------------------------------------
class MemoRecognizer:
    """A recognizer whose ``describe`` is remembered by the scan's content (shared by the runs of one intensity
    mode); everything else is the wrapped recognizer's."""

    def __init__(self, rec: Any, store: dict) -> None:
        self._rec = rec
        self._store = store

    def __getattr__(self, name: str) -> Any:
        return getattr(self._rec, name)

    def describe(self, scan: Scan) -> Any:
        h = hashlib.blake2b(digest_size=16)
        for a in (scan.xyz, scan.intensity):
            h.update(np.ascontiguousarray(a).tobytes())
        key = (self._rec.frontend_key, h.hexdigest())
        if key not in self._store:
            self._store[key] = self._rec.describe(scan)
        return self._store[key]


def make_config(
    mode: str,
    pipelines: tuple[str, ...],
    out_dir: str,
    params: dict[str, dict] | None = None,
    elevation: list[float] | None = None,
    ambiguity: float | None = None,
    thresholds: dict[str, float] | None = None,
) -> ExperimentConfig:
    """The run's experiment config in ``mode``; ``thresholds`` replace the presets' loop-closure thresholds."""
    evaluation: dict[str, Any] = {"mode": mode, "gt_distance": 5.0, "top_n": 5}
    if mode == "loop":
        evaluation["exclusion"] = {"frames": None, "seconds": GAP_S / 2, "metres": None}
    else:
        evaluation["localize"] = {"success_distance": SUCCESS_M, "ambiguity": {"max_ratio": ambiguity}}
    return parse_config({
        "name": f"cross-sensor-{mode}",
        # a placeholder dataset (the pairs' sequences are given): a sensor without settings of its own
        # (placerec.sensor_presets), so every pipeline runs its preset whatever the pair
        "dataset": {"source": "simulator", "simulator": {"world": "town", "sensor": "hdl64", "seed": 0}},
        "preprocess": {"min_range": 0.5, "intensity": {"mode": "raw"},
                       **({} if elevation is None else {"elevation_deg": elevation})},
        # the presets' thresholds: the placeholder dataset's sensor is none of a pair's (each pair mixes two)
        "pipelines": [{"name": n, "params": (params or {}).get(n, {}),
                       "threshold": (thresholds or {}).get(n, PIPELINES[n].threshold)} for n in pipelines],
        "evaluation": evaluation,
        "output": {"dir": out_dir, "cache_dir": None, "figures": False, "progress": False},
    })  # fmt: skip


def vertical_fov(sensor: str) -> tuple[float, float]:
    """(up, down) degrees above / below the horizon that ``sensor`` sees."""
    s = get_sensor(sensor)
    if s.beam_elevations_deg:
        return float(max(s.beam_elevations_deg)), float(-min(s.beam_elevations_deg))
    assert s.elevation_fov_deg is not None
    return float(s.elevation_fov_deg[0]), float(s.elevation_fov_deg[1])


def common_elevation(sensors: list[str]) -> list[float]:
    """``--crop common``: the elevation band (lowest, highest deg) every sensor of the run sees."""
    return [-min(vertical_fov(s)[1] for s in sensors), min(vertical_fov(s)[0] for s in sensors)]


def common_image_params(sensors: list[str], pipelines: tuple[str, ...], resolution: float) -> dict[str, dict]:
    """``--image common``: the 2D pipelines' images on one spherical grid for every sensor of the run (``resolution``
    degrees a pixel, the vertical field of view all the sensors see, gaps between beams filled vertically up to
    the sparsest sensor's beam spacing), features without row upsampling."""
    up = min(vertical_fov(s)[0] for s in sensors)
    down = min(vertical_fov(s)[1] for s in sensors)
    spacing = max(
        float(np.max(np.abs(np.diff(get_sensor(s).beam_elevations_deg))))
        if get_sensor(s).beam_elevations_deg
        else 0.0
        for s in sensors
    )
    image = {"mode": "spherical", "resolution_deg": resolution, "fov_up_deg": up, "fov_down_deg": down,
             "fill_radius_px": 1, "fill_holes_max_gap": int(np.ceil(spacing / resolution))}  # fmt: skip
    out = {}
    for name in pipelines:
        if "image" in type(make_pipeline(name).params).model_fields:
            out[name] = {"image": image, "feature_params": {"row_upsample": 1}}
    return out


def verifies(name: str) -> bool:
    """Whether pipeline ``name`` verifies its candidates with the shared verification (has ``verify.score``)."""
    verify = getattr(make_pipeline(name).params, "verify", None)
    return verify is not None and hasattr(verify, "score")


def loop_pipelines(names: tuple[str, ...]) -> tuple[str, ...]:
    """The pipelines run in loop mode: those with a fixed loop-closure threshold. The 3D voting pipelines
    (``ishot-*``, ``shot-*``, ``delight``) have none: they localise against a map, where an answer counts only if
    their verification accepted it, so they are judged in localise mode alone."""
    return tuple(n for n in names if PIPELINES[n].threshold is not None)


def loop_thresholds(items: list[str], pipelines: tuple[str, ...]) -> dict[str, float]:
    """``--loop-threshold PIPELINE=VALUE`` items as {pipeline: threshold}; SystemExit naming a bad item."""
    out = {}
    for item in items:
        name, _, value = item.partition("=")
        if name not in loop_pipelines(pipelines):
            raise SystemExit(
                f"--loop-threshold {item}: not a loop pipeline of this run {list(loop_pipelines(pipelines))}"
            )
        try:
            out[name] = float(value)
        except ValueError:
            raise SystemExit(f"--loop-threshold {item}: {value!r} is not a number") from None
        if not np.isfinite(out[name]) or out[name] < 0:
            raise SystemExit(f"--loop-threshold {item}: a threshold is a finite number >= 0")
    return out


def memo_pipelines(cfg: ExperimentConfig, store: dict) -> list[tuple[PipelineRecord, Any]]:
    return [(record, MemoRecognizer(rec, store)) for record, rec in build_pipelines(cfg)]


def localize_figures(
    record: PipelineRecord,
    map_poses: np.ndarray,
    query_poses: np.ndarray,
    ambiguity: AmbiguityParams | None = None,
) -> dict[str, Any]:
    """Success as `placerec.experiment.report` counts it (only an accepted answer of a verifying pipeline, not
    refused as ambiguous with ``--ambiguity``; the top one of a pipeline that does not verify), within
    `SUCCESS_M`."""
    estimates, basis, rule = localize_estimates(record.table(), map_poses, ambiguity)
    m = localization_metrics(estimates, query_poses[np.asarray(record.query_ids, dtype=np.int64)], SUCCESS_M,
                             basis=basis, answer_rule=rule)  # fmt: skip
    return {
        "success": m.success_rate,
        "r_at_p1": localise_r_at_p1(m.success_rate, m.n_wrong),
        "n_success": m.n_success,
        "n_no_answer": m.n_no_estimate,
        "n_wrong": m.n_wrong,
        "n_queries": m.n_queries,
        "answer_rule": rule,
    }


def localise_r_at_p1(success: float, n_wrong: int) -> float:
    """Localisation's recall at precision 1.00: the success rate when no accepted answer was wrong, else 0 (as
    ``r_at_p1`` in loop mode)."""
    return float(success) if n_wrong == 0 else 0.0


def loop_figures(
    cfg: ExperimentConfig,
    seq: ConcatSequence,
    records: list[PipelineRecord],
    truth: TruthClouds,
    ambiguity: AmbiguityParams | None = None,
):
    """Per pipeline: the pose-truth figures at its fixed threshold (queries of the second part only can close: the
    exclusion window keeps the first part from closing). With ``ambiguity`` (``--loop-ambiguity``) a query whose
    accepted answer the ambiguity rule refuses has no answer (every candidate refused), the first drive's poses
    placing the candidates as a map's poses do in localise mode (`ambiguous_answers`)."""
    poses, stamps = seq.poses, seq.timestamps
    tables = [r.table() for r in records]
    gts = pose_truths(cfg, tables, poses, stamps, truth)
    refused = [np.zeros(t.query_ids.shape, bool) for t in tables]
    if ambiguity is not None:
        refused = [ambiguous_answers(t, poses, ambiguity) for t in tables]
        tables = [
            t.refused(np.repeat(r[:, None], t.match_ids.shape[1], 1))
            for t, r in zip(tables, refused, strict=True)
        ]
    out = {}
    for record, table, gt, ambiguous in zip(records, tables, gts, refused, strict=True):
        _, summary = loop_summary(cfg, table, poses, stamps, record.threshold, truth, gt)
        op = summary["pose_truth"]["operating"]
        p, r = float(op["precision"]), float(op["recall"])
        out[record.pipeline] = {
            "threshold": record.threshold,
            "recall": r,
            "precision": p,
            "r_at_p1": r if p >= 1.0 else 0.0,
            "tp": op["tp"],
            "fp": op["fp"],
            "n_revisits": op["n_revisits"],
            "recall_at_100_precision": summary["pose_truth"]["recall_at_100_precision"],
            "max_false_score": summary["pose_truth"]["max_false_score"],
            "refused_ambiguous": int(ambiguous.sum()),
        }
    return out


def run_pair(
    split: dict[str, Any],
    map_sensor: str,
    query_sensor: str,
    mode: str,
    cals: dict[tuple[str, str], Calibration],
    args: argparse.Namespace,
    stores: dict[str, ScanStore],
    memo: dict,
    tmp: Path,
) -> dict[str, Any]:
    """Localise and loop figures of one pair under one intensity mode."""
    w, ws = split["world"], split["world_seed"]
    cfg = make_config(
        "localize", args.pipelines, str(tmp / "runs"), args.pipeline_params, args.elevation, args.ambiguity
    )
    seqs = []
    for sensor, role, seed, spacing in (
        (map_sensor, "map", split["map_seed"], args.map_spacing),
        (query_sensor, "query", split["query_seed"], args.query_spacing),
    ):
        base = base_sequence(w, ws, sensor, seed, UNITS[role], spacing)
        if base.name not in stores:
            stores[base.name] = ScanStore(base, tmp / "scans" / base.name)
        fn = intensity_fn(mode, sensor, cals.get((sensor, role)))
        seqs.append(
            places(stores[base.name], sensor, lambda s, fn=fn: IntensityView(s, fn, mode), spacing, cfg)
        )
    map_seq, query_seq = seqs
    out: dict[str, Any] = {"n_map": len(map_seq), "n_queries": len(query_seq)}
    t0 = time.perf_counter()
    _, _, records = run_localize(cfg, (map_seq, query_seq), memo_pipelines(cfg, memo))
    mp, qp = np.asarray(map_seq.poses), np.asarray(query_seq.poses)
    ambiguity = cfg.evaluation.localize.ambiguity
    out["localise"] = {r.pipeline: localize_figures(r, mp, qp, ambiguity) for r in records}
    looping = loop_pipelines(args.pipelines)
    out["loop"] = {}
    if looping:
        cfg = make_config("loop", looping, str(tmp / "runs"), args.pipeline_params, args.elevation,
                          thresholds=args.loop_thresholds)  # fmt: skip
        both = ConcatSequence(map_seq, query_seq)
        truth = TruthClouds(cfg.evaluation, both.poses)
        _, records = run_loop(cfg, both, memo_pipelines(cfg, memo), on_scan=truth)
        rule = None if args.loop_ambiguity is None else AmbiguityParams(max_ratio=args.loop_ambiguity)
        out["loop"] = loop_figures(cfg, both, records, truth, rule)
    out["seconds"] = round(time.perf_counter() - t0, 1)
    return out


# -- report ---------------------------------------------------------------------------------------------------------
def summarise(
    results: dict[str, Any], pairs: list[tuple[str, str]], args: argparse.Namespace
) -> dict[str, Any]:
    """Ratios cross / same (the query sensor's baseline) and the targets, per split."""
    out: dict[str, Any] = {}
    for split, per_mode in results.items():
        ratios: dict[str, Any] = {}
        for mode, per_pair in per_mode.items():
            for m, q in pairs:
                if m == q:
                    continue
                cross, same = per_pair.get(f"{m}>{q}"), per_pair.get(f"{q}>{q}")
                if cross is None or same is None or "error" in cross or "error" in same:
                    continue
                entry = {}
                for kind in ("loop", "localise"):
                    per = {}
                    for p in cross[kind]:
                        c, s = (run[kind][p]["r_at_p1"] for run in (cross, same))
                        per[p] = {"cross": c, "same": s, "ratio": (c / s) if s > 0 else None}
                    best = max(per, key=lambda p, per=per: per[p]["cross"]) if per else None
                    entry[kind] = {"pipelines": per, "best": best}
                    if kind == "localise" and per:
                        # the best pipeline across sensors against the best one on the query sensor's own map,
                        # which need not be the same pipeline: at precision 1.00, and against its success rate
                        # whatever its precision (a same-sensor baseline with a wrong answer has R@P1 0)
                        c = per[best]["cross"]
                        s1 = max(v["same"] for v in per.values())
                        s = max(same[kind][p]["success"] for p in per)
                        entry[kind]["best_over_best_same"] = (c / s1) if s1 > 0 else None
                        entry[kind]["best_over_best_same_success"] = (c / s) if s > 0 else None
                ratios.setdefault(f"{m}>{q}", {})[mode] = entry
        targets = {}
        for pair, per_mode_r in ratios.items():
            cal = per_mode_r.get("calibrated")
            raw = per_mode_r.get("raw")
            t: dict[str, Any] = {}
            if cal is not None and cal["loop"]["best"] is not None:
                b = cal["loop"]["best"]
                ratio = cal["loop"]["pipelines"][b]["ratio"]
                t["best_pipeline_calibrated"] = b
                t["loop_ratio_calibrated"] = ratio
                t["ratio_ge_0.8"] = ratio is not None and ratio >= 0.8
            if cal is not None:
                b = cal["localise"]["best"]
                ratio = cal["localise"]["pipelines"][b]["ratio"]
                t["best_localise_pipeline_calibrated"] = b
                t["localise_ratio_calibrated"] = ratio
                t["localise_ratio_ge_0.8"] = ratio is not None and ratio >= 0.8
                t["localise_best_over_best_same"] = cal["localise"].get("best_over_best_same")
                t["localise_best_over_best_same_success"] = cal["localise"].get("best_over_best_same_success")
            if cal is not None and raw is not None:
                if cal["loop"]["pipelines"]:
                    bc = max(v["cross"] for v in cal["loop"]["pipelines"].values())
                    br = max(v["cross"] for v in raw["loop"]["pipelines"].values())
                    t["best_loop_cross_calibrated_minus_raw"] = bc - br
                lc = max(v["cross"] for v in cal["localise"]["pipelines"].values())
                lr = max(v["cross"] for v in raw["localise"]["pipelines"].values())
                t["best_localise_cross_calibrated_minus_raw"] = lc - lr
            targets[pair] = t
        out[split] = {"ratios": ratios, "targets": targets}
    return out


def _pct(x: Any) -> str:
    return "-" if x is None else f"{100 * x:.0f}"


def print_tables(results: dict[str, Any], summary: dict[str, Any], args: argparse.Namespace) -> None:
    for split, per_mode in results.items():
        print(f"\n{split.upper()} split ({'tuning figures' if split == 'tuning' else 'figures to report'}): "
              f"{args.split_defs[split]}; loop: recall / precision % at the fixed threshold (pose truth), R@P1 = recall "
              "if precision is 100 else 0; localise: success % (accepted answers within 3 m), R@P1 = success if no accepted answer was wrong "
              "else 0; ratio = cross / the query sensor's same-sensor R@P1")  # fmt: skip
        print(f"{'pair':18} {'intensity':11} {'pipeline':16} {'maps':>4} {'qs':>3} {'loop R':>6} {'P':>4} "
              f"{'R@P1':>5} {'ratio':>5} {'loc':>4} {'R@P1':>5} {'ratio':>5} {'no ans':>6} {'wrong':>5}")  # fmt: skip
        for mode, per_pair in per_mode.items():
            for pair, res in per_pair.items():
                if "error" in res:
                    print(f"{pair.replace('>', ' -> '):18} {mode:11} failed: {res['error']}")
                    continue
                for p in args.pipelines:
                    lo, lc = res["loop"].get(p), res["localise"][p]
                    rat = summary[split]["ratios"].get(pair, {}).get(mode)
                    r1 = rat["loop"]["pipelines"][p]["ratio"] if rat and lo else None
                    r2 = rat["localise"]["pipelines"][p]["ratio"] if rat else None
                    loop_cols = (
                        f"{_pct(lo['recall']):>6} {_pct(lo['precision']):>4} {_pct(lo['r_at_p1']):>5} "
                        f"{_pct(r1) if rat else 'same':>5}"
                        if lo
                        else f"{'-':>6} {'-':>4} {'-':>5} {'-':>5}"
                    )
                    print(f"{pair.replace('>', ' -> '):18} {mode:11} {p:16} {res['n_map']:>4} {res['n_queries']:>3} "
                          f"{loop_cols} {_pct(lc['success']):>4} {_pct(lc['r_at_p1']):>5} "
                          f"{_pct(r2) if rat else 'same':>5} {lc['n_no_answer']:>6} {lc['n_wrong']:>5}")  # fmt: skip
        for pair, t in summary[split]["targets"].items():
            print(f"  target {pair}: {t}")


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="HDL-64 -> VLP-16 and VLP-16's baseline, sparser")
    ap.add_argument("--splits", nargs="+", choices=sorted(SPLITS), default=None, help="default: test")
    ap.add_argument(
        "--worlds",
        nargs="+",
        choices=protocol.TEST_WORLDS,
        default=["town"],
        help="worlds each split drives (default town)",
    )
    ap.add_argument("--pairs", nargs="+", default=None, help="MAP:QUERY pairs (default: the issue's four)")
    ap.add_argument("--pipelines", nargs="+", default=None, choices=sorted(PIPELINES))
    ap.add_argument("--intensity", nargs="+", default=None, choices=INTENSITIES)
    ap.add_argument(
        "--map-spacing", type=float, default=None, help="m between map scans (default 4; quick 8)"
    )
    ap.add_argument(
        "--query-spacing", type=float, default=None, help="m between queries (default 8; quick 16)"
    )
    ap.add_argument(
        "--cal-scans",
        type=int,
        default=None,
        help="scans per calibration drive (default 60, also with --quick: the same cached tables)",
    )
    ap.add_argument(
        "--image",
        choices=("pipeline", "common"),
        default="pipeline",
        help="2D pipelines' images: their own (default) or one spherical grid over the common field of view",
    )
    ap.add_argument("--image-resolution", type=float, default=0.4, help="deg a pixel with --image common")
    ap.add_argument(
        "--min-constraint",
        type=float,
        default=None,
        help="verify.score.min_constraint of every verifying pipeline (how well the overlap must pin the "
        "translation down; None: the presets', not tested)",
    )
    ap.add_argument(
        "--ambiguity",
        type=float,
        default=None,
        metavar="RATIO",
        help="localisation refuses an answer another place (more than 5 m away) scores RATIO of "
        "(evaluation.localize.ambiguity.max_ratio; default: off)",
    )
    ap.add_argument(
        "--loop-ambiguity",
        type=float,
        default=None,
        metavar="RATIO",
        help="loop mode: the same rule, the map drive's poses placing the candidates (as a session joining a "
        "prior map does: prior_map.join_ambiguity; default: off)",
    )
    ap.add_argument(
        "--loop-threshold",
        dest="loop_threshold_items",
        action="append",
        default=[],
        metavar="PIPELINE=VALUE",
        help="loop mode's fixed threshold of a pipeline (default: its preset's; repeatable)",
    )
    ap.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="PIPELINE.KEY=VALUE",
        help="a pipeline parameter for every pair, e.g. scan-context.full_shift_search=true (repeatable)",
    )
    ap.add_argument(
        "--crop",
        choices=("none", "common"),
        default="common",
        help="common (default): every scan cropped to the elevation band all the run's sensors see (preprocess.elevation_deg)",
    )
    ap.add_argument(
        "--cache-dir", default=".cache/cross_sensor", help="calibration tables and common-scale maps"
    )
    args = ap.parse_args(argv)
    q = args.quick
    args.splits = args.splits or ["test"]
    args.pipelines = tuple(args.pipelines or (QUICK_PIPELINES if q else PIPELINE_NAMES))
    args.intensity = tuple(args.intensity or INTENSITIES)
    args.map_spacing = args.map_spacing or (8.0 if q else 4.0)
    args.query_spacing = args.query_spacing or (16.0 if q else 8.0)
    args.cal_scans = args.cal_scans or 60
    cross = (
        [tuple(p.split(":")) for p in args.pairs] if args.pairs else list(QUICK_PAIRS if q else CROSS_PAIRS)
    )
    known = sensor_names()
    skipped = []
    for m, qs in list(cross):
        for s in (m, qs):
            if s not in known or (not is_spinning(s) and s not in protocol.CAPTURE):
                skipped.append(f"{m}:{qs} ({s} unavailable)")
                cross.remove((m, qs))
                break
    for split in args.splits:
        for seed in (SPLITS[split]["map_seed"], SPLITS[split]["query_seed"]):
            if split == "tuning" and protocol.is_test_seed(seed):
                raise SystemExit(f"tuning split uses test seed {seed}")
    args.split_defs = world_splits(args.splits, args.worlds)
    baselines = sorted({qs for _, qs in cross} | {m for m, _ in cross})
    pairs = [(m, qs) for m, qs in cross] + [(s, s) for s in baselines]
    args.pipeline_params = (
        common_image_params(baselines, args.pipelines, args.image_resolution)
        if args.image == "common"
        else {}
    )
    if args.min_constraint is not None:
        gate = {"verify": {"score": {"min_constraint": args.min_constraint}}}
        args.pipeline_params = {
            name: deep_merge(args.pipeline_params.get(name, {}), gate)
            for name in args.pipelines
            if verifies(name)
        }
    for item in args.overrides:
        if item.split(".", 1)[0] not in args.pipelines:
            raise SystemExit(
                f"--set {item}: the key starts with a pipeline of --pipelines {list(args.pipelines)}"
            )
    args.pipeline_params = apply_overrides(
        {name: dict(args.pipeline_params.get(name, {})) for name in args.pipelines}, args.overrides
    )
    args.elevation = common_elevation(baselines) if args.crop == "common" else None
    args.loop_thresholds = loop_thresholds(args.loop_threshold_items, args.pipelines)
    t_start = time.perf_counter()

    def say(s: str) -> None:
        print(s, flush=True)

    logging.basicConfig(level=logging.WARNING)
    say(f"pairs: {', '.join(f'{m}->{qs}' for m, qs in pairs)}; pipelines {', '.join(args.pipelines)}; "
        f"intensity {', '.join(args.intensity)}; splits {', '.join(args.splits)}")  # fmt: skip
    cals: dict[tuple[str, str], Calibration] = {}
    if "calibrated" in args.intensity:
        roles = sorted({(m, "map") for m, _ in pairs} | {(qs, "query") for _, qs in pairs})
        cals = calibrations(roles, args.cal_scans, Path(args.cache_dir), say)
    t_cal = time.perf_counter() - t_start
    results: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix="placerec-cross-sensor-") as tmpdir:
        tmp = Path(tmpdir)
        for split in args.split_defs:
            stores: dict[str, ScanStore] = {}
            for mode in args.intensity:
                memo: dict = {}  # descriptions of this mode's scans, shared by its localise and loop runs
                for m, qs in pairs:
                    try:
                        res = run_pair(args.split_defs[split], m, qs, mode, cals, args, stores, memo, tmp)
                    except Exception as exc:  # one failed pair is reported, not the end of the run
                        log.exception("%s %s %s -> %s failed", split, mode, m, qs)
                        res = {"error": repr(exc)}
                    results.setdefault(split, {}).setdefault(mode, {})[f"{m}>{qs}"] = res
                    if "error" in res:
                        continue
                    best = max(v["success"] for v in res["localise"].values())
                    say(
                        f"  {split} {mode} {m} -> {qs}: {res['n_map']} map, {res['n_queries']} queries, best "
                        f"localised {best:.2f}, {res['seconds']:.0f} s"
                    )
    summary = summarise(results, pairs, args)
    print_tables(results, summary, args)
    checks = {f"{s} {r}": c.check for (s, r), c in cals.items()}
    if checks:
        print("\ncalibration on the tuning drives (town, world seed 0) against the simulator's apparent reflectance "
              "(corr / MAE): raw/saturation, per-beam table, table + common scale")  # fmt: skip
        for k, c in checks.items():
            t = c["truth"]
            print(f"  {k:14} sat {c['saturation']:7.1f}  " + "  ".join(f"{n} {v['corr']:.3f}/{v['mae']:.3f}"
                                                                        for n, v in t.items()))  # fmt: skip
    out = {
        "tool": "eval_cross_sensor",
        "quick": q,
        "splits": {s: {**d, "label": s.split("-")[0]} for s, d in args.split_defs.items()},
        "units": UNITS,
        "calibration_drives": {
            "world": "town",
            "world_seed": 0,
            "seeds": CAL_SEEDS,
            "spacing_m": CAL_SPACING,
            "scans": args.cal_scans,
            "label": "tuning",
        },  # fmt: skip
        "pipelines": {p: args.loop_thresholds.get(p, PIPELINES[p].threshold) for p in args.pipelines},
        "image": args.image,
        "elevation_deg": args.elevation,
        "pipeline_params": args.pipeline_params,
        "min_constraint": args.min_constraint,
        "ambiguity": args.ambiguity,
        "loop_ambiguity": args.loop_ambiguity,
        "intensity": list(args.intensity),
        "skipped": skipped,
        "seconds": round(time.perf_counter() - t_start),
        "calibration_seconds": round(t_cal),
        "results": results,
        "summary": summary,
        "calibration_check": checks,
    }
    print(json.dumps(out, default=float))
    return out


if __name__ == "__main__":
    main()
