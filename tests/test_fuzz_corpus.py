"""The fuzz corpus (#27, `tests/fuzz`): every hostile input of every surface ends in its expected outcome class —
a placerec error naming the file or key to fix, or a correct result — never a traceback.

CI runs the fast subset (`fuzz.corpus.fast_cases`: every config case and a stable sample of the others, at least
one per reader, layout and artifact kind); ``pytest -m slow tests/test_fuzz_corpus.py`` runs the whole corpus.
The coverage tests below enumerate the registries at run time, so a new reader, dataset layout, artifact kind,
pipeline or config count cannot land without its hostile cases."""

from __future__ import annotations

import zlib

import pytest
from fuzz.configs import UNBOUNDED_INTS, unbounded_ints
from fuzz.corpus import SURFACES, Case, all_cases, fast_cases, outcome, run_case
from typer.testing import CliRunner

from placerec.artifacts import BUILDERS
from placerec.io.datasets import DATASET_LOADERS
from placerec.io.registry import SCAN_READERS
from placerec.recognizer import PIPELINES

ALL = all_cases()
FAST = fast_cases()


def _id(case: Case) -> str:
    return case.id


@pytest.mark.parametrize("case", FAST, ids=_id)
def test_fuzz_case(case: Case, tmp_path) -> None:
    run_case(case, tmp_path)


@pytest.mark.slow
@pytest.mark.parametrize("case", ALL, ids=_id)
def test_fuzz_case_full(case: Case, tmp_path) -> None:
    run_case(case, tmp_path)


# ------------------------------------------------------------------------------------------- through the CLI
def _cli_sample(cases: list[Case], every: int) -> list[Case]:
    """Cases whose input a CLI command reads (``placerec info`` summarises a sequence from its first scans, so a
    case damaging a later scan has no ``cli``): the first error case of each subject and one in ``every``."""
    with_cli = [c for c in cases if c.cli is not None and not c.slow]
    picked, seen = [], set()
    for c in with_cli:
        first = c.expect == "error" and c.subject not in seen
        if first or zlib.crc32(c.id.encode()) % every == 0:
            picked.append(c)
            seen.add(c.subject) if first else None
    return picked


def _through_cli(case: Case, tmp_path) -> None:
    from placerec.cli import app

    args = case.build(tmp_path)
    assert case.cli is not None
    argv = case.cli(args)
    result = CliRunner().invoke(app, argv)
    tb = (
        "" if result.exc_info is None else "".join(__import__("traceback").format_exception(*result.exc_info))
    )
    assert result.exception is None or isinstance(result.exception, SystemExit), (
        f"{case.id}: placerec {argv} ended in a traceback:\n{tb}"
    )
    if case.expect == "ok":
        assert result.exit_code == 0, f"{case.id}: placerec {argv}: exit {result.exit_code}\n{result.output}"
        return
    if case.expect == "either" and result.exit_code == 0:
        return
    assert result.exit_code == 2, f"{case.id}: placerec {argv}: exit {result.exit_code}\n{result.output}"
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:"), f"{case.id}: {result.output}"


@pytest.mark.parametrize("case", _cli_sample(FAST, 3), ids=_id)
def test_fuzz_case_through_the_cli(case: Case, tmp_path) -> None:
    _through_cli(case, tmp_path)


@pytest.mark.slow
@pytest.mark.parametrize("case", _cli_sample(ALL, 1), ids=_id)
def test_fuzz_case_through_the_cli_full(case: Case, tmp_path) -> None:
    _through_cli(case, tmp_path)


# ------------------------------------------------------------------------------------------- coverage
def _count(surface: str, subject: str) -> int:
    return sum(1 for c in ALL if c.surface == surface and c.subject == subject)


@pytest.mark.parametrize(
    ("surface", "registry"),
    [
        ("readers", lambda: list(SCAN_READERS)),
        ("datasets", lambda: list(DATASET_LOADERS)),
        ("artifacts", lambda: list(BUILDERS)),
        ("artifacts", lambda: [f"db:{p}" for p in PIPELINES if p != "map-closures" or _has_map_closures()]),
    ],
)
def test_every_registered_surface_has_hostile_cases(surface, registry) -> None:
    """A new reader, dataset layout, artifact builder or pipeline needs at least 3 cases in tests/fuzz."""
    thin = {name: _count(surface, name) for name in registry() if _count(surface, name) < 3}
    assert not thin, f"{surface}: registered without (enough) hostile cases in tests/fuzz: {thin}"


def _has_map_closures() -> bool:
    try:
        import map_closures  # noqa: F401
    except ImportError:
        return False
    return True


def test_every_surface_has_cases_and_the_fast_subset_samples_each() -> None:
    assert set(SURFACES) == {
        "readers",
        "datasets",
        "artifacts",
        "configs",
        "slam",
        "executors",
        "metrics",
        "weights",
    }
    for surface in SURFACES:
        assert any(c.surface == surface for c in FAST), surface
    subjects = {(c.surface, c.subject) for c in ALL if not c.slow}
    assert subjects == {(c.surface, c.subject) for c in FAST}
    assert [c for c in ALL if c.surface == "configs"] == [c for c in FAST if c.surface == "configs"]


def test_int_settings_are_capped_or_allowed_unbounded_on_purpose() -> None:
    """Every count a config can set must be bounded by what a machine can do (``le=``): an int field without an
    upper bound must be in `fuzz.configs.UNBOUNDED_INTS`, with the reason. Stale entries fail too."""
    found = set(unbounded_ints())
    new = sorted(found - set(UNBOUNDED_INTS))
    stale = sorted(set(UNBOUNDED_INTS) - found)
    assert not new, (
        f"int config fields without an upper bound (cap them with le=, or list them with why): {new}"
    )
    assert not stale, f"UNBOUNDED_INTS lists fields that are now bounded or gone (remove them): {stale}"


def test_outcome_turns_other_exceptions_into_failures(tmp_path) -> None:
    boom = Case("metrics", "self-test", lambda t: None, lambda a: [][1], names="x")
    with pytest.raises(AssertionError, match="IndexError escaped"):
        outcome(boom, None)
