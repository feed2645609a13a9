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
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass

import numpy as np

from placerec.errors import ConfigError
from placerec.types import SensorInfo

__all__ = ["SensorModel", "RayGrid", "SENSORS", "get_sensor", "sensor_names", "ray_grid"]


@dataclass(frozen=True)
class SensorModel:
    """A spinning multi-beam LiDAR.

    ``family`` is ``"velodyne"`` (8-bit intensity: 0..100 diffuse, 101..255 retro-reflective) or ``"ouster"``
    (16-bit range-compensated reflectivity, linear). ``intensity_scale`` is the raw value of a white Lambertian
    target (reflectance 1) at normal incidence and the reference range. ``range_10pct`` is the longest range at
    which a 10 % Lambertian target is still detected (half the time) at normal incidence; darker, farther or more
    oblique surfaces drop out. ``range_compensated`` False simulates a raw *signal* channel that falls ~1/R^2
    (as the 16-bit "intensity" of first-generation Ouster data in MulRan). ``response_gamma`` is the nominal
    exponent of the unit's per-beam response curves (see `placerec.sim.intensity.BeamResponse`).
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

    @property
    def n_beams(self) -> int:
        return len(self.beam_elevations_deg)

    @property
    def intensity_max(self) -> float:
        return float(2**self.intensity_bits - 1)

    @property
    def n_rays(self) -> int:
        return self.n_beams * self.columns

    def to_sensor_info(self) -> SensorInfo:
        """The `SensorInfo` every simulated scan of this sensor carries."""
        return SensorInfo(
            name=self.name,
            beam_elevations_deg=tuple(float(v) for v in self.beam_elevations_deg),
            columns=int(self.columns),
            intensity_max=self.intensity_max,
            min_range=float(self.min_range),
            max_range=float(self.max_range),
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
        mount_height=1.8,
    ),
    "os1-64-gen2": _OS1_GEN2,
    "os1-128": dataclasses.replace(_OS1_GEN2, name="os1-128", beam_elevations_deg=_uniform(22.5, -22.5, 128)),
}

_ALIASES = {
    "os1-64-gen1": "os1-64",
    "vlp-16": "vlp16",
    "hdl-64": "hdl64",
    "hdl64e": "hdl64",
    "os1-128-gen2": "os1-128",
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


@functools.lru_cache(maxsize=16)
def ray_grid(sensor: SensorModel) -> RayGrid:
    """The sensor-frame ray directions of one sweep, in the order the scan stores its points (cached)."""
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
