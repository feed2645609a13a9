"""placerec's LiDAR simulator: procedural worlds, real sensor beam layouts and a physical intensity model.

It is the default dataset of every placerec config and the test bed of every pipeline::

    from placerec.sim import SimulatedSequence, simulate
    seq = SimulatedSequence(world="town", sensor="os1-64", seed=0)   # ~380 scans, loop with revisits
    scan = seq[0]                                                   # rendered on demand, deterministic
    seq.poses, seq.timestamps, seq.revisits, seq.beam_response      # ground truth
    SimulatedSequence(sensor="avia", sweep_motion=True)             # Livox rosette, rendered while moving
    simulate("town", "hdl64", 200, 0, "out/town_hdl64")             # KITTI-style folder (the CLI's command)
    make_session_pair("town", "vlp16", 0, kind="partial")           # a map drive and a second session

See ``docs/simulator.md`` for the models, presets, file layout and what still differs from real scans.
"""

from __future__ import annotations

import logging

from placerec.sim.clutter import ClutterConfig
from placerec.sim.export import simulate, write_kitti_sequence
from placerec.sim.intensity import BeamResponse, IntensityModel, surface_response
from placerec.sim.localization import CONDITIONS, LocalizationSplit, make_localization_split
from placerec.sim.materials import MATERIALS, M, Material
from placerec.sim.odometry import OdometryDrift
from placerec.sim.presets import PRESETS, preset_names
from placerec.sim.routes import ROUTES, Revisit, Route, find_revisits, make_route
from placerec.sim.sensors import SENSORS, SensorModel, frame_rays, get_sensor, sensor_names
from placerec.sim.sequence import SimulatedSequence
from placerec.sim.sessions import KidnapTrial, SessionPair, kidnap_trials, make_session_pair
from placerec.sim.world import World, build_world

logging.getLogger(__name__).addHandler(logging.NullHandler())

__all__ = [
    "SimulatedSequence",
    "simulate",
    "write_kitti_sequence",
    "make_localization_split",
    "LocalizationSplit",
    "CONDITIONS",
    "make_session_pair",
    "SessionPair",
    "kidnap_trials",
    "KidnapTrial",
    "SensorModel",
    "SENSORS",
    "get_sensor",
    "sensor_names",
    "frame_rays",
    "World",
    "build_world",
    "PRESETS",
    "preset_names",
    "Route",
    "Revisit",
    "ROUTES",
    "make_route",
    "find_revisits",
    "BeamResponse",
    "IntensityModel",
    "surface_response",
    "ClutterConfig",
    "OdometryDrift",
    "M",
    "Material",
    "MATERIALS",
]
