"""Keyframes: consecutive scans accumulated over a time or distance window into one de-skewed cloud.

LiDARs that are not one 360 deg spinning sweep (Livox rosettes, 120 deg solid-state units) and sparse ones
(VLP-16) see too little of a place in one scan; a keyframe gathers the scans of a window and describes them as
one. docs/keyframes.md gives the config syntax and the measured cost.

Windows
-------
Scans are taken in order; a keyframe starts with the scan after the previous keyframe and *completes on* the first
scan at which its ``n`` scans span ``(x_last - x_first) * n / (n - 1) >= window`` (``x``: timestamps for
``seconds``, the distance travelled along the odometry for ``metres``): the span of their timestamps (or positions)
extended by one mean step, since ``n`` scans at a regular rate cover ``n`` steps. So 10 Hz scans and
``seconds: 0.5`` give 5 scans per keyframe, ``seconds: 0.25`` 3 (at least the window), and a keyframe holds at
least two scans; a gap in the stream (a pause in the data) ends the window it falls in rather than making a
keyframe of one scan. A window also completes after `KeyframeParams.max_scans` scans (a vehicle standing still
travels no metres). The online `KeyframeBuilder` and the offline `KeyframeSequence` apply this one rule
(`_completes`), so they cut a stream into the same keyframes; the scans after the last complete window form a
last, shorter keyframe (``flush`` online).

**Overlapping windows** (`KeyframeParams.every_metres`): instead of starting after the previous keyframe, a
keyframe ends on scan ``j`` when (a) the *trailing* window ending at ``j`` is complete by the rule above (the
shortest run of scans ending at ``j`` that completes; none: no keyframe yet) and (b) the odometry has travelled at
least ``every_metres`` from the previous keyframe's last scan to ``j`` (`placerec.types.path_length`; the first
keyframe: as soon as (a) holds). Its scans are that run, its frame, pose and timestamp scan ``j``'s as always. So
10 Hz scans at 9 m/s with ``seconds: 0.5, every_metres: 1.0`` give keyframes of 5 scans on every second scan
(the first on scan 4), 1.8 m apart (the first scan at least 1 m on) where windows one after another are 4.5 m
apart; each scan is then described in several keyframes (window length / keyframe spacing times the work: 2.5
here). A trailing window never starts before the previous complete one did (so the builder keeps only the scans
from there on; this differs from the shortest run overall only where the progress stalls or jumps: a ``metres``
window at rest, a gap in the data). At rest (no metres travelled) no keyframe follows the first. After the last
keyframe, ``flush`` (and `KeyframeSequence`'s last keyframe) gives one of the trailing scans (those from the start of
the last complete trailing window, or all of them before any) when at least one scan came after that keyframe.
`_overlapping` is the one rule of both.

Frame and de-skew
-----------------
A keyframe is expressed in the frame of its **last scan at that scan's timestamp** (the scan it completes on:
natural online), ``pose`` = that scan's odometry pose ``T_world_keyframe``, ``timestamp`` = its timestamp. A point
of scan ``i`` with per-point time ``t`` (`placerec.types.Scan.time`, seconds since the scan's timestamp) was
measured from the sensor pose at ``stamp_i + t``, `placerec.types.interpolate_trajectory` over the odometry poses of the window
(and of the scan before it): between scan ``i``'s pose and the next scan's (translation linear, rotation along the
rotation vector of the relative motion, i.e. slerp), extrapolated from the previous pair past the window's last
scan (the next scan is not known when the keyframe completes). It is mapped ``T_keyframe_world @ T_world_sensor(t)``.
The pose is evaluated once per `DESKEW_BIN_S` time bin, not per point (tools/bench_keyframes.py measures the
error that costs against exact per-point interpolation). Without ``deskew`` every point of scan ``i`` takes scan
``i``'s pose.

The keyframe's `Scan` has the valid points (`placerec.types.valid_points`) of its scans: ``xyz`` in the keyframe
frame, ``intensity``, ``ring`` when every scan has rings, ``time`` = seconds since the *keyframe's* timestamp (so
mostly negative) when every scan has per-point times, else None; ``sensor`` the scans' `SensorInfo` (the last
scan's); ``source`` names the scan range, e.g. ``"seq[10:15]"``. ``voxel_m`` keeps one point per voxel: the
centroid of its points with their mean intensity (`placerec.preprocess.voxel_downsample`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from pydantic import Field, SerializerFunctionWrapHandler, model_serializer, model_validator

from placerec.errors import ConfigError, ScanDataError
from placerec.params import Params
from placerec.preprocess import voxel_downsample
from placerec.types import (
    Scan,
    Sequence,
    as_pose,
    check_poses,
    interpolate_trajectory,
    path_length,
    valid_points,
)

if TYPE_CHECKING:
    from placerec.slam.odometry import KissIcpOdometry

__all__ = [
    "KeyframeParams",
    "Keyframe",
    "KeyframeBuilder",
    "KeyframeSequence",
    "keyframes_along",
    "DESKEW_BIN_S",
    "MAX_POINT_TIME_S",
    "deskewed_points",
]

log = logging.getLogger(__name__)

#: width (s) of the time bins of the de-skew: points of one bin take the pose at the bin's centre
DESKEW_BIN_S = 2.5e-4
#: largest |per-point time| (s) taken as seconds since the scan's timestamp; beyond it the times are taken to be
#: in another unit (ns, us) or absolute, and the scan is refused rather than extrapolated hours away
MAX_POINT_TIME_S = 10.0
#: relative slack of the window test, so that timestamps 0.1 s apart in binary floating point fill 0.5 s windows
_WINDOW_SLACK = 1e-9


class KeyframeParams(Params):
    """How scans are accumulated into keyframes (module docstring): a window of ``seconds`` or of ``metres``
    travelled (exactly one), de-skewed or not, over which odometry, optionally voxel-downsampled."""

    seconds: float | None = Field(None, gt=0, le=3600, description="window length in seconds (s)")
    metres: float | None = Field(None, gt=0, le=10_000, description="window length in metres travelled (m)")
    deskew: bool = Field(True, description="de-skew every point with the pose at its time (needs Scan.time)")
    odometry: Literal["poses", "kiss-icp"] = Field(
        "poses", description="poses: the odometry poses the caller gives; kiss-icp: KISS-ICP over the scans"
    )
    voxel_m: float | None = Field(
        None,
        gt=0,
        le=100,
        description="voxel (m) of the accumulated cloud: one centroid per voxel (None: off)",
    )
    max_scans: int = Field(
        200, ge=1, le=100_000, description="a window also completes after this many scans (a vehicle at rest)"
    )
    every_metres: float | None = Field(
        None,
        gt=0,
        le=10_000,
        description="one keyframe every this many metres travelled along the odometry, each holding the window"
        " of scans that ends there (overlapping windows); None: windows one after another",
    )

    @model_validator(mode="after")
    def _one_window(self) -> KeyframeParams:
        if (self.seconds is None) == (self.metres is None):
            raise ValueError("give exactly one of keyframes.seconds and keyframes.metres")
        return self

    @model_serializer(mode="wrap")
    def _dump(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        """The fields, without ``every_metres`` when it is None: the dump of windows one after another (the
        description cache key, closures.json) stays what it was before overlapping windows."""
        data: dict[str, Any] = handler(self)
        if self.every_metres is None:
            data.pop("every_metres", None)
        return data

    @property
    def window(self) -> float:
        """The window length, in seconds or metres."""
        value = self.seconds if self.seconds is not None else self.metres
        assert value is not None  # _one_window
        return float(value)


@dataclass(frozen=True, eq=False)
class Keyframe:
    """One keyframe: the accumulated ``scan`` (in the keyframe frame), ``pose`` = odometry ``T_world_keyframe``
    (the last scan's), ``timestamp`` (the last scan's; None when the scans have none) and ``scan_indices`` (the
    indices of its scans, in order)."""

    scan: Scan
    pose: np.ndarray
    timestamp: float | None
    scan_indices: tuple[int, ...]


def _completes(params: KeyframeParams, first: float, current: float, n_scans: int) -> bool:
    """Whether the window of ``n_scans`` scans from progress ``first`` to ``current`` is complete (module
    docstring: the span extended by one mean step reaches the window, or ``max_scans`` is reached)."""
    if n_scans >= params.max_scans:
        return True
    if n_scans < 2:
        return False
    span = (current - first) * n_scans / (n_scans - 1)
    return span >= params.window * (1.0 - _WINDOW_SLACK)


def _overlapping(
    params: KeyframeParams, x: Any, lo: int, j: int, travelled: float, last_travelled: float | None
) -> tuple[int | None, bool]:
    """Overlapping windows (module docstring): the start of the shortest run ``lo..j`` of progress ``x`` (indexable)
    that `_completes` (None: none), and whether it makes a keyframe ending on ``j``: complete and ``travelled``
    (distance at ``j``) at least ``every_metres`` past ``last_travelled`` (that at the previous keyframe's last
    scan; None: no keyframe yet)."""
    assert params.every_metres is not None
    current = float(x[j])
    for start in range(j, max(lo, j - params.max_scans + 1) - 1, -1):
        if _completes(params, float(x[start]), current, j - start + 1):
            moved = last_travelled is None or travelled - last_travelled >= params.every_metres * (
                1.0 - _WINDOW_SLACK
            )
            return start, moved
    return None, False


def deskewed_points(
    xyz: np.ndarray,
    time: np.ndarray,
    stamp: float,
    knot_stamps: np.ndarray,
    knot_poses: np.ndarray,
    T_frame_world: np.ndarray,
    bin_s: float | None = DESKEW_BIN_S,
) -> np.ndarray:
    """(N, 3) float32: the points ``xyz`` of a scan taken at ``stamp`` with per-point ``time`` (seconds since
    ``stamp``), each mapped ``T_frame_world @ T_world_sensor(stamp + time)`` with the sensor pose interpolated on the
    knots (`interpolate_trajectory`). With ``bin_s`` the pose is evaluated once per time bin of that width (at its
    centre) and gathered per point; None evaluates it at every point's own time (exact, the reference)."""
    t = np.asarray(time, dtype=np.float64)
    if t.size == 0:
        return np.empty((0, 3), dtype=np.float32)
    at: np.ndarray
    if bin_s is None:
        index = np.arange(t.size)
        at = stamp + t
    else:
        bins = np.floor(t / bin_s).astype(np.int64)
        lo = int(bins.min())
        index = bins - lo
        n_bins = int(index.max()) + 1
        if n_bins > 2 * MAX_POINT_TIME_S / bin_s + 1:  # one pose per bin: bounded with the times
            raise ScanDataError(f"time: per-point times span more than {2 * MAX_POINT_TIME_S:g} s")
        at = stamp + (lo + np.arange(n_bins, dtype=np.float64) + 0.5) * bin_s
    M = T_frame_world @ interpolate_trajectory(knot_stamps, knot_poses, at)
    M32 = M[:, :3, :].astype(np.float32)
    A = M32[index]
    return np.einsum("nij,nj->ni", A[:, :, :3], xyz) + A[:, :, 3]


def _where(scan: Scan, index: int | None) -> str:
    return scan.source or (f"scan {index}" if index is not None else "scan")


def _check_point_times(scan: Scan, index: int | None) -> None:
    """`ScanDataError` unless the scan's per-point times are present, finite and within `MAX_POINT_TIME_S`."""
    if scan.time is None:
        raise ScanDataError(
            f"{_where(scan, index)}: time: de-skew (keyframes.deskew) needs per-point times (Scan.time)"
        )
    t = scan.time
    if t.size and not (np.isfinite(t).all() and float(np.abs(t).max()) <= MAX_POINT_TIME_S):
        raise ScanDataError(
            f"{_where(scan, index)}: time: per-point times must be finite seconds since the scan's timestamp,"
            f" within +-{MAX_POINT_TIME_S:g} s"
        )


def _assemble(
    params: KeyframeParams,
    scans: list[Scan],
    indices: list[int],
    stamps: np.ndarray | None,
    poses: np.ndarray,
    before: tuple[float, np.ndarray] | None,
    label: str,
) -> Keyframe:
    """The keyframe of ``scans`` (already checked; their valid points only) at ``stamps`` with odometry ``poses``;
    ``before`` = (stamp, pose) of the scan before the window (a de-skew knot), when there is one."""
    T_world_kf = poses[-1]
    T_kf_world = np.linalg.inv(T_world_kf)
    if params.deskew:
        assert stamps is not None  # checked by the callers: de-skew needs timestamps
        knot_stamps, knot_poses = stamps, poses
        if before is not None:
            knot_stamps = np.r_[before[0], stamps]
            knot_poses = np.concatenate([before[1][None], poses])
    xyz_parts = []
    for k, scan in enumerate(scans):
        if params.deskew:
            assert stamps is not None and scan.time is not None
            xyz_parts.append(
                deskewed_points(scan.xyz, scan.time, float(stamps[k]), knot_stamps, knot_poses, T_kf_world)
            )
        else:
            M = (T_kf_world @ poses[k]).astype(np.float32)
            xyz_parts.append(scan.xyz @ M[:3, :3].T + M[:3, 3])
    has_ring = all(s.ring is not None for s in scans)
    has_time = stamps is not None and all(s.time is not None for s in scans)
    time = None
    if has_time:
        assert stamps is not None
        time = np.concatenate(
            [
                s.time + np.float32(stamps[k] - stamps[-1])
                for k, s in enumerate(scans)
                if s.time is not None  # every one (has_time)
            ]
        )
    cloud = Scan(
        xyz=np.concatenate(xyz_parts) if xyz_parts else np.empty((0, 3), np.float32),
        intensity=np.concatenate([s.intensity for s in scans]),
        ring=np.concatenate([s.ring for s in scans if s.ring is not None]) if has_ring else None,
        time=time,
        sensor=scans[-1].sensor,
        timestamp=None if stamps is None else float(stamps[-1]),
        source=f"{label}[{indices[0]}:{indices[-1] + 1}]",
    )
    if params.voxel_m is not None and len(cloud):
        cloud = voxel_downsample(cloud, params.voxel_m)
    return Keyframe(cloud, T_world_kf.copy(), None if stamps is None else float(stamps[-1]), tuple(indices))


def _needs_timestamps(params: KeyframeParams) -> str | None:
    """Why keyframes of ``params`` need timestamps (None: they do not)."""
    if params.seconds is not None:
        return "windows of keyframes.seconds"
    if params.deskew:
        return "keyframes.deskew"
    return None


def _kiss_icp(origin: np.ndarray | None) -> KissIcpOdometry:
    """KISS-ICP odometry (its defaults) starting at ``origin``; imported here, the SLAM extra being optional."""
    from placerec.slam.odometry import KissIcpOdometry

    return KissIcpOdometry(origin=origin)


class KeyframeBuilder:
    """Accumulates a stream of scans into keyframes online (module docstring).

    ``add(scan, odometry_pose, index)`` returns the `Keyframe` that ``scan`` completes, else None; ``flush()``
    returns the keyframe of the scans added since (None when there are none). With ``every_metres`` (overlapping
    windows) the builder holds the scans from the start of the last complete trailing window on, and ``flush()``
    returns the keyframe of those held scans when at least one scan was added since the last keyframe, else None
    (it keeps them: the stream may go on). With ``odometry: poses`` every scan
    needs its ``odometry_pose`` (``T_world_sensor``, e.g. from the SLAM front end); with ``kiss-icp`` the builder
    registers the scans with `placerec.slam.odometry.KissIcpOdometry` (starting at the first given pose, else the
    identity) and ignores later given poses. ``index`` (default: a running count) names the scan in
    ``Keyframe.scan_indices``. ``timestamp`` overrides ``scan.timestamp``. A scan refused (`ScanDataError` naming the
    field and the scan) changes nothing.
    """

    def __init__(self, params: KeyframeParams, label: str = "keyframe") -> None:
        self.params = params
        self.label = label
        self._scans: list[Scan] = []
        self._indices: list[int] = []
        self._stamps: list[float] = []
        self._poses: list[np.ndarray] = []
        self._first_x = 0.0
        self._last_stamp: float | None = None
        self._last_pose: np.ndarray | None = None
        self._before: tuple[float, np.ndarray] | None = None
        self._count = 0
        self._icp: KissIcpOdometry | None = None
        self._travelled = 0.0  # along the odometry, at the last scan
        # overlapping windows (every_metres): progress of the held scans, distance travelled at the last keyframe's
        # last scan and the count of scans added since the last keyframe
        self._xs: list[float] = []
        self._keyframe_travelled: float | None = None
        self._since = 0

    @property
    def pending(self) -> tuple[int, ...]:
        """Indices of the scans added since the last keyframe (overlapping windows: those of them still held)."""
        if self.params.every_metres is not None:
            return tuple(self._indices[len(self._indices) - min(self._since, len(self._indices)) :])
        return tuple(self._indices)

    def add(
        self,
        scan: Scan,
        odometry_pose: np.ndarray | None = None,
        index: int | None = None,
        timestamp: float | None = None,
    ) -> Keyframe | None:
        """Add the next scan; the keyframe it completes, else None."""
        p = self.params
        index = self._count if index is None else int(index)
        stamp = scan.timestamp if timestamp is None else timestamp
        where = _where(scan, index)
        if stamp is not None and not np.isfinite(stamp):
            raise ScanDataError(f"{where}: timestamp must be finite, got {stamp}")
        needs = _needs_timestamps(p)
        if needs is not None and stamp is None:
            raise ScanDataError(f"{where}: timestamp: {needs} need the scan's timestamp")
        if self._count and (stamp is None) != (self._last_stamp is None):
            raise ScanDataError(f"{where}: timestamp: every scan of a stream has one, or none does")
        if stamp is not None and self._last_stamp is not None and not stamp > self._last_stamp:
            raise ScanDataError(
                f"{where}: timestamp {stamp} does not increase (the scan before was at {self._last_stamp})"
            )
        if p.deskew:
            _check_point_times(scan, index)
        keep = valid_points(scan)
        points = scan.select(keep)
        if p.odometry == "poses":
            if odometry_pose is None:
                raise ScanDataError(
                    f"{where}: odometry_pose: keyframes (odometry: poses) need every scan's pose"
                )
            pose = as_pose(odometry_pose, what=f"{where}: odometry_pose")
        else:
            if self._icp is None:
                origin = (
                    None if odometry_pose is None else as_pose(odometry_pose, what=f"{where}: odometry_pose")
                )
                self._icp = _kiss_icp(origin)
            pose = self._icp.register(scan)
        # checked: from here on nothing raises
        step = 0.0 if self._last_pose is None else float(np.linalg.norm(pose[:3, 3] - self._last_pose[:3, 3]))
        self._travelled += step  # as `placerec.types.path_length` sums it
        if p.seconds is not None:
            assert stamp is not None  # _needs_timestamps
            x = float(stamp)
        else:
            x = self._travelled
        if not self._scans:
            self._first_x = x
        self._scans.append(points)
        self._indices.append(index)
        self._stamps.append(float(stamp) if stamp is not None else float("nan"))
        self._poses.append(pose)
        self._last_stamp, self._last_pose = stamp, pose
        self._count += 1
        if p.every_metres is not None:
            return self._add_overlapping(x, stamp)
        if _completes(p, self._first_x, x, len(self._scans)):
            return self.flush()
        return None

    def _add_overlapping(self, x: float, stamp: float | None) -> Keyframe | None:
        """`add`'s end with overlapping windows (``every_metres``; module docstring): the scan just held, at
        progress ``x``, ends a keyframe or not; the scans before the last complete trailing window are dropped."""
        self._xs.append(x)
        self._since += 1
        start, make = _overlapping(
            self.params, self._xs, 0, len(self._xs) - 1, self._travelled, self._keyframe_travelled
        )
        if start:  # no later window starts before this complete one: drop the scans before it
            if stamp is not None:
                self._before = (self._stamps[start - 1], self._poses[start - 1])
            for held in (self._scans, self._indices, self._stamps, self._poses, self._xs):
                del held[:start]
        return self._emit() if make else None

    def _emit(self) -> Keyframe:
        """Overlapping windows: the keyframe of the held scans, ending on the last one."""
        stamps = None if self._last_stamp is None else np.asarray(self._stamps)
        keyframe = _assemble(
            self.params, self._scans, self._indices, stamps, np.stack(self._poses), self._before, self.label
        )
        self._keyframe_travelled = self._travelled
        self._since = 0
        return keyframe

    def flush(self) -> Keyframe | None:
        """The keyframe of the scans added since the last one (None when there are none); starts a new window.
        With ``every_metres``: the keyframe of the held trailing scans when a scan was added since the last
        keyframe, else None (class docstring)."""
        if self.params.every_metres is not None:
            return self._emit() if self._since else None
        if not self._scans:
            return None
        stamps = None if self._last_stamp is None else np.asarray(self._stamps)
        keyframe = _assemble(
            self.params, self._scans, self._indices, stamps, np.stack(self._poses), self._before, self.label
        )
        if stamps is not None:
            self._before = (float(stamps[-1]), self._poses[-1])
        self._scans, self._indices, self._stamps, self._poses = [], [], [], []
        return keyframe


class KeyframeSequence:
    """The keyframes of a `placerec.types.Sequence`, as a `Sequence` (module docstring).

    ``odometry_poses`` (N, 4, 4) are the odometry of ``sequence``'s scans (``odometry: poses``; e.g. a simulator's
    drifting ``odometry_poses``, or the sequence's own poses); with ``odometry: kiss-icp`` KISS-ICP runs once over
    every scan here (about 17 ms per VLP-16 scan: docs/keyframes.md) from the sequence's first pose. The windows
    are computed once, here; ``seq[k]`` builds keyframe ``k``'s scan from its scans (``prepare``, e.g. the
    experiment's preprocessing, is applied to every scan first). ``poses`` / ``timestamps`` are the *source
    sequence's* (ground truth) of each keyframe's last scan, so an evaluation of keyframes is that of those scans;
    `keyframe_poses` the odometry ones. Bad input is a `ScanDataError` naming the field and the sequence.
    """

    def __init__(
        self,
        sequence: Sequence,
        params: KeyframeParams,
        odometry_poses: np.ndarray | None = None,
        prepare: Callable[[Scan], Scan] | None = None,
    ) -> None:
        self.base = sequence
        self.params = params
        self.prepare = prepare
        name = sequence.name
        n = len(sequence)
        stamps = sequence.timestamps
        if stamps is not None:
            stamps = np.asarray(stamps, dtype=np.float64).reshape(-1)
            if stamps.shape[0] != n:
                raise ScanDataError(f"{name}: timestamps: {stamps.shape[0]} for {n} scans")
            if not np.isfinite(stamps).all():
                raise ScanDataError(f"{name}: timestamps must be finite")
            bad = np.flatnonzero(np.diff(stamps) <= 0)
            if bad.size:
                i = int(bad[0]) + 1
                raise ScanDataError(
                    f"{name}: timestamps must increase: scan {i} at {stamps[i]} after {stamps[i - 1]}"
                )
        needs = _needs_timestamps(params)
        if needs is not None and stamps is None:
            raise ScanDataError(f"{name}: timestamps: {needs} need the sequence's timestamps")
        self._stamps = stamps
        if params.odometry == "kiss-icp":
            odometry_poses = self._kiss_icp(sequence)
        elif odometry_poses is None:
            raise ScanDataError(
                f"{name}: odometry_poses: keyframes (odometry: poses) need the scans' odometry"
            )
        self._odometry = check_poses(odometry_poses, n, f"{name}: odometry_poses")
        self._windows = self._cut(n)
        self._ref = np.array([w[-1] for w in self._windows], dtype=np.int64)

    def _kiss_icp(self, sequence: Sequence) -> np.ndarray:
        poses = sequence.poses
        icp = _kiss_icp(None if poses is None or not len(poses) else poses[0])
        return np.stack([icp.register(self._source(i)) for i in range(len(sequence))])

    def _cut(self, n: int) -> list[list[int]]:
        """The windows (lists of scan indices) of the whole sequence, by `_completes` (`_overlapping` with
        ``every_metres``)."""
        p = self.params
        travelled = path_length(self._odometry[:, :3, 3])
        if p.seconds is not None:
            assert self._stamps is not None
            x = self._stamps
        else:
            x = travelled
        windows: list[list[int]] = []
        if p.every_metres is not None:
            lo, last_end, last_travelled = 0, -1, None
            for j in range(n):
                start, make = _overlapping(p, x, lo, j, float(travelled[j]), last_travelled)
                if start is not None:
                    lo = start
                if make:
                    windows.append(list(range(lo, j + 1)))
                    last_end, last_travelled = j, float(travelled[j])
            if last_end < n - 1:  # scans after the last keyframe: one of the trailing scans (``flush``)
                windows.append(list(range(lo, n)))
            return windows
        current: list[int] = []
        for j in range(n):
            current.append(j)
            if _completes(p, float(x[current[0]]), float(x[j]), len(current)):
                windows.append(current)
                current = []
        if current:
            windows.append(current)
        return windows

    def _source(self, i: int) -> Scan:
        scan = self.base[i]
        return scan if self.prepare is None else self.prepare(scan)

    def __len__(self) -> int:
        return len(self._windows)

    def __getitem__(self, index: int) -> Scan:
        return self.keyframe(index).scan

    def keyframe(self, index: int) -> Keyframe:
        """Keyframe ``index`` (its scan built from the source scans)."""
        k = int(index)
        if k < 0:
            k += len(self)
        if not 0 <= k < len(self):
            raise IndexError(f"{self.name}: keyframe index {index} out of range for {len(self)} keyframes")
        window = self._windows[k]
        scans = []
        for i in window:
            scan = self._source(i)
            if self.params.deskew:
                _check_point_times(scan, i)
            scans.append(scan.select(valid_points(scan)))
        stamps = None if self._stamps is None else self._stamps[window]
        before = None
        if window[0] > 0 and self._stamps is not None:
            before = (float(self._stamps[window[0] - 1]), self._odometry[window[0] - 1])
        return _assemble(self.params, scans, window, stamps, self._odometry[window], before, self.base.name)

    def scan_indices(self, index: int) -> tuple[int, ...]:
        """Indices (in the source sequence) of keyframe ``index``'s scans."""
        return tuple(self._windows[index])

    @property
    def reference_indices(self) -> np.ndarray:
        """(K,) index of each keyframe's last scan (its frame, pose and timestamp)."""
        return self._ref

    @property
    def keyframe_poses(self) -> np.ndarray:
        """(K, 4, 4) odometry ``T_world_keyframe`` of every keyframe."""
        return self._odometry[self._ref]

    @property
    def poses(self) -> np.ndarray | None:
        poses = self.base.poses
        return None if poses is None else np.asarray(poses)[self._ref]

    @property
    def timestamps(self) -> np.ndarray | None:
        return None if self._stamps is None else self._stamps[self._ref]

    @property
    def name(self) -> str:
        return f"{self.base.name}-keyframes"


def keyframes_along(
    seq: Sequence, params: KeyframeParams, kiss_icp: bool, prepare: Callable[[Scan], Scan] | None = None
) -> KeyframeSequence:
    """The keyframes of a command's SOURCE (``--keyframes-seconds`` / ``--keyframes-metres``: `placerec detect`,
    `placerec localize`): accumulated along its poses (a poses file, or the dataset's own), or along KISS-ICP's
    (``kiss_icp``, the commands' ``--odometry kiss-icp``); de-skewed when its scans have per-point times (else not,
    with a warning); ``prepare`` applied to each scan first. `ConfigError` when there are no poses to accumulate
    along."""
    if kiss_icp:
        params = params.model_copy(update={"odometry": "kiss-icp"})
    elif seq.poses is None:
        raise ConfigError(
            f"--keyframes-seconds/--keyframes-metres: {seq.name} has no poses to accumulate scans along;"
            " give --poses FILE or --odometry kiss-icp"
        )
    if params.deskew and len(seq) and seq[0].time is None:
        log.warning("%s: scans without per-point times: keyframes accumulated without de-skew", seq.name)
        params = params.model_copy(update={"deskew": False})
    return KeyframeSequence(seq, params, seq.poses, prepare=prepare)
