"""Vocabulary training configs (`placerec.experiment.vocab_training`): strict keys with clear errors."""

import pytest

from placerec.errors import ConfigError
from placerec.experiment.vocab_training import VocabTrainingConfig, image_params_of, load_training_config


def test_training_config_errors_name_the_key_and_the_allowed_keys(tmp_path):
    cfg = tmp_path / "voc.yaml"
    cfg.write_text("features: orb\nn_imgaes: 10\n")
    with pytest.raises(ConfigError, match=r"voc.yaml: n_imgaes: unknown key; allowed keys there: .*n_images"):
        load_training_config(cfg)
    with pytest.raises(ConfigError, match=r"k: .*greater than or equal to 2"):
        load_training_config(None, k=1)
    assert load_training_config(None, k=4).k == 4


def test_training_image_section_is_validated_as_image_params():
    with pytest.raises(ConfigError, match=r"image\.widht: unknown key; allowed keys there: .*width"):
        image_params_of(VocabTrainingConfig(image={"widht": 512}))
    assert image_params_of(VocabTrainingConfig(image={"width": 512})).width == 512
