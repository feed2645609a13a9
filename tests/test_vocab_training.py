"""Vocabulary training configs (`placerec.artifacts.vocabulary`): strict keys with clear errors."""

import numpy as np
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


def test_keyframe_training_images_are_the_keyframes_an_experiment_describes():
    """With ``keyframes`` set (and the simulator driven as the benchmark drives a sensor that does not spin), the
    training images are the keyframes an experiment with the same settings describes: the same descriptors as the
    ORB-DBoW pipeline's front end on those keyframes, and another descriptor cache key than single scans."""
    from placerec.artifacts.vocabulary import collect_descriptors, descriptor_cache_key
    from placerec.config import ExperimentConfig
    from placerec.experiment.preprocessing import preprocessed_scan
    from placerec.experiment.runner import loop_sequence
    from placerec.keyframes import KeyframeSequence
    from placerec.recognizer import make_pipeline

    sim = {"worlds": ["town"], "sensors": ["avia"], "seeds": [101], "rate_hz": 10, "sweep_motion": True,
           "odometry_drift": 0.01}  # fmt: skip
    keyframes = {"seconds": 0.5, "every_metres": 1.8}
    cfg = VocabTrainingConfig(features="orb", n_images=2, simulator=sim, keyframes=keyframes)
    parts, labels = collect_descriptors(cfg)
    assert labels == ["town/avia/seed101"] * 2

    dataset = {"simulator": {"world": "town", "sensor": "avia", "seed": 101, "rate_hz": 10, "sweep_motion": True,
                             "odometry_drift": 0.01}}  # fmt: skip
    exp = ExperimentConfig.model_validate({"dataset": dataset, "keyframes": keyframes})
    seq = loop_sequence(exp)
    assert isinstance(seq, KeyframeSequence) and len(seq) < len(seq.base) / 2
    pipeline = make_pipeline("orb-dbow", {"verify": {"enabled": False}})
    for part, index in zip(parts, (0, len(seq) - 1), strict=True):
        scan, _ = preprocessed_scan(seq, index, exp.preprocess)
        assert scan.shape is None and scan.xyz.shape[0] > 0  # an unorganised keyframe cloud
        np.testing.assert_array_equal(part, pipeline.describe(scan)["descriptors"])

    single = cfg.model_copy(update={"keyframes": None})
    assert descriptor_cache_key(single) != descriptor_cache_key(cfg)
