import pytest
import yaml

from placerec.config import ExperimentConfig, apply_overrides, dump_default_config, load_config
from placerec.errors import ConfigError


def test_defaults_roundtrip_through_dump(tmp_path):
    path = tmp_path / "cfg.yaml"
    dump_default_config(path)
    assert load_config(path) == ExperimentConfig()


def test_typo_names_key_and_allowed_keys(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("preprocess:\n  max_rnage: 50\n")
    with pytest.raises(ConfigError) as exc:
        load_config(path)
    msg = str(exc.value)
    assert "preprocess.max_rnage" in msg and "max_range" in msg and str(path) in msg


def test_nested_typo_and_bad_value():
    with pytest.raises(ConfigError, match=r"dataset\.simulator\.sede.*seed"):
        load_config(None, ["dataset.simulator.sede=3"])
    with pytest.raises(ConfigError, match="voxel_size"):
        load_config(None, ["preprocess.voxel_size=-1"])
    with pytest.raises(
        ConfigError,
        match="bogus: unknown key; allowed keys there: dataset, evaluation, execution, keyframes, name",
    ):
        load_config(None, ["bogus=1"])
    with pytest.raises(ConfigError, match=r"preprocess\.intensity: mode 'linear' needs a 'saturation'"):
        load_config(None, ["preprocess.intensity.mode=linear"])
    with pytest.raises(ConfigError, match=r"preprocess\.intensity\.percentile: .*less than or equal to 100"):
        load_config(None, ["preprocess.intensity.percentile=101"])


def test_overrides_parse_yaml_values():
    cfg = load_config(
        None,
        [
            "dataset.simulator.n_scans=50",
            "preprocess.intensity.mode=linear",
            "preprocess.intensity.saturation=100",
        ],
    )
    assert cfg.dataset.simulator.n_scans == 50 and cfg.preprocess.intensity.saturation == 100.0
    with pytest.raises(ConfigError, match="key.path=value"):
        apply_overrides({}, ["novalue"])


def test_missing_and_malformed_files(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("a: [1, 2\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(bad)
    lst = tmp_path / "list.yaml"
    lst.write_text(yaml.safe_dump([1, 2]))
    with pytest.raises(ConfigError, match="mapping"):
        load_config(lst)


def test_path_source_needs_path():
    with pytest.raises(ConfigError, match="needs dataset.path"):
        load_config(None, ["dataset.source=path"])


def test_errors_inside_lists_and_optional_sections(tmp_path):
    path = tmp_path / "p.yaml"
    path.write_text("pipelines:\n  - name: scan-context\n    lable: sc\n")
    with pytest.raises(
        ConfigError,
        match=r"pipelines\[0\]\.lable: unknown key; allowed keys there: label, loop_filter, name, params",
    ):
        load_config(path)
    with pytest.raises(ConfigError, match=r"evaluation\.localize\.map\.pth.*path"):
        load_config(None, ["evaluation.localize.map.pth=x"])
    with pytest.raises(ConfigError, match="labels must be unique"):
        load_config(None, ["pipelines=[{name: a}, {name: a}]"])
