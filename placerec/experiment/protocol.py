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
# A sensor's operating thresholds, where the tuning rule picks others on its own tuning cells than the presets'
# (chosen on the spinning tuning matrix), are the registry's (`placerec.recognizer.PipelineEntry.sensor_thresholds`).

#: The 16- and 32-beam spinning sensors keep one scan a metre and per-beam images, but their visual pipelines keep
#: 1000 features an image instead of 300: the 16- and 32-row images repeat their features (58-70 %) yet match few
#: of them, and more features give 2-3x the correct matches (tools/eval_sparse_sensors.py, tuning data; chosen on
#: the town seed-0 cells: docs/intensity_images.md, "Sparse spinning sensors").
#: They also judge a verified pose's overlap against what a right alignment reaches at its displacement
#: (`placerec.verify.score`, ``min_fitness_ratio``): their false closures are look-alike places registered a few
#: decimetres off (fitness 0.3-0.49 where a right pose overlaps ~0.75), while right poses of scans metres apart score
#: under the 0.25 floor for want of overlap on the sparse rings. Each curve is the median fitness of the right
#: candidates of six tuning cells of the sensor (town, campus, industrial x seeds 0, 1): 0.75 at 0 m, falling by e
#: over 17.5 m (VLP-16) and 22.5 m (HDL-32E). The ratio 0.75 lies in the range that gave both sensors their highest
#: recall at precision 1.00 there (VLP-16 0.65-0.75, HDL-32E 0.70-0.80); the floor 0.10 gave the same tuning recall as
#: 0.05; each pipeline's threshold is the tuning rule's on those cells (docs/sensors.md, "An overlap gate for the
#: displacement").
_FITNESS_LENGTH_M = {"vlp16": 17.5, "hdl32": 22.5}
CAPTURE.update(
    {
        name: {
            "feature_params": {"nfeatures": 1000},
            "verify_score": {
                "min_fitness_ratio": 0.75,
                "expected_fitness": 0.75,
                "expected_fitness_length_m": length,
                "min_score": 0.10,
            },
        }
        for name, length in _FITNESS_LENGTH_M.items()
    }
)
#: The MID-360-like sensor's visual pipelines take the same gate with their own curve (six tuning cells as above,
#: candidates verified with the floor at 0.05: 0.71 at 0 m, falling by e over 37.5 m: 1 s keyframes of a 360 deg
#: sensor overlap well even metres apart) and the ratio in the middle of the range that gave the highest tuning
#: recall at precision 1.00 (0.60-0.70); the floor 0.10 again gave the same tuning recall as 0.05.
CAPTURE["mid360"]["verify_score"] = {
    "min_fitness_ratio": 0.65,
    "expected_fitness": 0.71,
    "expected_fitness_length_m": 37.5,
    "min_score": 0.10,
}
#: The gate reaches every pipeline of the sensor's cells that verifies with a score, Scan Context's ICP too: its
#: right candidates' fitness follows the same curve (0.75 exp(-d / 19.5 m) VLP-16, 0.75 exp(-d / 24 m) HDL-32E, 0.71
#: exp(-d / 29 m) MID-360 on the same cells) and its false closures are the same look-alikes (fitness ~0.3).
#: The tuning rule's thresholds with that gate, on each sensor's six tuning cells (`placerec bench
#: configs/benchmark_tuning.yaml --set 'sensors=[vlp16]' --set 'worlds=[town, campus, industrial]' --set 'seeds=[0,
#: 1]' --suggest`, and configs/benchmark_sensors_tuning.yaml with 'sensors=[hdl32]' or 'sensors=[mid360]').
CAPTURE["vlp16"]["thresholds"] = {
    "scan-context": 0.1,
    "orb-hbst": 0.2,
    "brisk-hbst": 0.1,
    "orb-dbow": 0.1,
    "surf-dbow": 0.1,
    "superpoint-dbow": 0.15,
}
CAPTURE["hdl32"]["thresholds"] = {"scan-context": 0.1, "orb-dbow": 0.1, "superpoint-dbow": 0.1}
CAPTURE["mid360"]["thresholds"] = {"scan-context": 0.2, "orb-dbow": 0.1, "superpoint-dbow": 0.1}

#: Localisation query draws (`placerec.sim.make_localization_split`'s ``draw``): the training queries, on which
#: the vote model, ``reject_weight`` and DELIGHT were chosen, and the held-out queries reported as results.
LOCALIZE_TUNING_DRAW = 1
LOCALIZE_TEST_DRAW = 2


def is_test_seed(seed: int) -> bool:
    """Whether ``seed`` is a test-split simulator seed (no default may be chosen on it)."""
    return int(seed) in TEST_SEEDS
