"""One parameter mechanism: every pipeline, component and config section is a strict `placerec.params.Params`.

The walk follows field annotations (``X``, ``X | None``, ``list[X]``, ``SerializeAsAny[X]``) and the values of
resolved instances (e.g. the extractor model behind a visual pipeline's ``feature_params``), so a nested section
added later on another base, or as a loose ``dict``, fails here.
"""

from __future__ import annotations

from typing import Any, get_args

import numpy as np
import pytest
from pydantic import BaseModel

from placerec.params import Params
from placerec.recognizer import PIPELINES, pipeline_params


def _models_in_annotation(annotation: Any) -> list[type]:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    return [m for arg in get_args(annotation) for m in _models_in_annotation(arg)]


def _walk(model: type[BaseModel], seen: dict[type, str], path: str) -> None:
    """Every model class reachable from ``model`` through its field annotations, with a path to it."""
    if model in seen:
        return
    seen[model] = path
    for name, field in model.model_fields.items():
        for nested in _models_in_annotation(field.annotation):
            _walk(nested, seen, f"{path}.{name}")


def _walk_values(value: Any, seen: dict[type, str], path: str) -> None:
    """Every model instance inside a resolved value (nested sections, lists of sections)."""
    if isinstance(value, BaseModel):
        _walk(type(value), seen, path)
        for name in type(value).model_fields:
            _walk_values(getattr(value, name), seen, f"{path}.{name}")
    elif isinstance(value, list | tuple):
        for i, item in enumerate(value):
            _walk_values(item, seen, f"{path}[{i}]")


def _loose_mappings(model: type[BaseModel]) -> list[str]:
    """Fields typed as a plain mapping of settings (validated later, if at all)."""
    return [
        name for name, f in model.model_fields.items() if getattr(f.annotation, "__origin__", None) is dict
    ]


def _assert_strict(seen: dict[type, str], allowed_dicts: dict[type, set[str]] | None = None) -> None:
    bad = []
    for model, path in seen.items():
        if not issubclass(model, Params):
            bad.append(f"{path}: {model.__qualname__} is not a Params model")
        elif model.model_config.get("extra") != "forbid":
            bad.append(f"{path}: {model.__qualname__} does not forbid unknown keys")
        loose = set(_loose_mappings(model)) - (allowed_dicts or {}).get(model, set())
        if loose:
            bad.append(f"{path}: {model.__qualname__} has loose dict fields {sorted(loose)}")
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("name", sorted(PIPELINES))
def test_every_registered_pipeline_has_strict_params_at_every_level(name):
    params = pipeline_params(name)
    seen: dict[type, str] = {}
    _walk(type(params), seen, name)
    _walk_values(params, seen, name)
    _assert_strict(seen)
    assert len(seen) >= 1


def test_every_config_section_is_a_strict_params_model():
    from placerec.artifacts.vocabulary import load_training_config
    from placerec.config import ExperimentConfig, PipelineSpec, load_config

    seen: dict[type, str] = {}
    for cfg, name in ((load_config(None), "experiment"), (load_training_config(None), "train-vocab")):
        _walk(type(cfg), seen, name)
        _walk_values(cfg, seen, name)
    # a pipeline's ``params`` are validated by the pipeline named beside them (the test above)
    _assert_strict(seen, {PipelineSpec: {"params"}})
    names = {m.__name__ for m in seen}
    assert {"DatasetConfig", "IntensityParams", "LocalizeConfig", "TrainingSimulator", "ImageParams"} <= names
    assert ExperimentConfig in seen


def test_component_models_are_strict():
    """Settings of the components the pipelines and commands build (also usable on their own)."""
    from placerec.calibration import CalibrationParams
    from placerec.features import EXTRACTORS
    from placerec.features.surf import SURFParams
    from placerec.intensity import IntensitySpec
    from placerec.preprocess import PreprocessParams
    from placerec.retrieval.dbow.vocabulary import VocabularyParams
    from placerec.retrieval.hbst import HBSTParams
    from placerec.three_d.descriptors import DESCRIPTOR_OPTIONS
    from placerec.three_d.places import PlacesParams

    roots = [
        CalibrationParams,
        SURFParams,
        IntensitySpec,
        PreprocessParams,
        VocabularyParams,
        HBSTParams,
        PlacesParams,
        *DESCRIPTOR_OPTIONS.values(),
        *(cls.Params for cls in EXTRACTORS.values()),
    ]
    seen: dict[type, str] = {}
    for root in roots:
        _walk(root, seen, root.__name__)
    _assert_strict(seen)


def test_the_walk_catches_a_section_on_another_base():
    """The check itself: a nested plain pydantic section, or a loose dict of settings, is reported."""

    class Loose(BaseModel):
        x: int = 0

    class Outer(Params):
        inner: Loose = Loose()
        extra_settings: dict[str, int] = {}

    seen: dict[type, str] = {}
    _walk(Outer, seen, "outer")
    with pytest.raises(AssertionError, match=r"outer\.inner: .*Loose is not a Params model"):
        _assert_strict(seen)
    with pytest.raises(AssertionError, match=r"loose dict fields \['extra_settings'\]"):
        _assert_strict({Outer: "outer"})


def test_model_validate_reports_like_building_the_model():
    """``Params.model_validate`` raises the same `ConfigError` as the constructor (no pydantic error wrapping the
    formatted one), at any nesting."""
    from placerec.config import ExperimentConfig
    from placerec.errors import ConfigError

    data = {"preprocess": {"intensity": {"mode": "linear"}}, "bogus": 1}
    with pytest.raises(ConfigError) as built:
        ExperimentConfig(**data)
    with pytest.raises(ConfigError) as validated:
        ExperimentConfig.model_validate(data)
    assert str(built.value) == str(validated.value)
    assert str(validated.value).splitlines() == [
        "ExperimentConfig:",
        "  preprocess.intensity: mode 'linear' needs a 'saturation' value",
        "  bogus: unknown key; allowed keys there: dataset, evaluation, execution, keyframes, name, output, pipelines, preprocess",
    ]


def test_the_exclusion_window_is_one_model_for_the_config_the_detector_and_the_ground_truth():
    from placerec.config import load_config
    from placerec.errors import ConfigError
    from placerec.eval.exclusion import ExclusionWindow

    window = load_config(None, ["evaluation.exclusion.metres=40"]).evaluation.exclusion
    assert (
        isinstance(window, ExclusionWindow)
        and window.model_dump() == ExclusionWindow(120, None, 40.0).model_dump()
    )
    positions = np.c_[np.arange(130.0) * 0.5, np.zeros((130, 2))]  # 0.5 m per frame: 80 frames make 40 m
    assert window.sequence_bounds(130, positions=positions)[-1] == 129 - 120  # both limits apply; frames bind
    with pytest.raises(
        ConfigError, match=r"evaluation\.exclusion\.frames: Input should be greater than or equal"
    ):
        load_config(None, ["evaluation.exclusion.frames=-1"])
    with pytest.raises(
        ConfigError, match=r"ExclusionWindow: frames: Input should be greater than or equal to 0"
    ):
        ExclusionWindow(-1)
