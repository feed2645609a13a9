"""The fuzz corpus: one `Case` per hostile input, gathered from one module per surface (`SURFACES`).

A case builds its input in a temporary folder (``build(tmp_path) -> args``), feeds it to placerec
(``run(args) -> result``) and says what must happen:

* ``"error"``: a `placerec.errors.PlacerecError` (of ``error``, a subclass) whose message contains ``names`` — the
  file name or dotted config key the user has to fix (by default the name of the `Path` that ``build`` returned);
* ``"ok"``: a result, which ``check(args, result)`` verifies;
* ``"either"``: one of the two (an input whose bytes may or may not still be valid, e.g. a flipped byte), with
  the same conditions on each.

Anything else — another exception (a traceback), an error not naming what to fix, a silent load of bad data —
fails the case. A module adds its cases to `SURFACES` through `surface_cases`; the registries it covers (readers,
dataset layouts, artifact kinds) are checked at run time to have cases (``subject``) by
`tests/test_fuzz_corpus.py`, so a new reader, layout or artifact cannot land without hostile cases.
"""

from __future__ import annotations

import importlib
import traceback
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from placerec.errors import PlacerecError, short_repr

__all__ = ["Case", "SURFACES", "all_cases", "fast_cases", "run_case", "outcome", "expected_name"]

#: surface -> module (under tests/fuzz) whose ``cases()`` generates that surface's cases
SURFACES: dict[str, str] = {
    "readers": "fuzz.readers",
    "datasets": "fuzz.datasets",
    "artifacts": "fuzz.artifacts",
    "configs": "fuzz.configs",
    "slam": "fuzz.slam",
    "executors": "fuzz.executors",
    "metrics": "fuzz.metrics",
    "weights": "fuzz.weights",
}


@dataclass(frozen=True)
class Case:
    """One hostile input and its expected outcome class (module docstring)."""

    surface: str
    name: str
    build: Callable[[Path], Any]
    run: Callable[[Any], Any]
    expect: str = "error"
    names: str | Callable[[Any], str] | None = None
    error: type[PlacerecError] = PlacerecError
    check: Callable[[Any, Any], None] | None = None
    #: the registry entry the case covers (reader format, dataset layout, artifact kind); "" for none
    subject: str = ""
    #: argv of a ``placerec`` command that reads the same input (``cli(args)``), run once through the CLI
    cli: Callable[[Any], list[str]] | None = None
    #: always in the fast subset (besides the deterministic sample)
    fast: bool = False
    #: cases that take seconds (a cluster, a timeout): never sampled into the fast subset
    slow: bool = False

    def __post_init__(self) -> None:
        if self.expect not in ("error", "ok", "either"):
            raise ValueError(f"{self.id}: expect must be 'error', 'ok' or 'either', not {self.expect!r}")
        if self.expect in ("ok", "either") and self.check is None:
            raise ValueError(f"{self.id}: a case that may load needs a check of its result")

    @property
    def id(self) -> str:
        return f"{self.surface}/{self.name}"


def expected_name(case: Case, args: Any) -> str | None:
    """The text an error of ``case`` (built as ``args``) must contain."""
    if callable(case.names):
        return case.names(args)
    if case.names is not None:
        return case.names
    if isinstance(args, Path):
        return args.name
    return None


def outcome(case: Case, args: Any) -> tuple[str, Any]:
    """Run ``case`` on ``args``: ("error", the PlacerecError) or ("ok", the result); any other exception is
    raised as an AssertionError carrying its traceback."""
    try:
        return "ok", case.run(args)
    except PlacerecError as exc:
        return "error", exc
    except Exception as exc:  # the point of the corpus: nothing but a placerec error escapes
        raise AssertionError(
            f"{case.id}: {type(exc).__name__} escaped (not a placerec error):\n{traceback.format_exc()}"
        ) from exc


def run_case(case: Case, tmp_path: Path) -> None:
    """Build ``case`` under ``tmp_path``, run it and assert its outcome class."""
    args = case.build(tmp_path)
    kind, value = outcome(case, args)
    if kind == "error":
        exc = value
        assert case.expect != "ok", f"{case.id}: expected a result, got {type(exc).__name__}: {exc}"
        assert isinstance(exc, case.error), (
            f"{case.id}: expected {case.error.__name__}, got {type(exc).__name__}: {exc}"
        )
        name = expected_name(case, args)
        assert name is None or name in str(exc), (
            f"{case.id}: the message does not name {name!r}: {type(exc).__name__}: {exc}"
        )
        return
    assert case.expect != "error", f"{case.id}: no error; it returned {short_repr(value)}"
    assert case.check is not None
    case.check(args, value)


_CASES: list[Case] | None = None


def all_cases() -> list[Case]:
    """Every case of every surface, in a stable order; ids are unique."""
    global _CASES
    if _CASES is None:
        cases: list[Case] = []
        for surface, module in SURFACES.items():
            made = importlib.import_module(module).cases()
            assert all(c.surface == surface for c in made), f"{module} makes cases of another surface"
            cases.extend(made)
        ids = [c.id for c in cases]
        dupes = sorted({i for i in ids if ids.count(i) > 1})
        assert not dupes, f"repeated case ids: {dupes}"
        _CASES = cases
    return _CASES


#: one case in SAMPLE_EVERY of each surface (by a hash of its id, so the sample is stable) is in the fast subset
SAMPLE_EVERY = {"configs": 1}
DEFAULT_SAMPLE_EVERY = 4


def fast_cases() -> list[Case]:
    """The subset CI runs: every case marked ``fast``, every config case, a stable sample of the others (one in
    `DEFAULT_SAMPLE_EVERY` by a hash of its id) and at least one case of every ``subject``; never a ``slow`` one."""
    picked: list[Case] = []
    subjects: set[tuple[str, str]] = set()
    for case in all_cases():
        every = SAMPLE_EVERY.get(case.surface, DEFAULT_SAMPLE_EVERY)
        if not case.slow and (case.fast or zlib.crc32(case.id.encode()) % every == 0):
            picked.append(case)
            subjects.add((case.surface, case.subject))
    for case in all_cases():
        if not case.slow and (case.surface, case.subject) not in subjects:
            picked.append(case)
            subjects.add((case.surface, case.subject))
    order = {c.id: i for i, c in enumerate(all_cases())}
    return sorted(picked, key=lambda c: order[c.id])
