"""Load a script of ``tools/`` as a module, for its tests: the tools are scripts, not a package."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

TOOLS = Path(__file__).resolve().parents[1] / "tools"


def load_tool(stem: str, name: str | None = None) -> ModuleType:
    """``tools/<stem>.py`` executed as the module ``name`` (default ``stem``), registered in `sys.modules` so
    that its dataclasses and pickled functions resolve their module."""
    spec = importlib.util.spec_from_file_location(name or stem, TOOLS / f"{stem}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module
