"""The data model every part of placerec shares: scans, sensors, sequences, candidates, recognizers.

Conventions
-----------
* Points are in the sensor frame: x forward, y left, z up (metres).
* A pose is a 4x4 float64 homogeneous matrix ``T_world_sensor`` that maps sensor-frame points into the world
  frame (KITTI's convention for ``poses.txt``).
* A ``Candidate.relative_pose`` is ``T_match_query``: it maps points of the *query* scan into the frame of the
  *matched* scan, so that ``T_world_query ~= T_world_match @ relative_pose``.
* Ids are the integers the caller gives to ``PlaceRecognizer.add``; placerec never renumbers them.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from collections.abc import Sequence as _Seq
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from placerec.errors import ScanDataError

__all__ = [
    "SensorInfo",
    "SENSOR_PATTERNS",
    "Scan",
    "Sequence",
    "ListSequence",
    "StoredSequenceInfo",
    "Candidate",
    "MAX_RANGE_M",
    "valid_points",
    "take_rows",
    "Verification",
    "REJECTIONS",
    "Description",
    "Prediction",
    "MotionPrior",
    "PlaceRecognizer",
    "as_pose",
    "relative_pose",
    "interpolate_trajectory",
]


#: scan patterns a `SensorInfo` may name
SENSOR_PATTERNS: tuple[str, ...] = ("spinning", "non-repetitive", "solid-state")


def _pair(v: Any) -> tuple[float, float]:
    if not isinstance(v, (list, tuple)) or len(v) != 2:
        raise ScanDataError(f"sensor description: elevation_fov_deg must be [up, down], got {v!r}")
    return float(v[0]), float(v[1])


@dataclass(frozen=True)
class SensorInfo:
    """What is known about the sensor that produced a scan.

    ``beam_elevations_deg`` lists one elevation per beam (ring), indexed by ring id; ``columns`` is the number of
    azimuth steps per revolution; ``intensity_max`` is the saturation value of the raw intensity channel (e.g. 255
    for 8-bit Velodyne, 65535 for 16-bit Ouster reflectivity, 1.0 for KITTI's float reflectance).

    Sensors that are not one 360 deg spinning sweep say so: ``pattern`` is ``"spinning"`` (None means the same),
    ``"non-repetitive"`` (Livox-style rosettes: the covered part of the field of view grows with integration time)
    or ``"solid-state"`` (a fixed raster over a limited field of view). ``horizontal_fov_deg`` is the width of the
    horizontal field of view centred on +x (None = 360); ``elevation_fov_deg`` = (up, down), both positive for a
    sensor that sees above and below the horizon, gives the vertical field of view of a sensor without a beam
    layout (a sensor with ``beam_elevations_deg`` takes it from them). ``rate_hz`` is the scan (frame) rate.
    """

    name: str = "unknown"
    beam_elevations_deg: tuple[float, ...] | None = None
    columns: int | None = None
    intensity_max: float | None = None
    min_range: float | None = None
    max_range: float | None = None
    pattern: str | None = None
    horizontal_fov_deg: float | None = None
    elevation_fov_deg: tuple[float, float] | None = None
    rate_hz: float | None = None

    def __post_init__(self) -> None:
        if self.pattern is not None and self.pattern not in SENSOR_PATTERNS:
            raise ScanDataError(
                f"sensor {self.name!r}: pattern {self.pattern!r} is not one of {SENSOR_PATTERNS}"
            )
        h = self.horizontal_fov_deg
        if h is not None and not (np.isfinite(h) and 0 < h <= 360):
            raise ScanDataError(f"sensor {self.name!r}: horizontal_fov_deg must be in (0, 360], got {h!r}")
        e = self.elevation_fov_deg
        if e is not None:
            if len(e) != 2 or not np.all(np.isfinite(e)) or not (-90 <= e[0] <= 90 and -90 <= e[1] <= 90):
                raise ScanDataError(
                    f"sensor {self.name!r}: elevation_fov_deg must be (up, down) in degrees, got {e!r}"
                )
            if e[0] + e[1] <= 0:
                raise ScanDataError(f"sensor {self.name!r}: elevation_fov_deg {e!r} spans no angle")
            object.__setattr__(self, "elevation_fov_deg", (float(e[0]), float(e[1])))
        if self.rate_hz is not None and not (np.isfinite(self.rate_hz) and self.rate_hz > 0):
            raise ScanDataError(f"sensor {self.name!r}: rate_hz must be positive, got {self.rate_hz!r}")

    @property
    def n_beams(self) -> int | None:
        return None if self.beam_elevations_deg is None else len(self.beam_elevations_deg)

    @property
    def vertical_fov_deg(self) -> tuple[float, float] | None:
        """(up, down) field of view in degrees, both positive for a sensor that sees above and below."""
        if not self.beam_elevations_deg:
            return self.elevation_fov_deg
        e = np.asarray(self.beam_elevations_deg)
        return float(e.max()), float(-e.min())

    @property
    def is_spinning(self) -> bool:
        """Whether one scan is a 360 deg spinning sweep (the cylindrical image's assumption)."""
        return (self.pattern in (None, "spinning")) and (self.horizontal_fov_deg in (None, 360.0))

    def to_dict(self) -> dict[str, Any]:
        d = {
            "name": self.name,
            "beam_elevations_deg": None
            if self.beam_elevations_deg is None
            else [float(v) for v in self.beam_elevations_deg],
            "columns": self.columns,
            "intensity_max": self.intensity_max,
            "min_range": self.min_range,
            "max_range": self.max_range,
        }
        # the fields of sensors that are not spinning are written only when set, so the description of a
        # spinning sensor (and every hash of it) stays what it was before they existed
        if self.pattern is not None:
            d["pattern"] = self.pattern
        if self.horizontal_fov_deg is not None:
            d["horizontal_fov_deg"] = float(self.horizontal_fov_deg)
        if self.elevation_fov_deg is not None:
            d["elevation_fov_deg"] = [float(v) for v in self.elevation_fov_deg]
        if self.rate_hz is not None:
            d["rate_hz"] = float(self.rate_hz)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SensorInfo:
        allowed = {"name", "beam_elevations_deg", "columns", "intensity_max", "min_range", "max_range", "pattern",
                   "horizontal_fov_deg", "elevation_fov_deg", "rate_hz"}  # fmt: skip
        unknown = set(d) - allowed
        if unknown:
            raise ScanDataError(
                f"sensor description has unknown keys {sorted(unknown)}; allowed: {sorted(allowed)}"
            )
        elev = d.get("beam_elevations_deg")
        return cls(
            name=str(d.get("name", "unknown")),
            beam_elevations_deg=None if elev is None else tuple(float(v) for v in elev),
            columns=None if d.get("columns") is None else int(d["columns"]),
            intensity_max=None if d.get("intensity_max") is None else float(d["intensity_max"]),
            min_range=None if d.get("min_range") is None else float(d["min_range"]),
            max_range=None if d.get("max_range") is None else float(d["max_range"]),
            pattern=None if d.get("pattern") is None else str(d["pattern"]),
            horizontal_fov_deg=None
            if d.get("horizontal_fov_deg") is None
            else float(d["horizontal_fov_deg"]),
            elevation_fov_deg=None if d.get("elevation_fov_deg") is None else _pair(d["elevation_fov_deg"]),
            rate_hz=None if d.get("rate_hz") is None else float(d["rate_hz"]),
        )


@dataclass(frozen=True, eq=False)
class Scan:
    """One LiDAR sweep.

    ``xyz`` (N, 3) float32 and ``intensity`` (N,) float32 are always present. ``ring`` (N,) int16 is the beam
    index (0 = the beam listed first in ``sensor.beam_elevations_deg``), ``time`` (N,) float32 the per-point time
    offset in seconds. ``shape`` = (rows, cols) marks an *organised* scan: then N == rows * cols, points are stored
    row-major (row = beam, top beam first) and invalid returns are rows of zeros.
    """

    xyz: np.ndarray
    intensity: np.ndarray
    ring: np.ndarray | None = None
    time: np.ndarray | None = None
    shape: tuple[int, int] | None = None
    sensor: SensorInfo = field(default_factory=SensorInfo)
    timestamp: float | None = None
    source: str | None = None

    def __post_init__(self) -> None:
        xyz = np.ascontiguousarray(self.xyz, dtype=np.float32)
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise ScanDataError(f"{self._where()}xyz must have shape (N, 3), got {xyz.shape}")
        n = xyz.shape[0]
        inten = np.ascontiguousarray(self.intensity, dtype=np.float32).reshape(-1)
        if inten.shape[0] != n:
            raise ScanDataError(f"{self._where()}intensity has {inten.shape[0]} values for {n} points")
        object.__setattr__(self, "xyz", xyz)
        object.__setattr__(self, "intensity", inten)
        if self.ring is not None:
            ring = np.ascontiguousarray(self.ring, dtype=np.int16).reshape(-1)
            if ring.shape[0] != n:
                raise ScanDataError(f"{self._where()}ring has {ring.shape[0]} values for {n} points")
            object.__setattr__(self, "ring", ring)
        if self.time is not None:
            t = np.ascontiguousarray(self.time, dtype=np.float32).reshape(-1)
            if t.shape[0] != n:
                raise ScanDataError(f"{self._where()}time has {t.shape[0]} values for {n} points")
            object.__setattr__(self, "time", t)
        if self.shape is not None:
            rows, cols = (int(v) for v in self.shape)
            if rows * cols != n:
                raise ScanDataError(f"{self._where()}organised shape {rows}x{cols} does not match {n} points")
            object.__setattr__(self, "shape", (rows, cols))

    def _where(self) -> str:
        return f"{self.source}: " if self.source else ""

    def __len__(self) -> int:
        return int(self.xyz.shape[0])

    @property
    def is_organized(self) -> bool:
        return self.shape is not None

    @property
    def ranges(self) -> np.ndarray:
        """Euclidean range of every point (float32)."""
        return np.sqrt(np.einsum("ij,ij->i", self.xyz, self.xyz, dtype=np.float32))

    @property
    def fields(self) -> list[str]:
        names = ["x", "y", "z", "intensity"]
        if self.ring is not None:
            names.append("ring")
        if self.time is not None:
            names.append("time")
        return names

    def select(self, mask_or_index: np.ndarray) -> Scan:
        """A new unorganised scan with the selected points (boolean mask or integer index)."""
        sel = np.asarray(mask_or_index)
        return replace(
            self,
            xyz=take_rows(self.xyz, sel),
            intensity=self.intensity[sel],
            ring=None if self.ring is None else self.ring[sel],
            time=None if self.time is None else self.time[sel],
            shape=None,
        )

    def with_intensity(self, intensity: np.ndarray) -> Scan:
        return replace(self, intensity=intensity)

    def transformed(self, pose: np.ndarray) -> Scan:
        """The scan with its points mapped by the 4x4 ``pose`` (e.g. into the world frame)."""
        T = as_pose(pose)
        xyz = (self.xyz.astype(np.float64) @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
        return replace(self, xyz=xyz)

    def organized(self, name: str) -> np.ndarray:
        """A per-point array reshaped to (rows, cols[, ...]); only for organised scans."""
        if self.shape is None:
            raise ScanDataError(f"{self._where()}scan is not organised")
        arr = getattr(self, name)
        if arr is None:
            raise ScanDataError(f"{self._where()}scan has no field {name!r}")
        return arr.reshape(self.shape + arr.shape[1:])


@runtime_checkable
class Sequence(Protocol):
    """A dataset of scans in acquisition order. Every loader and the simulator implement it.

    ``poses`` is an (N, 4, 4) float64 array of ``T_world_sensor`` or None when unknown; ``timestamps`` an (N,)
    float64 array of seconds (monotonic) or None.
    """

    def __len__(self) -> int: ...

    def __getitem__(self, index: int) -> Scan: ...

    @property
    def poses(self) -> np.ndarray | None: ...

    @property
    def timestamps(self) -> np.ndarray | None: ...

    @property
    def name(self) -> str: ...


def iter_scans(seq: Sequence) -> Iterator[Scan]:
    for i in range(len(seq)):
        yield seq[i]


class StoredSequenceInfo:
    """The `Sequence` properties of a sequence that holds them as ``_poses``, ``_timestamps`` and ``_name``."""

    _poses: np.ndarray | None
    _timestamps: np.ndarray | None
    _name: str

    @property
    def poses(self) -> np.ndarray | None:
        return self._poses

    @property
    def timestamps(self) -> np.ndarray | None:
        return self._timestamps

    @property
    def name(self) -> str:
        return self._name


class ListSequence(StoredSequenceInfo):
    """A `Sequence` over scans already in memory (handy for tests and small experiments)."""

    def __init__(
        self,
        scans: _Seq[Scan],
        poses: np.ndarray | None = None,
        timestamps: np.ndarray | None = None,
        name: str = "in-memory",
    ) -> None:
        self._scans = list(scans)
        self._poses = None if poses is None else check_poses(poses, len(self._scans), name)
        self._timestamps = (
            None if timestamps is None else np.asarray(timestamps, dtype=np.float64).reshape(-1)
        )
        if self._timestamps is not None and self._timestamps.shape[0] != len(self._scans):
            raise ScanDataError(
                f"{name}: {self._timestamps.shape[0]} timestamps for {len(self._scans)} scans"
            )
        self._name = name

    def __len__(self) -> int:
        return len(self._scans)

    def __getitem__(self, index: int) -> Scan:
        return self._scans[index]


def as_pose(pose: np.ndarray, what: str = "a pose") -> np.ndarray:
    """Validate and return a 4x4 float64 pose (accepts 3x4): a rigid motion (`rigid_problem`), else
    `ScanDataError` naming ``what``."""
    T = np.asarray(pose, dtype=np.float64)
    if T.shape == (3, 4):
        T = np.vstack([T, [0.0, 0.0, 0.0, 1.0]])
    if T.shape != (4, 4):
        raise ScanDataError(f"{what} must be 4x4 (or 3x4), got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise ScanDataError(f"{what} contains NaN or inf")
    problem = rigid_problem(T[None])
    if problem is not None:
        raise ScanDataError(f"{what} is no rigid motion: {problem[1]}")
    return T


#: Largest ``max |R^T R - I|`` of a pose's rotation block taken as a rotation: files with 6 significant digits
#: round off about 1e-6; a scaled, sheared or zero block is off by far more.
ROTATION_TOLERANCE = 1e-3
#: Largest pose translation (m) taken as a position: beyond Earth-centred coordinates (6.4e6 m), a unit error.
MAX_TRANSLATION_M = 1e8


def rigid_problem(poses: np.ndarray) -> tuple[int, str] | None:
    """The first (N, 4, 4) pose that is no rigid motion and why: not finite, a bottom row other than (0, 0, 0, 1),
    a rotation block that is not orthonormal (`ROTATION_TOLERANCE`) or a reflection (det < 0), a translation beyond
    `MAX_TRANSLATION_M`; None when every pose is one."""
    P = np.asarray(poses, dtype=np.float64)
    if P.shape[0] == 0:
        return None
    finite = np.isfinite(P).all(axis=(1, 2))
    if not finite.all():
        return int(np.argmin(finite)), "contains NaN or inf"
    bottom = np.abs(P[:, 3, :] - [0.0, 0.0, 0.0, 1.0]).max(axis=1) > 1e-9
    if bottom.any():
        return int(
            np.argmax(bottom)
        ), f"bottom row {P[int(np.argmax(bottom)), 3].tolist()}, expected [0, 0, 0, 1]"
    R = P[:, :3, :3]
    off = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
    if (off > ROTATION_TOLERANCE).any():
        i = int(np.argmax(off > ROTATION_TOLERANCE))
        return (
            i,
            f"rotation block is not a rotation (max |R^T R - I| = {off[i]:.3g} > {ROTATION_TOLERANCE:g})",
        )
    det = np.linalg.det(R)
    if (det < 0).any():
        return int(
            np.argmax(det < 0)
        ), f"rotation block is a reflection (det {det[int(np.argmax(det < 0))]:.3g})"
    far = np.abs(P[:, :3, 3]).max(axis=1) > MAX_TRANSLATION_M
    if far.any():
        return int(np.argmax(far)), f"translation beyond {MAX_TRANSLATION_M:g} m"
    return None


def check_poses(poses: np.ndarray, n: int | None, where: str) -> np.ndarray:
    """``poses`` as (N, 4, 4) float64 rigid motions (`rigid_problem`), ``n`` of them when given; `ScanDataError`
    naming ``where`` and the first bad pose otherwise."""
    P = np.asarray(poses, dtype=np.float64)
    if P.ndim != 3 or P.shape[1:] != (4, 4):
        raise ScanDataError(f"{where}: poses must have shape (N, 4, 4), got {P.shape}")
    if n is not None and P.shape[0] != n:
        raise ScanDataError(f"{where}: {P.shape[0]} poses for {n} scans")
    problem = rigid_problem(P)
    if problem is not None:
        raise ScanDataError(f"{where}: pose {problem[0]} is no rigid motion: {problem[1]}")
    return P


#: Points at or beyond this range (m) are not returns of any LiDAR (e.g. 1e30 fill values) and count as invalid.
MAX_RANGE_M = 1e4
#: Points closer than this (m) sit at the origin: how organised scans mark a beam without return.
MIN_RETURN_M = 1e-6


def valid_points(scan: Scan, intensity: bool = False, ranges: np.ndarray | None = None) -> np.ndarray:
    """Mask of the points that are real returns: finite, not at the origin (organised scans' invalid returns),
    closer than `MAX_RANGE_M`; with ``intensity`` also a finite intensity. The one definition every stage uses.
    ``ranges``: ``scan.ranges`` where the caller has computed them already."""
    r = scan.ranges if ranges is None else ranges
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(r) & (r > MIN_RETURN_M) & (r < MAX_RANGE_M)
    return ok & np.isfinite(scan.intensity) if intensity else ok


def take_rows(a: np.ndarray, index: np.ndarray) -> np.ndarray:
    """``a[index]`` for the rows of a 2D array (``index``: boolean mask or integers), each row copied as one block
    of bytes when ``a`` is C-contiguous: the same array, several times faster than numpy's row-wise indexing of
    narrow rows (an (N, 3) float32 array: ~2 ms -> ~0.3 ms for 120k rows)."""
    if a.ndim != 2 or not a.flags.c_contiguous or a.shape[1] == 0:
        return a[index]
    row = np.dtype((np.void, a.shape[1] * a.itemsize))
    return a.view(row).reshape(-1)[index].view(a.dtype).reshape(-1, a.shape[1])


def path_length(positions: np.ndarray) -> np.ndarray:
    """(N,) cumulative distance travelled along the trajectory (0 at the first position)."""
    p = np.asarray(positions, dtype=np.float64)
    if p.ndim != 2 or p.shape[0] == 0:
        return np.zeros(p.shape[0] if p.ndim else 0)
    steps = np.linalg.norm(np.diff(p, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def interpolate_trajectory(stamps: np.ndarray, poses: np.ndarray, at: np.ndarray) -> np.ndarray:
    """(Q, 4, 4) poses at times ``at`` on the trajectory through ``poses`` (K, 4, 4) at strictly increasing
    ``stamps`` (K,): between two knots the translation is linear and the rotation turns along the rotation vector
    of the relative rotation (slerp); before the first / after the last knot the end segment is extrapolated; a
    single knot is a constant pose. The keyframes' de-skew and the simulator's scans taken while moving both ride
    on it. (`placerec.io.datasets.trajectory.interpolate_poses` interpolates ground truth and refuses times outside
    it; these must extrapolate.)"""
    from scipy.spatial.transform import Rotation

    at = np.asarray(at, dtype=np.float64)
    out = np.empty((at.size, 4, 4))
    if len(stamps) == 1:
        out[:] = poses[0]
        return out
    seg = np.clip(np.searchsorted(stamps, at, side="right") - 1, 0, len(stamps) - 2)
    s = (at - stamps[seg]) / (stamps[seg + 1] - stamps[seg])
    R = poses[:, :3, :3]
    # rotation vector of each segment's relative rotation R_a^T R_b, expressed in frame a
    rotvec = Rotation.from_matrix(np.einsum("kji,kjl->kil", R[:-1], R[1:])).as_rotvec()
    step = Rotation.from_rotvec(s[:, None] * rotvec[seg]).as_matrix()
    out[:, :3, :3] = R[seg] @ step
    p = poses[:, :3, 3]
    out[:, :3, 3] = p[seg] + s[:, None] * (p[seg + 1] - p[seg])
    out[:, 3] = (0.0, 0.0, 0.0, 1.0)
    return out


def relative_pose(T_world_match: np.ndarray, T_world_query: np.ndarray) -> np.ndarray:
    """``T_match_query``: maps query-frame points into the match frame (see module docstring)."""
    return np.linalg.inv(as_pose(T_world_match)) @ as_pose(T_world_query)


@dataclass(frozen=True)
class Verification:
    """The outcome of verifying one candidate.

    ``T_match_query``: 4x4 (the ICP result, refined when accepted with ``refine.enabled``; the RANSAC pose, or the
    initial guess, when rejected before ICP).
    ``score`` in [0, 1] (0 when rejected before ICP), ``accepted`` by ``params.score.acceptance``.
    ``inliers``: RANSAC inliers among all given pairs (with grouping: of the best cluster's pose, refit on them;
    None for ICP-only), ``correspondences``: pairs given. ``fitness``, ``rmse`` (m), ``residual`` (m^2, the eps_ICP
    quantity): ICP statistics of the judged pose (NaN when ICP did not run). ``rejected_at``: the stage that ended
    it early (``grouping``, ``ransac``) or None. ``timings_ms``: per stage (``prepare``, ``grouping``, ``ransac``,
    ``icp``, ``refine`` when the accepted pose was refined, ``total``). ``inlier_mask``: over the given
    correspondences, those RANSAC kept (None for ICP-only). ``rejection``: why it was rejected, one of
    `REJECTIONS`' keys (None when accepted). ``constraint``: how well the overlap pins the translation down
    (`placerec.verify.icp.alignment_stats`; NaN unless ``score.min_constraint`` asked for it).
    """

    T_match_query: np.ndarray
    score: float
    accepted: bool
    inliers: int | None
    correspondences: int
    fitness: float
    rmse: float
    residual: float
    ransac_iterations: int = 0
    icp_iterations: int = 0
    rejected_at: str | None = None
    timings_ms: dict[str, float] = field(default_factory=dict)
    inlier_mask: np.ndarray | None = None
    rejection: str | None = None
    constraint: float = math.nan

    def as_dict(self) -> dict[str, Any]:
        """Scalars only (for a Candidate's ``extra`` or a CSV row); ``constraint`` only where it was measured."""
        extra = {"constraint": self.constraint} if math.isfinite(self.constraint) else {}
        return {
            "score": self.score,
            "accepted": self.accepted,
            "inliers": self.inliers,
            "correspondences": self.correspondences,
            "fitness": self.fitness,
            "rmse": self.rmse,
            "residual": self.residual,
            "ransac_iterations": self.ransac_iterations,
            "icp_iterations": self.icp_iterations,
            "rejected_at": self.rejected_at,
            "rejection": self.rejection,
            **extra,
            **{f"ms_{k}": v for k, v in self.timings_ms.items()},
        }


#: Why verification rejects a candidate (`Verification.rejection`), the stages in the order they are applied.
REJECTIONS: dict[str, str] = {
    "grouping": "too few consistent correspondences",
    "ransac": "too few RANSAC inliers",
    "rank": "not refined: ICP was spent on better candidates",
    "coarse_fitness": "ICP from a rough guess: the coarse stages' overlap below verify.icp_only_min_coarse_fitness",
    "fitness": "ICP overlap (fitness) below min_fitness",
    "fitness_ratio": "ICP overlap below min_fitness_ratio of what a right alignment overlaps at that displacement",
    "constraint": "the overlap leaves the translation free along a direction (constraint below min_constraint)",
    "score": "verified score below min_score",
    "residual": "ICP residual above eps_icp",
    "guided_score": "posed from the matches a motion prior allows, its verified score below verify.guided.min_score",
}


@dataclass(frozen=True)
class Candidate:
    """One answer of a place recognizer to a query.

    ``query_id`` is the id of the query scan, ``match_id`` the id under which the matched scan (or place) was
    added. ``score``: higher is more confident; its scale is the recognizer's own (documented per recognizer) and
    thresholds are applied on it. ``relative_pose`` is ``T_match_query`` (4x4) when the recognizer estimates one
    (Scan Context gives a yaw-only rotation), else None. ``inliers`` counts the supporting correspondences when the
    recognizer verifies geometrically.

    What a verifying recognizer decided is typed: ``accepted`` (True / False; None when the recognizer does not
    verify), ``verification`` (the `Verification`: statistics and, when rejected, the stage that rejected it),
    ``retrieval_score`` (the score that ranked the candidate before verification), ``verify_ms`` (milliseconds
    spent verifying it, its share of the verification stage) and ``T_world_query`` (the query's pose in the map
    when the recognizer knows the matched entry's pose). ``matches`` (M, 2) int32: the (query feature, match
    feature) indices of the correspondences verification was given, row-aligned with
    ``verification.inlier_mask`` (for the visual pipelines the indices of the descriptions' ``keypoints``); None
    when it verified without feature correspondences. ``extra`` holds recognizer-specific diagnostics only:
    nothing outside the recognizer depends on them.
    """

    query_id: int
    match_id: int
    score: float
    relative_pose: np.ndarray | None = None
    inliers: int | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    accepted: bool | None = None
    verification: Verification | None = None
    retrieval_score: float | None = None
    verify_ms: float = 0.0
    T_world_query: np.ndarray | None = None
    matches: np.ndarray | None = None

    @property
    def rejection(self) -> str | None:
        """Why verification rejected this candidate: its `Verification.rejection` (a key of `REJECTIONS`), or
        ``"rejected"`` when it names none; None when the candidate was accepted or not verified."""
        if self.accepted is not False:
            return None
        v = self.verification
        return (v.rejection if v is not None else None) or "rejected"


#: A scan's description by a recognizer's front end: named NumPy arrays (so it can be cached as ``.npz``).
Description = dict[str, np.ndarray]


@dataclass(frozen=True)
class Prediction:
    """Where a caller's odometry puts a query relative to one earlier place: the predicted ``T_match_query`` and how
    far a closure may differ from it (``metres``, ``radians``) and still agree with the odometry."""

    T_match_query: np.ndarray
    metres: float
    radians: float


class MotionPrior(Protocol):
    """What a caller with odometry knows about a query's motion (`placerec.odometry_gate.ChainPrior`): the
    `Prediction` against database entry ``match_id``, or None where it has none; and the entries it predicts
    within ``metres`` of the query with a translation bound of at most ``reach``, nearest first. A recognizer may
    use it to choose which features to compare and which places to register (`placerec.verify.guided`); it never
    decides acceptance."""

    def predict(self, match_id: int) -> Prediction | None: ...

    def near(self, metres: float, reach: float) -> list[tuple[int, Prediction]]: ...


@runtime_checkable
class PlaceRecognizer(Protocol):
    """The one interface every pipeline, baseline and peer adapter implements (`placerec.recognizer.Recognizer`
    is its base class, which derives ``add``/``query`` from the three primitives).

    A recognizer is a *front end* that turns a scan into a `Description` and a *database* of descriptions, kept
    apart so descriptions can be computed once, cached and shared:

    * ``frontend_key`` identifies the front end and its parameters: equal keys give identical descriptions.
    * ``describe(scan)`` is the front end; a scan it cannot describe (blank, a few points) is a `ScanDataError`.
    * ``add_description(scan_id, description, pose=None)`` inserts under ``scan_id`` (unique, caller-chosen).
    * ``query_description(description, k=1, max_id=None, query_id=-1, prior=None)`` returns up to ``k``
      candidates, best first, among database entries with ``id <= max_id`` (all entries when None). Loop-closure
      callers number scans in acquisition order, so the exclusion window of recent frames becomes one bound. It
      never modifies the database; ``query_id`` is only copied into the returned candidates. ``prior`` (a
      `MotionPrior`) is what the caller's odometry predicts; a recognizer may ignore it (one without the
      parameter is called without it).
    * ``add(scan_id, scan, pose=None)`` / ``query(scan, ...)``: the same on a scan (``describe`` first).
    * ``save(path)`` / ``load(path)`` persist the database (atomic, versioned; `ArtifactError` on a wrong file).
    """

    @property
    def name(self) -> str: ...

    @property
    def frontend_key(self) -> str: ...

    def describe(self, scan: Scan) -> Description: ...

    def add_description(
        self, scan_id: int, description: Description, pose: np.ndarray | None = None
    ) -> None: ...

    def query_description(
        self,
        description: Description,
        k: int = 1,
        max_id: int | None = None,
        query_id: int = -1,
        prior: MotionPrior | None = None,
    ) -> list[Candidate]: ...

    def add(self, scan_id: int, scan: Scan, pose: np.ndarray | None = None) -> None: ...

    def query(
        self, scan: Scan, k: int = 1, max_id: int | None = None, query_id: int = -1
    ) -> list[Candidate]: ...

    def save(self, path: str | Path) -> None: ...

    def load(self, path: str | Path) -> None: ...
