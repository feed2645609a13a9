"""The map artifact (``placerec map build``): a sequence with poses turned into a map folder
(`placerec.maps.artifact`): keyframes every ``keyframe_metres`` along the poses, each preprocessed, described
and added to every chosen pipeline's database under its keyframe id, its voxelised cloud stored for tracking.
With ``keyframes`` (a Livox-style or solid-state scanner's frames) the map's places are accumulated keyframes of
the sequence (`placerec.keyframes.KeyframeSequence`, along the map's poses), each at its window's last scan; such
a map is queried with keyframes too (``placerec localize --keyframes-seconds``).

`build_map` reads the source and writes the map; `write_map` does the same for a sequence already open (the
Python API and the session evaluation use it).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

import numpy as np
from pydantic import Field

from placerec.artifacts.sources import FilePath, SequenceSource
from placerec.config import PipelineSpec
from placerec.errors import ConfigError, ScanDataError
from placerec.keyframes import KeyframeParams, KeyframeSequence
from placerec.maps.artifact import MapWriter, check_pose_fit, pose_fit, pose_fit_probes
from placerec.params import Params
from placerec.preprocess import PreprocessParams, preprocess_scan
from placerec.recognizer import make_pipeline
from placerec.types import PlaceRecognizer, Sequence, valid_points
from placerec.verify.voxel_grid import voxel_points

log = logging.getLogger(__name__)

__all__ = ["MapBuild", "build_map", "write_map", "select_keyframes", "intensity_label"]


class MapBuild(Params):
    """What ``placerec map build`` builds: the map of ``source`` (a sequence with poses, its own or a poses file,
    or a simulated world's route) with ``pipelines``' databases, keyframes ``keyframe_metres`` apart."""

    source: SequenceSource
    out: FilePath
    pipelines: list[PipelineSpec] = Field(
        default_factory=lambda: [PipelineSpec(name="orb-hbst"), PipelineSpec(name="scan-context")],
        description="pipelines whose databases the map holds; global search asks them in this order (chosen on the"
        " tuning split: tools/tune_map_pipelines.py, docs/maps.md)",
    )
    preprocess: PreprocessParams = Field(default_factory=PreprocessParams)
    keyframe_metres: float = Field(
        0.5, ge=0, description="m travelled between keyframes (0: every scan is a keyframe)"
    )
    cloud_voxel_m: float = Field(0.4, gt=0, description="m; voxel grid of the stored clouds (ICP target's)")
    keyframes: KeyframeParams | None = Field(
        None,
        description="places accumulated from consecutive scans along the map's poses (placerec.keyframes,"
        " docs/keyframes.md), e.g. {seconds: 0.5} for a Livox-style scanner; None: single scans",
    )
    overwrite: bool = Field(False, description="replace an existing map at out")


def intensity_label(preprocess: PreprocessParams) -> str:
    """How a map's scans were made comparable in intensity (what a query must use too): the calibration table, or
    the normalisation mode."""
    spec = preprocess.intensity
    if spec.calibration:
        return f"calibrated:{Path(spec.calibration).name}"
    return f"normalised:{spec.mode}"


def select_keyframes(poses: np.ndarray, metres: float) -> np.ndarray:
    """Indices of the scans that become keyframes: the first, then each scan at least ``metres`` (path length)
    after the previous keyframe; every scan when ``metres`` is 0."""
    n = len(poses)
    if metres <= 0 or n == 0:
        return np.arange(n)
    steps = np.r_[0.0, np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)]
    path = np.cumsum(steps)
    keep, last = [0], path[0]
    for i in range(1, n):
        if path[i] - last >= metres:
            keep.append(i)
            last = path[i]
    return np.array(keep, np.int64)


def build_map(config: MapBuild, progress: Callable[[int, int], None] | None = None) -> Path:
    """Build the map of ``config`` and write it (atomically); returns its folder."""
    seq = config.source.route()
    return write_map(seq, config, progress=progress)


def write_map(
    seq: Sequence,
    config: MapBuild,
    poses: np.ndarray | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> Path:
    """The map of ``seq`` at ``poses`` (default: the sequence's own), written to ``config.out``. A keyframe the
    pipelines cannot describe (too few points) is left out of the map, with a warning."""
    if poses is None:
        if seq.poses is None:
            raise ConfigError(f"{seq.name}: a map needs poses (the sequence has none: give source.poses)")
        poses = np.asarray(seq.poses, np.float64)
        source = "file" if config.source.path is not None else "ground-truth"
    else:
        source = "slam"
    if len(poses) != len(seq):
        raise ConfigError(f"{seq.name}: {len(poses)} poses for {len(seq)} scans")
    scan_of = np.arange(len(seq))  # the source scan of each place
    # places: keyframes accumulated along the map's poses, each at its last scan
    if config.keyframes is not None:
        seq = KeyframeSequence(seq, config.keyframes.model_copy(update={"odometry": "poses"}), poses)
        poses, scan_of = seq.keyframe_poses, seq.reference_indices
    chosen = select_keyframes(poses, config.keyframe_metres)
    first = seq[int(chosen[0])] if len(chosen) else None  # its sensor is the map's; read once
    sensor = None if first is None else first.sensor
    model = None if sensor is None else sensor.name  # its pipelines' settings and thresholds on it
    recs: dict[str, tuple[PlaceRecognizer, float | None]] = {}
    for k, spec in enumerate(config.pipelines):
        key = spec.name
        if key in recs:
            raise ConfigError(
                f"pipelines[{k}]: {key!r} is listed twice (a map holds one database per pipeline)"
            )
        recs[key] = (
            make_pipeline(spec.name, spec.params, path=f"pipelines[{k}].params", sensor=model),
            spec.threshold_for(model),
        )
    if not recs:
        raise ConfigError("pipelines: a map needs at least one pipeline")
    with MapWriter(
        config.out,
        recs,
        name=seq.name,
        sensor=sensor,
        intensity=intensity_label(config.preprocess),
        preprocess=config.preprocess.saved_dump(),
        config=config.model_dump(mode="json"),
        poses_source=source,
        cloud_voxel_m=config.cloud_voxel_m,
        overwrite=config.overwrite,
    ) as writer:
        skipped = 0
        # a few consecutive keyframes spread over the map, to check that the poses fit the scans before writing
        probes = set(pose_fit_probes(len(chosen)).tolist())
        probed: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        for done, i in enumerate(chosen, 1):
            i = int(i)
            raw = first if done == 1 and first is not None else seq[i]
            scan = preprocess_scan(raw, config.preprocess, keep_organized=True)
            try:
                descriptions = [(rec, rec.describe(scan)) for rec, _ in recs.values()]
            except ScanDataError as exc:
                log.warning("%s: scan %d is no keyframe: %s", seq.name, int(scan_of[i]), exc)
                skipped += 1
                continue
            kf = len(writer)
            for rec, desc in descriptions:
                rec.add_description(kf, desc, poses[i])
            stamp = None if seq.timestamps is None else float(seq.timestamps[i])
            xyz = scan.xyz[valid_points(scan)]
            writer.add_keyframe(poses[i], xyz, stamp, scan_index=int(scan_of[i]))
            if done - 1 in probes or done - 2 in probes:
                probed[done - 1] = (poses[i], voxel_points(xyz, config.cloud_voxel_m))
            if progress is not None:
                progress(done, len(chosen))
        if len(writer) == 0:
            raise ScanDataError(f"{seq.name}: no scan could be described; no map written")
        if skipped:
            log.warning("%s: %d of %d keyframe scans could not be described", seq.name, skipped, len(chosen))
        pairs = [(probed[k], probed[k + 1]) for k in sorted(probes) if k in probed and k + 1 in probed]
        check_pose_fit([pose_fit(Ta, a, Tb, b) for (Ta, a), (Tb, b) in pairs], f"{seq.name} ({source} poses)")
        return writer.finish()
