"""The package layout: no import cycles, algorithm layers independent of the experiment layer, shipped data found
as package data (so a wheel install works)."""

from __future__ import annotations

import ast
import importlib.metadata
import importlib.resources
import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
import tomllib

from placerec.errors import ArtifactError
from placerec.pipelines.dbow import SHIPPED, default_vocabulary_path, resolve_vocabulary

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "placerec"
#: The intended layering, top to bottom (see the file's own comments).
LAYERS_FILE = ROOT / "layers.toml"


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_type_checking(node: ast.If) -> bool:
    t = node.test
    return (isinstance(t, ast.Name) and t.id == "TYPE_CHECKING") or (
        isinstance(t, ast.Attribute) and t.attr == "TYPE_CHECKING"
    )


def _imports(module: str, path: Path, modules: set[str]) -> set[tuple[str, bool]]:
    """(imported placerec module, whether the import is inside a function) for every import in ``path``.

    ``from a.b import c`` counts as importing ``a.b.c`` when that is a module, else ``a.b``. Imports under
    ``if TYPE_CHECKING:`` never run and are skipped.
    """
    package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    found: set[tuple[str, bool]] = set()

    def visit(node: ast.AST, lazy: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and _is_type_checking(child):
                for stmt in child.orelse:
                    visit(stmt, lazy)
                continue
            inner = lazy or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            if isinstance(child, ast.Import):
                found.update((a.name, inner) for a in child.names)
            elif isinstance(child, ast.ImportFrom):
                if child.level:
                    parent = package[: len(package) - child.level + 1]
                    base = ".".join(parent + ([child.module] if child.module else []))
                else:
                    base = child.module or ""
                for a in child.names:
                    sub = f"{base}.{a.name}"
                    found.add((sub if sub in modules else base, inner))
            visit(child, inner)

    visit(ast.parse(path.read_text(), str(path)), False)
    return {(name, lazy) for name, lazy in found if name in modules and name != module}


def import_graph() -> dict[str, set[tuple[str, bool]]]:
    """Module -> {(placerec module it imports, lazy)} over every module of the package."""
    paths = {_module_name(p): p for p in PACKAGE.rglob("*.py")}
    names = set(paths)
    return {m: _imports(m, p, names) for m, p in paths.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def connect(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            connect(v)
    return found


def test_cycle_finder_on_a_hand_made_graph():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a", "e"}, "e": {"d"}, "f": set()}
    assert _cycles(graph) == [["a", "b", "c"], ["d", "e"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_import_graph_resolves_relative_lazy_and_type_checking_imports(tmp_path):
    src = tmp_path / "mod.py"
    src.write_text(
        "from typing import TYPE_CHECKING\nfrom . import b\nfrom .c import thing\n"
        "if TYPE_CHECKING:\n    from pkg.d import D\n"
        "def f():\n    import pkg.e\n"
    )
    modules = {"pkg.mod", "pkg.b", "pkg.c", "pkg.d", "pkg.e"}
    assert _imports("pkg.mod", src, modules) == {("pkg.b", False), ("pkg.c", False), ("pkg.e", True)}


def test_no_import_cycles():
    """No two modules of the package depend on each other, directly or through others.

    Function-level (lazy) imports count: they only defer the circle to the first call, the two layers still depend
    on each other. A package importing its own submodules (``__init__`` re-exports) is not an edge back: importing
    ``a.b`` runs ``a/__init__.py`` first, but that is Python's package mechanism, not a dependency of ``a.b``.
    """
    graph = import_graph()
    cycles = _cycles({m: {t for t, _ in edges} for m, edges in graph.items()})
    lines = []
    for cycle in cycles:
        lines.append(" <-> ".join(cycle))
        for m in cycle:
            lines += [
                f"    {m} -> {t}{' (lazy)' if lazy else ''}" for t, lazy in sorted(graph[m]) if t in cycle
            ]
    assert not cycles, "import cycles:\n" + "\n".join(lines)


def read_layers(path: Path = LAYERS_FILE) -> list[tuple[str, list[str]]]:
    """(name, module prefixes) of every layer in ``path``, top to bottom; `ValueError` for a prefix listed twice."""
    data = tomllib.loads(path.read_text(encoding="utf-8"))
    layers = [(str(layer["name"]), [str(m) for m in layer["modules"]]) for layer in data["layer"]]
    listed = [m for _, modules in layers for m in modules]
    twice = sorted({m for m in listed if listed.count(m) > 1})
    if twice:
        raise ValueError(f"{path.name}: listed in more than one layer: {twice}")
    return layers


def layer_of(module: str, layers: list[tuple[str, list[str]]]) -> int | None:
    """Index (0 = top) of the layer listing the longest prefix of ``module`` (the bare package name matches only
    the package's ``__init__``); None when no layer lists it."""
    best: tuple[int, int] | None = None
    for i, (_, prefixes) in enumerate(layers):
        for p in prefixes:
            hit = module == p or (module.startswith(p + ".") and "." in p)
            if hit and (best is None or len(p) > best[1]):
                best = (i, len(p))
    return None if best is None else best[0]


def layering_violations(
    graph: dict[str, set[tuple[str, bool]]], layers: list[tuple[str, list[str]]]
) -> tuple[list[str], list[str]]:
    """(modules in no layer, imports that go up: ``module (layer) -> target (layer)``) of an import graph."""
    unlisted = sorted(m for m in graph if layer_of(m, layers) is None)
    upward = []
    for m, edges in sorted(graph.items()):
        mine = layer_of(m, layers)
        for t, lazy in sorted(edges):
            theirs = layer_of(t, layers)
            if mine is not None and theirs is not None and theirs < mine:
                upward.append(
                    f"{m} ({layers[mine][0]}) -> {t} ({layers[theirs][0]}){' (lazy)' if lazy else ''}"
                )
    return unlisted, upward


def test_layering_checker_catches_an_upward_import_and_an_unlisted_module(tmp_path):
    layers_file = tmp_path / "layers.toml"
    layers_file.write_text(
        '[[layer]]\nname = "app"\nmodules = ["pkg.app"]\n'
        '[[layer]]\nname = "core"\nmodules = ["pkg", "pkg.core", "pkg.core.special"]\n'
    )
    layers = read_layers(layers_file)
    graph = {
        "pkg": set(),
        "pkg.app.run": {("pkg.core.math", False)},  # down: fine
        "pkg.core.math": {("pkg.app.run", True)},  # up, inside a function: still a violation
        "pkg.core.special.x": {("pkg.core.math", False)},  # same layer: fine
        "pkg.stray": {("pkg.core.math", False)},  # no layer lists it (the bare "pkg" names only the package)
    }
    unlisted, upward = layering_violations(graph, layers)
    assert unlisted == ["pkg.stray"]
    assert upward == ["pkg.core.math (core) -> pkg.app.run (app) (lazy)"]
    layers_file.write_text(
        '[[layer]]\nname = "a"\nmodules = ["pkg.x"]\n[[layer]]\nname = "b"\nmodules = ["pkg.x"]\n'
    )
    with pytest.raises(ValueError, match="more than one layer"):
        read_layers(layers_file)


def test_every_import_follows_the_layers_file():
    """layers.toml says which layer every module is in; no module imports a layer above its own."""
    unlisted, upward = layering_violations(import_graph(), read_layers())
    assert not unlisted, "modules that layers.toml does not place in a layer:\n" + "\n".join(unlisted)
    assert not upward, "imports of a higher layer (layers.toml):\n" + "\n".join(upward)


def test_shipped_vocabularies_are_package_data():
    """The default vocabulary is found with importlib.resources inside the installed package, not the checkout."""
    data = importlib.resources.files("placerec").joinpath("vocab")
    for features, name in SHIPPED.items():
        path = default_vocabulary_path(features)
        assert path == Path(str(data.joinpath(name))) and path.is_file()
        assert resolve_vocabulary(None, features) == path


def test_vocabulary_paths_are_read_from_the_working_directory(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    shipped = default_vocabulary_path("orb")
    # a relative path naming a shipped file that is not in the working directory: the shipped one
    assert resolve_vocabulary("vocab/orb_k10L5.dbow", "orb") == shipped
    own = tmp_path / "vocab" / "orb_k10L5.dbow"
    own.parent.mkdir()
    own.write_bytes(b"mine")
    assert resolve_vocabulary("vocab/orb_k10L5.dbow", "orb").resolve() == own  # the user's own file wins
    with pytest.raises(ArtifactError, match="missing/voc.dbow"):
        resolve_vocabulary("missing/voc.dbow", "orb")


def _distribution(requirement: str) -> str:
    """The normalised distribution name of a requirement (PEP 503)."""
    return re.sub(r"[-_.]+", "-", re.match(r"[A-Za-z0-9_.-]+", requirement).group(0)).lower()


def _third_party_imports(*folders: Path) -> set[str]:
    names: set[str] = set()
    for folder in folders:
        for path in folder.rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, ast.Import):
                    names.update(a.name.split(".")[0] for a in node.names)
                elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
                    names.add(node.module.split(".")[0])
    return names - set(sys.stdlib_module_names) - {"placerec"}


def test_dependencies_match_what_the_code_imports():
    """A default code path needs only core dependencies: faiss searches the 3D pipelines' compressed stores. Every
    package placerec imports is declared, and an extra lists only packages that the package, its tests or its tools
    import (no empty ``learned`` extra before a module uses torch)."""
    tomllib = pytest.importorskip("tomllib", reason="reading pyproject.toml needs Python >= 3.11")
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    core = {_distribution(r) for r in project["dependencies"]}
    extras = {
        k: {_distribution(r) for r in v} for k, v in project["optional-dependencies"].items() if k != "dev"
    }
    assert "faiss-cpu" in core
    provides = {
        m: {_distribution(d) for d in ds} for m, ds in importlib.metadata.packages_distributions().items()
    }
    # rerun-sdk puts its `rerun` package on the path with a .pth file, which packages_distributions does not read
    provides.setdefault("rerun", {"rerun-sdk"})
    declared = core.union(*extras.values())
    undeclared = {m for m in _third_party_imports(PACKAGE) if m in provides and not provides[m] & declared}
    assert not undeclared, f"placerec imports packages no dependency declares: {sorted(undeclared)}"
    used = set().union(
        *(provides.get(m, set()) for m in _third_party_imports(PACKAGE, ROOT / "tests", ROOT / "tools"))
    )
    unused = {k: sorted(v - used) for k, v in extras.items() if v - used}
    assert not unused, f"extras listing packages nothing imports: {unused}"


@pytest.mark.slow
def test_wheel_carries_the_vocabularies_and_finds_them(tmp_path):
    """Build a wheel, unpack it (what pip install does) and resolve and load the default vocabulary from there."""
    src = tmp_path / "src"  # a clean copy: no stale build/ folder, nothing written into the checkout
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    shutil.copytree(PACKAGE, src / "placerec", ignore=shutil.ignore_patterns("__pycache__"))
    wheels = tmp_path / "wheels"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "-q",
            "--no-deps",
            "--no-build-isolation",
            "-w",
            str(wheels),
            str(src),
        ],
        check=True,
        cwd=tmp_path,
    )
    (wheel,) = wheels.glob("placerec-*.whl")
    with zipfile.ZipFile(wheel) as zf:
        names = set(zf.namelist())
        site = tmp_path / "site"
        zf.extractall(site)
    for name in set(SHIPPED.values()):
        assert f"placerec/vocab/{name}" in names
        assert f"placerec/vocab/{Path(name).stem}.json" in names
    code = (
        "import placerec, sys\n"
        "from placerec.pipelines.dbow import default_vocabulary_path\n"
        "from placerec.retrieval.dbow.io import load_vocabulary\n"
        "p = default_vocabulary_path('orb')\n"
        f"assert str(p).startswith({str(site)!r}), (placerec.__file__, p)\n"
        "print(load_vocabulary(p).n_words)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        cwd=tmp_path,
        env={"PYTHONPATH": str(site), "PATH": "/usr/bin:/bin"},
        capture_output=True,
        text=True,
    )
    assert out.returncode == 0, out.stderr
    assert int(out.stdout) > 5000
