"""docs/papers.md names only functions and classes that exist (checked on the source, without importing it)."""

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
NAME = re.compile(r"`([a-z_]+(?:\.[A-Za-z_0-9]+)+)`")


def _defined(tree: ast.Module) -> dict[str, set[str]]:
    """Top-level names of a module -> names defined in their body (methods and attributes of classes)."""
    out: dict[str, set[str]] = {}
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            inner = {
                n.name for n in getattr(node, "body", []) if isinstance(n, (ast.FunctionDef, ast.ClassDef))
            }
            out[node.name] = inner
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            out.update({t.id: set() for t in targets if isinstance(t, ast.Name)})
    return out


def _resolve(dotted: str) -> bool:
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        base = ROOT / "placerec" / Path(*parts[:cut])
        path = base.with_suffix(".py") if base.with_suffix(".py").is_file() else base / "__init__.py"
        if path.is_file():
            if cut == len(parts):
                return True
            top, *member = parts[cut:]  # a module's name, then at most one member of it
            names = _defined(ast.parse(path.read_text(encoding="utf-8")))
            return len(member) <= 1 and top in names and all(m in names[top] for m in member)
    return False


def test_every_cited_name_exists():
    text = (ROOT / "docs" / "papers.md").read_text(encoding="utf-8")
    cited = {n for n in NAME.findall(text) if n != "module.function"}
    assert len(cited) > 50
    missing = sorted(n for n in cited if not _resolve(n))
    assert not missing, f"docs/papers.md cites names that do not exist: {missing}"


def test_cited_files_exist():
    text = (ROOT / "docs" / "papers.md").read_text(encoding="utf-8")
    for path in re.findall(r"`((?:tools|configs)/[\w./-]+)`|(docs/[\w.-]+\.md)", text):
        name = path[0] or path[1]
        assert (ROOT / name).is_file(), name
