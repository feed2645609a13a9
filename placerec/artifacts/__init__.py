"""Builders of placerec's saved artifacts: one module per artifact type, each with a ``build_<artifact>(config)``
that reads its inputs (a sequence on disk or a simulated world, `placerec.artifacts.sources`), runs the algorithm's
own computation and writes the artifact atomically, returning its path. The CLI commands and the Python API both
call these builders.

* `placerec.artifacts.calibration` — the intensity calibration table (``placerec calibrate``).
* `placerec.artifacts.places` — the places database (``placerec build-places``).
* `placerec.artifacts.votes` — the vote model of probabilistic voting (``placerec fit-votes``).
* `placerec.artifacts.vocabulary` — a DBoW vocabulary (``placerec train-vocab``).
* `placerec.artifacts.superpoint` — SuperPoint's weights (``tools/train_superpoint.py``; needs torch).
* `placerec.artifacts.map` — a map folder for relocalisation and multi-session SLAM (``placerec map build``).

::

    from placerec.artifacts import build
    build("places-db", {"source": {"sim": {"world": "town"}}, "out": "places.npz", "params": {"window_m": 0}})

`BUILDERS` names each builder as ``module:function``; a new artifact is its module plus one line there. The
builder's ``config`` annotation is its settings class (a `placerec.params.Params`), which `build` resolves a
mapping into.
"""

from __future__ import annotations

import importlib
import typing
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from placerec.errors import ConfigError
from placerec.params import Params, resolve

__all__ = ["BUILDERS", "builder", "config_type", "build"]

#: Artifact type -> its builder, ``module:function`` (imported when first used).
BUILDERS: dict[str, str] = {
    "calibration": "placerec.artifacts.calibration:build_calibration",
    "places-db": "placerec.artifacts.places:build_places_db",
    "vote-model": "placerec.artifacts.votes:build_vote_model",
    "vocabulary": "placerec.artifacts.vocabulary:build_vocabulary",
    "superpoint-weights": "placerec.artifacts.superpoint:build_superpoint_weights",
    "map": "placerec.artifacts.map:build_map",
}


def builder(name: str) -> Callable[..., Path]:
    """The builder of artifact type ``name``; `ConfigError` naming the known types for another name."""
    if name not in BUILDERS:
        raise ConfigError(f"unknown artifact {name!r} (expected one of {sorted(BUILDERS)})")
    module, function = BUILDERS[name].split(":")
    return getattr(importlib.import_module(module), function)


def config_type(name: str) -> type[Params]:
    """The settings class of artifact type ``name``'s builder (its ``config`` annotation)."""
    fn = builder(name)
    return typing.get_type_hints(fn)["config"]


def build(name: str, config: Params | Mapping[str, Any], **options: Any) -> Path:
    """Build artifact ``name`` from ``config`` (its settings object, or a mapping resolved into it) and write it;
    ``options`` (e.g. ``progress``) go to the builder. Returns the artifact's path."""
    fn = builder(name)
    if not isinstance(config, Params):
        config = resolve(config_type(name), config, where=f"{name} settings")
    return fn(config, **options)
