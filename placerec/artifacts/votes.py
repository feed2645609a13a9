"""The vote model of probabilistic voting (kind ``vote-model``, ISHOT paper Sec. IV-D) fitted from a places
database and training scans with ground truth.

::

    from placerec.artifacts.votes import fit_votes
    model = fit_votes(places_db, training_sequence)     # scans with ground-truth poses in the map's frame
    model.save("vote_model.npz"); plot_vote_model(model, "vote_model.png")

Every descriptor of every training scan is matched against all places (2-NN, eq. 4): its vote lands on the place of
its nearest neighbour, at a distance from the scan's true position; `fit_vote_model` fits eq. 7 per tau range to
those distances. `build_vote_model` (``placerec fit-votes``) reads the database and the training scans, checks
that simulated training scans come from the database's map, fits and writes the model.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import Field

from placerec.artifacts.sources import FilePath, SimWorld, open_path, require_one_source
from placerec.errors import ConfigError, ScanDataError
from placerec.intensity import normalize_intensity
from placerec.params import Params
from placerec.pipelines.keypoint_voting import nn_ratio
from placerec.three_d.features import FeatureParams, extract_features
from placerec.three_d.places import PlacesDatabase
from placerec.three_d.vote_model import VoteModel, VoteModelParams, fit_vote_model, plot_vote_model
from placerec.types import Scan, Sequence

__all__ = [
    "VoteModelBuild",
    "build_vote_model",
    "check_same_map",
    "place_extent",
    "describe_training",
    "training_votes",
    "fit_votes",
]


class VoteModelBuild(Params):
    """What ``placerec fit-votes`` builds: the vote model of the places database ``places``, fitted with
    ``params`` on the ``training`` sequences (ground-truth poses in the map's frame, read with ``format``) or on
    ``n_training`` scans per condition of another draw of the simulated world ``sim``'s localisation queries (the
    world the database was built from), written to ``out``; ``figure``: also draw the fitted vs empirical CDFs."""

    places: FilePath
    out: FilePath
    training: list[FilePath] = Field(default_factory=list)
    format: str | None = None
    sim: SimWorld | None = None
    n_training: int = 30
    figure: FilePath | None = None
    params: VoteModelParams = Field(default_factory=VoteModelParams)


def build_vote_model(config: VoteModelBuild, progress: Callable[[int, int], None] | None = None) -> Path:
    """Fit the vote model and write it (atomically), and the figure when asked; returns the model's path.

    `ConfigError` unless exactly one of ``training`` and ``sim`` is given, or when the simulated map is not the
    one the places database was built from (`check_same_map`). ``progress(done, total)`` counts training scans.
    """
    db = PlacesDatabase.load(config.places)
    require_one_source(bool(config.training), config.sim, "TRAINING sequence paths")
    seqs: list[Sequence]
    if config.sim is not None:
        split = config.sim.localization_split(config.n_training, draw=1)
        check_same_map(db, split.map, config.places)
        seqs = list(split.queries.values())
    else:
        seqs = [open_path(p, config.format or None) for p in config.training]
    model = fit_votes(
        db, seqs, config.params, progress=progress, provenance={"places_file": str(config.places)}
    )
    model.save(config.out)
    if config.figure is not None:
        title = f"vote model of {config.places.name} ({model.provenance['n_votes']} votes)"
        plot_vote_model(model, config.figure, title)
    return config.out


def check_same_map(db: PlacesDatabase, map_seq: Sequence, where: str | Path) -> None:
    """`ConfigError` unless ``map_seq`` (a simulated localisation map) has the poses of the map the places
    database ``db`` (read from ``where``) was built from."""
    assert map_seq.poses is not None  # a simulated map has its poses
    same = map_seq.poses.shape == db.scan_poses.shape and np.allclose(map_seq.poses, db.scan_poses)
    if not same:
        raise ConfigError(
            f"{where} was built from another map ({db.sequence}, {len(db.scan_poses)} scans) than the "
            f"simulated {map_seq.name} ({len(map_seq)} scans): check --sim-world/--sim-scans/--seed"
        )


def place_extent(place_xyz: np.ndarray) -> float:
    """``d_max`` of the vote model: the diagonal of the places' bounding box (at least 1 m)."""
    xyz = np.asarray(place_xyz, np.float64).reshape(-1, 3)
    return max(1.0, float(np.linalg.norm(xyz.max(axis=0) - xyz.min(axis=0)))) if len(xyz) else 1.0


def describe_training(
    seq: Sequence,
    features: FeatureParams,
    intensity: Callable[[Scan], Scan] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """(descriptors, true position) of every scan of ``seq`` (which needs poses); a scan that cannot be described
    is skipped."""
    if seq.poses is None:
        raise ConfigError(f"{seq.name}: fitting the vote model needs training scans with ground-truth poses")
    fn = intensity or normalize_intensity
    for i in range(len(seq)):
        try:
            lf = extract_features(fn(seq[i]), features)
        except ScanDataError:
            lf = None
        if progress is not None:
            progress(i + 1, len(seq))
        if lf is not None and len(lf):
            yield lf.descriptors, np.asarray(seq.poses[i][:3, 3], np.float64)


def training_votes(
    db: PlacesDatabase,
    queries: Iterable[tuple[np.ndarray, np.ndarray]],
    backend: str = "faiss",
    threads: int | None = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """(distances, taus) of every vote of ``queries`` = (descriptors (K, D), true position (3,)) pairs against the
    places of ``db``: the distance from the voted place's centre to the query's true position, and ``d1 / d2``."""
    rows = db.descriptors.view()  # searched as stored (float32, float16 or sq8 codes)
    if rows.shape[0] < 2:
        raise ScanDataError(
            f"votes: the places database has {rows.shape[0]} descriptors, at least 2 are needed"
        )
    row_place, place_xyz = db.row_place, db.poses[:, :3, 3]
    dist, taus = [], []
    for desc, xyz in queries:
        q = np.asarray(desc, np.float32).reshape(-1, rows.shape[1])
        if q.shape[0] == 0:
            continue
        nd, idx = rows.knn2(q, backend, threads)
        voted = row_place[idx[:, 0]]
        dist.append(np.linalg.norm(place_xyz[voted] - np.asarray(xyz, np.float64)[None, :3], axis=1))
        taus.append(nn_ratio(nd))
    if not dist:
        raise ScanDataError("votes: no training scan had a descriptor")
    return np.concatenate(dist), np.concatenate(taus)


def fit_votes(
    db: PlacesDatabase,
    training: Sequence | list[Sequence],
    params: VoteModelParams | None = None,
    intensity: Callable[[Scan], Scan] | None = None,
    progress: Callable[[int, int], None] | None = None,
    provenance: dict[str, Any] | None = None,
) -> VoteModel:
    """The vote model of ``db`` fitted on the scans of ``training`` (one or several sequences with ground-truth poses
    in the map's frame), described with the database's own feature settings; provenance records both.
    ``progress(done, total)`` counts training scans."""
    seqs = list(training) if isinstance(training, list | tuple) else [training]
    total = sum(len(s) for s in seqs)

    def described() -> Iterator[tuple[np.ndarray, np.ndarray]]:
        done = 0
        for s in seqs:
            step = None if progress is None else (lambda i, _n, base=done: progress(base + i, total))
            yield from describe_training(s, db.params.features, intensity, step)
            done += len(s)

    d, tau = training_votes(db, described())
    prov = {
        "places_sequence": db.sequence,
        "n_places": len(db),
        "descriptor": db.descriptor,
        "intensity": db.intensity,
        "training_sequences": [s.name for s in seqs],
        "n_training_scans": total,
        "n_votes": int(d.size),
        **(provenance or {}),
    }
    return fit_vote_model(d, tau, place_extent(db.poses[:, :3, 3]), params, prov)
