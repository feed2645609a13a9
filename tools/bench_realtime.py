"""Real-time profile of the real path: `placerec slam` and the loop-closure detector per stage, KISS-SLAM beside.

Sequences (``--sequences``):

* ``kitti-raw``: the 22 real KITTI raw HDL-64 frames of ``../shared/data/real/kitti_raw_hdl64_sequence`` (PCD)
  played forward then backward (frames 0..21, 20..0: 43 scans, 10 Hz time stamps), so the database grows and the
  backward half revisits the forward half. The revisits are the very same scans (their ICP converges at once) and
  the exclusion window is cut to ``--real-exclusion`` frames (default 10: scan 21+m may match frame 21-m from
  m = 5, and the forward half queries frames 10 back). No ground truth.
* ``kitti00``: the 4 real KITTI 00 frames (94, 95, 198, 199) in that order, exclusion 1 frame. Not a trajectory
  (two pairs 100 frames apart): times only, no ATE.
* ``sim-revisit`` (asked for by name; for ``--realtime``): simulated HDL-64 along the town's second street, then
  back along it one lane over (scans 72-91 and 335-354 of the default route), 40 scans, exclusion 15 frames: a
  real revisit (reverse direction), so closures are accepted. ATE against the true poses.
* ``sim-hdl64``, ``sim-os1-128``: `placerec.sim.SimulatedSequence` (town, route default, seed 0, ``--scans``
  scans), exported once as KITTI-style folders (`placerec.sim.write_kitti_sequence`, cached in ``--cache``) and
  read back from them, so placerec and KISS-SLAM see the same files; ATE against their true poses.

For every sequence and pipeline of ``--pipelines`` (orb-hbst, orb-dbow, scan-context) two runs in this process:

* **slam**: `placerec.slam_app.run.slam_sequence` with configs/slam_kitti.yaml (KISS-ICP odometry, the pipeline
  at ``loops.threshold`` 0.25 with its accepted poses refined, Cauchy loop factors, GNC batch; exclusion 100 frames
  on the simulated sequences); with ground truth also the ATE and each accepted closure's pose error against the
  true relative pose of its two scans (median / max);
* **detector**: `placerec.loop_closure.LoopClosureDetector` alone (same pipeline, threshold, exclusion and k) over
  the same scans read and preprocessed beforehand: describe + query + verify + insert.

Per scan, wall and CPU (``time.process_time``: the process's, all threads) ms of every stage, reported as median /
p95 / max. The stages come from wrappers this tool puts around library functions for the run (no change in the
library; restored after): ``read`` (the sequence's ``__getitem__``), ``preprocess`` (`preprocess_scan`),
``odometry`` (KISS-ICP's ``register``), ``describe`` / ``query`` / ``insert`` (the recognizer's ``describe``,
``query_description``, ``add_description``), inside describe ``projection`` (`make_image`; Scan Context: its
polar descriptor `make_descriptor`), ``features`` (the extractor's ``extract``) and ``icp cloud`` (`scan_cloud`,
the voxelised cloud a description keeps); inside query ``ransac`` (`hypothesise`: grouping + RANSAC),
``icp prepare`` (`as_source` / `as_target`: the query's cloud once per query, each database cloud once, cached)
and ``icp`` (`refine`), ``verify`` (= ransac + `as_source` + `complete`: all of the verification) and
``retrieval`` (= query - verify: the retrieval and the correspondence matching); ``graph`` (slam: the online
back end's graph + iSAM2 update from ``SlamResult.timing_ms``; its CPU is the loop's CPU less the stages above).
``loop closure`` = describe + query + insert; ``total`` = every stage of the scan.

KISS-SLAM (PyPI ``kiss-slam``, `bench_slam_matrix.run_kiss_slam`, its own venv ``.venv-kiss-slam``, defaults) runs on
the same sequences in the same run (the real ones written as KITTI ``.bin`` folders in play order). Its time per
scan is the "Average Runtime" its pipeline logs (its loop over the frames); its process's wall and CPU per scan
(start-up and final optimisation included) are reported beside. Ratios placerec / KISS-SLAM: mean slam total
wall per scan / KISS-SLAM's runtime, and ATE (simulated sequences only).

**Real-time mode** (``--realtime BUDGET_MS``; this replaces the profile above): for every sequence and pipeline
the detector alone and `slam_sequence`, each sequential then with the detector's real-time mode
(`placerec.realtime.RealtimeParams`: ``budget_ms``, ``--max-backlog``), scans fed at ``--rate-hz`` (a scan is
not given before its time slot; a call that overruns its slot delays the next). Reported per mode: the wall time
of each ``process()`` call (detector) or of each scan's whole loop (slam: odometry + preprocess + the online
back end, the worker's wait included) as median / p95 / max, scans over the budget, the closures deferred
(returned by a later call than their scan's) and the most scans late, the flush at the end, and whether the
accepted closures (ids, scores, poses to 1e-9) are the sequential run's. No stage wrappers (they are not
thread-safe); KISS-SLAM not run.

    .venv/bin/python tools/bench_realtime.py                            # everything, --scans 150
    .venv/bin/python tools/bench_realtime.py --scans 60 --pipelines orb-hbst --no-kiss-slam
    .venv/bin/python tools/bench_realtime.py --realtime 100 --sequences kitti-raw sim-hdl64 --scans 60
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import resource
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_slam_matrix import KISS_SLAM_VENV, export_sequence, kiss_slam_version, run_kiss_slam  # noqa: E402

from placerec.eval.pose_error import pose_errors  # noqa: E402
from placerec.eval.trajectory import trajectory_errors  # noqa: E402
from placerec.experiment.tables import print_rows  # noqa: E402
from placerec.io import open_sequence  # noqa: E402
from placerec.io.kitti import write_kitti_bin  # noqa: E402
from placerec.slam_app.config import SlamConfig, load_slam_config  # noqa: E402
from placerec.types import relative_pose  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT.parent / "shared" / "data" / "real"
CONFIG = ROOT / "configs" / "slam_kitti.yaml"
PIPELINES = ("orb-hbst", "orb-dbow", "scan-context")
#: verified pipelines the profile also runs when named (issue #30 part 4)
MORE_PIPELINES = ("superpoint-dbow",)
SEQUENCES = ("kitti-raw", "kitti00", "sim-hdl64", "sim-os1-128")
#: a simulated revisit for the real-time mode (not in the default profile)
REVISIT = "sim-revisit"
SIM_SENSORS = {"sim-hdl64": "hdl-64", "sim-os1-128": "os1-128"}
#: Reported stages in order; the indented ones are parts of the one above them.
STAGES = (
    "read", "odometry", "preprocess", "describe", "  projection", "  features", "  icp cloud", "query",
    "  retrieval", "  verify", "    ransac", "    icp prepare", "    icp", "insert", "graph", "loop closure", "total",
)  # fmt: skip


# --- timing wrappers --------------------------------------------------------------------------------------------


@dataclass
class StageClock:
    """Wall and CPU ms per stage, summed over the calls of the current scan (`end_scan` closes a scan)."""

    now: dict[str, list[float]] = field(default_factory=dict)
    scans: list[dict[str, tuple[float, float]]] = field(default_factory=list)

    def wrap(self, stage: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        def timed(*args: Any, **kwargs: Any) -> Any:
            w, c = time.perf_counter(), time.process_time()
            try:
                return fn(*args, **kwargs)
            finally:
                acc = self.now.setdefault(stage, [0.0, 0.0])
                acc[0] += (time.perf_counter() - w) * 1e3
                acc[1] += (time.process_time() - c) * 1e3

        return timed

    def add(self, stage: str, wall: float, cpu: float) -> None:
        acc = self.now.setdefault(stage, [0.0, 0.0])
        acc[0] += wall
        acc[1] += cpu

    def end_scan(self) -> None:
        self.scans.append({k: (v[0], v[1]) for k, v in self.now.items()})
        self.now = {}


#: (module, attribute, stage): library functions timed while a run is profiled.
MODULE_TARGETS = (
    ("placerec.slam_app.run", "preprocess_scan", "preprocess"),
    ("placerec.pipelines.visual", "make_image", "projection"),
    ("placerec.baselines.scan_context", "make_descriptor", "projection"),
    ("placerec.pipelines.visual", "scan_cloud", "icp cloud"),
    ("placerec.baselines.scan_context", "scan_cloud", "icp cloud"),
    ("placerec.verify.candidates", "hypothesise", "ransac"),
    ("placerec.verify.candidates", "as_source", "prepare source"),
    ("placerec.verify.candidates", "as_target", "prepare target"),
    ("placerec.verify.candidates", "complete", "complete"),
    ("placerec.verify.verify", "refine", "icp"),
)


@contextlib.contextmanager
def profiled(clock: StageClock, rec: Any) -> Iterator[None]:
    """`MODULE_TARGETS` and ``rec``'s describe / query / insert (and its extractor's ``extract``) timed into
    ``clock``; everything restored on exit."""
    import importlib

    saved: list[tuple[Any, str, Any]] = []
    for mod_name, attr, stage in MODULE_TARGETS:
        mod = importlib.import_module(mod_name)
        saved.append((mod, attr, getattr(mod, attr)))
        setattr(mod, attr, clock.wrap(stage, getattr(mod, attr)))
    own = [
        (rec, "describe", "describe"),
        (rec, "query_description", "query"),
        (rec, "add_description", "insert"),
    ]
    if getattr(rec, "extractor", None) is not None:
        own.append((rec.extractor, "extract", "features"))
    for obj, attr, stage in own:
        setattr(obj, attr, clock.wrap(stage, getattr(obj, attr)))
    try:
        yield
    finally:
        for mod, attr, fn in saved:
            setattr(mod, attr, fn)
        for obj, attr, _ in own:
            with contextlib.suppress(AttributeError):
                delattr(obj, attr)


def derived(
    scan: dict[str, tuple[float, float]], slam: dict[str, float] | None
) -> dict[str, tuple[float, float]]:
    """One scan's reported stages (`STAGES`, names stripped) from the timed calls (and the slam loop's timing)."""
    g = lambda k: np.array(scan.get(k, (0.0, 0.0)))  # noqa: E731
    verify = g("ransac") + g("prepare source") + g("complete")
    out = {
        k: g(k) for k in ("read", "odometry", "preprocess", "describe", "projection", "features", "icp cloud")
    }
    out |= {"query": g("query"), "retrieval": g("query") - verify, "verify": verify, "ransac": g("ransac")}
    out |= {"icp prepare": g("prepare source") + g("prepare target"), "icp": g("icp"), "insert": g("insert")}
    out["loop closure"] = g("describe") + g("query") + g("insert")
    out["graph"] = np.zeros(2)
    if slam is not None:
        cpu = slam["cpu"] - out["preprocess"][1] - out["loop closure"][1]
        out["graph"] = np.array([slam["graph"] + slam["isam2"], max(cpu, 0.0)])
    out["total"] = out["read"] + out["odometry"] + out["preprocess"] + out["loop closure"] + out["graph"]
    return {k: (float(v[0]), float(v[1])) for k, v in out.items()}


def stats(values: list[float]) -> list[float]:
    """[median, p95, max, mean] (rounded to 0.01 ms)."""
    a = np.asarray(values, np.float64)
    return [round(float(x), 2) for x in (np.median(a), np.percentile(a, 95), a.max(), a.mean())]


def profile(scans: list[dict[str, tuple[float, float]]]) -> dict[str, dict[str, list[float]]]:
    """Per stage: {"wall": stats, "cpu": stats} over the scans."""
    names = [s.strip() for s in STAGES]
    return {n: {m: stats([s[n][j] for s in scans]) for j, m in enumerate(("wall", "cpu"))} for n in names}


# --- sequences ------------------------------------------------------------------------------------------------


class Replayed:
    """``base``'s scans in the order ``index`` (each read from ``base`` when asked, timed in ``reads``), 10 Hz
    time stamps, ``base``'s poses in that order when it has them."""

    def __init__(
        self, base: Any, index: list[int], name: str, pace: Callable[[int], None] | None = None
    ) -> None:
        self.base, self.index, self.name, self.pace = base, list(index), name, pace
        self.poses = None if base.poses is None else np.asarray(base.poses)[self.index]
        self.timestamps = np.arange(len(self.index)) * 0.1
        self.points: list[int] = []  # points of each scan read
        self.reads: list[tuple[float, float]] = []  # wall and CPU ms of each read

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, i: int) -> Any:
        if self.pace is not None:  # the real-time mode's sensor rate: not before the scan's time slot
            self.pace(i)
        w, c = time.perf_counter(), time.process_time()
        scan = self.base[self.index[i]]
        self.reads.append(((time.perf_counter() - w) * 1e3, (time.process_time() - c) * 1e3))
        self.points.append(len(scan.xyz))
        return scan


@dataclass
class Source:
    """A sequence to profile: its base sequence, play order, exclusion window, and KISS-SLAM's folder."""

    name: str
    base: Any
    index: list[int]
    exclusion: int
    folder: Path
    ground_truth: bool


def _write_bins(base: Any, index: list[int], folder: Path) -> Path:
    """``base``'s scans in play order as a KITTI ``velodyne/*.bin`` folder (x y z intensity float32), once."""
    if not (folder / "done").is_file():
        (folder / "velodyne").mkdir(parents=True, exist_ok=True)
        for k, i in enumerate(index):
            scan = base[i]
            ok = np.isfinite(scan.xyz).all(axis=1) & np.any(scan.xyz != 0, axis=1)
            write_kitti_bin(folder / "velodyne" / f"{k:06d}.bin", scan.select(ok))
        (folder / "done").write_text("")
    return folder


def _revisit_folder(folder: Path) -> Path:
    """``sim-revisit``: simulated HDL-64 scans along the town's second street (scans 72-91 of the default route),
    then the same street the other way one lane over (scans 335-354: the demo's reverse-direction revisit), 40
    scans, exclusion 15 frames, written once as a KITTI folder."""
    if not (folder / "sensor.yaml").is_file():
        from placerec.sim import SimulatedSequence, write_kitti_sequence
        from placerec.sim.routes import Route

        full = SimulatedSequence("town", "hdl-64", seed=0)
        index = np.r_[72:92, 335:355]
        route = Route(full.poses[index], np.arange(index.size, dtype=float), "reverse-street")
        write_kitti_sequence(SimulatedSequence("town", "hdl-64", seed=0, route=route), folder, progress=False)
    return folder


def sources(
    names: list[str], n_scans: int, real_exclusion: int, cache: Path, sim_exclusion: int = 100
) -> list[Source]:
    """The sequences of ``names`` (module docstring); a real one whose data is missing is left out, said so."""
    out = []
    for name in names:
        if name == REVISIT:
            folder = _revisit_folder(cache / "sequences" / REVISIT)
            base = open_sequence(folder)
            out.append(Source(name, base, list(range(len(base))), 15, folder, True))
            continue
        if name in SIM_SENSORS:
            over = [f"dataset.simulator.sensor={SIM_SENSORS[name]}", f"dataset.simulator.n_scans={n_scans}"]
            cfg = load_slam_config(ROOT / "configs" / "slam_demo.yaml", over)
            folder = export_sequence(cfg, cache / "sequences" / f"{name}_{n_scans}")
            base = open_sequence(folder)
            out.append(Source(name, base, list(range(len(base))), sim_exclusion, folder, True))
            continue
        src = REAL / ("kitti_raw_hdl64_sequence" if name == "kitti-raw" else "kitti00_frames")
        if not src.is_dir():
            print(f"{name}: {src} not found, left out")
            continue
        base = open_sequence(src)
        n = len(base)
        index = [*range(n), *range(n - 2, -1, -1)] if name == "kitti-raw" else list(range(n))
        exclusion = real_exclusion if name == "kitti-raw" else 1
        folder = _write_bins(base, index, cache / "sequences" / f"{name}_{len(index)}")
        out.append(Source(name, base, index, exclusion, folder, False))
    return out


# --- the runs -------------------------------------------------------------------------------------------------


#: ``--set`` overrides of the SLAM config (e.g. ``loops.pipeline.params.feature_params.backend=onnxruntime``),
#: applied to every run of this process after the tool's own; set once by `main`
SETS: list[str] = []


def slam_config(pipeline: str, exclusion: int, *more: str) -> SlamConfig:
    over = [f"loops.pipeline.name={pipeline}", f"loops.exclusion.frames={exclusion}", "output.progress=false"]
    return load_slam_config(CONFIG, [*over, *more, *SETS])


def run_slam(src: Source, pipeline: str) -> dict[str, Any]:
    """`slam_sequence` on ``src`` with every stage timed; also the ATE (ground truth only) and the points."""
    from placerec.recognizer import make_pipeline
    from placerec.slam_app.run import odometry_source, slam_sequence

    cfg = slam_config(pipeline, src.exclusion)
    clock = StageClock()
    seq = Replayed(src.base, src.index, src.name)
    rec = make_pipeline(pipeline, cfg.loops.pipeline.params)
    odo = clock.wrap("odometry", odometry_source(cfg, seq))
    ends = _ending(clock, odo)
    with profiled(clock, rec):
        result = slam_sequence(cfg, seq, rec, ends)  # type: ignore[arg-type]
    clock.end_scan()  # the last scan (the batch optimisation after it is not timed)
    for scan, read in zip(clock.scans, seq.reads, strict=True):
        scan["read"] = read
    timing = result.timing_ms
    scans = [
        derived(s, {k: timing[k][i] for k in ("cpu", "graph", "isam2")}) for i, s in enumerate(clock.scans)
    ]
    out: dict[str, Any] = {
        "stages": profile(scans),
        "points": int(np.median(seq.points)),
        "scans": len(scans),
    }
    out["loops"] = len(result.loops)
    if src.ground_truth and result.ground_truth is not None:
        gt = result.ground_truth
        out["ate_m"] = trajectory_errors(result.optimized, gt).ate_rmse
        if result.loops:  # each accepted closure's pose against the true relative pose of its two scans
            est = np.stack([lp.T_match_query for lp in result.loops])
            true = np.stack([relative_pose(gt[lp.match_id], gt[lp.query_id]) for lp in result.loops])
            te, re_deg = pose_errors(est, true)
            out["loop_error_cm"] = [round(float(np.median(te)) * 100, 2), round(float(te.max()) * 100, 2)]
            out["loop_error_deg"] = [round(float(np.median(re_deg)), 3), round(float(re_deg.max()), 3)]
    out["poses"] = result.optimized
    return out


def warm_up(src: Source, pipeline: str, scans: int = 4) -> float:
    """Seconds of `slam_sequence` over ``src``'s first ``scans`` scans (exclusion 1, so they query and verify),
    not timed otherwise: the process's first-call costs (imports; Numba's first dispatch, ~0.3 s) are paid before
    the timed runs, as in the real-time mode, instead of landing on the first pipeline's first scan."""
    from placerec.recognizer import make_pipeline
    from placerec.slam_app.run import odometry_source, slam_sequence

    t0 = time.perf_counter()
    cfg = slam_config(pipeline, 1)
    seq = Replayed(src.base, src.index[:scans], src.name)
    slam_sequence(cfg, seq, make_pipeline(pipeline, cfg.loops.pipeline.params), odometry_source(cfg, seq))  # type: ignore[arg-type]
    return time.perf_counter() - t0


def _ending(clock: StageClock, odometry: Callable[..., Any]) -> Callable[..., Any]:
    """``odometry`` that first closes the previous scan in ``clock`` (slam_sequence calls it first for a scan)."""

    def odo(i: int, scan: Any) -> Any:
        if i:
            clock.end_scan()
        return odometry(i, scan)

    return odo


def run_detector(src: Source, pipeline: str) -> dict[str, Any]:
    """`LoopClosureDetector` alone over ``src``'s scans, read and preprocessed first (timed too)."""
    from placerec.loop_closure import LoopClosureDetector
    from placerec.preprocess import preprocess_scan
    from placerec.recognizer import make_pipeline

    cfg = slam_config(pipeline, src.exclusion)
    clock = StageClock()
    seq = Replayed(src.base, src.index, src.name)
    pre = clock.wrap("preprocess", preprocess_scan)
    scans = []
    for i in range(len(seq)):
        scans.append(pre(seq[i], cfg.preprocess, keep_organized=True))
        clock.now["read"] = list(seq.reads[i])
        clock.end_scan()
    rec = make_pipeline(pipeline, cfg.loops.pipeline.params)
    ex = cfg.loops.exclusion
    det = LoopClosureDetector(rec, cfg.loops.threshold, ex.frames, k=cfg.loops.k)
    accepted = 0
    with profiled(clock, rec):
        for i, scan in enumerate(scans):
            clock.now = {k: list(v) for k, v in clock.scans[i].items()}
            accepted += len(det.process(scan, timestamp=float(i) * 0.1))
            clock.scans[i] = {k: (v[0], v[1]) for k, v in clock.now.items()}
    return {"stages": profile([derived(s, None) for s in clock.scans]), "closures": accepted}


def run_kiss(src: Source, venv: Path, cache: Path, poses: np.ndarray | None) -> dict[str, Any]:
    """KISS-SLAM on ``src``'s folder: its logged runtime per scan, its process's wall and CPU per scan, ATE.
    A real sequence gets placerec's poses as ``poses.txt`` (`run_kiss_slam` scores against it; not reported)."""
    from placerec.io import write_kitti_poses

    if not src.ground_truth:
        assert poses is not None
        write_kitti_poses(src.folder / "poses.txt", poses)
    out = cache / "kiss_slam" / src.name
    cpu0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    res = run_kiss_slam(venv, src.folder, out, 10)
    cpu1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (cpu1.ru_utime + cpu1.ru_stime - cpu0.ru_utime - cpu0.ru_stime) * 1e3
    log = (out / "latest" / "result_metrics.log").read_text()
    runtime = re.search(r"Average Runtime\s*\|\s*([\d.]+)", log)
    n = res["scans"]
    return {
        "runtime_ms": float(runtime.group(1)) if runtime else None,
        "wall_ms": res["seconds"] * 1e3 / n,
        "cpu_ms": cpu / n,
        "closures": res["closures"],
        "ate_m": res["after"]["ate_rmse"] if src.ground_truth else None,
    }


def bench(
    names: list[str],
    pipelines: list[str],
    n_scans: int,
    cache: Path,
    kiss_venv: Path | None,
    real_exclusion: int = 10,
    sim_exclusion: int = 100,
) -> dict[str, Any]:
    """The whole profile (the tool's core, one dict): per sequence its points, per pipeline the slam and detector
    profiles, KISS-SLAM's figures (``kiss_venv`` None: not run) and the ratios."""
    report: dict[str, Any] = {"bench": "realtime", "cpus": os.cpu_count(), "load_before": os.getloadavg()}
    report["sequences"] = {}
    for src in sources(names, n_scans, real_exclusion, cache, sim_exclusion):
        entry: dict[str, Any] = {"scans": len(src.index), "exclusion": src.exclusion, "pipelines": {}}
        poses = None
        for p in pipelines:
            print(f"{src.name}: {p} slam ...", flush=True)
            warm_s = warm_up(src, p)
            slam = run_slam(src, p)
            poses = slam.pop("poses") if poses is None else poses
            entry["points"] = slam.pop("points")
            print(f"{src.name}: {p} detector ...", flush=True)
            det = run_detector(src, p)
            lc, odo = slam["stages"]["loop closure"]["cpu"][3], slam["stages"]["odometry"]["cpu"][3]
            entry["pipelines"][p] = {
                "slam": slam,
                "detector": det,
                "lc_cpu_over_odometry": lc / odo if odo else None,
                "warm_up_s": round(warm_s, 2),
            }
        if kiss_venv is not None:
            print(f"{src.name}: KISS-SLAM ...", flush=True)
            kiss = entry["kiss_slam"] = run_kiss(src, kiss_venv, cache, poses)
            for v in entry["pipelines"].values():
                ms = v["slam"]["stages"]["total"]["wall"][3]
                v["time_ratio"] = ms / kiss["runtime_ms"] if kiss["runtime_ms"] else None
                ate = v["slam"].get("ate_m")
                v["ate_ratio"] = ate / kiss["ate_m"] if ate is not None and kiss["ate_m"] else None
        report["sequences"][src.name] = entry
    report["load_after"] = os.getloadavg()
    return report


# --- the real-time mode -----------------------------------------------------------------------------------------


def _slots(rate_hz: float) -> Callable[[int], None]:
    """``wait(i)``: sleep until scan ``i``'s time slot (``i / rate_hz`` after the first call's)."""
    start: list[float] = []

    def wait(i: int) -> None:
        if not start:
            start.append(time.perf_counter())
        ahead = start[0] + i / rate_hz - time.perf_counter()
        if ahead > 0:
            time.sleep(ahead)

    return wait


def _closure_keys(closures: list[Any]) -> list[tuple[int, int, float]]:
    return sorted((int(c.match_id), int(c.query_id), float(c.score)) for c in closures)


def _same_closures(a: list[Any], b: list[Any]) -> bool:
    """The same accepted closures (ids, scores; poses to 1e-9), in whatever order they came."""
    if _closure_keys(a) != _closure_keys(b):
        return False
    key = lambda c: (int(c.match_id), int(c.query_id), float(c.score))  # noqa: E731
    pa = {key(c): c for c in a}
    pose = lambda c: getattr(c, "relative_pose", getattr(c, "T_match_query", None))  # noqa: E731
    for c in b:
        px, py = pose(pa[key(c)]), pose(c)
        if (px is None) != (py is None):
            return False
        if px is not None and py is not None and not np.allclose(px, py, atol=1e-9, rtol=0):
            return False
    return True


def _rt_summary(ms: list[float], budget_ms: float) -> dict[str, Any]:
    return {"ms": stats(ms)[:3], "over_budget": int(sum(m > budget_ms for m in ms)), "scans": len(ms)}


def run_detector_modes(
    src: Source, pipeline: str, budget_ms: float, max_backlog: int, rate_hz: float
) -> dict[str, Any]:
    """The detector alone over ``src``'s scans (read and preprocessed first), sequential then real-time."""
    from placerec.loop_closure import LoopClosureDetector, RealtimeParams
    from placerec.preprocess import preprocess_scan
    from placerec.recognizer import make_pipeline

    cfg = slam_config(pipeline, src.exclusion)
    seq = Replayed(src.base, src.index, src.name)
    scans = [preprocess_scan(seq[i], cfg.preprocess, keep_organized=True) for i in range(len(seq))]
    warm = LoopClosureDetector(make_pipeline(pipeline, cfg.loops.pipeline.params), cfg.loops.threshold, 1)
    for i, scan in enumerate(
        scans[:4]
    ):  # untimed: first-call costs (imports, compiled kernels) out of both modes
        warm.process(scan, timestamp=0.1 * i)
    out: dict[str, Any] = {}
    closures: dict[str, list[Any]] = {}
    for mode, rt in (
        ("sequential", None),
        ("realtime", RealtimeParams(budget_ms=budget_ms, max_backlog=max_backlog)),
    ):
        det = LoopClosureDetector(
            make_pipeline(pipeline, cfg.loops.pipeline.params), cfg.loops.threshold, cfg.loops.exclusion.frames,
            k=cfg.loops.k, realtime=rt,
        )  # fmt: skip
        wait, ms, got = _slots(rate_hz), [], []
        cpu0 = time.process_time()
        with det:
            for i, scan in enumerate(scans):
                wait(i)
                t0 = time.perf_counter()
                got += det.process(scan, timestamp=0.1 * i)
                ms.append((time.perf_counter() - t0) * 1e3)
            t0 = time.perf_counter()
            got += det.flush()
            flush_ms = (time.perf_counter() - t0) * 1e3
        entry = _rt_summary(ms, budget_ms) | {"closures": len(got), "flush_ms": round(flush_ms, 1)}
        entry["cpu_ms_per_scan"] = round((time.process_time() - cpu0) * 1e3 / len(scans), 1)
        if det.realtime_stats is not None:
            st = det.realtime_stats.as_dict()
            entry |= {k: st[k] for k in ("deferred_closures", "max_delay", "waited", "max_backlog")}
            entry["worker_ms"] = [round(st["worker_ms"][k], 2) for k in ("median", "p95", "max")]
        out[mode], closures[mode] = entry, got
    out["identical"] = _same_closures(closures["sequential"], closures["realtime"])
    return out


def run_slam_modes(
    src: Source, pipeline: str, budget_ms: float, max_backlog: int, rate_hz: float
) -> dict[str, Any]:
    """`slam_sequence` on ``src`` (KISS-ICP odometry), sequential then with ``loops.realtime``; per scan the wall
    time of its whole loop (odometry + preprocess + online back end), scans paced at ``rate_hz``."""
    from placerec.recognizer import make_pipeline
    from placerec.slam.result import ONLINE_STAGES
    from placerec.slam_app.run import odometry_source, slam_sequence

    out: dict[str, Any] = {}
    loops: dict[str, list[Any]] = {}
    for mode in ("sequential", "realtime"):
        more = (
            [f"loops.realtime={{budget_ms: {budget_ms}, max_backlog: {max_backlog}}}"]
            if mode == "realtime"
            else []
        )
        cfg = slam_config(pipeline, src.exclusion, *more)
        seq = Replayed(src.base, src.index, src.name, pace=_slots(rate_hz))
        cpu0 = time.process_time()
        rec = make_pipeline(pipeline, cfg.loops.pipeline.params)
        result = slam_sequence(cfg, seq, rec, odometry_source(cfg, seq))
        t = result.timing_ms
        stages = [*ONLINE_STAGES, "odometry", *(["wait"] if "wait" in t else [])]
        per_scan = np.sum([t[s] for s in stages], axis=0)
        reads = [r[0] for r in seq.reads]
        total = [float(a + b) for a, b in zip(per_scan, reads, strict=True)]
        entry = _rt_summary(total, budget_ms) | {"loops": len(result.loops)}
        entry["cpu_ms_per_scan"] = round((time.process_time() - cpu0) * 1e3 / len(total), 1)
        if result.realtime is not None:
            r = result.realtime
            entry |= {k: r[k] for k in ("deferred_closures", "max_delay", "waited", "max_backlog")}
            entry["detector_over_budget"] = r["over_budget"]
        if src.ground_truth and result.ground_truth is not None:
            entry["ate_m"] = round(trajectory_errors(result.optimized, result.ground_truth).ate_rmse, 4)
        out[mode], loops[mode] = entry, result.loops
    out["identical"] = _same_closures(loops["sequential"], loops["realtime"])
    return out


def bench_realtime_mode(
    names: list[str], pipelines: list[str], n_scans: int, cache: Path, budget_ms: float, max_backlog: int,
    rate_hz: float, real_exclusion: int = 10, sim_exclusion: int = 100,
) -> dict[str, Any]:  # fmt: skip
    """``--realtime``: per sequence and pipeline the detector's and the slam loop's modes (module docstring)."""
    report: dict[str, Any] = {"bench": "realtime-mode", "budget_ms": budget_ms, "max_backlog": max_backlog,
                              "rate_hz": rate_hz, "cpus": os.cpu_count(), "load_before": os.getloadavg()}  # fmt: skip
    report["sequences"] = {}
    for src in sources(names, n_scans, real_exclusion, cache, sim_exclusion):
        entry: dict[str, Any] = {"scans": len(src.index), "exclusion": src.exclusion, "pipelines": {}}
        for p in pipelines:
            print(f"{src.name}: {p} detector, sequential and real-time ...", flush=True)
            det = run_detector_modes(src, p, budget_ms, max_backlog, rate_hz)
            print(f"{src.name}: {p} slam, sequential and real-time ...", flush=True)
            slam = run_slam_modes(src, p, budget_ms, max_backlog, rate_hz)
            entry["pipelines"][p] = {"detector": det, "slam": slam}
        report["sequences"][src.name] = entry
    report["load_after"] = os.getloadavg()
    return report


def print_realtime(report: dict[str, Any]) -> None:
    f = lambda xs: "/".join(f"{x:.0f}" for x in xs)  # noqa: E731
    rows = []
    for name, seq in report["sequences"].items():
        for p, v in seq["pipelines"].items():
            for path in ("detector", "slam"):
                r = v[path]
                for mode in ("sequential", "realtime"):
                    e = r[mode]
                    deferred = (
                        f"{e['deferred_closures']} (<= {e['max_delay']})" if "deferred_closures" in e else "-"
                    )
                    rows.append([
                        f"{name} {p}", path, mode, f(e["ms"]), f"{e['over_budget']} / {e['scans']}",
                        str(e.get("closures", e.get("loops"))), deferred, str(e.get("waited", "-")),
                        f"{e['cpu_ms_per_scan']:.0f}", "yes" if r["identical"] else "NO",
                    ])  # fmt: skip
    header = ["sequence pipeline", "path", "mode", "wall ms/scan med/p95/max",
              f"over {report['budget_ms']:g} ms", "closures", "deferred (scans late)", "waited", "CPU ms/scan",
              "same closures"]  # fmt: skip
    print_rows(header, rows, f"real-time mode at {report['rate_hz']:g} Hz", show_legend=False)


# --- output ---------------------------------------------------------------------------------------------------


def print_report(report: dict[str, Any]) -> None:
    f = "{:.1f}".format
    for name, seq in report["sequences"].items():
        rows = []
        for stage in STAGES:
            row = [stage]
            for v in seq["pipelines"].values():
                s = v["slam"]["stages"][stage.strip()]
                row += ["/".join(f(x) for x in s["wall"][:3]), "/".join(f(x) for x in s["cpu"][:3])]
            rows.append(row)
        header = ["stage"] + [f"{p}: {k} ms med/p95/max" for p in seq["pipelines"] for k in ("wall", "CPU")]
        title = f"placerec slam per scan, {name} ({seq['scans']} scans, median {seq['points']} points a scan)"
        print_rows(header, rows, title, show_legend=False)
    rows = []
    for name, seq in report["sequences"].items():
        kiss = seq.get("kiss_slam")
        for p, v in seq["pipelines"].items():
            st, det = v["slam"]["stages"], v["detector"]["stages"]
            ratio, ater = v.get("time_ratio"), v.get("ate_ratio")
            rows.append([
                f"{name} {p}", f(st["total"]["wall"][3]), f(st["total"]["cpu"][3]),
                "/".join(f(x) for x in det["loop closure"]["wall"][:3]),
                "/".join(f(x) for x in det["loop closure"]["cpu"][:3]),
                f"{v['lc_cpu_over_odometry']:.2f}x" if v["lc_cpu_over_odometry"] else "-",
                str(v["slam"]["loops"]), "-" if kiss is None else f"{kiss['runtime_ms']:.0f} ({f(kiss['wall_ms'])})",
                "-" if ratio is None else f"{ratio:.2f}x",
                "-" if "ate_m" not in v["slam"] else f"{v['slam']['ate_m']:.3f}",
                "-" if kiss is None or kiss["ate_m"] is None else f"{kiss['ate_m']:.3f}",
                "-" if ater is None else f"{ater:.2f}x",
                "/".join(f"{x:.2f}" for x in v["slam"].get("loop_error_cm", [])) or "-",
            ])  # fmt: skip
    header = [
        "sequence pipeline", "slam wall ms/scan (mean)", "slam CPU ms/scan (mean)", "detector alone: LC wall ms",
        "LC CPU ms med/p95/max", "LC CPU / odometry CPU", "loops", "KISS-SLAM ms/scan (process wall)",
        "time placerec / KISS-SLAM", "ATE [m]", "KISS-SLAM ATE [m]", "ATE ratio", "loop pose error cm med/max",
    ]  # fmt: skip
    print_rows(header, rows, "summary (LC = describe + query + insert)", show_legend=False)


def summary(report: dict[str, Any]) -> dict[str, Any]:
    """The JSON line: per sequence and pipeline, every stage's [median, p95, max, mean] wall and CPU ms."""
    out = {k: v for k, v in report.items() if k != "sequences"}
    out["sequences"] = {}
    for name, seq in report["sequences"].items():
        s = {k: v for k, v in seq.items() if k != "pipelines"}
        s["pipelines"] = {}
        for p, v in seq["pipelines"].items():
            s["pipelines"][p] = {
                "slam": {st: [x["wall"], x["cpu"]] for st, x in v["slam"]["stages"].items()},
                "detector": {st: [x["wall"], x["cpu"]] for st, x in v["detector"]["stages"].items()},
                **{
                    k: v[k]
                    for k in ("lc_cpu_over_odometry", "time_ratio", "ate_ratio", "warm_up_s")
                    if k in v
                },
                "ate_m": v["slam"].get("ate_m"),
                "loops": v["slam"]["loops"],
                **{k: v["slam"][k] for k in ("loop_error_cm", "loop_error_deg") if k in v["slam"]},
            }
        out["sequences"][name] = s
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequences", nargs="+", choices=[*SEQUENCES, REVISIT], default=list(SEQUENCES))
    ap.add_argument("--pipelines", nargs="+", choices=[*PIPELINES, *MORE_PIPELINES], default=list(PIPELINES))
    ap.add_argument("--scans", type=int, default=150, help="scans of each simulated sequence")
    ap.add_argument("--real-exclusion", type=int, default=10, help="exclusion window (frames) on kitti-raw")
    ap.add_argument("--cache", type=Path, default=ROOT / "results" / "bench_realtime")
    ap.add_argument("--kiss-slam-venv", type=Path, default=KISS_SLAM_VENV)
    ap.add_argument("--no-kiss-slam", action="store_true", help="placerec only")
    ap.add_argument(
        "--realtime", type=float, metavar="BUDGET_MS", help="the real-time mode's comparison instead"
    )
    ap.add_argument(
        "--max-backlog", type=int, default=3, help="real-time mode: scans the worker may be behind"
    )
    ap.add_argument("--rate-hz", type=float, default=10.0, help="real-time mode: scans fed at this rate")
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override the SLAM config of every run (repeatable), e.g. "
        "loops.pipeline.params.feature_params.backend=onnxruntime; recorded in the JSON line",
    )
    args = ap.parse_args()
    SETS[:] = args.set
    if args.realtime is not None:
        rt = bench_realtime_mode(
            args.sequences, args.pipelines, args.scans, args.cache, args.realtime, args.max_backlog, args.rate_hz,
            args.real_exclusion,
        )  # fmt: skip
        print_realtime(rt)
        print(json.dumps({**rt, "sets": SETS}))
        return
    venv = None
    if not args.no_kiss_slam:
        version = kiss_slam_version(args.kiss_slam_venv)
        if version is None:
            sys.exit(
                f"KISS-SLAM not found in {args.kiss_slam_venv}: tools/bench_slam_matrix.py --install-kiss-slam"
            )
        venv = args.kiss_slam_venv
    report = bench(args.sequences, args.pipelines, args.scans, args.cache, venv, args.real_exclusion)
    print_report(report)
    print(json.dumps({**summary(report), "sets": SETS}))


if __name__ == "__main__":
    main()
