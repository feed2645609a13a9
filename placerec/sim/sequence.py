"""`SimulatedSequence`: a lazily generated `placerec.types.Sequence` of simulated scans.

Poses and timestamps are computed when the sequence is made (cheap); a scan is rendered only when indexed, and
always the same one for the same (world, sensor, route, seed, index): scan ``i`` draws its noise from an RNG
seeded by ``(seed, i)`` and its clutter from its timestamp, so scans can be generated in any order or in parallel
processes. The world is built once per (preset, world seed) per process and shared by all sequences over it.

With ``sweep_motion=True`` every ray is cast from the sensor pose at that ray's own time (the sensor moves during
the sweep): the pose is interpolated along the route from this scan's pose to the next one's (translation
linearly, rotation along the rotation vector of the relative rotation; extrapolated from the previous step for
the last scan), and the points stay in the sensor frame at their own time, as a driver delivers them. The scan's
pose is the pose at its timestamp, the start of the frame.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from placerec.errors import ConfigError
from placerec.sim.clutter import ClutterConfig
from placerec.sim.intensity import BeamResponse, IntensityModel
from placerec.sim.odometry import OdometryDrift, drift_poses
from placerec.sim.render import Renderer
from placerec.sim.routes import Revisit, Route, make_route
from placerec.sim.sensors import SensorModel, get_sensor
from placerec.sim.world import World, build_world
from placerec.types import Scan, SensorInfo, interpolate_trajectory

__all__ = ["SimulatedSequence", "SequenceSpec", "frame_end_poses"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SequenceSpec:
    """The parameters that fully determine a simulated sequence (recorded in ``simulation.yaml`` by the exporter)."""

    world: str
    world_seed: int
    sensor: str
    seed: int
    route: str
    n_scans: int
    clutter: bool
    occluders: bool
    unit_seed: int
    sweep_motion: bool = False

    def as_dict(self) -> dict:
        """The fields (``sweep_motion`` only when set, so the records of static sequences stay what they were)."""
        d = dict(self.__dict__)
        if not d["sweep_motion"]:
            del d["sweep_motion"]
        return d


class SimulatedSequence:
    """Simulated LiDAR scans along a route through a procedural world; implements `placerec.types.Sequence`.

    Parameters
    ----------
    world: a preset name (``town``, ``campus``/``park``, ``industrial``) or a built `World`.
    sensor: a sensor preset (``vlp16``, ``hdl32``, ``hdl64``, ``os1-64`` (gen1), ``os1-64-gen2``, ``os1-128``,
        the Livox-like ``avia`` and ``mid360``, the solid-state ``e1r``) or a `SensorModel` (e.g.
        ``dataclasses.replace(get_sensor("os1-64"), range_compensated=False)``).
    n_scans: number of scans; None = the route's natural length (``default`` town route: ~380 at 1 m).
    seed: seeds everything: the world (unless ``world_seed`` is given), the route's small motions, the per-beam
        response curves (unless ``unit_seed``), and the noise of every scan.
    route: a route kind (``default``, ``loop``, ``long``; see `placerec.sim.routes`) or a `Route` with explicit
        poses and timestamps.
    clutter: dynamic clutter (moving cars, pedestrians, changing parked cars); True, False or a `ClutterConfig`.
    occluders: near-sensor occluders in every scan (the ISHOT paper's occlusion condition).
    odometry_drift: None, True, a relative translation error (e.g. 0.01) or an `OdometryDrift`; enables
        ``odometry_poses``.
    sensor_height: sensor above ground (m); default the sensor preset's mount height.
    spacing / rate_hz: one scan every ``spacing`` metres, or ``rate_hz`` scans per second along the speed profile.
    sweep_motion: render each ray from the sensor pose at its own time (motion distortion, see the module
        docstring); default False: the whole sweep from the scan's pose.
    """

    def __init__(
        self,
        world: str | World = "town",
        sensor: str | SensorModel = "os1-64",
        n_scans: int | None = None,
        seed: int = 0,
        route: str | Route = "default",
        clutter: bool | ClutterConfig = True,
        occluders: bool = False,
        odometry_drift: OdometryDrift | float | bool | None = None,
        sensor_height: float | None = None,
        spacing: float = 1.0,
        rate_hz: float | None = None,
        unit_seed: int | None = None,
        world_seed: int | None = None,
        name: str | None = None,
        sweep_motion: bool = False,
    ) -> None:
        if n_scans is not None and n_scans < 1:
            raise ConfigError(f"sim.n_scans must be >= 1, got {n_scans}")
        self._init_args = dict(world=world, sensor=sensor, n_scans=n_scans, seed=seed, route=route, clutter=clutter,
                               occluders=occluders, odometry_drift=odometry_drift, sensor_height=sensor_height,
                               spacing=spacing, rate_hz=rate_hz, unit_seed=unit_seed, world_seed=world_seed, name=name,
                               sweep_motion=sweep_motion)  # fmt: skip
        self._seed = int(seed)
        self._world = build_world(world, self._seed if world_seed is None else int(world_seed))
        self._sensor = get_sensor(sensor)
        height = self._sensor.mount_height if sensor_height is None else float(sensor_height)
        if isinstance(route, Route):
            self._route = (
                route
                if n_scans is None
                else Route(
                    route.poses[:n_scans],
                    route.timestamps[:n_scans],
                    route.name,
                    [r for r in route.revisits if r.stop <= n_scans],
                    None if route.arc_length is None else route.arc_length[:n_scans],
                    route.plan,
                )
            )
        else:
            self._route = make_route(
                self._world,
                route,
                n_scans=n_scans,
                spacing=spacing,
                rate_hz=rate_hz,
                sensor_height=height,
                seed=self._seed,
            )
        if len(self._route) == 0:
            raise ConfigError("sim: the route has no scans")
        cfg = ClutterConfig() if clutter is True else (clutter or None)
        self._clutter = cfg
        self._occluders = bool(occluders)
        self._unit_seed = self._seed if unit_seed is None else int(unit_seed)
        self._response = BeamResponse.draw(self._sensor, self._unit_seed)
        self._model = IntensityModel.for_sensor(self._sensor)
        self._renderer = Renderer(self._world, self._sensor, self._response, self._model, cfg)
        self._drift = OdometryDrift.coerce(odometry_drift)
        self._odometry = (
            None if self._drift is None else drift_poses(self._route.poses, self._drift, self._seed)
        )
        self._poses = np.ascontiguousarray(self._route.poses, dtype=np.float64)
        self._times = np.ascontiguousarray(self._route.timestamps, dtype=np.float64)
        self._sweep_motion = bool(sweep_motion)
        self._end_poses = (
            frame_end_poses(self._poses, self._times, 1.0 / self._sensor.rotation_hz)
            if self._sweep_motion
            else None
        )
        for arr in (self._poses, self._times):
            arr.setflags(write=False)
        rname = route.name if isinstance(route, Route) else route
        self._name = name or f"sim-{self._world.preset}-{self._sensor.name}-{rname}-s{self._seed}"
        self.spec = SequenceSpec(self._world.preset, self._world.seed, self._sensor.name, self._seed, rname, len(self._route),
                                 cfg is not None, self._occluders, self._unit_seed, self._sweep_motion)  # fmt: skip

    # -- Sequence protocol -------------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self._route)

    def __getitem__(self, index: int) -> Scan:
        if not isinstance(index, (int, np.integer)):
            raise TypeError(f"{self._name}: scans are indexed by int, got {type(index).__name__}")
        i = int(index)
        n = len(self)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(f"{self._name}: scan index {index} out of range for {n} scans")
        end = None if self._end_poses is None else self._end_poses[i]
        return self._renderer.render(
            self._poses[i], float(self._times[i]), self._seed, i, self._occluders, source=f"{self._name}[{i}]",
            pose_end=end,
        )  # fmt: skip

    def __iter__(self):
        for i in range(len(self)):
            yield self[i]

    @property
    def poses(self) -> np.ndarray:
        """Ground-truth ``T_world_sensor`` poses (N, 4, 4)."""
        return self._poses

    @property
    def timestamps(self) -> np.ndarray:
        return self._times

    @property
    def name(self) -> str:
        return self._name

    # -- simulator extras ----------------------------------------------------------------------------------------
    @property
    def sweep_motion(self) -> bool:
        """Whether scans are rendered while moving (each ray from the pose at its own time)."""
        return self._sweep_motion

    @property
    def frame_end_poses(self) -> np.ndarray | None:
        """With ``sweep_motion``: the sensor pose at the end of each scan's frame (N, 4, 4), else None."""
        return self._end_poses

    @property
    def odometry_poses(self) -> np.ndarray | None:
        """Drifting odometry poses (N, 4, 4) when ``odometry_drift`` was given, else None."""
        return self._odometry

    @property
    def sensor_info(self) -> SensorInfo:
        return self._sensor.to_sensor_info()

    @property
    def sensor(self) -> SensorModel:
        return self._sensor

    @property
    def world(self) -> World:
        return self._world

    @property
    def route(self) -> Route:
        return self._route

    @property
    def revisits(self) -> list[Revisit]:
        """Ground-truth revisit segments of the route (see `placerec.sim.routes.find_revisits`)."""
        return self._route.revisits

    @property
    def beam_response(self) -> BeamResponse:
        """The per-beam response curves of this simulated unit (ground truth for intensity calibration)."""
        return self._response

    @property
    def intensity_model(self) -> IntensityModel:
        return self._model

    @property
    def seed(self) -> int:
        return self._seed

    def scan_at(
        self,
        pose: np.ndarray,
        timestamp: float = 0.0,
        index: int = 0,
        occluders: bool | None = None,
        pose_end: np.ndarray | None = None,
    ) -> Scan:
        """Render a scan at an arbitrary pose with this sequence's world, sensor and unit (``pose_end``: the pose
        at the end of the frame, for a scan taken while moving)."""
        occ = self._occluders if occluders is None else occluders
        return self._renderer.render(
            np.asarray(pose, dtype=np.float64),
            float(timestamp),
            self._seed,
            int(index),
            occ,
            source=f"{self._name}@pose",
            pose_end=None if pose_end is None else np.asarray(pose_end, dtype=np.float64),
        )

    def __getstate__(self) -> dict:
        """Pickle the constructor arguments only; the scans are regenerated identically after unpickling."""
        return self._init_args

    def __setstate__(self, state: dict) -> None:
        type(self).__init__(self, **state)

    def __repr__(self) -> str:
        return f"SimulatedSequence({self._name!r}, {len(self)} scans)"


def frame_end_poses(poses: np.ndarray, times: np.ndarray, period: float) -> np.ndarray:
    """The pose ``period`` seconds after each pose along the route through ``poses`` at ``times``
    (`placerec.types.interpolate_trajectory`: translation linear, rotation along the relative rotation vector
    between consecutive poses; past the last pose the last step's motion continues); a lone pose is static."""
    times = np.asarray(times, dtype=np.float64)
    out = interpolate_trajectory(times, np.asarray(poses, dtype=np.float64), times + float(period))
    out.setflags(write=False)
    return out
