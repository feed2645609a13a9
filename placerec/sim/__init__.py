"""placerec's LiDAR simulator: procedural worlds, real sensor beam layouts and a physical intensity model.

It is the default dataset of every placerec config and the test bed of every pipeline::

    from placerec.sim import SimulatedSequence, simulate
    seq = SimulatedSequence(world="town", sensor="os1-64", seed=0)   # ~380 scans, loop with revisits
    scan = seq[0]                                                   # rendered on demand, deterministic
    seq.poses, seq.timestamps, seq.revisits, seq.beam_response      # ground truth
    SimulatedSequence(sensor="avia", sweep_motion=True)             # Livox rosette, rendered while moving
    simulate("town", "hdl64", 200, 0, "out/town_hdl64")             # KITTI-style folder (the CLI's command)
    make_session_pair("town", "vlp16", 0, kind="partial")           # a map drive and a second session

See ``docs/simulator.md`` for the models, presets, file layout and what still differs from real scans. Names
are imported on first use, so ``import placerec.sim.odometry`` (a config's drift model) does not import the
renderer.
"""

import logging

from placerec._lazy import lazy_exports

logging.getLogger(__name__).addHandler(logging.NullHandler())

_EXPORTS = {
    "SimulatedSequence": "sequence",
    "simulate": "export",
    "write_kitti_sequence": "export",
    "make_localization_split": "localization",
    "LocalizationSplit": "localization",
    "CONDITIONS": "localization",
    "make_session_pair": "sessions",
    "SessionPair": "sessions",
    "kidnap_trials": "sessions",
    "KidnapTrial": "sessions",
    "SensorModel": "sensors",
    "SENSORS": "sensors",
    "get_sensor": "sensors",
    "sensor_names": "sensors",
    "frame_rays": "sensors",
    "World": "world",
    "build_world": "world",
    "PRESETS": "presets",
    "preset_names": "presets",
    "Route": "routes",
    "Revisit": "routes",
    "ROUTES": "routes",
    "make_route": "routes",
    "find_revisits": "routes",
    "BeamResponse": "intensity",
    "IntensityModel": "intensity",
    "surface_response": "intensity",
    "ClutterConfig": "clutter",
    "OdometryDrift": "odometry",
    "M": "materials",
    "Material": "materials",
    "MATERIALS": "materials",
}

__all__ = list(_EXPORTS)
__getattr__ = lazy_exports(__name__, _EXPORTS)
