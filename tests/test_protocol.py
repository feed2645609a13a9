"""The tuning / test split (`placerec.experiment.protocol`, docs/protocol.md): no committed config or preset may
name a test-split seed, so no default can be chosen on the held-out benchmark."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from placerec.experiment import protocol
from placerec.recognizer import PIPELINES
from placerec.safe_yaml import load_yaml_file

ROOT = Path(__file__).resolve().parents[1]


def _seeds(node: Any, path: str = "") -> list[tuple[str, int]]:
    """(dotted key, value) of every integer under a key naming a seed, at any depth of a YAML / preset tree."""
    found: list[tuple[str, int]] = []
    if isinstance(node, dict):
        for key, value in node.items():
            where = f"{path}.{key}" if path else str(key)
            if "seed" in str(key).lower():
                values = value if isinstance(value, list) else [value]
                found += [(where, v) for v in values if isinstance(v, int) and not isinstance(v, bool)]
            found += _seeds(value, where)
    elif isinstance(node, list):
        for i, value in enumerate(node):
            found += _seeds(value, f"{path}[{i}]")
    return found


def test_seed_finder_reads_nested_keys_and_lists():
    tree = {"a": {"seed": 4}, "b": [{"seeds": [1, 2]}], "validation_seed": 3, "c": {"x": 4601}}
    assert sorted(_seeds(tree)) == [
        ("a.seed", 4),
        ("b[0].seeds", 1),
        ("b[0].seeds", 2),
        ("validation_seed", 3),
    ]


def test_test_split_is_disjoint_from_the_tuning_split():
    assert not set(protocol.TEST_SEEDS) & set(protocol.TUNING_SEEDS)
    assert protocol.LOCALIZE_TEST_DRAW != protocol.LOCALIZE_TUNING_DRAW
    assert protocol.is_test_seed(protocol.TEST_SEEDS[0]) and not protocol.is_test_seed(0)


@pytest.mark.parametrize("path", sorted((ROOT / "configs").glob("*.yaml")), ids=lambda p: p.name)
def test_no_committed_config_names_a_test_seed(path):
    bad = [(k, v) for k, v in _seeds(load_yaml_file(path)) if protocol.is_test_seed(v)]
    assert not bad, f"{path.name} names test-split seeds {bad}: no default may be chosen on the test split"


def test_no_preset_names_a_test_seed():
    bad = [
        (name, k, v) for name, e in PIPELINES.items() for k, v in _seeds(e.preset) if protocol.is_test_seed(v)
    ]
    assert not bad


def test_a_config_naming_a_test_seed_is_caught(tmp_path):
    path = tmp_path / "tuned.yaml"
    path.write_text(f"dataset:\n  simulator: {{world: town, seed: {protocol.TEST_SEEDS[1]}}}\n")
    assert [v for _, v in _seeds(load_yaml_file(path)) if protocol.is_test_seed(v)] == [
        protocol.TEST_SEEDS[1]
    ]
