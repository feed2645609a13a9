"""A pipeline's settings on one sensor's scans, where that sensor's tuning cells chose others than the preset's.

The registry (`placerec.recognizer.PipelineEntry.sensors`) holds `SENSOR_PRESETS`: `make_pipeline(name, params,
sensor=...)` merges the sensor's ``params`` under the given ones and `PipelineEntry.threshold_for(sensor)` gives
its operating threshold, so what the benchmark measured on a sensor is what every user of that sensor gets: an
experiment or a benchmark cell on the simulator, `LoopClosureDetector.for_pipeline(..., sensor=)`, map builds
(`placerec map build`, `placerec slam --save-map`: the scans' sensor, recorded in the map) and `placerec slam`'s
loop pipeline (whose threshold is the config's ``loops.threshold``). A threshold and the parameters it was chosen
with travel together: a threshold chosen with an acceptance gate is never applied without it.

Every value was chosen by the tuning rule of docs/protocol.md (above every false closure's score on the tuning
cells, rounded up to 0.05, never below the verification's floor) on the sensor's own tuning cells, never on the
test split (docs/sensors.md has the figures).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

__all__ = ["SensorPreset", "SENSOR_PRESETS", "VISUAL_PIPELINES"]


@dataclass(frozen=True)
class SensorPreset:
    """A pipeline's operating ``threshold`` (None: the pipeline's own) and parameter overrides on one sensor;
    ``odometry``: the threshold and overrides chosen on that sensor's tuning cells with the odometry gate
    (`placerec.odometry_gate`), for a detector that has it (None: the same as without)."""

    threshold: float | None = None
    params: Mapping[str, Any] = field(default_factory=dict)
    odometry: SensorPreset | None = None

    def with_odometry(self, odometry: bool) -> SensorPreset:
        """The preset for a detector with (``odometry``) or without the odometry gate."""
        return self.odometry if odometry and self.odometry is not None else self


#: The registered pipelines with an intensity-image front end.
VISUAL_PIPELINES = ("orb-hbst", "brisk-hbst", "orb-dbow", "surf-dbow", "superpoint-dbow")

#: The 16- and 32-beam spinning sensors' visual pipelines keep 1000 features an image instead of 300: the 16- and
#: 32-row images repeat their features (58-70 %) yet match few of them, and more features give 2-3x the correct
#: matches (tools/eval_sparse_sensors.py; chosen on the town seed-0 cells: docs/intensity_images.md, "Sparse
#: spinning sensors").
_SPARSE_FEATURES = {"nfeatures": 1000}


def _overlap_gate(ratio: float, fitness: float, length_m: float) -> dict[str, Any]:
    """The verification's acceptance with the overlap gate for the displacement (`placerec.verify.score`): accept
    when the ICP fitness reaches ``ratio`` x ``fitness`` exp(-d / ``length_m``), d the verified pose's translation,
    with the score floor at 0.10."""
    return {
        "verify": {
            "score": {
                "min_fitness_ratio": ratio,
                "expected_fitness": fitness,
                "expected_fitness_length_m": length_m,
                "min_score": 0.10,
            }
        }
    }


#: Sparse sensors judge a verified pose's overlap against what a right alignment reaches at its displacement: their
#: false closures are look-alike places registered a few decimetres off (fitness 0.3-0.49 where a right pose
#: overlaps ~0.75), while right poses of scans metres apart score under the 0.25 floor for want of overlap on the
#: sparse rings. Each curve is the median fitness of the right candidates of six tuning cells of the sensor (town,
#: campus, industrial x seeds 0, 1; candidates verified with the floor at 0.05): 0.75 at 0 m falling by e over
#: 17.5 m (VLP-16) and 22.5 m (HDL-32E); 0.71 over 37.5 m for the MID-360-like scanner, whose 1 s keyframes of a
#: 360 deg field overlap well even metres apart. The ratio lies in the range that gave the highest recall at
#: precision 1.00 on those cells (VLP-16 0.65-0.75, HDL-32E 0.70-0.80, MID-360 0.60-0.70); the floor 0.10 gave the
#: same tuning recall as 0.05 (docs/sensors.md, "An overlap gate for the displacement"). Scan Context's ICP takes
#: the same gate: its right candidates follow the same curve on the same cells (0.75 exp(-d / 19.5 m) VLP-16, 0.75
#: exp(-d / 24 m) HDL-32E, 0.71 exp(-d / 29 m) MID-360; `tools/eval_overlap_gate.py`) and its false closures are the
#: same look-alikes.
_GATES = {
    "vlp16": _overlap_gate(0.75, 0.75, 17.5),
    "hdl32": _overlap_gate(0.75, 0.75, 22.5),
    "mid360": _overlap_gate(0.65, 0.71, 37.5),
}
_FEATURES = {"vlp16": _SPARSE_FEATURES, "hdl32": _SPARSE_FEATURES, "mid360": None}

#: Operating thresholds on each sensor's tuning cells, with the settings above: the six gated cells per sensor
#: (`placerec bench configs/benchmark_tuning.yaml --set 'sensors=[vlp16]' --set 'worlds=[town, campus,
#: industrial]' --set 'seeds=[0, 1]' --suggest`, and configs/benchmark_sensors_tuning.yaml with 'sensors=[hdl32]'
#: or 'sensors=[mid360]'); the E1R-like sensor's from its tuning cell (no gate: its false closures, repeated blocks
#: 40-100 m away seen by a 120 deg, 30 m cone, score up to 0.35-0.40 and are pinned down in every direction).
_THRESHOLDS: dict[str, dict[str, float]] = {
    "scan-context": {"vlp16": 0.1, "hdl32": 0.1, "mid360": 0.2, "e1r": 0.4},
    "orb-hbst": {"vlp16": 0.2},
    "brisk-hbst": {"vlp16": 0.1},
    "orb-dbow": {"vlp16": 0.1, "hdl32": 0.1, "mid360": 0.1, "e1r": 0.35},
    "surf-dbow": {"vlp16": 0.1},
    "superpoint-dbow": {"vlp16": 0.15, "hdl32": 0.1, "mid360": 0.1, "e1r": 0.4},
}


#: With the odometry gate (`placerec.odometry_gate`) the forward-looking sensors' look-alike closures (repeated
#: blocks 40-100 m away, which set their thresholds above) are refused, so their verification floor comes down to
#: 0.05 and the tuning rule picks its thresholds again with the gate in place, on the tuning cells of each
#: sensor (`placerec bench configs/benchmark_sensors_tuning.yaml --set 'sensors=[avia, e1r]' --set 'worlds=[town,
#: campus, industrial]' --set 'seeds=[0, 1, 2, 3]' --set pipelines.{0,1,2}.params.verify.score.min_score=0.05 --set
#: 'evaluation.odometry_gate={}' --suggest`; tuning recall at precision 1.00 in docs/sensors.md). Without the gate
#: the same cells have 9-108 false closures a cell at that floor, scoring up to 0.40. The thresholds are the gate's
#: through loops (its default, `placerec.odometry_gate.LoopChain`): a look-alike near a stretch already closed is
#: judged over the path since that closure, which refuses the last false closures that set the thresholds with the
#: odometry alone (Avia 0.20 / 0.20 / 0.15 and E1R 0.35 / 0.15 / 0.15 for Scan Context / ORB-DBoW / SuperPoint-DBoW
#: then); the rule, walked up the grid with each threshold judged with the closures accepted at it, picks these on
#: twelve tuning cells of each sensor (seeds 0-3: on seeds 0 and 1 alone it had picked the verification's floor,
#: 0.05, for the E1R's Scan Context and both sensors' SuperPoint-DBoW, and 0.10 for the E1R's ORB-DBoW, which seeds
#: 2 and 3 show false closures above; docs/sensors.md).
_ODOMETRY_FLOOR = {"verify": {"score": {"min_score": 0.05}}}
_ODOMETRY_THRESHOLDS: dict[str, dict[str, float]] = {
    "scan-context": {"avia": 0.25, "e1r": 0.35},
    "orb-dbow": {"avia": 0.05, "e1r": 0.15, "mid360": 0.05, "vlp16": 0.05, "hdl32": 0.05},
    "superpoint-dbow": {"avia": 0.05, "e1r": 0.25, "vlp16": 0.15},
}
#: With the gate, what was left setting the E1R's ORB-DBoW threshold (0.30) were right places registered 0.50-0.57
#: m off, just outside the pose truth's 0.5 m: its ICP aligned a query voxelised at 1.5 m, a few hundred points of a
#: 120 deg cone. A 0.75 m query grid registers them within it; on the same six tuning cells with the gate the rule
#: then picks 0.15 and the recall at precision 1.00 rises from 0.395 to 0.532 (`... --set 'sensors=[avia, e1r]'
#: ... --set 'pipelines=[{name: orb-dbow, params: {verify: {icp: {source_voxel_size: 0.75}}}}, ...]' --suggest`,
#: docs/sensors.md). Not the Avia's: its recall fell (0.525 -> 0.479); SuperPoint-DBoW's moved by less than the
#: runs' revisit sets do (Avia 0.347 -> 0.321, E1R 0.364 -> 0.379) and keeps its grid.
#: With the gate through loops, the Avia's ORB-DBoW verifies 40 candidates by RANSAC and 4 by ICP (20 and 2 in the
#: preset): on its six tuning cells the right closures at the rule's threshold (0.10 either way) rose from 189 to 201
#: at ~1.5x the time a keyframe (`placerec bench configs/benchmark_sensors_tuning.yaml ... --set 'pipelines=[{name:
#: orb-dbow, label: orb-k40-icp4, params: {verify: {top_k: 40, icp_top_k: 4}}}, ...]' --suggest`, docs/sensors.md).
#: Not the E1R's: 192 -> 170 (its rule picked 0.20), and ICP on 4 of 20 gave 195, within the runs' spread.
#: Their keyframe images, on the twelve tuning cells of each sensor with the gate (right closures at the threshold
#: the rule picks, the preset's 389 Avia / 332 E1R at 0.10 / 0.20): the Avia's ORB-DBoW keeps 1000 features an
#: image (464 at 0.05; 600 features 431 at 0.10; 2 points a pixel 394), the E1R's sizes its pixels to 2 points
#: (357 at 0.15; with 1000 features as well 366 at 0.05, within the runs' 3 % spread of one another and 1.25x the
#: time, so the cheaper); a vocabulary trained on their keyframe images (configs/vocab_orb_solid_state.yaml) gave
#: 391 / 332 and is not used (docs/sensors.md, "Features and a vocabulary for the keyframe images"). Then, on top
#: of those, RANSAC's inlier residual at 1.0 m (0.6 m in the preset) gave the E1R's 380 at 0.15 (the Avia's 449 at
#: 0.15) and 5 inliers (8) the Avia's 481 at 0.05 (the E1R's 333 at 0.20): kept for the E1R (+6 %), not for the
#: Avia (+4 %, within the spread). Then the E1R's matches within the gate's prediction where it rests on a closure
#: a few metres back (`verify.guided`, its defaults: reach at most 2 m, accepted from 0.15): 414 right closures at
#: 0.15 against 380, no false one (`... --set "pipelines=[{name: orb-dbow, label: orb-gm2, params: {verify: {guided:
#: {enabled: true, min_score: 0.15, max_metres: 2.0}, score: {min_score: 0.05}}}}]" --suggest`, docs/sensors.md), at
#: ~1.75x the time a keyframe; the Avia's, the same setting: 464 -> 531 right closures at its 0.05 (+14 %), no false
#: one, the time a keyframe within the runs' spread (a looser reach, any prediction from 0.25, had given +3 % at
#: 2.9x the time). With it, since session 28, the places the prior predicts within 30 m registered by ICP from the
#: prediction where the candidates give no answer, before the matching within the prior (`verify.guided`'s
#: defaults ``near_metres`` 30, ``near_candidates`` 4): the E1R's 414 -> 484 right closures at 0.15 (+17 %), the
#: Avia's 531 -> 537 at 0.05, none false, the rule's thresholds unchanged (docs/sensors.md, "Places predicted
#: near"). Their ICP from a prediction (the only ICP-only verification these pipelines run) starts on a 3 m query
#: grid (`icp_only_coarse_voxel_size`): the same right closures on both sensors' tuning cells (484, and the Avia's
#: recall 0.719), about half the time of that verification. That verification also ends after the coarse stages when
#: they leave less than 0.10 (Avia) / 0.02 (E1R) of the query's grid overlapping (`icp_only_min_coarse_fitness`;
#: the E1R's right places, seen through its 120° cone from a prediction up to 2 m off, start as low as 0.03): each
#: sensor's twelve tuning cells' candidates files the same bytes, 14 % / ~10 % less time a keyframe (docs/sensors.md).
#: After its stage at the ICP's 1 m gate, one more at 0.5 m (`icp_only_fine_distances`): on the same tuning cells the
#: near places' registration error (pose truth) falls from 0.080 to 0.040 m at the median (p99 0.29 -> 0.23 m,
#: rotation p99 0.81 -> 0.43 deg) on the E1R, 0.060 -> 0.030 m (p99 0.23 -> 0.18 m, 0.57 -> 0.21 deg) on the Avia,
#: as precise as the poses matches give; the same right closures (484 / 537), none false (docs/sensors.md).
#: The MID-360-like scanner's ORB-DBoW with the gate takes the same verification (matching within the prediction,
#: the places predicted near by ICP from a 3 m query grid, the 0.5 m stage; the floor at 0.05): on its twelve tuning
#: cells with the gate the right closures rise from 583 (its preset, at 0.10) to 759 at the 0.05 the rule picks
#: (758 at 0.10; recall at 0.10, precision 1.00, 0.681 -> 0.885, worst cell 0.49 -> 0.79), none false; near places 0.03
#: m off at the median (max 0.09 m) (`... --set 'sensors=[mid360]' ... --set "pipelines=[{name: orb-dbow, label:
#: preset}, {name: orb-dbow, label: near05, params: {verify: {score: {min_score: 0.05}, guided: {enabled: true},
#: icp_only_coarse_voxel_size: 3.0, icp_only_fine_distances: [0.5]}}}]" --suggest`, docs/sensors.md). So do the
#: VLP-16's and HDL-32E's (the same command with 'sensors=[vlp16, hdl32]', 595 s): right closures 1102 -> 1538 and
#: 1046 -> 1617 at the 0.05 the rule picks (0.10 before; 1508 / 1599 at 0.10), none false; recall at 0.10 (precision
#: 1.00) 0.624 -> 0.847 and 0.562 -> 0.853 (worst cells 0.22 -> 0.65, 0.13 -> 0.76). And the VLP-16's SuperPoint-DBoW
#: (its best pipeline at precision 1.00 on the test cells): 1286 -> 1497 right closures at the 0.15 the rule picks
#: either way, none false, recall 0.725 -> 0.841 (worst cell 0.52 -> 0.54) (913 s).
#: Every accepted closure's pose refined (`verify.refine`, docs/verification.md): on the five sensors' tuning cells
#: with the gate (`placerec bench configs/benchmark_sensors_tuning.yaml --set 'sensors=[vlp16, hdl32, avia, mid360,
#: e1r]' --set "pipelines=[{name: orb-dbow, params: {verify: {refine: {enabled: true}}}}, {name: superpoint-dbow,
#: params: ...}]" --set 'evaluation.odometry_gate={}'`, town seed 0) the same closures, none false, their pose error
#: (pose truth) 2.3-4.0 -> 0.5-2.6 cm at the median and 5.8-20.6 -> 2.1-5.7 cm / 0.18-1.25 -> 0.10-0.30 deg at the
#: most, ~10 ms more a keyframe (docs/sensors.md).
#: What every entry of `_ODOMETRY_PARAMS` verifies with (merged under the entry's own settings).
_NEAR_PLACES: dict[str, Any] = {
    "verify": {
        "guided": {"enabled": True},
        "icp_only_coarse_voxel_size": 3.0,
        "icp_only_fine_distances": [0.5],
        "refine": {"enabled": True},
    },
}
_ODOMETRY_PARAMS: dict[str, dict[str, dict[str, Any]]] = {
    "orb-dbow": {
        "e1r": {
            "verify": {
                "icp": {"source_voxel_size": 0.75},
                "ransac": {"inlier_threshold": 1.0},
                "icp_only_min_coarse_fitness": 0.02,
            },
            "image": {"density_points_per_pixel": 2.0},
        },
        "avia": {
            "verify": {"top_k": 40, "icp_top_k": 4, "icp_only_min_coarse_fitness": 0.1},
            "feature_params": {"nfeatures": 1000},
        },
        "mid360": {},
        "vlp16": {},
        "hdl32": {},
    },
    "superpoint-dbow": {"vlp16": {}},
}


def _presets() -> dict[str, dict[str, SensorPreset]]:
    from placerec.params import deep_merge

    out: dict[str, dict[str, SensorPreset]] = {}
    for pipeline in ("scan-context", *VISUAL_PIPELINES):
        thresholds = _THRESHOLDS.get(pipeline, {})
        with_odometry = _ODOMETRY_THRESHOLDS.get(pipeline, {})
        by_sensor: dict[str, SensorPreset] = {}
        for sensor in sorted(set(thresholds) | set(_GATES) | set(with_odometry)):
            params: dict[str, Any] = dict(_GATES.get(sensor, {}))
            if pipeline in VISUAL_PIPELINES and _FEATURES.get(sensor):
                params = {"feature_params": _FEATURES[sensor], **params}
            odometry = None
            if sensor in with_odometry:
                own = _ODOMETRY_PARAMS.get(pipeline, {}).get(sensor)
                extra = () if own is None else (_NEAR_PLACES, own)
                odometry = SensorPreset(with_odometry[sensor], deep_merge(params, _ODOMETRY_FLOOR, *extra))
            by_sensor[sensor] = SensorPreset(thresholds.get(sensor), params, odometry)
        out[pipeline] = by_sensor
    return out


#: pipeline name -> sensor model name (`placerec.sim.sensors.SENSORS`) -> its settings there.
SENSOR_PRESETS: dict[str, dict[str, SensorPreset]] = _presets()
