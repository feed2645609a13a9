"""DELIGHT (Cop, Borges & Dube, ICRA 2018): the ISHOT paper's baseline (c) of Table III, "2-stage wake-up".

The ISHOT paper sums DELIGHT up as a global descriptor made of several histograms of raw intensity values over
parts of the scan, matched first to eliminate unlikely places before a precise localisation. `Delight`
(registered as ``delight``) builds it from that structure; what the summary leaves open is chosen here and said so.

Descriptor (`make_descriptor`), from the scan's valid points (`placerec.recognizer.valid_points`):

* **Parts**: two concentric spheres around the sensor (the inner ball of radius ``inner_radius``, the shell up
  to ``outer_radius``; a point belongs to the inner ball when its 3D range is below ``inner_radius``, to the shell
  when it is below ``outer_radius``, to neither beyond) x 8 sectors of 45 degrees of azimuth: sector ``s`` covers
  ``[45 s, 45 (s + 1))`` degrees counter-clockwise from the sensor's +x axis. 16 parts, array (2, 8, bins).
* **Histograms**: per part, the intensities in ``bins`` equal bins over [0, 1] (bin ``b`` holds ``[b, b + 1) /
  bins``; 1 and above go to the last bin, below 0 to the first), divided by the part's point count (a part
  without points: all zeros).
* **Intensity**: the scan's intensity as every placerec intensity pipeline gets it: mapped to [0, 1] by the
  sensor's normalisation (`placerec.intensity`; raw values above 1 are normalised with the sensor default here
  too). No per-beam calibration is applied, which is what "raw" means in DELIGHT's setting (its counterpart is
  calibrated intensity); for the VLP-16 the map is linear (raw 0-100 to 0-1), so equal bins over [0, 1] are equal
  bins over the raw diffuse range, and retro-reflective returns (raw > 100) share the last bin.

Distance (`delight_distance`): the chi-squared distance summed over the 16 parts and their bins,
``sum (q - m)^2 / (q + m)`` (terms with ``q + m = 0`` are 0), in [0, 32] for normalised histograms. A heading
is unknown at localisation, so the query's sectors are compared with a map entry's under the 8 cyclic shifts
and the smallest distance is kept: exactly invariant to yaw rotations by multiples of 45 degrees, and about
as coarse otherwise as the sectors themselves (a sector's content moves at most half a sector from where a
shift puts it). The alternative, aligning both scans by a reference direction of their own, depends on what is
occluded and was not taken. ``sector_shifts = False`` compares the sectors as they are (a known heading). The
search over every map entry is one array expression (in blocks of entries to bound memory).
``shift`` is the ``s`` for which ``np.roll(entry, s, axis=1)`` matches the query: the query's heading is then
about ``-45 s`` degrees from the entry's (``extra["yaw_deg"]``).

Second stage: the map entries are ranked by that distance and go, best first, through the verification every
localisation pipeline shares (the ISHOT paper Sec. V-C: "the same geometric verification module is used for all
pipelines"): the front end's keypoints (ISS-BR) and descriptors (SHOT in the registry preset, as baselines (a)
and (b)) are matched against the candidate's local map, then geometric consistency grouping, RANSAC and ICP
accepted by eps_ICP (`KeypointVoting`'s verification, with the ``LOCALIZE_VERIFY`` preset: local maps of 15 m,
candidates 7.5 m apart). ``verify.top_k`` candidates are verified at a time until one is accepted, up to
``verify.fallback_top_k`` in all: the descriptor discards the rest of the map. ``score``: the verified score
(``extra["retrieval_score"]`` = ``1 - distance / 32``, in [0, 1]); without verification that retrieval score,
and no pose.

Entries: every added scan, or with ``places.spacing_m`` the scans that far from every earlier entry (as for
(a) and (b)); a places database (``places.database``) or accumulated places (``places.window_m``) hold no intensity
histograms and are refused. The radii (30 / 60 m) and bins (64) are ours, chosen on the tuning split by the
first stage's recall (``tools/tune_delight.py``, docs/localization.md): the published values are not available
here.

``extra``: ``distance``, ``shift``, ``yaw_deg``, ``rank`` (position in the DELIGHT ranking), ``n_ranked``.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from pydantic import Field, model_validator

from placerec.errors import ArtifactError, ConfigError, ScanDataError
from placerec.io.artifact_schema import Member
from placerec.io.atomic import load_artifact, save_artifact
from placerec.params import Params
from placerec.pipelines.keypoint_voting import KeypointVoting, VotingParams, voting_schema
from placerec.pipelines.voting_engine import Query, Shortlist, VoteStrategy
from placerec.recognizer import params_key, require_points, require_varying_intensity, valid_points
from placerec.three_d.entries import EntryTable
from placerec.three_d.places import PlacesDatabase
from placerec.types import Description, Scan

__all__ = [
    "ARTIFACT_KIND",
    "N_SPHERES",
    "N_SECTORS",
    "DelightParams",
    "Delight",
    "make_descriptor",
    "chi_squared",
    "delight_distance",
]

ARTIFACT_KIND = "delight-db"
FORMAT_VERSION = 1
N_SPHERES = 2
N_SECTORS = 8
#: entries compared at once by `delight_distance` (bounds its temporary arrays to ~8 shifts x 2048 x 16 x bins)
_BLOCK = 2048


class DelightParams(VotingParams):
    """`VotingParams` (front end, entries, the shared verification) plus the DELIGHT descriptor. The ``search``
    section and ``score`` do not apply: entries are ranked by the descriptor."""

    inner_radius: float = Field(
        30.0, gt=0, description="m; radius of the inner sphere (ours, tuning split: tools/tune_delight.py)"
    )
    outer_radius: float = Field(
        60.0, gt=0, description="m; radius of the outer sphere, points beyond ignored (ours, tuning split)"
    )
    bins: int = Field(
        64, ge=2, description="intensity histogram bins per part over [0, 1] (ours, tuning split)"
    )
    sector_shifts: bool = Field(
        True, description="compare sectors under the 8 cyclic shifts (unknown heading) or as they are"
    )

    @model_validator(mode="after")
    def _spheres_and_entries(self) -> DelightParams:
        if self.inner_radius >= self.outer_radius:
            raise ValueError(
                f"inner_radius ({self.inner_radius}) must be below outer_radius ({self.outer_radius})"
            )
        if self.places.database is not None or self.places.window_m > 0:
            raise ValueError(
                "places.database and places.window_m are not supported: DELIGHT describes each added scan "
                "(use places.spacing_m to keep scans apart)"
            )
        return self

    def descriptor_dict(self) -> dict[str, Any]:
        """What the DELIGHT histograms depend on (stored with a saved database)."""
        return {"inner_radius": self.inner_radius, "outer_radius": self.outer_radius, "bins": self.bins}


def make_descriptor(scan: Scan, params: DelightParams | None = None) -> np.ndarray:
    """The (2, 8, bins) float32 DELIGHT descriptor of a scan whose intensity is in [0, 1] (module docstring)."""
    p = params or DelightParams()
    ok = valid_points(scan)
    xyz = scan.xyz[ok].astype(np.float64)
    inten = scan.intensity[ok].astype(np.float64)
    r = np.sqrt(np.einsum("ni,ni->n", xyz, xyz))
    keep = (r < p.outer_radius) & np.isfinite(inten)
    xyz, inten, r = xyz[keep], inten[keep], r[keep]
    sphere = (r >= p.inner_radius).astype(np.int64)
    azimuth = np.mod(np.arctan2(xyz[:, 1], xyz[:, 0]), 2.0 * np.pi)
    sector = np.minimum((azimuth * (N_SECTORS / (2.0 * np.pi))).astype(np.int64), N_SECTORS - 1)
    b = np.clip(np.floor(inten * p.bins), 0, p.bins - 1).astype(np.int64)
    cell = (sphere * N_SECTORS + sector) * p.bins + b
    hist = np.bincount(cell, minlength=N_SPHERES * N_SECTORS * p.bins).astype(np.float64)
    hist = hist.reshape(N_SPHERES, N_SECTORS, p.bins)
    count = hist.sum(axis=2, keepdims=True)
    return np.divide(hist, count, out=np.zeros_like(hist), where=count > 0).astype(np.float32)


def chi_squared(a: np.ndarray, b: np.ndarray, axes: tuple[int, ...] = (-3, -2, -1)) -> np.ndarray:
    """``sum (a - b)^2 / (a + b)`` over ``axes`` of two broadcastable arrays of histograms, 0 where ``a + b`` is
    0 (the chi-squared distance DELIGHT compares descriptors with)."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    s = a + b
    d = a - b
    terms = np.divide(d * d, s, out=np.zeros(np.broadcast(a, b).shape), where=s > 0)
    return terms.sum(axis=axes)


def delight_distance(
    query: np.ndarray, entries: np.ndarray, shifts: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Chi-squared distance of a (2, 8, B) query descriptor to (M, 2, 8, B) entries, the smallest over the 8
    cyclic sector shifts (``shifts``; else the sectors as they are). Returns ``(distance (M,), shift (M,))``
    with ``np.roll(entries[m], shift[m], axis=1)`` the best aligned entry."""
    q = np.asarray(query, np.float64)
    e = np.asarray(entries, np.float64)
    if e.ndim == 3:
        e = e[None]
    if e.shape[1:] != q.shape or q.shape[:2] != (N_SPHERES, N_SECTORS):
        raise ScanDataError(f"delight: query of shape {q.shape} against entries of shape {e.shape[1:]}")
    n_shift = N_SECTORS if shifts else 1
    # rolling the entry by s matches rolling the query by -s: q_s[s] is the query seen by an entry rolled by s
    q_s = np.stack([np.roll(q, -s, axis=1) for s in range(n_shift)])  # (S, 2, 8, B)
    dist = np.empty((e.shape[0], n_shift))
    for a in range(0, e.shape[0], _BLOCK):
        dist[a : a + _BLOCK] = chi_squared(q_s[None], e[a : a + _BLOCK, None])
    best = np.argmin(dist, axis=1) if e.shape[0] else np.zeros(0, np.int64)
    return dist[np.arange(e.shape[0]), best], best.astype(np.int64)


class HistogramRanking(VoteStrategy["Delight"]):
    """DELIGHT's query: the eligible entries ranked once by the distance of their histograms to the query's (ties:
    lower id); no keypoint is matched against the database, the best ``verify.fallback_top_k`` (default ``verify.top_k``)
    are verified ``verify.top_k`` at a time until one is accepted."""

    def __init__(self, rec: Delight, query: Query) -> None:
        if query.k < 1:
            raise ScanDataError(f"{rec.name}: k must be >= 1, got {query.k}")
        super().__init__(rec, query)
        self.histogram = rec.histogram(query.description)

    def possible(self) -> bool:
        verifies = self.rec.params.verify.enabled
        return bool(self.query.eligible.any()) and (self.n > 0 or not verifies)

    def fallback(self) -> Shortlist:
        rec, eligible = self.rec, self.query.eligible
        rows = np.flatnonzero(eligible)
        dist, shift = delight_distance(self.histogram, rec._hist[rows], rec.params.sector_shifts)
        ranked = rows[np.lexsort((np.asarray(rec.entries.ids)[rows], dist))]
        info = {int(e): (float(d), int(s)) for e, d, s in zip(rows, dist, shift, strict=True)}
        rank = {int(e): i for i, e in enumerate(ranked)}

        def extra(e: int) -> dict[str, Any]:
            d, s = info[e]
            yaw = float((-45.0 * s + 180.0) % 360.0 - 180.0)
            return {"distance": d, "shift": s, "yaw_deg": yaw, "rank": rank[e], "n_ranked": int(rows.size)}

        p = rec.params
        return Shortlist(
            ranked,
            score=lambda e: 1.0 - info[e][0] / (2.0 * N_SPHERES * N_SECTORS),
            extra=extra,
            top_k=(p.verify.fallback_top_k or p.verify.top_k) if p.verify.enabled else None,
        )


class Delight(KeypointVoting):
    """`PlaceRecognizer`: DELIGHT ranking, then the shared keypoint verification (module docstring)."""

    name: ClassVar[str] = "delight"
    Params: ClassVar[type[Params]] = DelightParams
    params: DelightParams
    Strategy: ClassVar[type[VoteStrategy[Any]]] = HistogramRanking

    def _reset(self, entries: EntryTable | None = None) -> None:
        super()._reset(entries)
        self._hist = np.zeros((0, N_SPHERES, N_SECTORS, self.params.bins), np.float32)

    def use_places(self, db: PlacesDatabase) -> None:
        raise ConfigError(f"{self.name}: a places database holds no intensity histograms to rank with")

    @property
    def frontend_key(self) -> str:
        icp = self.params.verify.icp
        return params_key(
            self.name,
            {
                "features": self._features.model_dump(mode="json"),
                "delight": self.params.descriptor_dict(),
                "icp_cloud": [icp.voxel_size, icp.max_range],
            },
        )

    def describe(self, scan: Scan) -> Description:
        """`KeypointVoting.describe`'s keypoints, descriptors and ICP cloud, plus ``delight``, the (2, 8, bins)
        descriptor; `ScanDataError` for too few valid points or an intensity that is constant or not finite over
        them (every part's histogram would be one bin: any two such scans would look alike)."""
        ok = require_points(scan, self.name)
        require_varying_intensity(scan, ok, self.name, "DELIGHT's histograms need varying intensity")
        out = dict(super().describe(scan))
        out["delight"] = make_descriptor(self._normalised(scan), self.params)
        return out

    def histogram(self, description: Description) -> np.ndarray:
        if not isinstance(description, Mapping) or "delight" not in description:
            raise ScanDataError(
                f"{self.name}: the description has no 'delight' histograms (describe() gives it)"
            )
        h = np.asarray(description["delight"], np.float32)
        if h.shape != self._hist.shape[1:] or not np.isfinite(h).all():
            raise ScanDataError(
                f"{self.name}: histograms of shape {h.shape}, expected {self._hist.shape[1:]}"
            )
        return h

    def add_description(self, scan_id: int, description: Description, pose: np.ndarray | None = None) -> None:
        h = self.histogram(description)
        n = len(self.entries)
        super().add_description(scan_id, description, pose)
        if len(self.entries) > n:  # the scan became an entry (places.spacing_m may skip it)
            self._hist = np.concatenate([self._hist, h[None]])

    # -- persistence ----------------------------------------------------------------------------------------
    def save(self, path: str | Path) -> None:
        """The entries (`KeypointVoting`'s arrays) and their DELIGHT histograms (kind ``delight-db``, version 1)."""
        arrays, meta = self._state()
        arrays["delight"] = self._hist
        save_artifact(path, ARTIFACT_KIND, FORMAT_VERSION, arrays, meta)

    def load(self, path: str | Path) -> None:
        """Replace the database by a saved one; `ArtifactError` if it is corrupt or was made with other
        parameters."""
        schema = {
            **voting_schema(self._dim),
            "delight": Member("f", ("n_entries", N_SPHERES, N_SECTORS, self.params.bins), finite=True),
        }
        arrays, header = load_artifact(path, ARTIFACT_KIND, (FORMAT_VERSION,), schema)
        hist = np.asarray(arrays["delight"], np.float32)
        if hist.size and (hist.min() < 0 or hist.max() > 1):
            raise ArtifactError(f"{path}: 'delight' histograms hold values outside [0, 1]")
        self._restore(path, arrays, header)
        self._hist = hist.copy()
