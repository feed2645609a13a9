"""A pipeline's settings on one sensor (`placerec.sensor_presets`) reach every path that knows the sensor, with the
threshold chosen under them."""

from __future__ import annotations

from pathlib import Path

import pytest

from placerec.config import parse_config
from placerec.experiment.runner import build_pipelines
from placerec.loop_closure import LoopClosureDetector
from placerec.recognizer import PIPELINES, make_pipeline, pipeline_params
from placerec.sensor_presets import SENSOR_PRESETS, VISUAL_PIPELINES

ROOT = Path(__file__).resolve().parents[1]


def test_a_sensors_settings_sit_between_the_preset_and_the_given_params():
    sp = make_pipeline("superpoint-dbow", sensor="vlp16").params
    assert (
        sp.feature_params.nfeatures == 1000 and sp.verify.top_k == 20
    )  # the sensor's, and the preset's kept
    assert sp.verify.score.min_fitness_ratio == 0.75 and sp.verify.score.expected_fitness_length_m == 17.5
    given = make_pipeline(
        "superpoint-dbow", {"verify": {"score": {"min_fitness_ratio": None}}}, sensor="vlp16"
    )
    assert (
        given.params.verify.score.min_fitness_ratio is None and given.params.feature_params.nfeatures == 1000
    )
    for other in (None, "hdl64", "os1-64", "no-such-sensor"):
        assert pipeline_params("superpoint-dbow", sensor=other) == pipeline_params("superpoint-dbow")
    assert pipeline_params("scan-context", sensor="mid360").verify.score.min_fitness_ratio == 0.65
    assert "feature_params" not in type(pipeline_params("scan-context")).model_fields


def test_every_sensor_threshold_is_reachable_under_the_settings_it_was_chosen_with():
    """A sensor's threshold below the pipeline's acceptance floor is only reachable with the floor its settings
    lower; each sensor's settings are valid parameters of the pipeline."""
    for name, by_sensor in SENSOR_PRESETS.items():
        assert name in PIPELINES and PIPELINES[name].sensors is by_sensor
        for sensor, preset in by_sensor.items():
            params = pipeline_params(name, sensor=sensor)  # validates them
            if preset.threshold is not None:
                assert params.verify.score.min_score <= preset.threshold, (name, sensor)
            if preset.odometry is not None:  # the same for the settings chosen with the odometry gate
                gated = pipeline_params(name, sensor=sensor, odometry=True)
                assert gated.verify.score.min_score <= preset.odometry.threshold, (name, sensor)
            if name in VISUAL_PIPELINES and sensor in ("vlp16", "hdl32"):
                assert params.feature_params.nfeatures == 1000, (name, sensor)


def test_a_detector_for_a_sensor_gets_its_threshold_and_settings_together():
    det = LoopClosureDetector.for_pipeline("scan-context", sensor="vlp16")
    assert det.threshold == 0.1 and det.recognizer.params.verify.score.min_fitness_ratio == 0.75
    plain = LoopClosureDetector.for_pipeline("scan-context")
    assert plain.threshold == 0.3 and plain.recognizer.params.verify.score.min_fitness_ratio is None
    own = LoopClosureDetector.for_pipeline("superpoint-dbow", {"verify": {"top_k": 5}}, sensor="hdl32")
    assert own.threshold == 0.1 and own.recognizer.params.verify.top_k == 5
    assert own.recognizer.params.verify.score.expected_fitness_length_m == 22.5


@pytest.mark.parametrize("sensor, nfeatures, threshold", [("vlp16", 1000, 0.15), ("os1-64", 300, 0.25)])
def test_an_experiment_on_the_simulator_runs_its_sensors_settings(sensor, nfeatures, threshold):
    cfg = parse_config(
        {
            "dataset": {
                "source": "simulator",
                "simulator": {"world": "town", "sensor": sensor, "n_scans": 5},
            },
            "pipelines": [{"name": "superpoint-dbow"}],
        }
    )
    ((record, rec),) = build_pipelines(cfg)
    assert rec.params.feature_params.nfeatures == nfeatures
    assert record.params["feature_params"]["nfeatures"] == nfeatures  # the run records what it ran with
    assert cfg.operating_threshold(cfg.pipelines[0]) == threshold


def test_with_the_odometry_gate_a_forward_looking_sensor_gets_the_settings_chosen_with_it():
    from placerec.experiment.benchmark import _cell_key, load_benchmark_config
    from placerec.odometry_gate import OdometryGateParams

    gate = OdometryGateParams()
    det = LoopClosureDetector.for_pipeline("orb-dbow", sensor="avia", odometry_gate=gate)
    assert det.threshold == 0.05 and det.recognizer.params.verify.score.min_score == 0.05
    assert det.odometry_gate == gate
    plain = LoopClosureDetector.for_pipeline("orb-dbow", sensor="avia")
    assert plain.threshold == 0.25 and plain.recognizer.params.verify.score.min_score == 0.25
    # the E1R's ORB-DBoW registers on a finer query grid with the gate (and only with it)
    e1r = LoopClosureDetector.for_pipeline("orb-dbow", sensor="e1r", odometry_gate=gate)
    assert e1r.threshold == 0.15 and e1r.recognizer.params.verify.icp.source_voxel_size == 0.75
    assert e1r.recognizer.params.verify.score.min_score == 0.05
    e1r_plain = LoopClosureDetector.for_pipeline("orb-dbow", sensor="e1r")
    assert e1r_plain.threshold == 0.35 and e1r_plain.recognizer.params.verify.icp.source_voxel_size == 1.5
    assert det.recognizer.params.verify.icp.source_voxel_size == 1.5  # not the Avia's
    # the Avia's verifies more candidates with the gate (and only with it)
    assert (det.recognizer.params.verify.top_k, det.recognizer.params.verify.icp_top_k) == (40, 4)
    assert (plain.recognizer.params.verify.top_k, plain.recognizer.params.verify.icp_top_k) == (20, 2)
    assert (e1r.recognizer.params.verify.top_k, e1r.recognizer.params.verify.icp_top_k) == (20, 2)
    # their keyframe images with the gate: the Avia's keep 1000 features, the E1R's pixels hold 2 points
    assert det.recognizer.params.feature_params.nfeatures == 1000
    assert plain.recognizer.params.feature_params.nfeatures == 300
    assert e1r.recognizer.params.feature_params.nfeatures == 300
    assert e1r.recognizer.params.image.density_points_per_pixel == 2.0
    assert e1r.recognizer.params.verify.ransac.inlier_threshold == 1.0
    assert det.recognizer.params.verify.ransac.inlier_threshold == 0.6
    assert e1r_plain.recognizer.params.verify.ransac.inlier_threshold == 0.6
    assert e1r_plain.recognizer.params.image.density_points_per_pixel == 1.0
    assert det.recognizer.params.image.density_points_per_pixel == 1.0
    # the sparse spinning and the 360 deg rosette sensors' ORB-DBoW too: the places predicted near, on their own
    # features and overlap gate
    for sensor, ratio in (("vlp16", 0.75), ("hdl32", 0.75), ("mid360", 0.65)):
        own = LoopClosureDetector.for_pipeline("orb-dbow", sensor=sensor, odometry_gate=gate)
        v = own.recognizer.params.verify
        assert own.threshold == 0.05 and v.score.min_score == 0.05 and v.score.min_fitness_ratio == ratio
        assert v.guided.enabled and v.icp_only_coarse_voxel_size == 3.0 and v.icp_only_fine_distances == [0.5]
        alone = LoopClosureDetector.for_pipeline("orb-dbow", sensor=sensor)
        assert alone.threshold == 0.1 and not alone.recognizer.params.verify.guided.enabled
        assert alone.recognizer.params.verify.icp_only_fine_distances == []
    sp = LoopClosureDetector.for_pipeline("superpoint-dbow", sensor="vlp16", odometry_gate=gate)
    assert sp.threshold == 0.15 and sp.recognizer.params.verify.icp_only_fine_distances == [0.5]
    assert sp.recognizer.params.feature_params.nfeatures == 1000
    # a sensor without settings of its own for the gate keeps its own with it
    vlp = LoopClosureDetector.for_pipeline("scan-context", sensor="vlp16", odometry_gate=gate)
    assert vlp.threshold == 0.1 and vlp.recognizer.params.verify.score.min_fitness_ratio == 0.75
    # a benchmark judged with the gate runs its cells with them, so their stamps differ from the ungated ones
    with_gate = ["sensors=[avia, vlp16, os1-64]", "seeds=[0]", "worlds=[town]", "evaluation.odometry_gate={}"]
    bench = load_benchmark_config(ROOT / "configs" / "benchmark_sensors_tuning.yaml", with_gate)
    alone = load_benchmark_config(ROOT / "configs" / "benchmark_sensors_tuning.yaml", with_gate[:-1])
    for cell in bench.cells():
        cfg, cfg0 = bench.cell_config(cell), alone.cell_config(cell)
        orb = next(p for p in cfg.pipelines if p.name == "orb-dbow")
        floor = (orb.params or {}).get("verify", {}).get("score", {}).get("min_score")
        assert cfg.operating_threshold(orb) == {"avia": 0.05, "vlp16": 0.05, "os1-64": 0.25}[cell.sensor]
        assert floor == {"avia": 0.05, "vlp16": 0.05, "os1-64": None}[cell.sensor]
        assert (_cell_key(cfg) == _cell_key(cfg0)) == (cell.sensor == "os1-64")
