"""Declarative layouts of artifact arrays, and the consistency checks loaders share.

A loader states its layout once, as a mapping from member name to `Member`, and passes it to
`placerec.io.atomic.load_artifact`; `check_members` then verifies that exactly the expected members are present
with the expected dtype kinds, number of dimensions and sizes. A size given as a string names a dimension that must
be the same wherever it appears (e.g. ``("n_places",)`` for ids and ``("n_places", 4, 4)`` for poses), so counts
that must agree are checked without code. `check_offsets`, `check_counts` and `check_unique` cover the rest.
Every failure is an `ArtifactError` naming the file, the member and what was expected.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from placerec.errors import ArtifactError

__all__ = ["Member", "Schema", "check_members", "check_offsets", "check_counts", "check_unique"]

_KIND_NAMES = {"b": "bool", "i": "signed int", "u": "unsigned int", "f": "float"}


@dataclass(frozen=True)
class Member:
    """The expected layout of one artifact array.

    ``kinds``: allowed numpy dtype kinds ("b" bool, "i" int, "u" unsigned, "f" float). ``shape``: one entry per
    axis, an int (that size), a str (a named size shared by every member that uses the name) or None (any); None
    for the whole shape allows any shape. ``optional``: the member may be absent. ``finite``: no NaN or inf.
    ``min_value``: the smallest allowed element.
    """

    kinds: str
    shape: tuple[int | str | None, ...] | None = None
    optional: bool = False
    finite: bool = False
    min_value: float | None = None

    def describe(self) -> str:
        kinds = " or ".join(_KIND_NAMES.get(k, k) for k in self.kinds)
        return kinds if self.shape is None else f"{kinds} of shape ({', '.join(map(str, self.shape))})"


Schema = Mapping[str, Member]


def check_members(arrays: Mapping[str, np.ndarray], schema: Schema, where: str | Path) -> dict[str, int]:
    """Check ``arrays`` against ``schema`` (no missing or unexpected member, dtypes, shapes, named sizes, values);
    returns the named sizes."""
    unexpected = sorted(set(arrays) - set(schema))
    if unexpected:
        raise ArtifactError(f"{where}: unexpected arrays {unexpected}; expected {sorted(schema)}")
    dims: dict[str, int] = {}
    for name, member in schema.items():
        if name not in arrays:
            if member.optional:
                continue
            raise ArtifactError(f"{where}: missing array {name!r} (expected {member.describe()})")
        arr = arrays[name]
        if arr.dtype.kind not in member.kinds or arr.dtype.names is not None:
            raise ArtifactError(f"{where}: array {name!r} is {arr.dtype}, expected {member.describe()}")
        if member.shape is not None:
            _check_shape(name, arr.shape, member, dims, where)
        if member.finite and arr.dtype.kind == "f" and not np.isfinite(arr).all():
            raise ArtifactError(f"{where}: array {name!r} holds NaN or infinite values")
        if member.min_value is not None and arr.size and arr.min() < member.min_value:
            raise ArtifactError(
                f"{where}: array {name!r} holds {arr.min()}, expected values >= {member.min_value}"
            )
    return dims


def _check_shape(
    name: str, shape: tuple[int, ...], member: Member, dims: dict[str, int], where: str | Path
) -> None:
    expected = member.shape or ()
    ok = len(shape) == len(expected)
    for size, want in zip(shape, expected, strict=False):
        if isinstance(want, str):
            if dims.setdefault(want, size) != size:
                raise ArtifactError(
                    f"{where}: array {name!r} has shape {shape}: its size {want}={size} disagrees with "
                    f"{want}={dims[want]} of another array"
                )
        elif want is not None and size != want:
            ok = False
    if not ok:
        raise ArtifactError(f"{where}: array {name!r} has shape {shape}, expected {member.describe()}")


def check_offsets(offsets: np.ndarray, n: int, total: int, where: str | Path, name: str) -> None:
    """``offsets`` must be the ``n + 1`` row starts of ``n`` consecutive blocks covering ``total`` rows:
    0 first, ``total`` last, never decreasing."""
    offsets = offsets.astype(np.int64)  # unsigned offsets would wrap in np.diff
    if offsets.shape != (n + 1,):
        raise ArtifactError(f"{where}: {name!r} has shape {offsets.shape}, expected ({n + 1},)")
    if offsets[0] != 0 or offsets[-1] != total or (np.diff(offsets) < 0).any():
        raise ArtifactError(
            f"{where}: {name!r} are not offsets of consecutive blocks: expected 0 first, {total} last and no "
            f"decrease, got first {offsets[0]}, last {offsets[-1]}"
        )


def check_counts(counts: np.ndarray, total: int, where: str | Path, name: str) -> None:
    """``counts`` (non-negative) must add up to ``total``."""
    if (counts.size and counts.min() < 0) or int(counts.sum()) != total:
        raise ArtifactError(
            f"{where}: {name!r} must be non-negative counts adding up to {total}, got sum {int(counts.sum())}"
        )


def check_unique(values: np.ndarray, where: str | Path, name: str) -> None:
    """``values`` must hold no repeats."""
    if np.unique(values).size != values.size:
        raise ArtifactError(f"{where}: {name!r} holds repeated values; expected unique ones")
