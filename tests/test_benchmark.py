"""``placerec bench``: the config's rules, a 2-cell benchmark end to end, resuming from the cells done."""

from __future__ import annotations

import json

import pytest
import yaml

from placerec.errors import ConfigError
from placerec.experiment import protocol
from placerec.experiment.benchmark import (
    BenchmarkConfig,
    CaptureParams,
    cell_metrics,
    load_benchmark_config,
    run_benchmark,
    suggestions,
)
from placerec.experiment.benchmark_summary import (
    bench_line,
    rule_inputs,
    suggest_by_sensor,
    suggest_thresholds,
    tuning_pick,
)
from placerec.params import resolve
from placerec.recognizer import make_pipeline


def _write(tmp_path, data):
    path = tmp_path / "bench.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


BASE = {"pipelines": [{"name": "scan-context"}]}


@pytest.mark.parametrize(
    "change, key",
    [
        ({"worlds": ["atlantis"]}, "worlds"),
        ({"sensors": ["hdl128"]}, "sensors"),
        ({"split": "tuning", "seeds": [protocol.TEST_SEEDS[0]]}, "seeds"),
        ({"pipelines": []}, "pipelines"),
        ({"evaluation": {"mode": "localize"}}, "evaluation.mode"),
        ({"worlds": ["town"], "extra": 1}, "extra"),
    ],
)
def test_a_bad_benchmark_config_is_a_config_error_naming_the_key(tmp_path, change, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        load_benchmark_config(_write(tmp_path, {**BASE, **change}))


def test_the_matrix_is_the_splits_unless_narrowed():
    test = resolve(BenchmarkConfig, BASE)
    cells = test.cells()
    assert len(cells) == len(protocol.TEST_WORLDS) * len(protocol.TEST_SENSORS) * len(protocol.TEST_SEEDS)
    assert {c.seed for c in cells} == set(protocol.TEST_SEEDS)
    tuning = resolve(BenchmarkConfig, {**BASE, "split": "tuning", "sensors": ["vlp16"]})
    assert {(c.sensor, c.seed) for c in tuning.cells()} == {("vlp16", s) for s in protocol.TUNING_SEEDS}
    cfg = tuning.cell_config(tuning.cells()[0])
    assert cfg.dataset.simulator.seed == protocol.TUNING_SEEDS[0] and cfg.evaluation.mode == "loop"


def test_sensors_that_do_not_spin_are_driven_as_their_capture_says():
    """A Livox-style cell: 10 Hz frames taken while moving, keyframes de-skewed with a drifting odometry, an
    exclusion window in metres; a spinning sensor's cell is left as it was (one scan a metre, no keyframes)."""
    bench = resolve(BenchmarkConfig, {**BASE, "split": "tuning", "sensors": ["avia", "hdl32"]})
    avia, hdl32 = (bench.cell_config(c) for c in bench.cells())
    assert set(protocol.CAPTURE) <= {*protocol.SENSOR_MATRIX, *protocol.TEST_SENSORS}
    sim = avia.dataset.simulator
    assert (sim.sensor, sim.rate_hz, sim.sweep_motion, sim.odometry_drift) == ("avia", 10.0, True, 0.01)
    assert avia.keyframes is not None and avia.keyframes.seconds == 0.5
    assert avia.evaluation.exclusion.frames is None and avia.evaluation.exclusion.metres == 120.0
    plain = hdl32.dataset.simulator
    assert (
        hdl32.keyframes is None and plain.rate_hz is None and not plain.sweep_motion and plain.spacing == 1.0
    )
    assert hdl32.evaluation.exclusion.frames == 120
    # a 32-row image: the visual pipelines keep more features; Scan Context (no image) is left as it is
    specs = {p.name: p.params for p in hdl32.pipelines}
    assert specs["scan-context"] == {} or "feature_params" not in specs["scan-context"]
    visual = resolve(
        BenchmarkConfig,
        {
            "pipelines": [{"name": "orb-dbow", "params": {"feature_params": {"fast_threshold": 9}}}],
            "sensors": ["vlp16"],
        },
    )
    orb = visual.cell_config(visual.cells()[0]).pipelines[0].params["feature_params"]
    assert orb == {"nfeatures": 1000, "fast_threshold": 9}
    own = resolve(
        BenchmarkConfig, {**BASE, "sensors": ["avia"], "capture": {"avia": {"keyframes": {"metres": 5}}}}
    )
    cfg = own.cell_config(own.cells()[0])
    assert cfg.keyframes is not None and cfg.keyframes.metres == 5 and cfg.dataset.simulator.rate_hz is None
    with pytest.raises(ConfigError, match="capture"):
        resolve(BenchmarkConfig, {**BASE, "capture": {"hdl128": {}}})


def test_a_sensors_verify_score_reaches_its_verified_pipelines_under_their_own_settings():
    """``capture.<sensor>.verify_score`` is merged into the verification of that sensor's pipelines that verify
    with a score (the intensity-image ones and Scan Context); a pipeline's own ``verify.score`` keys win,
    MapClosures (no such verification) and other sensors' cells are left alone."""
    gate = {"min_fitness_ratio": 0.7, "min_score": 0.05}
    bench = resolve(
        BenchmarkConfig,
        {
            "split": "tuning",
            "sensors": ["os1-64", "hdl64"],
            "pipelines": [
                {"name": "orb-dbow", "params": {"verify": {"top_k": 7, "score": {"min_score": 0.1}}}},
                {"name": "superpoint-dbow"},
                {"name": "scan-context"},
                {"name": "map-closures"},
            ],
            "capture": {"os1-64": {"verify_score": gate}},
        },
    )
    os1, hdl64 = (bench.cell_config(c) for c in bench.cells())
    orb, sp, sc, mc = (p.params for p in os1.pipelines)
    assert orb["verify"] == {"top_k": 7, "score": {"min_fitness_ratio": 0.7, "min_score": 0.1}}
    assert sp["verify"] == {"score": gate} and sc["verify"] == {"score": gate} and not mc
    assert all("verify" not in (p.params or {}) or p.name == "orb-dbow" for p in hdl64.pipelines)
    assert hdl64.pipelines[0].params["verify"] == {"top_k": 7, "score": {"min_score": 0.1}}
    assert make_pipeline("scan-context", sc).params.verify.score.min_fitness_ratio == 0.7
    built = make_pipeline("superpoint-dbow", sp)
    assert (
        built.params.verify.score.min_fitness_ratio == 0.7 and built.params.verify.top_k == 20
    )  # preset kept
    for bad in ({"min_fitness_ratio": 2}, {"min_fitnes_ratio": 0.7}):
        with pytest.raises(ConfigError, match="verify_score"):
            resolve(BenchmarkConfig, {**BASE, "capture": {"vlp16": {"verify_score": bad}}})


def test_a_cell_runs_with_the_registrys_settings_for_its_sensor_and_shows_them_in_its_config():
    """A VLP-16 cell's pipelines carry the registry's VLP-16 settings (`placerec.sensor_presets`: 1000 features,
    the overlap gate) in their params and are judged at the VLP-16 thresholds; an HDL-64 cell's carry none."""
    bench = resolve(
        BenchmarkConfig,
        {
            "split": "tuning",
            "worlds": ["town"],
            "seeds": [0],
            "sensors": ["vlp16", "hdl64"],
            "pipelines": [{"name": "superpoint-dbow"}, {"name": "scan-context"}],
        },
    )
    vlp16, hdl64 = (bench.cell_config(c) for c in bench.cells())
    sp, sc = vlp16.pipelines
    assert sp.params["feature_params"] == {"nfeatures": 1000} and "feature_params" not in sc.params
    assert (
        sp.params["verify"]["score"]["min_fitness_ratio"] == sc.params["verify"]["score"]["min_fitness_ratio"]
    )
    assert [vlp16.operating_threshold(p) for p in vlp16.pipelines] == [0.15, 0.1]
    assert all(not p.params for p in hdl64.pipelines)
    assert [hdl64.operating_threshold(p) for p in hdl64.pipelines] == [0.25, 0.3]


def test_a_sensors_thresholds_replace_the_presets_in_its_cells_only():
    """``capture.<sensor>.thresholds`` sets the operating threshold of that sensor's cells; a pipeline's own
    ``threshold:`` still wins; the E1R-like sensor's defaults are the ones its tuning cells picked."""
    bench = resolve(
        BenchmarkConfig,
        {
            "pipelines": [{"name": "scan-context"}, {"name": "orb-dbow", "threshold": 0.5}],
            "sensors": ["avia", "mid360"],
            "worlds": ["town"],
            "seeds": [protocol.TEST_SEEDS[0]],
            "capture": {"avia": {"thresholds": {"scan-context": 0.45, "orb-dbow": 0.3}}},
        },
    )
    avia, mid360 = (bench.cell_config(c) for c in bench.cells())
    assert [avia.operating_threshold(p) for p in avia.pipelines] == [0.45, 0.5]
    # the registry's MID-360 threshold (a config's capture for another sensor leaves it)
    assert [mid360.operating_threshold(p) for p in mid360.pipelines] == [0.2, 0.5]
    defaults = resolve(BenchmarkConfig, {**BASE, "sensors": ["avia", "mid360", "e1r", "vlp16", "hdl64"]})
    cells = [defaults.cell_config(c) for c in defaults.cells()[:10:2]]
    assert [c.dataset.simulator.sensor for c in cells] == ["avia", "mid360", "e1r", "vlp16", "hdl64"]
    picked = [c.operating_threshold(c.pipelines[0]) for c in cells]
    # the presets' for the Avia and HDL-64, the others' own tuning cells' picks (placerec.sensor_presets)
    assert picked == [0.3, 0.2, 0.4, 0.1, 0.3]
    for bad in (-0.1, float("nan"), "high"):
        with pytest.raises(ConfigError, match="thresholds"):
            resolve(BenchmarkConfig, {**BASE, "capture": {"avia": {"thresholds": {"scan-context": bad}}}})


def test_an_unknown_pipeline_fails_before_any_cell_runs(tmp_path):
    cfg = resolve(
        BenchmarkConfig, {"pipelines": [{"name": "no-such"}], "worlds": ["town"], "sensors": ["vlp16"]}
    )
    with pytest.raises(ConfigError, match="no-such"):
        run_benchmark(cfg, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_two_cells_end_to_end_at_fixed_thresholds_and_resumed(tmp_path):
    """The fast variant of the benchmark: 2 cells (town, two sensors; the block loop driven twice, 3 m apart)."""
    cfg = resolve(
        BenchmarkConfig,
        {
            "name": "two",
            "split": "tuning",
            "worlds": ["town"],
            "sensors": ["vlp16", "os1-64"],
            "route": "loop",
            "spacing": 3.0,
            "pipelines": [{"name": "scan-context"}, {"name": "orb-hbst", "threshold": 0.3}],
            "evaluation": {"exclusion": {"frames": 30}},
            "output": {"dir": str(tmp_path), "cache_dir": str(tmp_path / "cache"), "progress": False},
        },
    )
    folder, payload = run_benchmark(cfg)
    assert payload["cells_run"] == 2 and payload["cells"] == ["town_vlp16_0", "town_os1-64_0"]
    orb = payload["pipelines"]["orb-hbst"]
    assert orb["threshold"] == 0.3
    recall = orb["figures"]["recall"]["cells"]
    assert all(0.5 < r <= 1.0 for r in recall.values()), recall  # the second lap closes on the first
    # the second lap is driven the same way, and the same-direction revisits are the ones closed
    same = orb["figures"]["pose_same_direction_recall"]["cells"]
    assert all(recall[c] <= same[c] <= 1.0 for c in recall) and same != recall, (same, recall)
    assert orb["figures"]["precision"]["worst"] == 1.0
    assert orb["accepted_translation_m"]["n"] > 10 and orb["accepted_translation_m"]["p95"] < 0.5
    for name in ("benchmark.json", "cells.csv", "heatmap_recall.png", "heatmap_max_f1.png", "index.html"):
        assert (folder / name).is_file(), name
    line = json.loads(bench_line(payload))
    assert line["cells"] == 2 and line["pipelines"]["orb-hbst"]["false_closures"] == 0

    cells = {c: json.loads((folder / "cells" / c / "cell.json").read_text()) for c in payload["cells"]}
    picked = suggest_thresholds(cfg, cells)
    assert set(picked) == {"scan-context", "orb-hbst"} and all(
        v is not None and v >= 0.25 for v in picked.values()
    )

    strict = cfg.model_copy(
        update={"pipelines": [cfg.pipelines[0], cfg.pipelines[1].model_copy(update={"threshold": 0.95})]}
    )
    _, judged = run_benchmark(strict)  # another threshold: judged again from the cells' files, nothing rerun
    assert judged["cells_run"] == 0 and judged["pipelines"]["orb-hbst"]["threshold"] == 0.95
    stricter = judged["pipelines"]["orb-hbst"]["figures"]["recall"]["cells"]
    assert all(stricter[c] <= recall[c] for c in recall) and stricter != recall

    by_sensor = suggest_by_sensor(cfg, cells)
    assert set(by_sensor) == {"vlp16", "os1-64"} and all(set(v) == set(picked) for v in by_sensor.values())
    assert all(
        max(v[k] for v in by_sensor.values()) == picked[k] for k in picked
    )  # the matrix's is the highest

    per_sensor = cfg.model_copy(
        update={
            "capture": {
                **cfg.capture,
                "os1-64": resolve(CaptureParams, {"thresholds": {"scan-context": 0.95}}),
            }
        }
    )
    _, sensor_judged = run_benchmark(per_sensor)  # judged again from the cells' files, nothing rerun
    sc = sensor_judged["pipelines"]["scan-context"]
    assert sensor_judged["cells_run"] == 0 and sorted(map(float, sc["threshold"])) == [0.1, 0.95]  # VLP-16's
    before = payload["pipelines"]["scan-context"]["figures"]["recall"]["cells"]
    after = sc["figures"]["recall"]["cells"]
    assert (
        after["town_vlp16_0"] == before["town_vlp16_0"] and after["town_os1-64_0"] <= before["town_os1-64_0"]
    )

    gate = {"bounds": {"metres": 0.001, "per_metre": 0.0, "degrees": 0.001, "degrees_per_metre": 0.0}}
    data = cfg.model_dump(mode="json")
    data["evaluation"]["odometry_gate"] = gate
    gated = resolve(BenchmarkConfig, data)
    _, refused = run_benchmark(gated)  # the odometry gate: judged again from the cells' files, nothing rerun
    assert refused["cells_run"] == 0 and refused["odometry_gate"] and not payload["odometry_gate"]
    assert json.loads(bench_line(refused))["odometry_gate"] is True
    assert (
        max(refused["pipelines"]["orb-hbst"]["figures"]["recall"]["cells"].values()) == 0.0
    )  # no pose agrees

    # the tuning rule with a gate through loops: the first threshold of the grid whose own judgement (the closures
    # accepted at it in the chain) has no false closure scoring as high
    data["evaluation"]["odometry_gate"] = {}
    through = resolve(BenchmarkConfig, data)
    walked, walked_by_sensor = suggestions(through, folder, cells)
    assert set(walked) == set(picked) and set(walked_by_sensor) == {"vlp16", "os1-64"}

    def rule_at(label, t):
        judged = {
            n: {
                **c,
                "metrics": cell_metrics(through, by_name[n], folder / "cells" / n, c["metrics"], {label: t}),
            }
            for n, c in cells.items()
        }
        return tuning_pick(*rule_inputs(through, judged)[label])

    by_name = {c.name: c for c in through.cells()}
    for label, t in walked.items():
        assert t is not None and rule_at(label, t) <= t
        floor = tuning_pick(-float("inf"), rule_inputs(through, cells)[label][1])
        if t > max(floor, 0.05):
            assert rule_at(label, round(t - 0.05, 6)) > t - 0.05
    data["evaluation"]["odometry_gate"] = {"bounds": {"through_loops": False}}
    alone = resolve(BenchmarkConfig, data)
    assert suggestions(alone, folder, cells) == (
        suggest_thresholds(alone, cells),
        suggest_by_sensor(alone, cells),
    )

    (folder / "cells" / "town_os1-64_0" / "cell.json").unlink()  # interrupted before this cell finished
    _, again = run_benchmark(cfg)
    assert again["cells_run"] == 1
    assert again["pipelines"]["orb-hbst"]["figures"]["recall"] == orb["figures"]["recall"]


def test_a_detector_for_a_registered_pipeline_runs_at_its_operating_threshold():
    from placerec.loop_closure import LoopClosureDetector
    from placerec.recognizer import PIPELINES

    loop_pipelines = ("scan-context", "orb-hbst", "brisk-hbst", "orb-dbow", "surf-dbow", "superpoint-dbow")
    assert all(PIPELINES[n].threshold is not None for n in loop_pipelines)
    assert LoopClosureDetector.for_pipeline("orb-hbst").threshold == PIPELINES["orb-hbst"].threshold
    assert LoopClosureDetector.for_pipeline("orb-hbst", threshold=0.6, k=3).threshold == 0.6
    with pytest.raises(ConfigError, match="no operating threshold"):
        LoopClosureDetector.for_pipeline("ishot-votes")


def test_a_pipelines_threshold_on_a_sensor_is_its_own_where_one_was_chosen():
    """`PipelineEntry.threshold_for`: the sensor's operating threshold where its tuning cells picked one, else the
    preset's; a spec's own ``threshold`` wins; a detector for a sensor accepts at that sensor's."""
    from placerec.config import PipelineSpec
    from placerec.loop_closure import LoopClosureDetector
    from placerec.recognizer import PIPELINES

    sc = PIPELINES["scan-context"]
    assert sc.threshold_for(None) == sc.threshold_for("hdl64") == sc.threshold == 0.3
    assert sc.threshold_for("vlp16") == 0.1 and sc.threshold_for("e1r") == 0.4
    assert (
        PIPELINES["orb-hbst"].threshold_for("e1r") == 0.25
        and PIPELINES["orb-dbow"].threshold_for("e1r") == 0.35
    )
    assert PipelineSpec(name="scan-context").threshold_for("vlp16") == 0.1
    assert PipelineSpec(name="scan-context", threshold=0.5).threshold_for("vlp16") == 0.5
    assert PipelineSpec(name="scan-context").threshold_for(None) == 0.3
    assert LoopClosureDetector.for_pipeline("scan-context", sensor="vlp16").threshold == 0.1
    assert LoopClosureDetector.for_pipeline("scan-context", sensor="velodyne-vlp16").threshold == 0.3
    assert all(
        0 <= t and n in protocol.TEST_SENSORS + protocol.SENSOR_MATRIX
        for e in PIPELINES.values()
        for n, t in ((n, p.threshold or 0) for n, p in e.sensors.items())
    )


def test_a_cells_stamp_holds_its_pipelines_resolved_parameters(monkeypatch):
    """A benchmark cell's stamp holds each pipeline's resolved parameters: a registry preset changed since makes
    the cells of that pipeline run again (their config did not change), and a change to another pipeline's
    preset does not."""
    import dataclasses

    from placerec.experiment.benchmark import _cell_key
    from placerec.recognizer import PIPELINES

    cfg = resolve(BenchmarkConfig, {"name": "b", "split": "tuning", "pipelines": [{"name": "orb-dbow"}]})
    cell = cfg.cell_config(cfg.cells()[0])
    before = _cell_key(cell)
    other = dataclasses.replace(PIPELINES["orb-hbst"], preset={"features": "orb", "verify": {"top_k": 3}})
    monkeypatch.setitem(PIPELINES, "orb-hbst", other)
    assert _cell_key(cell) == before
    changed = dataclasses.replace(PIPELINES["orb-dbow"], preset={"features": "orb", "verify": {"top_k": 10}})
    monkeypatch.setitem(PIPELINES, "orb-dbow", changed)
    assert _cell_key(cell) != before
