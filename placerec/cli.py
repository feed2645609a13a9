"""The ``placerec`` command line. Heavy modules (open3d, torch, the pipelines) are imported inside commands so
``placerec --help`` stays instant."""

from __future__ import annotations

import json
import logging
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from placerec import cli_support as support
from placerec._version import __version__

if TYPE_CHECKING:
    from placerec.viewer import ViewerTarget

app = typer.Typer(
    name="placerec",
    help="LiDAR place recognition and loop-closure detection with intensity.\n\n"
    "Examples:\n\n"
    "  placerec info ../shared/data/real/kitti00_frames/000094.bin\n\n"
    "  placerec dump-config --out my.yaml",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _version_callback(value: bool) -> None:
    if not value:
        return
    from placerec.errors import DependencyError

    typer.echo(f"placerec {__version__}")
    try:
        for label, ver in support.native_versions().items():
            typer.echo(f"  {label} {ver}")
    except DependencyError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(1) from None
    raise typer.Exit(0)


@app.callback()
def _main(
    version: Annotated[
        bool | None,
        typer.Option("--version", callback=_version_callback, is_eager=True, help="Print versions and exit."),
    ] = None,
    verbose: Annotated[
        int, typer.Option("--verbose", "-v", count=True, help="More log output (-v, -vv).")
    ] = 0,
) -> None:
    level = logging.WARNING if verbose == 0 else logging.INFO if verbose == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")


def _command(name: str | None = None) -> Callable[[Callable[..., None]], Callable[..., None]]:
    """``app.command(name)`` for a command whose placerec errors end as one line on stderr, status 2."""
    return lambda command: app.command(name)(support.reports_errors(command))


@_command("dump-config")
def dump_config(
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Write here instead of stdout.")] = None,
) -> None:
    """Print (or write) the default experiment configuration as YAML."""
    from placerec.config import dump_default_config

    text = dump_default_config(out)
    if out is None:
        typer.echo(text, nl=False)
    else:
        typer.echo(f"wrote {out}")


@_command()
def pipelines(
    name: Annotated[str | None, typer.Argument(help="A registered pipeline: list its parameters.")] = None,
) -> None:
    """List the registered pipelines, or every parameter of one (dotted path, default, type, source).

    Examples: placerec pipelines;  placerec pipelines orb-dbow
    """
    if name is None:
        support.print_pipelines()
    else:
        support.print_pipeline_params(name)


@_command()
def info(
    path: Annotated[
        Path,
        typer.Argument(
            help="A scan file (.bin .pcd .ply .npy .npz), a sequence folder/bag, or a map folder."
        ),
    ],
    format: Annotated[
        str | None, typer.Option(help="Force a reader (.bin files are recognised as 'kitti' or 'nclt').")
    ] = None,
    dataset: Annotated[
        str | None,
        typer.Option(
            help="Dataset layout (kitti, mulran, newer-college, helipr, nclt, mcap); default: detected."
        ),
    ] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON instead of a table.")] = False,
    check: Annotated[
        bool, typer.Option("--check", help="A map folder: hash every file against its manifest.")
    ] = False,
) -> None:
    """Summarise a scan, a sequence (points, fields, intensity and range percentiles, beams, poses), an artifact
    or a map folder (keyframes, extent, pipelines, size, the trajectory figure)."""
    summary = support.summarise(path, format, dataset, check)
    if as_json:
        typer.echo(json.dumps(summary, indent=2, default=str))
    else:
        support.print_summary(summary)


cache_app = typer.Typer(
    help="The description cache (output.cache_dir): its size and entries, and clearing it. Its size limit:"
    " PLACEREC_CACHE_MAX_MB (default 2000; 0 or off: none), kept by evicting least recently used entries.",
    no_args_is_help=True,
)
app.add_typer(cache_app, name="cache")
CacheDir = Annotated[
    Path | None, typer.Option("--dir", help="The cache folder (default: the config's output.cache_dir).")
]
CacheConfig = Annotated[
    Path | None, typer.Option("--config", "-c", help="Experiment YAML whose output.cache_dir to use.")
]


def _cache_folder(folder: Path | None, config: Path | None) -> Path:
    from placerec.config import load_config
    from placerec.errors import ConfigError

    if folder is not None:
        return folder
    cache_dir = load_config(config).output.cache_dir
    if cache_dir is None:
        raise ConfigError(f"{config or 'the default config'}: output.cache_dir is null (the cache is off)")
    return Path(cache_dir)


@cache_app.command("info")
@support.reports_errors
def cache_info(
    folder: CacheDir = None,
    config: CacheConfig = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON instead of a table.")] = False,
) -> None:
    """The cache folder, its size and limit, entries per front end, oldest and newest use."""
    from placerec.experiment.cache import cache_info as info_of

    summary = info_of(_cache_folder(folder, config))
    if as_json:
        typer.echo(json.dumps(summary, indent=2))
    else:
        support.print_summary(summary)


@cache_app.command("clear")
@support.reports_errors
def cache_clear(
    folder: CacheDir = None,
    config: CacheConfig = None,
    older_than: Annotated[
        float | None, typer.Option("--older-than", help="Only entries not used for this many days.")
    ] = None,
    frontend: Annotated[
        str | None, typer.Option("--frontend", help="Only this front end: a key or a name (scan-context).")
    ] = None,
) -> None:
    """Remove the cache's entries: all, or those --older-than DAYS, or of one --frontend (both: both apply)."""
    from placerec.experiment.cache import clear_cache

    root = _cache_folder(folder, config)
    count, size = clear_cache(root, older_than, frontend)
    typer.echo(f"removed {count} entries ({size / 1e6:.1f} MB) from {root}")


#: The options `run` and `slam` share.
ResultsRoot = Annotated[Path | None, typer.Option("--out", "-o", help="Results root (default: output.dir).")]
Overrides = Annotated[
    list[str] | None,
    typer.Option(
        "--set",
        "-s",
        help="Override a config value: key.path=value (repeatable); a pipeline by index or label:"
        " pipelines.0.params.feature_params.nfeatures=500.",
    ),
]

#: ``--viewer`` and ``--rrd`` of the commands that can log to Rerun (`placerec.viewer`, docs/viewer.md)
Viewer = Annotated[
    bool,
    typer.Option("--viewer", help="Show the run live in a Rerun viewer it starts (extra: placerec[viewer])."),
]
Rrd = Annotated[
    Path | None,
    typer.Option(
        "--rrd", help="Save a Rerun recording of the run to this .rrd file (open it with `rerun FILE`)."
    ),
]


def _viewer(viewer: bool, rrd: Path | None) -> ViewerTarget:
    """The Rerun target of ``--viewer`` / ``--rrd``, checked before anything runs (`check_target`)."""
    from placerec.viewer import ViewerTarget, check_target

    target = ViewerTarget(spawn=viewer, rrd=rrd)
    check_target(target)
    return target


#: ``--wide`` of the commands that print a results table
Wide = Annotated[
    bool,
    typer.Option(
        "--wide",
        help="Print every column (default: the headline ones, to fit the terminal; all are in the files).",
    ),
]


@_command()
def run(
    config: Annotated[
        Path, typer.Argument(help="Experiment YAML (see configs/ and `placerec dump-config`).")
    ],
    out: ResultsRoot = None,
    set_: Overrides = None,
    workers: Annotated[
        int | None,
        typer.Option(
            help="Describe scans in N processes (execution.workers; executor: dask uses a cluster)."
        ),
    ] = None,
    wide: Wide = False,
    viewer: Viewer = False,
    rrd: Rrd = None,
) -> None:
    """Run an experiment: every pipeline of CONFIG on its dataset; metrics, figures and a report.

    Examples:

      placerec run configs/demo.yaml --set dataset.simulator.n_scans=200 --workers 2

      placerec run configs/demo.yaml --rrd demo.rrd   (then: rerun demo.rrd)
    """
    from placerec.config import load_config
    from placerec.experiment import run_experiment
    from placerec.experiment.tables import print_table
    from placerec.viewer import recording

    target = _viewer(viewer, rrd)
    overrides = (set_ or []) + ([] if workers is None else [f"execution.workers={workers}"])
    cfg = load_config(config, overrides)
    with recording(target, f"run {cfg.name}"):
        run_dir, payload = run_experiment(cfg, out)
    print_table(payload, f"{cfg.name} ({payload['mode']} mode)", wide=wide)
    typer.echo(f"results: {run_dir}  (report: {run_dir / 'index.html'})")


@_command()
def bench(
    config: Annotated[
        Path, typer.Argument(help="Benchmark YAML (configs/benchmark.yaml: the held-out test split).")
    ],
    out: Annotated[
        Path | None, typer.Option("--out", "-o", help="Benchmark folder (default: output.dir/<name>).")
    ] = None,
    set_: Overrides = None,
    workers: Annotated[
        int | None,
        typer.Option(help="Run N cells at once (execution.workers; executor: dask uses a cluster)."),
    ] = None,
    fresh: Annotated[bool, typer.Option(help="Run every cell again, even those already done.")] = False,
    suggest: Annotated[
        bool,
        typer.Option(help="Also print the operating thresholds the tuning rule picks (tuning split only)."),
    ] = False,
    wide: Wide = False,
) -> None:
    """Every pipeline of CONFIG over a matrix of simulated worlds x sensors x seeds, at fixed thresholds.

    Cells already done with the same config are read back (an interrupted benchmark resumes); the last line is
    one JSON object. Example: placerec bench configs/benchmark.yaml --workers 2
    """
    from placerec.errors import ConfigError
    from placerec.experiment.benchmark import load_benchmark_config, run_benchmark, suggestions
    from placerec.experiment.benchmark_summary import bench_line, rows
    from placerec.experiment.tables import print_rows

    overrides = (set_ or []) + ([] if workers is None else [f"execution.workers={workers}"])
    cfg = load_benchmark_config(config, overrides)
    if suggest and cfg.split != "tuning":
        raise ConfigError("--suggest picks thresholds on the tuning split only (split: tuning)")
    folder, payload = run_benchmark(cfg, out, fresh=fresh)
    print_rows(
        *rows(payload, wide),
        f"{cfg.name} ({cfg.split} split, {len(payload['cells'])} cells"
        f"{', judged with the odometry gate' if payload['odometry_gate'] else ''}): matrix mean / worst",
    )
    if suggest:
        import json

        cells = {c: json.loads((folder / "cells" / c / "cell.json").read_text()) for c in payload["cells"]}
        overall, per_sensor = suggestions(cfg, folder, cells)
        typer.echo(f"operating thresholds the tuning rule picks: {overall}")
        if len({c.sensor for c in cfg.cells()}) > 1:
            typer.echo(f"the same rule on each sensor's cells alone: {per_sensor}")
    typer.echo(f"benchmark: {folder}  (report: {folder / 'index.html'})")
    typer.echo(bench_line(payload))


@_command()
def detect(
    source: Annotated[
        Path,
        typer.Argument(help="A sequence: a scan folder, a dataset layout, a bag/mcap, an Ouster .pcap."),
    ],
    pipeline: Annotated[
        str | None,
        typer.Option(help="Registered pipeline (default: the held-out benchmark's best with a threshold)."),
    ] = None,
    threshold: Annotated[
        float | None, typer.Option(help="Accept closures scoring at least this (default: the preset's).")
    ] = None,
    format: Annotated[str | None, typer.Option(help="Force a scan reader, e.g. 'kitti', 'nclt'.")] = None,
    dataset: Annotated[
        str | None, typer.Option(help="Dataset layout (kitti, mulran, ...); default: detected.")
    ] = None,
    poses: Annotated[
        Path | None, typer.Option(help="Poses file: drawn, and the closures scored against it.")
    ] = None,
    odometry: Annotated[
        str | None, typer.Option(help="'kiss-icp': poses from the scans, to draw the closures on.")
    ] = None,
    exclusion_frames: Annotated[
        int | None,
        typer.Option(
            help="Match scans at least this many frames older (default 120, or half the scans if fewer)."
        ),
    ] = None,
    exclusion_seconds: Annotated[
        float | None, typer.Option(help="... and this many seconds older (needs scan times).")
    ] = None,
    exclusion_metres: Annotated[
        float | None, typer.Option(help="... and this many metres travelled before (needs poses).")
    ] = None,
    keyframes_seconds: Annotated[
        float | None, typer.Option(help="Match keyframes of the scans of each S seconds (docs/keyframes.md).")
    ] = None,
    keyframes_metres: Annotated[
        float | None,
        typer.Option(help="Match keyframes of the scans of each M metres travelled (needs poses)."),
    ] = None,
    out: Annotated[
        Path | None,
        typer.Option("--out", "-o", help="Results folder (default: results/detect_<name>_<timestamp>)."),
    ] = None,
) -> None:
    """Loop closures in your own sequence, no config or ground truth needed: closures.csv/.json, a figure.

    Examples:

      placerec detect ../shared/data/real/ouster_os1_64_revisit_pair

      placerec detect sim/town_hdl64 --pipeline orb-hbst --exclusion-frames 50
    """
    from placerec.detect import DEFAULT_PIPELINE, options_config, summary_lines
    from placerec.detect import detect as run_detect

    values = {
        "source": str(source),
        "format": format,
        "dataset": dataset,
        "poses": None if poses is None else str(poses),
        "pipeline": pipeline or DEFAULT_PIPELINE,
        "threshold": threshold,
        "exclusion_seconds": exclusion_seconds,
        "exclusion_metres": exclusion_metres,
        "odometry": odometry or "none",
    }
    if exclusion_frames is not None:
        values["exclusion_frames"] = exclusion_frames
    cfg = options_config(
        values
        if keyframes_seconds is None and keyframes_metres is None
        else {**values, "keyframes": {"seconds": keyframes_seconds, "metres": keyframes_metres}}
    )
    with support.progress_bar(f"detecting ({cfg.pipeline})") as progress:
        run_dir, summary = run_detect(cfg, out, progress)
    for line in summary_lines(run_dir, summary):
        typer.echo(line)


@_command()
def slam(
    config: Annotated[
        Path | None, typer.Argument(help="SLAM YAML (see configs/slam_*.yaml); none: the defaults.")
    ] = None,
    out: ResultsRoot = None,
    set_: Overrides = None,
    dump: Annotated[bool, typer.Option("--dump-config", help="Print the resolved config and exit.")] = False,
    save_map: Annotated[
        Path | None,
        typer.Option(
            "--save-map", help="Also save a map folder here (output.save_map) for `placerec localize`."
        ),
    ] = None,
    prior_map: Annotated[
        Path | None,
        typer.Option("--prior-map", help="Run as a second session against this map (prior_map.path)."),
    ] = None,
    viewer: Viewer = False,
    rrd: Rrd = None,
) -> None:
    """SLAM back end: odometry + verified loop closures + a GTSAM pose graph; poses, g2o, ATE/RPE, a report.

    Examples:

      placerec slam configs/slam_demo.yaml

      placerec slam configs/slam_kitti.yaml --set dataset.path=/data/kitti/sequences/00

      placerec slam configs/slam_demo.yaml --set robustness.false_loops=10

      placerec slam configs/slam_demo.yaml --save-map maps/town

      placerec slam configs/slam_demo.yaml --prior-map maps/town --save-map maps/both

      placerec slam configs/slam_demo.yaml --rrd slam.rrd
    """
    from placerec.slam_app.config import load_slam_config
    from placerec.viewer import recording

    target = _viewer(viewer, rrd)
    overrides = list(set_ or [])
    if save_map is not None:
        overrides.append(f"output.save_map={save_map}")
    if prior_map is not None:
        overrides.append(f"prior_map.path={prior_map}")
    cfg = load_slam_config(config, overrides)
    if dump:
        from placerec.config import config_to_yaml

        typer.echo(config_to_yaml(cfg), nl=False)
        return
    from placerec.slam_app.report import print_slam_table
    from placerec.slam_app.run import run_slam

    with recording(target, f"slam {cfg.name}"):
        run_dir, payload = run_slam(cfg, out)
    print_slam_table(payload, f"{cfg.name} (slam, {payload['n_scans']} scans)")
    typer.echo(f"results: {run_dir}  (report: {run_dir / 'index.html'})")
    if "prior_map" in payload:
        typer.echo(f"prior map {cfg.prior_map.path}: {payload['prior_map']['summary']}")
    if cfg.output.save_map is not None and Path(cfg.output.save_map).is_dir():
        typer.echo(f"map: {cfg.output.save_map}  (placerec info {cfg.output.save_map})")


@_command()
def simulate(
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder (KITTI odometry layout).")],
    preset: Annotated[str, typer.Option(help="World preset: town, campus, industrial.")] = "town",
    sensor: Annotated[
        str, typer.Option(help="Sensor: vlp16, hdl64, os1-64, os1-64-gen2, os1-128.")
    ] = "os1-64",
    scans: Annotated[int | None, typer.Option(help="Number of scans (default: the whole route).")] = None,
    seed: Annotated[int, typer.Option(help="World and noise seed.")] = 0,
) -> None:
    """Simulate a sequence with revisits: velodyne/*.bin, ring/*.npy, poses.txt, times.txt, sensor.yaml.

    Example: placerec simulate --preset town --sensor hdl64 --scans 300 --seed 1 --out sim/town_hdl64
    """
    from placerec.sim import simulate as run_simulation

    path = run_simulation(preset, sensor, scans, seed, out, progress=True)
    typer.echo(f"wrote {path}")


@_command("train-vocab")
def train_vocab(
    config: Annotated[
        Path | None, typer.Option("--config", "-c", help="Training YAML (see configs/vocab_*.yaml).")
    ] = None,
    out: Annotated[
        Path | None, typer.Option("--out", "-o", help="Vocabulary file (default: output).")
    ] = None,
    n_images: Annotated[int | None, typer.Option(help="Override n_images.")] = None,
    workers: Annotated[int | None, typer.Option(help="Processes extracting features.")] = None,
) -> None:
    """Train a DBoW vocabulary (hierarchical k-means++, TF-IDF) on intensity images; writes it and a .json.

    Example: placerec train-vocab --config configs/vocab_orb.yaml
    """
    from placerec.artifacts.vocabulary import build_vocabulary, load_training_config

    cfg = load_training_config(config, n_images=n_images, workers=workers)
    path = build_vocabulary(cfg, out, progress=True)
    typer.echo(f"wrote {path} and {path.with_suffix('.json')}")


@_command()
def calibrate(
    out: Annotated[Path, typer.Option("--out", "-o", help="Calibration table to write (.npz).")],
    sequence: Annotated[
        Path | None, typer.Argument(help="A sequence with poses and rings (anything `placerec info` reads).")
    ] = None,
    format: Annotated[str | None, typer.Option(help="Force a reader, e.g. 'nclt'.")] = None,
    poses: Annotated[Path | None, typer.Option(help="Poses file (default: the sequence's own).")] = None,
    sim_world: Annotated[
        str | None,
        typer.Option("--sim-world", help="Calibrate on the simulator instead: town, campus, industrial."),
    ] = None,
    sim_sensor: Annotated[str, typer.Option("--sim-sensor", help="Simulated sensor.")] = "vlp16",
    sim_scans: Annotated[
        int | None, typer.Option("--sim-scans", help="Simulated scans (default: the route).")
    ] = None,
    seed: Annotated[int, typer.Option(help="Simulator seed.")] = 0,
    voxel_size: Annotated[float, typer.Option(help="Map cell size (m).")] = 0.25,
    max_range: Annotated[float, typer.Option(help="Intensity range cut-off (m).")] = 30.0,
    iterations: Annotated[int, typer.Option(help="Maximum EM iterations.")] = 100,
    step: Annotated[int, typer.Option(help="Use every step-th scan.")] = 1,
    set_: Annotated[
        list[str] | None,
        typer.Option("--set", "-s", help="Another CalibrationParams field: key=value (repeatable)."),
    ] = None,
) -> None:
    """Per-beam intensity calibration (Levinson & Thrun) from registered scans; writes the lookup table.

    Use it in preprocessing with `preprocess.intensity.calibration: <table>` in an experiment config.

    Examples:

      placerec calibrate sim/town_vlp16 --out vlp16_calibration.npz

      placerec calibrate --sim-world town --sim-sensor vlp16 --sim-scans 300 --seed 1 --out calib.npz
    """
    import time

    from placerec.artifacts.calibration import CalibrationBuild, build_calibration
    from placerec.calibration import CalibrationParams, CalibrationTable

    source = support.sequence_source(
        sequence, format, poses, support.sim_world(sim_world, sim_sensor, sim_scans, seed)
    )
    values = {"voxel_size": voxel_size, "max_range": max_range, "iterations": iterations, "step": step}
    params = support.with_overrides(CalibrationParams, values, set_, "calibration parameters")
    t0 = time.perf_counter()
    with support.progress_bar("reading scans") as progress:
        path = build_calibration(CalibrationBuild(source=source, out=out, params=params), progress)
    table = CalibrationTable.load(path)
    m = table.meta
    typer.echo(
        f"{table.sensor}: {table.n_beams} beams, {m['n_cells']} cells, {m['n_observations']} observations, "
        f"{m['em_iterations']} EM iterations, saturation {m['saturation']:g} ({time.perf_counter() - t0:.1f} s)"
    )
    typer.echo(f"wrote {out}")


@_command("build-places")
def build_places_cmd(
    out: Annotated[Path, typer.Option("--out", "-o", help="Places database to write (.npz).")],
    sequence: Annotated[
        Path | None, typer.Argument(help="A map sequence with poses (anything `placerec info` reads).")
    ] = None,
    format: Annotated[str | None, typer.Option(help="Force a reader, e.g. 'kitti'.")] = None,
    poses: Annotated[Path | None, typer.Option(help="Poses file (default: the sequence's own).")] = None,
    sim_world: Annotated[
        str | None,
        typer.Option("--sim-world", help="Use the simulator's localisation map: town, campus, ..."),
    ] = None,
    sim_sensor: Annotated[str, typer.Option("--sim-sensor", help="Simulated sensor.")] = "vlp16",
    sim_scans: Annotated[int | None, typer.Option("--sim-scans", help="Simulated map scans.")] = None,
    seed: Annotated[int, typer.Option(help="Simulator seed.")] = 0,
    set_: Annotated[
        list[str] | None,
        typer.Option("--set", "-s", help="A PlacesParams field: key=value, e.g. window_m=0 (repeatable)."),
    ] = None,
) -> None:
    """Cut a map sequence with poses into places and describe them (ISHOT paper Sec. IV-B).

    Examples:

      placerec build-places --sim-world town --set window_m=0 --out places_town.npz

      placerec build-places sim/town_vlp16 --set spacing_m=5 --set features.descriptor=shot --out places.npz
    """
    from placerec.artifacts.places import PlacesBuild, build_places_db
    from placerec.three_d.places import PlacesDatabase, PlacesParams

    params = support.with_overrides(PlacesParams, {}, set_, "places parameters")
    source = support.sequence_source(
        sequence, format, poses, support.sim_world(sim_world, sim_sensor, sim_scans, seed)
    )
    with support.progress_bar("describing places") as progress:
        path = build_places_db(PlacesBuild(source=source, out=out, params=params), progress)
    db = PlacesDatabase.load(path, mmap=True)  # counted from the file, however large
    n_kp = int(db.kp_offsets[-1])
    typer.echo(f"{db.sequence}: {len(db)} places, {n_kp} keypoints ({n_kp / max(len(db), 1):.0f} per place)")
    typer.echo(f"wrote {out}")


@_command("fit-votes")
def fit_votes_cmd(
    places: Annotated[Path, typer.Option("--places", help="Places database (placerec build-places).")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Vote model to write (.npz).")],
    training: Annotated[
        list[Path] | None,
        typer.Argument(help="Training sequences with ground-truth poses in the map's frame."),
    ] = None,
    format: Annotated[str | None, typer.Option(help="Force a reader for the training sequences.")] = None,
    sim_world: Annotated[
        str | None,
        typer.Option("--sim-world", help="Train on the simulator: another draw of its localisation queries."),
    ] = None,
    sim_sensor: Annotated[str, typer.Option("--sim-sensor", help="Simulated sensor.")] = "vlp16",
    sim_scans: Annotated[int | None, typer.Option("--sim-scans", help="Simulated map scans.")] = None,
    seed: Annotated[int, typer.Option(help="Simulator seed (the map's).")] = 0,
    n_training: Annotated[int, typer.Option(help="Simulated training scans per condition.")] = 30,
    figure: Annotated[
        Path | None, typer.Option(help="Also draw fitted vs empirical CDFs here (.png).")
    ] = None,
    set_: Annotated[
        list[str] | None,
        typer.Option("--set", "-s", help="A VoteModelParams field: key=value, e.g. min_votes=50."),
    ] = None,
) -> None:
    """Fit the probabilistic-voting model (ISHOT paper Sec. IV-D, eq. 7) from training scans with ground truth.

    Examples:

      placerec fit-votes --places places_town.npz --sim-world town --out votes_town.npz --figure votes.png

      placerec fit-votes --places places.npz train_seq_1 train_seq_2 --out votes.npz
    """
    from placerec.artifacts.votes import VoteModelBuild, build_vote_model
    from placerec.three_d.vote_model import VoteModel, VoteModelParams

    params = support.with_overrides(VoteModelParams, {}, set_, "vote model parameters")
    sim = support.sim_world(sim_world, sim_sensor, sim_scans, seed)
    config = VoteModelBuild(places=places, out=out, training=training or [], format=format, sim=sim,
                            n_training=n_training, figure=figure, params=params)  # fmt: skip
    with support.progress_bar("describing training scans") as progress:
        path = build_vote_model(config, progress)
    model = VoteModel.load(path)
    for row in model.summary():
        typer.echo(
            f"tau {row['tau']}: sigma {row['sigma_m']} m, lambda {row['lambda']}, {row['n_votes']} votes"
        )
    typer.echo(f"wrote {out}" + (f" and {figure}" if figure else ""))


map_app = typer.Typer(
    help="Maps that outlive a session: build one from a sequence with poses (or save one from `placerec slam"
    " --save-map`), then localise against it (`placerec localize`) or extend it (`placerec slam --prior-map`)."
    " `placerec info MAP` summarises one.",
    no_args_is_help=True,
)
app.add_typer(map_app, name="map")


@map_app.command("build")
@support.reports_errors
def map_build(
    out: Annotated[Path, typer.Option("--out", "-o", help="Map folder to write.")],
    sequence: Annotated[
        Path | None, typer.Argument(help="A sequence with poses (anything `placerec info` reads).")
    ] = None,
    format: Annotated[str | None, typer.Option(help="Force a reader, e.g. 'kitti'.")] = None,
    poses: Annotated[Path | None, typer.Option(help="Poses file (default: the sequence's own).")] = None,
    sim_world: Annotated[
        str | None, typer.Option("--sim-world", help="Map a simulated world's route: town, campus, ...")
    ] = None,
    sim_sensor: Annotated[str, typer.Option("--sim-sensor", help="Simulated sensor.")] = "vlp16",
    sim_scans: Annotated[int | None, typer.Option("--sim-scans", help="Simulated route scans.")] = None,
    seed: Annotated[int, typer.Option(help="Simulator seed.")] = 0,
    pipeline: Annotated[
        list[str] | None,
        typer.Option(
            "--pipeline",
            "-p",
            help="A pipeline whose database the map holds (repeatable; default: orb-hbst, scan-context).",
        ),
    ] = None,
    config: Annotated[
        Path | None,
        typer.Option("--config", "-c", help="A map build YAML (MapBuild: pipelines with params)."),
    ] = None,
    set_: Annotated[
        list[str] | None,
        typer.Option("--set", "-s", help="A MapBuild field: key=value, e.g. keyframe_metres=2 (repeatable)."),
    ] = None,
    overwrite: Annotated[bool, typer.Option(help="Replace an existing map at --out.")] = False,
) -> None:
    """Build a map folder: keyframes along the poses, each pipeline's database, clouds for tracking.

    Examples:

      placerec map build --sim-world town --pipeline orb-hbst --pipeline scan-context --out maps/town

      placerec map build ../shared/data/real/kitti_raw_0027 --out maps/kitti27
    """
    from placerec.artifacts.map import MapBuild, build_map
    from placerec.config import read_config_file
    from placerec.maps import MapArtifact

    values = {} if config is None else read_config_file(config)
    values = dict(values, out=str(out), overwrite=overwrite or bool(values.get("overwrite", False)))
    if pipeline:
        values["pipelines"] = [{"name": name} for name in pipeline]
    source = (
        support.sequence_source(
            sequence, format, poses, support.sim_world(sim_world, sim_sensor, sim_scans, seed)
        )
        if sequence is not None or sim_world is not None
        else None
    )
    if source is not None:
        values["source"] = source.model_dump(exclude_none=True, mode="json")
    cfg = support.with_overrides(MapBuild, values, set_, "map build")
    with support.progress_bar("describing keyframes") as progress:
        path = build_map(cfg, progress)
    summary = MapArtifact.open(path).summary()
    names = ", ".join(summary["pipelines"])
    typer.echo(
        f"{summary['name']}: {summary['keyframes']} keyframes, {summary['path_length_m']} m, {names}; "
        f"{summary['bytes'] / 1e6:.1f} MB"
    )
    typer.echo(f"wrote {path}")


@_command()
def localize(
    map_dir: Annotated[Path, typer.Argument(metavar="MAP", help="A map folder (`placerec map build`).")],
    sequence: Annotated[
        Path,
        typer.Argument(
            metavar="SEQUENCE", help="The scans to localise (anything `placerec info` reads, a bag too)."
        ),
    ],
    out: Annotated[
        Path | None,
        typer.Option("--out", "-o", help="Results folder (default: results/localize_<name>_<timestamp>)."),
    ] = None,
    mode: Annotated[
        str,
        typer.Option(help="tracking: from the last fix, global search on failure; global: each scan alone."),
    ] = "tracking",
    odometry: Annotated[
        str,
        typer.Option(
            help="Tracking's motion between scans: none (constant velocity) or kiss-icp (with keyframes also what"
            " they are accumulated along)."
        ),
    ] = "none",
    pipeline: Annotated[
        str | None, typer.Option(help="The map pipeline for global search (default: the map's first).")
    ] = None,
    format: Annotated[str | None, typer.Option(help="Force a scan reader, e.g. 'kitti'.")] = None,
    poses: Annotated[
        Path | None, typer.Option(help="Ground-truth poses file: the fixes are scored against it.")
    ] = None,
    allow_other_sensor: Annotated[
        bool, typer.Option("--allow-other-sensor", help="Localise scans of another sensor than the map's.")
    ] = False,
    set_: Annotated[
        list[str] | None,
        typer.Option("--set", "-s", help="A LocalizerParams field: key=value, e.g. tracking.radius_m=20."),
    ] = None,
    keyframes_seconds: Annotated[
        float | None,
        typer.Option(
            help="Localise keyframes of the scans of each S seconds (a Livox-style scanner; docs/keyframes.md)."
        ),
    ] = None,
    keyframes_metres: Annotated[
        float | None, typer.Option(help="Localise keyframes of the scans of each M metres travelled.")
    ] = None,
    keyframes_every_metres: Annotated[
        float | None, typer.Option(help="With keyframes: one ending every E metres (overlapping windows).")
    ] = None,
    viewer: Viewer = False,
    rrd: Rrd = None,
) -> None:
    """Relocalise a sequence's scans in a map (query only: the map is never changed): poses, fixes.csv, a figure.

    Examples:

      placerec localize maps/town sim/town_vlp16_day2 --out results/loc

      placerec localize maps/town drive.mcap --mode global --pipeline scan-context

      placerec localize maps/town sim/town_vlp16_day2 --viewer

      placerec localize maps/hdl64 avia_drive.mcap --allow-other-sensor --keyframes-seconds 0.5 --odometry kiss-icp
    """
    from placerec.artifacts.sources import open_path
    from placerec.keyframes import KeyframeParams
    from placerec.maps import MapArtifact
    from placerec.maps.localizer import LocalizerParams
    from placerec.slam_app.localize import default_out, localize_sequence, report_localize
    from placerec.viewer import recording

    target = _viewer(viewer, rrd)
    the_map = MapArtifact.open(map_dir)
    seq = open_path(sequence, format, poses)
    values = {"pipeline": pipeline, "allow_other_sensor": allow_other_sensor}
    params = support.with_overrides(LocalizerParams, values, set_, "localizer parameters")
    keyframes = None
    if (keyframes_seconds, keyframes_metres, keyframes_every_metres) != (None, None, None):
        window = {
            "seconds": keyframes_seconds,
            "metres": keyframes_metres,
            "every_metres": keyframes_every_metres,
        }
        keyframes = support.with_overrides(KeyframeParams, window, None, "--keyframes-*")
    with recording(target, f"localize {seq.name}"), support.progress_bar(f"localizing ({mode})") as progress:
        run = localize_sequence(the_map, seq, params, mode, odometry, progress, keyframes)  # type: ignore[arg-type]
    folder = out or default_out(seq.name)
    m = report_localize(run, folder)
    line = f"{m['sequence']}: {m['accepted']} of {m['scans']} scans fixed"
    if "correct" in m:
        line += f", {m['correct']} within 1 m / 5 deg, {m['false_fixes']} false fixes"
    tm = m["time_ms"]
    for key in ("tracking", "global"):
        if tm[key]["n"]:
            line += f"; {key} {tm[key]['median']:.0f} ms median"
    typer.echo(line)
    typer.echo(f"results: {folder}")


def main() -> None:
    """The console script: a placerec error that a command let through still ends as one line, status 2."""
    from placerec.errors import PlacerecError

    try:
        app()
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        sys.exit(130)
    except PlacerecError as exc:
        print(support.error_line(exc), file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    main()
