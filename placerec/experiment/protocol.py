"""The tuning split and the test split: which simulated data may choose a default, and which may only be reported.

Every default of placerec that was chosen on data (a preset's operating threshold, ``top_k``, a verification
setting, the SLAM acceptance threshold, DELIGHT's radii and bins, the localisation vote model) was chosen on the
**tuning split**. The **test split** is the held-out benchmark (`placerec bench`, ``configs/benchmark.yaml``): no
default may ever be chosen on it, and a committed config or preset that names one of its seeds fails the suite
(``tests/test_protocol.py``). ``docs/protocol.md`` lists both splits in words.

Tuning split
    * loop closure: the demo sequence (town, OS1-64, route ``default``, seed 0) and the tuning matrix
      (`TUNING_WORLDS` x `TUNING_SENSORS` x `TUNING_SEEDS`);
    * localisation: query draw `LOCALIZE_TUNING_DRAW` (``draw=1``) of the town VLP-16 map, seed 0;
    * the verification pairs and SuperPoint's training / validation seeds (100-109), the DBoW vocabularies'
      training seeds (100-109), the feature evaluation's seeds (200-203).

Test split
    * loop closure and SLAM: `TEST_WORLDS` x `TEST_SENSORS` x `TEST_SEEDS`, route ``default`` (same- and
      opposite-direction revisits);
    * localisation: query draw `LOCALIZE_TEST_DRAW` of the maps (town, campus, industrial; VLP-16, seed 0).
"""

from __future__ import annotations

__all__ = [
    "TEST_WORLDS",
    "TEST_SENSORS",
    "TEST_SEEDS",
    "TUNING_WORLDS",
    "TUNING_SENSORS",
    "TUNING_SEEDS",
    "SENSOR_MATRIX",
    "CAPTURE",
    "LOCALIZE_TUNING_DRAW",
    "LOCALIZE_TEST_DRAW",
    "is_test_seed",
]

#: Worlds of the held-out benchmark.
TEST_WORLDS: tuple[str, ...] = ("town", "campus", "industrial")
#: Sensors of the held-out benchmark.
TEST_SENSORS: tuple[str, ...] = ("vlp16", "hdl64", "os1-64", "os1-128")
#: Simulator seeds of the held-out benchmark: used nowhere else in placerec, never to choose a default.
TEST_SEEDS: tuple[int, ...] = (4601, 4602)

#: The tuning matrix the operating thresholds are chosen on: the demo's world with every sensor (town OS1-64 seed 0
#: is the demo sequence). Campus and industrial have no tuning cell: the test split measures whether the thresholds
#: transfer to worlds they were not chosen on.
TUNING_WORLDS: tuple[str, ...] = ("town",)
TUNING_SENSORS: tuple[str, ...] = ("vlp16", "hdl64", "os1-64", "os1-128")
TUNING_SEEDS: tuple[int, ...] = (0,)

#: Sensors that are not one 360 deg spinning sweep (and the 32-beam spinning HDL-32E), benchmarked in their own
#: matrices (configs/benchmark_sensors*.yaml) over the same worlds and seeds as the split they belong to.
SENSOR_MATRIX: tuple[str, ...] = ("hdl32", "avia", "mid360", "e1r")

#: How the benchmark drives each sensor that is not a spinning sensor's one scan a metre
#: (`placerec.experiment.benchmark.CaptureParams`): frames at the sensor's rate taken while moving, accumulated
#: into keyframes de-skewed with a 1 %-drift odometry, and a loop exclusion window of 120 m (the 120 frames of
#: the spinning cells at their 1 m spacing). The keyframe lengths were chosen on the tuning split
#: (tools/sweep_keyframes.py, docs/sensors.md): windows of 0.5 s for the Avia- and E1R-like sensors and of 1 s for
#: the sparser MID-360-like one (20k points a frame over 360 x 59 deg), overlapping: one keyframe every 1.8 m
#: travelled (every other frame at 9 m/s), which raised the best pipeline's tuning recall of all three over windows
#: one after another (+0.03 / +0.08 / +0.04).
_KEYFRAME_SECONDS = {"avia": 0.5, "mid360": 1.0, "e1r": 0.5}
_KEYFRAME_EVERY_METRES = 1.8
CAPTURE: dict[str, dict] = {
    name: {
        "rate_hz": 10.0,
        "sweep_motion": True,
        "odometry_drift": 0.01,
        "keyframes": {"seconds": seconds, "every_metres": _KEYFRAME_EVERY_METRES},
        "exclusion": {"frames": None, "metres": 120.0},
    }
    for name, seconds in _KEYFRAME_SECONDS.items()
}
# A sensor's pipeline settings and operating thresholds, where its own tuning cells chose others than the presets'
# (the 16- and 32-beam spinning sensors' feature counts, the overlap gate of the sparse sensors, their thresholds),
# are the registry's (`placerec.sensor_presets`), so a user of the sensor gets what its cells measured.

#: Localisation query draws (`placerec.sim.make_localization_split`'s ``draw``): the training queries, on which
#: the vote model, ``reject_weight`` and DELIGHT were chosen, and the held-out queries reported as results.
LOCALIZE_TUNING_DRAW = 1
LOCALIZE_TEST_DRAW = 2


def is_test_seed(seed: int) -> bool:
    """Whether ``seed`` is a test-split simulator seed (no default may be chosen on it)."""
    return int(seed) in TEST_SEEDS
