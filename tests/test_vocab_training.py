"""Vocabulary training configs (`placerec.artifacts.vocabulary`): strict keys with clear errors."""

import pytest

from placerec.artifacts.vocabulary import VocabTrainingConfig, load_training_config
from placerec.errors import ConfigError


def test_training_config_errors_name_the_key_and_the_allowed_keys(tmp_path):
    cfg = tmp_path / "voc.yaml"
    cfg.write_text("features: orb\nn_imgaes: 10\n")
    with pytest.raises(ConfigError, match=r"voc.yaml: n_imgaes: unknown key; allowed keys there: .*n_images"):
        load_training_config(cfg)
    with pytest.raises(ConfigError, match=r"k: .*greater than or equal to 2"):
        load_training_config(None, k=1)
    assert load_training_config(None, k=4).k == 4


def test_training_front_end_sections_are_validated_when_the_config_is_read(tmp_path):
    """``image`` and ``feature_params`` are the visual front end's models, checked with the rest of the config
    (before any image is formed), and the vocabulary settings are `VocabularyParams`."""
    from placerec.image import ImageParams
    from placerec.retrieval.dbow.vocabulary import VocabularyParams

    with pytest.raises(ConfigError, match=r"image\.widht: unknown key; allowed keys there: .*width"):
        VocabTrainingConfig(image={"widht": 512})
    cfg = tmp_path / "voc.yaml"
    cfg.write_text("features: brisk\nfeature_params: {nfeatures: 0}\n")
    with pytest.raises(
        ConfigError, match=r"voc.yaml: feature_params\.nfeatures: Input should be greater than 0"
    ):
        load_training_config(cfg)
    with pytest.raises(ConfigError, match=r"max_fit: Input should be greater than or equal to 100"):
        load_training_config(None, max_fit=10)
    read = VocabTrainingConfig(image={"width": 512}, features="brisk", feature_params={"octaves": 2})
    assert (
        isinstance(read.image, ImageParams) and read.image.width == 512 and read.feature_params.octaves == 2
    )
    assert isinstance(read, VocabularyParams) and (read.k, read.L, read.weighting) == (10, 5, "tf-idf")


def test_training_configs_are_read_like_experiment_configs(tmp_path):
    """One YAML config reader (`placerec.config.read_config_file`): same limits and messages for both kinds."""
    from placerec.config import load_config

    listed = tmp_path / "list.yaml"
    listed.write_text("- features: orb\n")
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text(
        "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(f"b{i}: &b{i} [*a, *a]\n" for i in range(200))
    )
    for load in (load_config, load_training_config):
        with pytest.raises(
            ConfigError, match="list.yaml: the top level of a config must be a mapping, got list"
        ):
            load(listed)
        with pytest.raises(ConfigError, match="nope.yaml: config file not found"):
            load(tmp_path / "nope.yaml")
        with pytest.raises(ConfigError, match="bomb.yaml"):
            load(bomb)
