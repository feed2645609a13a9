"""The places database (kind ``places-db``): a mapping sequence partitioned into places
(`placerec.three_d.places.partition_places`), each place's scans merged, described and stored as a
`placerec.three_d.places.PlacesDatabase`.

`build_places` makes the database in memory; `build_places_db` reads the map, builds it and writes the file.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

import numpy as np
from pydantic import Field

from placerec.artifacts.sources import FilePath, SequenceSource
from placerec.errors import ConfigError, ScanDataError
from placerec.intensity import normalize_intensity
from placerec.params import Params
from placerec.preprocess import crop, remove_invalid
from placerec.retrieval.descriptor_store import DescriptorStore
from placerec.three_d.features import extract_features
from placerec.three_d.places import PlacesDatabase, PlacesParams, partition_places, place_cloud
from placerec.types import Scan, Sequence

log = logging.getLogger(__name__)

__all__ = ["PlacesBuild", "build_places", "build_places_db"]

IntensityFn = Callable[[Scan], Scan]


class PlacesBuild(Params):
    """What ``placerec build-places`` builds: the places of the map ``source`` (a sequence with poses, or the map
    of a simulated world's localisation split), cut and described with ``params``, written to ``out``."""

    source: SequenceSource
    out: FilePath
    params: PlacesParams = Field(default_factory=PlacesParams)


def build_places_db(config: PlacesBuild, progress: Callable[[int, int], None] | None = None) -> Path:
    """Build the places database of the map and write it (atomically); returns its path. ``progress(done,
    total)`` counts the places described."""
    seq = config.source.localization_map()
    build_places(seq, config.params, progress=progress).save(config.out)
    return config.out


def _prepared(scan: Scan, intensity: IntensityFn, max_range: float | None) -> Scan:
    scan, _ = remove_invalid(intensity(scan))
    return scan if max_range is None else crop(scan, max_range=max_range)


def build_places(
    seq: Sequence,
    params: PlacesParams | None = None,
    intensity: IntensityFn | None = None,
    intensity_label: str = "sensor-default",
    progress: Callable[[int, int], None] | None = None,
) -> PlacesDatabase:
    """Partition ``seq`` into places, accumulate and describe each (see the module docstring).

    ``intensity`` maps every raw scan to [0, 1] intensity before accumulation (default: the sensor's default
    normalisation, `placerec.intensity.normalize_intensity`; pass a calibration's ``apply`` for ISHOT-C) and
    ``intensity_label`` names it in the database. ``progress(done, total)`` is called after every place.
    """
    params = params or PlacesParams()
    poses = seq.poses
    if poses is None:
        raise ConfigError(f"{seq.name}: building places needs a sequence with poses")
    poses = np.asarray(poses, dtype=np.float64)
    part = partition_places(poses, seq.timestamps, params)
    fn = intensity or normalize_intensity
    feats = params.features
    cache: dict[int, Scan] = {}
    kps, clouds = [], []
    descs: list[np.ndarray | None] = []  # None: a place that could not be described
    dim = None
    for p, (c, members) in enumerate(zip(part.centres, part.members, strict=True)):
        cache = {
            int(j): cache[int(j)] if int(j) in cache else _prepared(seq[int(j)], fn, feats.max_range)
            for j in members
        }
        cloud = place_cloud(cache, poses, int(c), members)
        try:
            lf = extract_features(cloud, feats)
            kps.append(lf.keypoints.astype(np.float32))
            descs.append(lf.descriptors)
            dim = lf.descriptors.shape[1]
            if params.store_clouds:
                clouds.append((lf.points.astype(np.float32), lf.intensity.astype(np.float32)))
        except ScanDataError as exc:
            log.warning("place %d (scan %d): %s; stored without keypoints", p, c, exc)
            kps.append(np.zeros((0, 3), np.float32))
            descs.append(None)
            clouds.append((np.zeros((0, 3), np.float32), np.zeros(0, np.float32)))
        if progress is not None:
            progress(p + 1, len(part))
    if dim is None:
        raise ScanDataError(f"{seq.name}: no place had enough points to be described")
    rows = [np.zeros((0, dim), np.float32) if d is None else d for d in descs]
    counts = np.array([k.shape[0] for k in kps], dtype=np.int64)
    log.info(
        "%s: %d places, %d keypoints (%.0f per place), %s", seq.name, len(part), counts.sum(), counts.mean(),
        feats.descriptor,
    )  # fmt: skip
    return PlacesDatabase(
        ids=part.centres.copy(),
        poses=poses[part.centres].copy(),
        sources=part.members,
        kp_offsets=np.r_[0, np.cumsum(counts)].astype(np.int64),
        keypoints=np.concatenate(kps),
        descriptors=DescriptorStore.from_rows(np.concatenate(rows), params.descriptor_store),
        params=params,
        scan_poses=poses.copy(),
        clouds=clouds if params.store_clouds else None,
        intensity=intensity_label,
        sequence=seq.name,
    )
