"""YAML loading with limits, for every YAML file placerec reads (configs, ``sensor.yaml``, training configs).

`yaml.safe_load` refuses code but not size: a few hundred bytes of nested aliases ("billion laughs") compose to a
small graph that expands to billions of nodes in whatever walks it next (validation, ``repr`` in an error
message), and a few thousand nested brackets exhaust the recursion limit. `load_yaml` rejects, before anything
walks the document:

* documents over ``max_bytes`` (`MAX_BYTES`, 1 MiB),
* nesting deeper than ``max_depth`` (`MAX_DEPTH`, 64 levels), checked while composing,
* more than ``max_aliases`` alias references (`MAX_ALIASES`, 1000),
* documents whose nodes, with every alias expanded, number more than ``max_nodes`` (`MAX_NODES`, 100 000), and
  recursive aliases (a node that contains itself).

Every failure raises the caller's placerec error class (`ConfigError` by default) naming the file and the limit.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from placerec.errors import ConfigError, PlacerecError

__all__ = ["load_yaml", "load_yaml_file", "MAX_BYTES", "MAX_DEPTH", "MAX_ALIASES", "MAX_NODES"]

MAX_BYTES = 1 << 20
MAX_DEPTH = 64
MAX_ALIASES = 1000
MAX_NODES = 100_000


class _LimitExceeded(Exception):
    """Raised inside the loader; `load_yaml` turns it into the caller's error class."""


class _BoundedLoader(yaml.SafeLoader):
    """`yaml.SafeLoader` that counts nesting depth and alias references while composing the node graph."""

    def __init__(self, stream: str, max_depth: int, max_aliases: int) -> None:
        super().__init__(stream)
        self._depth, self._aliases = 0, 0
        self._max_depth, self._max_aliases = max_depth, max_aliases

    def compose_node(self, parent: yaml.Node | None, index: Any) -> yaml.Node:
        if self.check_event(yaml.AliasEvent):
            self._aliases += 1
            if self._aliases > self._max_aliases:
                raise _LimitExceeded(f"more than {self._max_aliases} alias references")
        self._depth += 1
        if self._depth > self._max_depth:
            raise _LimitExceeded(f"nesting deeper than {self._max_depth} levels")
        try:
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


def _children(node: yaml.Node) -> list[yaml.Node]:
    if isinstance(node, yaml.SequenceNode):
        return list(node.value)
    if isinstance(node, yaml.MappingNode):
        return [part for pair in node.value for part in pair]
    return []


def _check_expansion(root: yaml.Node, max_nodes: int) -> None:
    """Raise `_LimitExceeded` if the graph, with shared (aliased) nodes expanded, exceeds ``max_nodes`` nodes or
    contains a cycle. Sizes are memoised per node, so the walk costs the graph's size, not its expansion's."""
    size: dict[int, int] = {}
    on_path: set[int] = set()
    stack: list[tuple[yaml.Node, bool]] = [(root, False)]
    while stack:
        node, done = stack.pop()
        key = id(node)
        if done:
            on_path.discard(key)
            size[key] = min(1 + sum(size[id(c)] for c in _children(node)), max_nodes + 1)
            if size[key] > max_nodes:
                raise _LimitExceeded(f"more than {max_nodes} nodes once aliases are expanded")
            continue
        if key in size:
            continue
        if key in on_path:
            raise _LimitExceeded("a recursive alias (a node that contains itself)")
        on_path.add(key)
        stack.append((node, True))
        stack.extend((c, False) for c in _children(node) if id(c) not in size)


def load_yaml(
    data: str | bytes,
    where: str | Path,
    error: type[PlacerecError] = ConfigError,
    *,
    max_bytes: int = MAX_BYTES,
    max_depth: int = MAX_DEPTH,
    max_aliases: int = MAX_ALIASES,
    max_nodes: int = MAX_NODES,
) -> Any:
    """Parse one YAML document (safe tags only) within the module's limits; ``error`` names ``where`` on failure."""
    if len(data) > max_bytes:
        raise error(f"{where}: YAML document of {len(data)} bytes exceeds the limit of {max_bytes} bytes")
    try:
        text = data.decode("utf-8") if isinstance(data, bytes) else data
    except UnicodeDecodeError as exc:
        raise error(f"{where}: YAML is not UTF-8 text ({exc})") from None
    loader = _BoundedLoader(text, max_depth, max_aliases)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        _check_expansion(node, max_nodes)
        return loader.construct_document(node)
    except _LimitExceeded as exc:
        raise error(f"{where}: YAML document rejected: {exc} (placerec.safe_yaml limits)") from None
    except yaml.YAMLError as exc:
        raise error(f"{where}: not valid YAML ({exc})") from None
    finally:
        loader.dispose()


def load_yaml_file(path: str | Path, error: type[PlacerecError] = ConfigError, **limits: int) -> Any:
    """`load_yaml` of a file's contents; the size is checked before the file is read."""
    p = Path(path)
    max_bytes = limits.get("max_bytes", MAX_BYTES)
    try:
        size = p.stat().st_size
        if size > max_bytes:
            raise error(f"{p}: YAML file of {size} bytes exceeds the limit of {max_bytes} bytes")
        data = p.read_bytes()
    except OSError as exc:
        raise error(f"{p}: cannot read YAML file ({exc})") from None
    return load_yaml(data, p, error, **limits)
