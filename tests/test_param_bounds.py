"""Every integer parameter is bounded (issue #27 item 2): counts that set the work or memory of a run have their own
cap, every other integer `MAX_INT`; a value over it is a `ConfigError` naming the key and the cap."""

from __future__ import annotations

import importlib
import pkgutil
from typing import get_args

import pytest

import placerec
from placerec.errors import ConfigError
from placerec.params import MAX_INT, Params


def _all_params() -> set[type[Params]]:
    for mod in pkgutil.walk_packages(placerec.__path__, "placerec."):
        try:
            importlib.import_module(mod.name)
        except ImportError:  # an optional dependency (torch) missing
            continue
    out: set[type[Params]] = set()
    todo = [Params]
    while todo:
        for sub in todo.pop().__subclasses__():
            out.add(sub)
            todo.append(sub)
    return out


def _upper(field) -> int | None:
    for m in field.metadata:
        if getattr(m, "le", None) is not None:
            return int(m.le)
        if getattr(m, "lt", None) is not None:
            return int(m.lt) - 1
    return None


def test_every_integer_parameter_has_an_upper_bound():
    unbounded = []
    n = 0
    for cls in _all_params():
        for name, field in cls.model_fields.items():
            ann = field.annotation
            if ann is int or set(get_args(ann)) == {int, type(None)}:
                n += 1
                if _upper(field) is None or _upper(field) > MAX_INT:
                    unbounded.append(f"{cls.__module__}.{cls.__name__}.{name}")
    assert n > 100 and unbounded == []


def test_a_new_params_class_gets_the_default_bound():
    class Counts(Params):
        n: int = 1
        m: int | None = None

    with pytest.raises(ConfigError, match=r"n: Input should be less than or equal to 1000000000"):
        Counts(n=10**12)
    with pytest.raises(ConfigError, match=r"m: Input should be less than or equal to 1000000000"):
        Counts(m=MAX_INT + 1)
    assert Counts(n=MAX_INT).n == MAX_INT and Counts().m is None


@pytest.mark.parametrize(
    ("pipeline", "key", "value", "cap"),
    [
        ("orb-hbst", "image.width", 10**6, 32768),
        ("orb-hbst", "feature_params.nfeatures", 10**7, 100_000),
        ("orb-hbst", "verify.top_k", 10**6, 1000),
        ("orb-hbst", "verify.icp.max_iterations", 10**8, 10_000),
        ("orb-hbst", "verify.ransac.max_iterations", 10**8, 1_000_000),
        ("scan-context", "verify.icp.num_threads", 10**5, 1024),
        ("scan-context", "num_sectors", 10**12, MAX_INT),
    ],
)
def test_huge_counts_are_config_errors_naming_the_key_and_cap(pipeline, key, value, cap):
    from placerec.params import deep_merge
    from placerec.recognizer import make_pipeline

    nested: dict = value
    for part in reversed(key.split(".")):
        nested = {part: nested}
    with pytest.raises(
        ConfigError, match=rf"{key.split('.')[-1]}: Input should be less than or equal to {cap}"
    ):
        make_pipeline(pipeline, deep_merge({}, nested))


def test_vocabulary_words_are_bounded():
    from placerec.retrieval.dbow.vocabulary import VocabularyParams

    with pytest.raises(ConfigError, match=r"k\^L = 1000\^5 words is more than 10\^8"):
        VocabularyParams(k=1000, L=5)
    assert VocabularyParams(k=10, L=8).k == 10
