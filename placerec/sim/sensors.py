"""LiDAR sensor models: beam layouts, ranges, noise and intensity channels of real sensors.

Ring order: for **every** preset ring 0 is the top beam and ring ``n_beams - 1`` the bottom one, so
``beam_elevations_deg`` is in descending order and an organised scan's row ``r`` holds ring ``r``. (The ROS
``velodyne_pointcloud`` driver numbers rings from the bottom; placerec's simulator does not. Consumers should read
``beam_elevations_deg`` rather than assume an order.)

Azimuth: column ``c`` of ``C`` looks along ``theta_c = pi - 2 pi (c + 0.5) / C`` (column 0 looks backwards, the
azimuth decreases clockwise as seen from above), which is the column convention of the VPR paper's cylindrical
projection (eq. 2): projecting a simulated point with ``u = 0.5 (1 - theta / pi) W`` gives back its column.

Velodyne-like presets produce unorganised scans (invalid returns dropped) in firing order (column by column);
Ouster-like presets produce organised, destaggered ``rows x columns`` scans, row-major, invalid returns all zeros.

Sensors that do not spin (``pattern``): ``"non-repetitive"`` Livox-like rosettes (``avia``, ``mid360``), whose rays
differ from frame to frame (`frame_rays` of the frame index; ``ring`` = laser line), and ``"solid-state"`` rasters
(``e1r``; ``ring`` = raster row). Their scans are unorganised, in firing order, and the scan patterns themselves
live in `placerec.sim.scan_patterns`. The sources of every preset's figures are listed in ``docs/simulator.md``
(section "Sensors"); values not found in a datasheet are marked there and in the comments below as assumptions.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass

import numpy as np

from placerec.errors import ConfigError
from placerec.sim.scan_patterns import raster_rays, rosette_rays, spinning_wedge_rays
from placerec.types import SensorInfo

__all__ = [
    "SensorModel",
    "RayGrid",
    "SENSORS",
    "PATTERNS",
    "get_sensor",
    "sensor_names",
    "ray_grid",
    "frame_rays",
    "frame_index",
]

PATTERNS = ("spinning", "non-repetitive", "solid-state")


@dataclass(frozen=True)
class SensorModel:
    """A LiDAR: a spinning multi-beam sensor, a non-repetitive (Risley prism) scanner or a solid-state raster.

    ``family`` is ``"velodyne"`` (8-bit intensity: 0..100 diffuse, 101..255 retro-reflective) or ``"ouster"``
    (16-bit range-compensated reflectivity, linear). ``intensity_scale`` is the raw value of a white Lambertian
    target (reflectance 1) at normal incidence and the reference range. ``range_10pct`` is the longest range at
    which a 10 % Lambertian target is still detected (half the time) at normal incidence; darker, farther or more
    oblique surfaces drop out. ``range_compensated`` False simulates a raw *signal* channel that falls ~1/R^2
    (as the 16-bit "intensity" of first-generation Ouster data in MulRan). ``response_gamma`` is the nominal
    exponent of the unit's per-beam response curves (see `placerec.sim.intensity.BeamResponse`). ``family``
    ``"livox"`` (8-bit reflectivity: 0..150 diffuse, 151..255 retro-reflective) and ``"robosense"`` (8-bit,
    0..100 diffuse, 101..255 retro) use the same piecewise scheme as Velodyne with their own diffuse scale.

    ``rotation_hz`` is the sweep or frame rate. ``pattern`` is ``"spinning"`` (the beam layout
    ``beam_elevations_deg`` x ``columns`` azimuth steps), ``"non-repetitive"`` or ``"solid-state"``; those have
    no beam layout (``beam_elevations_deg`` empty) and say their field of view: ``horizontal_fov_deg`` (None = 360)
    and ``elevation_fov_deg`` = (up, down). ``lines`` is the number of laser lines (Livox) or raster rows (solid
    state), ``columns`` the raster columns (solid state), ``point_rate`` the points per second of a
    non-repetitive scanner and ``scan_hz`` the two rates of its optics (Risley prisms, or rotor and wedge; see
    `placerec.sim.scan_patterns`). ``describe_pattern`` False keeps the `SensorInfo` of the presets that existed
    before these fields (no pattern, rate or field of view), so their descriptions and hashes are unchanged.
    """

    name: str
    beam_elevations_deg: tuple[float, ...]
    columns: int
    family: str
    min_range: float
    max_range: float
    range_noise_std: float
    intensity_bits: int
    intensity_scale: float
    range_10pct: float
    beam_divergence_mrad: float
    organized: bool
    mount_height: float = 1.8
    rotation_hz: float = 10.0
    range_compensated: bool = True
    degradation_range: float = 30.0
    response_gamma: float = 1.0
    pattern: str = "spinning"
    horizontal_fov_deg: float | None = None
    elevation_fov_deg: tuple[float, float] | None = None
    lines: int = 0
    point_rate: float = 0.0
    scan_hz: tuple[float, float] = (0.0, 0.0)
    describe_pattern: bool = True

    def __post_init__(self) -> None:
        if self.pattern not in PATTERNS:
            raise ConfigError(f"sensor {self.name!r}: pattern {self.pattern!r} is not one of {PATTERNS}")
        if self.pattern == "spinning" and not self.beam_elevations_deg:
            raise ConfigError(f"sensor {self.name!r}: a spinning sensor needs beam_elevations_deg")
        if self.pattern != "spinning" and (self.lines < 1 or self.elevation_fov_deg is None):
            raise ConfigError(
                f"sensor {self.name!r}: a {self.pattern} sensor needs lines and elevation_fov_deg"
            )

    @property
    def n_beams(self) -> int:
        """Beams (spinning), laser lines (non-repetitive) or raster rows (solid state): the ring count."""
        return len(self.beam_elevations_deg) or int(self.lines)

    @property
    def intensity_max(self) -> float:
        return float(2**self.intensity_bits - 1)

    @property
    def n_rays(self) -> int:
        """Rays per frame (before dropouts)."""
        if self.pattern == "non-repetitive":
            lines = self.n_beams
            return lines * int(round(self.point_rate / self.rotation_hz / lines))
        return self.n_beams * self.columns

    def to_sensor_info(self) -> SensorInfo:
        """The `SensorInfo` every simulated scan of this sensor carries."""
        info = SensorInfo(
            name=self.name,
            beam_elevations_deg=tuple(float(v) for v in self.beam_elevations_deg) or None,
            columns=int(self.columns) or None,
            intensity_max=self.intensity_max,
            min_range=float(self.min_range),
            max_range=float(self.max_range),
        )
        if not self.describe_pattern:
            return info
        return dataclasses.replace(
            info,
            pattern=self.pattern,
            horizontal_fov_deg=None if self.horizontal_fov_deg is None else float(self.horizontal_fov_deg),
            elevation_fov_deg=None if self.beam_elevations_deg else self.elevation_fov_deg,
            rate_hz=float(self.rotation_hz),
        )


@dataclass(frozen=True)
class RayGrid:
    """Unit ray directions of one sweep in output order, with each ray's ring and column."""

    directions: np.ndarray  # (N, 3) float32, sensor frame
    ring: np.ndarray  # (N,) int16
    column: np.ndarray  # (N,) int32
    time: np.ndarray  # (N,) float32 seconds since the start of the sweep


def _uniform(top: float, bottom: float, n: int) -> tuple[float, ...]:
    return tuple(round(float(v), 4) for v in np.linspace(top, bottom, n))


def _hdl64_elevations() -> tuple[float, ...]:
    """HDL-64E: an upper block of 32 lasers at ~1/3 deg and a lower block at ~1/2 deg, plus calibration errors.

    The two spacings do not divide the 26.9 deg field evenly, so a uniform cylindrical projection with 64 rows
    leaves some rows empty in the lower half, as in KITTI. Per-beam errors (sigma 0.04 deg) are fixed for the
    preset, like a real unit's calibration file.
    """
    upper = np.linspace(2.0, -8.33, 32)
    lower = np.linspace(-8.87, -24.9, 32)
    err = np.random.default_rng(6401).normal(0.0, 0.04, 64)
    err[[0, 63]] = 0.0  # keep the nominal field of view
    elev = np.sort(np.concatenate([upper, lower]) + err)[::-1]
    return tuple(round(float(v), 4) for v in elev)


_OS1_GEN2 = SensorModel(
    name="os1-64-gen2",
    beam_elevations_deg=_uniform(22.5, -22.5, 64),
    columns=1024,
    family="ouster",
    min_range=0.5,
    max_range=120.0,
    range_noise_std=0.015,
    intensity_bits=16,
    intensity_scale=1000.0,
    range_10pct=45.0,
    beam_divergence_mrad=2.5,
    organized=True,
    describe_pattern=False,
    mount_height=1.8,
)

SENSORS: dict[str, SensorModel] = {
    "vlp16": SensorModel(
        name="vlp16",
        beam_elevations_deg=_uniform(15.0, -15.0, 16),
        columns=1800,
        family="velodyne",
        min_range=0.5,
        max_range=100.0,
        range_noise_std=0.015,
        intensity_bits=8,
        intensity_scale=100.0,
        range_10pct=45.0,
        beam_divergence_mrad=3.0,
        organized=False,
        describe_pattern=False,
        mount_height=1.8,
    ),
    "hdl64": SensorModel(
        name="hdl64",
        beam_elevations_deg=_hdl64_elevations(),
        columns=2083,
        family="velodyne",
        min_range=0.9,
        max_range=120.0,
        range_noise_std=0.02,
        intensity_bits=8,
        intensity_scale=255.0,
        range_10pct=50.0,
        beam_divergence_mrad=2.0,
        organized=False,
        describe_pattern=False,
        mount_height=1.73,
        response_gamma=0.5,
    ),
    "os1-64": SensorModel(
        name="os1-64",
        beam_elevations_deg=_uniform(16.6, -16.6, 64),
        columns=1024,
        family="ouster",
        min_range=0.8,
        max_range=120.0,
        range_noise_std=0.02,
        intensity_bits=16,
        intensity_scale=1000.0,
        range_10pct=40.0,
        beam_divergence_mrad=3.0,
        organized=True,
        describe_pattern=False,
        mount_height=1.8,
    ),
    "os1-64-gen2": _OS1_GEN2,
    "os1-128": dataclasses.replace(_OS1_GEN2, name="os1-128", beam_elevations_deg=_uniform(22.5, -22.5, 128)),
    # Velodyne HDL-32E (User's Manual 63-9113): 32 lasers +10.67..-30.67 deg every 1.33 deg, 360 deg, 10 Hz,
    # returns up to 100 m, < 2 cm accuracy. One firing sequence of the 32 lasers takes 46.08 us (manual, "Laser
    # Timing"), i.e. 21 701 per second: 2170 azimuth steps (0.166 deg) per revolution at 10 Hz, ~694 000 points/s.
    # Assumptions (no datasheet figure): 10 % range 50 m, divergence 2.8 mrad, minimum range 1 m (the manual's
    # 5 cm is the packet format's limit; drivers drop returns under ~1 m from the housing).
    "hdl32": SensorModel(
        name="hdl32",
        beam_elevations_deg=_uniform(10.67, -30.67, 32),
        columns=2170,
        family="velodyne",
        min_range=1.0,
        max_range=100.0,
        range_noise_std=0.02,
        intensity_bits=8,
        intensity_scale=100.0,
        range_10pct=50.0,
        beam_divergence_mrad=2.8,
        organized=False,
        mount_height=1.8,
    ),
    # Livox Avia (User Manual v1.0, "Specifications"): non-repetitive FoV 70.4 (h) x 77.2 (v) deg, 240 000
    # points/s, 10 Hz frames, 190 m @ 10 % reflectivity (100 klx), 320 m @ 80 %, range error < 2 cm (1 sigma @
    # 20 m), beam divergence 0.28 x 0.03 deg, 6 laser lines whose repetitive-scan mode covers 70.4 x 4.5 deg (so
    # the lines span 4.5 deg vertically), 8-bit reflectivity (0..150 diffuse, 151..255 retro). Assumptions: the
    # prism rates (not published), blind zone 1 m, degradation beyond 60 m.
    "avia": SensorModel(
        name="avia",
        beam_elevations_deg=(),
        columns=0,
        family="livox",
        min_range=1.0,
        max_range=320.0,
        range_noise_std=0.02,
        intensity_bits=8,
        intensity_scale=150.0,
        range_10pct=190.0,
        beam_divergence_mrad=4.9,
        organized=False,
        degradation_range=60.0,
        pattern="non-repetitive",
        horizontal_fov_deg=70.4,
        elevation_fov_deg=(38.6, 38.6),
        lines=6,
        point_rate=240_000.0,
        scan_hz=(110.3, -68.17),
    ),
    # Livox MID-360 (User Manual v1.0, "Specifications"): 360 x 59 deg (elevation -7..+52), 200 000 points/s,
    # 10 Hz, 40 m @ 10 %, 70 m @ 80 %, blind zone 0.1 m, range precision <= 2 cm (1 sigma @ 10 m), 8-bit
    # reflectivity as the Avia. Assumptions: 4 lines (the brief's figure), rotor and wedge rates, divergence.
    "mid360": SensorModel(
        name="mid360",
        beam_elevations_deg=(),
        columns=0,
        family="livox",
        min_range=0.1,
        max_range=70.0,
        range_noise_std=0.02,
        intensity_bits=8,
        intensity_scale=150.0,
        range_10pct=40.0,
        beam_divergence_mrad=4.0,
        organized=False,
        mount_height=1.8,
        pattern="non-repetitive",
        horizontal_fov_deg=None,
        elevation_fov_deg=(52.0, 7.0),
        lines=4,
        point_rate=200_000.0,
        scan_hz=(23.61, 157.3),
    ),
    # RoboSense E1R (product specification): 120 (h, -60..+60) x 90 (v, -45..+45) deg, 30 m @ 10 % NIST target,
    # 10 Hz, ~260 000 points/s (26 000 per frame), average horizontal resolution 0.625 deg (192 columns), blind
    # zone 0.1 m, ranging precision 5 cm (1 sigma). Assumptions: 135 rows (vertical resolution not published:
    # 26 000 / 192), row-by-row read-out, 60 m maximum range, 8-bit intensity 0..100 diffuse / 101..255 retro, a
    # pixel footprint of 10 mrad.
    "e1r": SensorModel(
        name="e1r",
        beam_elevations_deg=(),
        columns=192,
        family="robosense",
        min_range=0.1,
        max_range=60.0,
        range_noise_std=0.05,
        intensity_bits=8,
        intensity_scale=100.0,
        range_10pct=30.0,
        beam_divergence_mrad=10.0,
        organized=False,
        pattern="solid-state",
        horizontal_fov_deg=120.0,
        elevation_fov_deg=(45.0, 45.0),
        lines=135,
    ),
}

_ALIASES = {
    "os1-64-gen1": "os1-64",
    "vlp-16": "vlp16",
    "hdl-64": "hdl64",
    "hdl64e": "hdl64",
    "os1-128-gen2": "os1-128",
    "hdl-32": "hdl32",
    "hdl32e": "hdl32",
    "hdl-32e": "hdl32",
    "livox-avia": "avia",
    "mid-360": "mid360",
    "livox-mid360": "mid360",
    "livox-mid-360": "mid360",
    "rs-e1r": "e1r",
    "robosense-e1r": "e1r",
}


def sensor_names() -> list[str]:
    """Names of the sensor presets."""
    return sorted(SENSORS)


def get_sensor(sensor: str | SensorModel) -> SensorModel:
    """A sensor preset by name (case-insensitive; aliases such as ``os1-64-gen1``), or the model itself."""
    if isinstance(sensor, SensorModel):
        return sensor
    key = str(sensor).lower()
    key = _ALIASES.get(key, key)
    if key not in SENSORS:
        raise ConfigError(f"sim.sensor: unknown sensor preset {sensor!r}; allowed: {sensor_names()}")
    return SENSORS[key]


def frame_index(sensor: SensorModel, timestamp: float) -> int:
    """The frame a scan stamped ``timestamp`` is: frames start at multiples of ``1 / rotation_hz`` from time 0,
    and the scan is the frame whose start is nearest its timestamp."""
    return int(np.floor(float(timestamp) * sensor.rotation_hz + 0.5))


def frame_rays(sensor: SensorModel, frame: int = 0) -> RayGrid:
    """The rays of frame ``frame``: the pattern over ``[frame / rate, (frame + 1) / rate)`` for a non-repetitive
    sensor (cached for the last few frames), the fixed `ray_grid` for the others."""
    if sensor.pattern == "non-repetitive":
        return _pattern_frame(sensor, int(frame))
    return ray_grid(sensor)


@functools.lru_cache(maxsize=8)
def _pattern_frame(sensor: SensorModel, frame: int) -> RayGrid:
    """The rays a non-repetitive sensor fires during frame ``frame`` (``column`` = pulse index in the frame)."""
    period = 1.0 / sensor.rotation_hz
    t0 = frame * period
    fov = sensor.elevation_fov_deg
    assert fov is not None
    if sensor.horizontal_fov_deg is None:  # 360 deg: rotor and wedge (MID-360)
        d, line, time = spinning_wedge_rays(fov[0], fov[1], sensor.n_beams, sensor.point_rate, period, t0,
                                            sensor.scan_hz[0], sensor.scan_hz[1])  # fmt: skip
    else:  # Risley rosette in front (Avia); the lines sit in a vertical column at the centre
        half_v = 0.5 * (fov[0] + fov[1])
        span = 4.5 / half_v  # the lines span 4.5 deg (the Avia's repetitive-mode field is 70.4 x 4.5 deg)
        offs = np.stack(
            [np.zeros(sensor.n_beams), np.linspace(0.5 * span, -0.5 * span, sensor.n_beams)], axis=1
        )
        d, line, time = rosette_rays(0.5 * sensor.horizontal_fov_deg, half_v, sensor.point_rate, period, t0,
                                     sensor.scan_hz, offs)  # fmt: skip
        if fov[0] != fov[1]:  # an off-centre field: tilt the pattern up by the centre's elevation
            d = _tilt(d, 0.5 * (fov[0] - fov[1]))
    pulse = np.arange(len(line), dtype=np.int32) // sensor.n_beams
    return _frozen(RayGrid(directions=d, ring=line, column=pulse, time=time))


def _tilt(d: np.ndarray, deg: float) -> np.ndarray:
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    x, z = d[:, 0].astype(np.float64), d[:, 2].astype(np.float64)
    out = d.copy()
    out[:, 0] = c * x - s * z
    out[:, 2] = s * x + c * z
    return out


def _frozen(grid: RayGrid) -> RayGrid:
    for arr in (grid.directions, grid.ring, grid.column, grid.time):
        arr.setflags(write=False)
    return grid


@functools.lru_cache(maxsize=16)
def ray_grid(sensor: SensorModel) -> RayGrid:
    """The sensor-frame ray directions of one sweep, in the order the scan stores its points (cached).

    Solid-state sensors: their fixed raster; non-repetitive sensors: frame 0 (see `frame_rays`). ``column`` is the
    azimuth step (spinning), the raster column (solid state) or the pulse index in the frame (non-repetitive).
    """
    if sensor.pattern == "non-repetitive":
        return frame_rays(sensor, 0)
    if sensor.pattern == "solid-state":
        fov = sensor.elevation_fov_deg
        assert fov is not None and sensor.horizontal_fov_deg is not None
        d, row, col, time = raster_rays(sensor.horizontal_fov_deg, fov[0], fov[1], sensor.n_beams, sensor.columns,
                                        1.0 / sensor.rotation_hz)  # fmt: skip
        return _frozen(RayGrid(directions=d, ring=row, column=col, time=time))
    elev = np.radians(np.asarray(sensor.beam_elevations_deg, dtype=np.float64))
    cols = np.arange(sensor.columns)
    theta = np.pi - 2.0 * np.pi * (cols + 0.5) / sensor.columns
    if sensor.organized:
        E, A = np.meshgrid(elev, theta, indexing="ij")  # row-major: ring, column
        R, C = np.meshgrid(np.arange(sensor.n_beams), cols, indexing="ij")
    else:
        A, E = np.meshgrid(theta, elev, indexing="ij")  # firing order: column, ring
        C, R = np.meshgrid(cols, np.arange(sensor.n_beams), indexing="ij")
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=-1).reshape(-1, 3)
    col = C.reshape(-1).astype(np.int32)
    grid = RayGrid(
        directions=np.ascontiguousarray(d, dtype=np.float32),
        ring=R.reshape(-1).astype(np.int16),
        column=col,
        time=(col.astype(np.float32) / np.float32(sensor.columns * sensor.rotation_hz)),
    )
    for arr in (grid.directions, grid.ring, grid.column, grid.time):
        arr.setflags(write=False)
    return grid
