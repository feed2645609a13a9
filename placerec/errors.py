"""placerec's exceptions. Every error placerec raises on bad input is a `PlacerecError`.

* `ScanFormatError` — a scan/pose/sequence file is missing, empty, truncated or malformed; the message names the
  file and what was expected.
* `ScanDataError` — in-memory data is inconsistent (shapes, NaN poses, empty scans where points are needed).
* `ConfigError` — a configuration key is unknown or a value is invalid; the message names the key path and the
  allowed keys or values.
* `ArtifactError` — a saved artifact (database, vocabulary, calibration table, cache) is corrupt, of an
  unsupported format version, or was made with another configuration.
* `DependencyError` — an optional or native dependency cannot be imported; the message says what to install.
"""

from __future__ import annotations

import reprlib


class PlacerecError(Exception):
    """Base class of every placerec error."""


class ScanFormatError(PlacerecError, ValueError):
    """A scan, pose or sequence file cannot be read as the format it claims to be."""


class ScanDataError(PlacerecError, ValueError):
    """In-memory scan or pose data is inconsistent."""


class ConfigError(PlacerecError, ValueError):
    """A configuration key or value is invalid."""


class ArtifactError(PlacerecError):
    """A saved artifact is corrupt, of an unsupported version, or does not match the configuration."""


class DependencyError(PlacerecError, ImportError):
    """A required native or optional dependency is missing."""


def short_repr(value: object, limit: int = 80) -> str:
    """``repr(value)`` for an error message, at most ``limit`` characters; never walks more than a few elements
    of a container, so a huge (or alias-expanded) input cannot make the message itself expensive."""
    r = reprlib.Repr()
    r.maxlevel, r.maxstring, r.maxother = 3, limit, limit
    r.maxlist = r.maxtuple = r.maxdict = r.maxset = r.maxfrozenset = 6
    text = r.repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."
