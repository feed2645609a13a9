"""One strict parameter mechanism: deep-merged presets and overrides, dotted-path errors with the allowed keys,
range and type checks, classes from configs checked before anything runs, the resolved parameters in the run
folder, `placerec pipelines`, and describe times that do not depend on the cache or the pipeline order."""

import os

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from placerec.cli import app
from placerec.config import load_config
from placerec.errors import ConfigError
from placerec.experiment.report import report_loop
from placerec.experiment.run_folder import make_run_dir
from placerec.experiment.runner import run_loop
from placerec.recognizer import PIPELINES, make_pipeline, pipeline_params
from placerec.sim import SimulatedSequence
from placerec.types import ListSequence, Scan


def test_a_partial_nested_section_keeps_the_pipeline_defaults():
    rec = make_pipeline("ishot-votes", {"features": {"iss": {"salient_radius": 2.0}}})
    assert rec.params.features.iss.salient_radius == 2.0
    assert rec.params.features.iss.max_keypoints == 300  # the pipeline's default, not ISSParams' None
    assert rec.params.features.iss.non_max_radius == 1.6


def test_preset_and_overrides_merge_deeply():
    p = pipeline_params("brisk-hbst", {"feature_params": {"nfeatures": 100}, "image": {"width": 512}})
    assert p.features == "brisk" and p.feature_params.nfeatures == 100 and p.feature_params.octaves == 3
    assert p.image.width == 512 and p.image.percentile == 99.0


def _config(tmp_path, *pipelines, overrides=()):
    overrides = [f"output.dir={tmp_path}", "output.cache_dir=null", "output.progress=false", *overrides]
    cfg = load_config(None, overrides)
    return cfg.model_copy(update={"pipelines": [type(cfg.pipelines[0])(**p) for p in pipelines]})


def test_an_unknown_nested_key_names_its_full_path_and_the_allowed_keys(tmp_path):
    cfg = _config(
        tmp_path, {"name": "scan-context"}, {"name": "orb-hbst", "params": {"hbst": {"delta_mx": 0.2}}}
    )
    with pytest.raises(ConfigError) as err:
        run_loop(cfg, ListSequence([]))
    msg = str(err.value)
    assert "pipelines[1].params.hbst.delta_mx: unknown key" in msg
    assert "delta_max, leaf_size, max_depth, threshold" in msg


def test_feature_parameters_are_validated_by_the_named_extractor():
    with pytest.raises(ConfigError, match=r"feature_params\.scale_factor: unknown key.*octaves"):
        make_pipeline("brisk-hbst", {"feature_params": {"scale_factor": 1.3}})  # an ORB key
    assert (
        make_pipeline("orb-hbst", {"feature_params": {"scale_factor": 1.3}}).extractor.params.scale_factor
        == 1.3
    )
    with pytest.raises(ConfigError, match=r"feature_params\.fast_threshold: Input should be greater than 0"):
        make_pipeline("surf-dbow", {"feature_params": {"fast_threshold": 0}})


@pytest.mark.parametrize(
    "name, params, where",
    [
        ("scan-context", {"num_sectors": 0}, "num_sectors"),
        ("scan-context", {"num_rings": "20"}, "num_rings"),  # strict types: no strings for numbers
        ("orb-hbst", {"hbst": {"delta_max": 0.9}}, "hbst.delta_max"),
        ("orb-hbst", {"image": {"percentile": 150}}, "image.percentile"),
        ("orb-dbow", {"loop": {"use_nss": "yes"}}, "loop.use_nss"),
        ("orb-dbow", {"nn_ratio": 0}, "nn_ratio"),
        ("ishot-votes", {"search": {"tau_max": 1.5}}, "search.tau_max"),
        ("ishot-votes", {"features": {"normals": {"max_nn": 2}}}, "features.normals.max_nn"),
        ("ishot-votes", {"features": {"descriptor": "sift"}}, "features.descriptor"),
        ("map-closures", {"top_k": 0}, "top_k"),
    ],
)
def test_values_are_type_and_range_checked(name, params, where):
    with pytest.raises(ConfigError, match=rf"{name}: params\.{where}: "):
        pipeline_params(name, params)


def test_errors_never_repeat_a_huge_input():
    with pytest.raises(ConfigError) as err:
        pipeline_params("orb-hbst", {"verify": "x" * 1_000_000})
    assert len(str(err.value)) < 500


def test_parameters_are_immutable_and_keyed_by_value():
    a, b = make_pipeline("orb-hbst"), make_pipeline("orb-dbow")
    with pytest.raises(ValueError):
        a.params.hbst.delta_max = 0.2
    assert a.frontend_key == b.frontend_key  # same image and features: shared descriptions
    assert a.frontend_key != make_pipeline("orb-hbst", {"feature_params": {"nfeatures": 100}}).frontend_key


@pytest.mark.parametrize(
    "target",
    [
        "subprocess:run",
        "os:system",
        "collections:OrderedDict",
        "placerec.types:Scan",
        "placerec.recognizer:nope",
    ],
)
def test_config_classes_must_implement_the_protocol_before_anything_runs(tmp_path, target, monkeypatch):
    monkeypatch.chdir(tmp_path)
    cfg = _config(tmp_path, {"name": target, "params": {"args": "touch x", "shell": True}})
    with pytest.raises(ConfigError, match="PlaceRecognizer|not a class|nothing"):
        run_loop(cfg, ListSequence([]))
    assert not os.path.exists(tmp_path / "x")


@pytest.mark.parametrize(
    "source, error",
    [
        ("raise RuntimeError('plugin set-up failed')\n", "RuntimeError: 'plugin set-up failed'"),
        ("def broken(:\n", "SyntaxError"),
        ("import placerec_no_such_dependency\n", "ModuleNotFoundError"),
    ],
)
def test_a_config_module_that_fails_to_import_is_a_config_error_naming_it(
    tmp_path, monkeypatch, source, error
):
    (tmp_path / "bad_plugin.py").write_text(source)
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(ConfigError, match=f"cannot import module 'bad_plugin' \\({error}"):
        make_pipeline("bad_plugin:Recognizer")


def test_resolved_parameters_are_written_to_the_run_folder(tmp_path):
    from tests.test_experiment import pole_world_sequence

    cfg = _config(tmp_path, {"name": "scan-context", "params": {"num_candidates": 5}})
    seq, records = run_loop(cfg, pole_world_sequence(n_loop=20, n_revisit=0))
    run = make_run_dir(cfg)
    report_loop(cfg, run, seq, records)
    saved = yaml.safe_load((run / "pipelines.yaml").read_text())
    assert saved["scan-context"]["pipeline"] == "scan-context"
    assert saved["scan-context"]["params"]["num_candidates"] == 5
    assert saved["scan-context"]["params"]["num_rings"] == 20  # defaults resolved too


def test_placerec_pipelines_lists_pipelines_and_parameters():
    runner = CliRunner()
    listing = runner.invoke(app, ["pipelines"], env={"COLUMNS": "200"})
    assert listing.exit_code == 0 and all(name in listing.output for name in PIPELINES)
    detail = runner.invoke(app, ["pipelines", "orb-dbow"], env={"COLUMNS": "250"})
    assert detail.exit_code == 0
    for text in (
        "feature_params.fast_threshold",
        "VPR paper Table I",
        "loop.use_nss",
        "n_check",
        "image.mode",
    ):
        assert text in detail.output
    assert runner.invoke(app, ["pipelines", "nope"]).exit_code == 2


@pytest.fixture(scope="module")
def sim_scans():
    seq = SimulatedSequence(world="town", sensor="vlp16", n_scans=4, seed=5, clutter=False)
    return ListSequence([seq[i] for i in range(len(seq))], seq.poses, seq.timestamps, name="sim4")


def _describe_ms(tmp_path, names, seq=None, *overrides):
    """Describe times per pipeline of a run on a 4-scan simulation (or ``seq``) with a description cache."""
    sim = "dataset.simulator={world: town, sensor: vlp16, n_scans: 4, seed: 5, clutter: false}"
    cfg = load_config(
        None,
        [f"output.dir={tmp_path}", f"output.cache_dir={tmp_path / 'cache'}", "output.progress=false", sim]
        + list(overrides),
    )
    cfg = cfg.model_copy(update={"pipelines": [type(cfg.pipelines[0])(name=n) for n in names]})
    _, records = run_loop(cfg, seq)
    return {r.label: r.timing_ms["describe"] for r in records}


def test_describe_times_do_not_depend_on_the_cache_or_the_order(tmp_path):
    cold = _describe_ms(tmp_path, ["orb-hbst", "orb-dbow"])
    assert cold["orb-hbst"] == cold["orb-dbow"] and min(cold["orb-hbst"]) > 0  # one front end, one time
    warm = _describe_ms(tmp_path, ["orb-hbst", "orb-dbow"])
    swapped = _describe_ms(tmp_path, ["orb-dbow", "orb-hbst"])
    assert warm == cold and swapped == cold
    assert np.all(np.isfinite(cold["orb-hbst"]))


def test_a_sequence_given_to_run_loop_is_not_served_from_the_configs_cache(tmp_path, sim_scans):
    """The cache is keyed by the config's dataset: other scans passed in must not get its descriptions."""
    _describe_ms(tmp_path, ["scan-context"])  # fills the cache for the config's dataset
    blank = ListSequence([Scan(np.zeros((1000, 3)), np.zeros(1000))] * 4, sim_scans.poses, name="blank")
    got = _describe_ms(tmp_path, ["scan-context"], blank, "evaluation.exclusion.frames=0")
    assert got == {"scan-context": [0.0] * 4}  # every blank scan refused, none found in the cache


@pytest.mark.parametrize("path", ["configs/demo.yaml", "configs/vpr_os1_64.yaml", "configs/vpr_hdl64.yaml"])
def test_shipped_configs_resolve_under_the_strict_parameters(path):
    from pathlib import Path

    cfg = load_config(Path(__file__).resolve().parents[1] / path)
    for i, spec in enumerate(cfg.pipelines):
        assert pipeline_params(spec.name, spec.params, f"pipelines[{i}].params") is not None


def test_placerec_run_refuses_code_in_a_config(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    config = tmp_path / "evil.yaml"
    config.write_text(
        'pipelines: [{name: "subprocess:run", params: {args: "touch x", shell: true}}]\n'
        "output: {progress: false, cache_dir: null}\n"
    )
    result = CliRunner().invoke(app, ["run", str(config), "--out", str(tmp_path / "results")])
    assert (
        result.exit_code == 2 and "not a class implementing placerec.types.PlaceRecognizer" in result.output
    )
    assert not (tmp_path / "x").exists()


def test_runner_keeps_scan_indices_when_a_pipeline_refuses_a_scan(tmp_path):
    from placerec.types import Scan
    from tests.test_experiment import pole_world_sequence

    seq = pole_world_sequence(n_loop=40, n_revisit=10)
    scans = [seq[i] for i in range(len(seq))]
    scans[5] = Scan(np.zeros((1000, 3)), np.zeros(1000))  # a blank frame (every return invalid)
    seq = ListSequence(scans, seq.poses, seq.timestamps, name="poles-with-a-blank")
    cfg = _config(tmp_path, {"name": "scan-context"}, overrides=["evaluation.exclusion.frames=20"])
    _, (record,) = run_loop(cfg, seq)
    assert record.query_ids == list(range(len(seq))) and record.candidates[5] == []
    assert all(c.match_id != 5 for cands in record.candidates for c in cands)
    revisits = [record.candidates[q][0].match_id for q in range(40, 50) if q != 45]
    assert revisits == [
        q - 40 for q in range(40, 50) if q != 45
    ]  # ids are still scan indices after the blank
