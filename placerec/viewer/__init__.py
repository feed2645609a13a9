"""Rerun recordings of a run, a SLAM session or a relocalisation (docs/viewer.md).

`recording(target, name)` opens a `placerec.viewer.recorder.Recorder` for the duration of a ``with`` block:
``target.spawn`` streams to a Rerun viewer it starts, ``target.rrd`` writes an ``.rrd`` file (atomically: the
file appears complete when the block ends, and not at all when the block raises). Inside the block `active()`
returns that recorder, and the runners (`placerec.experiment.runner`, `placerec.slam_app.run`,
`placerec.slam_app.localize`) log to it; outside it `active()` is None and they log nothing.

``rerun`` (PyPI ``rerun-sdk``, the extra ``viewer``) is imported only by `placerec.viewer.recorder`, which this
module imports only when a recording is asked for: a run without ``--viewer`` or ``--rrd`` never imports it.
`check_target` is what the command line calls before a run starts: the extra installed, the ``.rrd`` path
writable.
"""

from __future__ import annotations

import contextvars
import os
import shutil
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from placerec.errors import ConfigError, DependencyError

if TYPE_CHECKING:
    from placerec.viewer.recorder import Recorder

__all__ = ["ViewerTarget", "check_target", "recording", "active", "viewer_executable", "INSTALL_HINT"]

INSTALL_HINT = "pip install 'placerec[viewer]'"

_active: contextvars.ContextVar[Recorder | None] = contextvars.ContextVar("placerec_viewer", default=None)


@dataclass(frozen=True)
class ViewerTarget:
    """Where a recording goes: a spawned Rerun viewer (``spawn``), an ``.rrd`` file (``rrd``), or both.
    ``max_points``: points per logged scan (subsampled evenly to at most this many). ``every_candidate``: the
    image pair and the aligned clouds of every candidate, not only of each query's best and accepted ones (about
    twice the recording's cost with visual pipelines verifying their top 5; docs/viewer.md)."""

    spawn: bool = False
    rrd: Path | None = None
    max_points: int = 4000
    every_candidate: bool = False

    @property
    def enabled(self) -> bool:
        return self.spawn or self.rrd is not None


def check_target(target: ViewerTarget) -> None:
    """Refuse, before anything runs, a target that cannot work: `DependencyError` naming the extra when
    ``rerun-sdk`` is not installed (or, for ``spawn``, its viewer executable cannot be found), `ConfigError` when
    ``spawn`` has no display to open a window on (Linux) or ``rrd`` cannot be written (its folder missing, not a
    folder or not writable; the path itself a folder)."""
    if not target.enabled:
        return
    try:
        import rerun  # noqa: F401
    except ImportError as exc:
        raise DependencyError(
            f"--viewer / --rrd need the Rerun SDK, which is not installed ({exc}): {INSTALL_HINT}"
        ) from None
    if target.spawn and sys.platform.startswith("linux") and not _has_display():
        raise ConfigError(
            "--viewer opens a window, but there is no display (DISPLAY and WAYLAND_DISPLAY are unset): write a "
            "recording with --rrd FILE and open it with `rerun FILE` where there is one"
        )
    if target.spawn and viewer_executable() is None:
        raise DependencyError(
            "--viewer starts the Rerun viewer, the executable 'rerun' that rerun-sdk installs: it is neither on "
            f"PATH nor beside {sys.executable} ({INSTALL_HINT}, or write a recording with --rrd FILE)"
        )
    if target.rrd is None:
        return
    path = Path(target.rrd).expanduser()
    folder = path.parent
    if path.is_dir():
        raise ConfigError(f"--rrd {target.rrd}: is a folder, not a file to write the recording to")
    if not folder.is_dir():
        raise ConfigError(f"--rrd {target.rrd}: the folder {folder} does not exist")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise ConfigError(f"--rrd {target.rrd}: the folder {folder} is not writable")
    if path.exists() and not os.access(path, os.W_OK):
        # atomic_write replaces the file, which the folder's permission allows; a read-only file says "keep me"
        raise ConfigError(f"--rrd {target.rrd}: the file exists and is read-only")


def _has_display() -> bool:
    return bool(
        os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY") or os.environ.get("WAYLAND_SOCKET")
    )


def viewer_executable() -> Path | None:
    """The Rerun viewer executable ``rerun``: the one on PATH, else the one beside this Python (a virtual
    environment used without activating it); None when there is neither."""
    found = shutil.which("rerun")
    if found is not None:
        return Path(found)
    beside = shutil.which("rerun", path=str(Path(sys.executable).parent))
    return None if beside is None else Path(beside)


@contextmanager
def recording(target: ViewerTarget, name: str) -> Iterator[Recorder | None]:
    """The recorder of ``target`` named ``name`` (the Rerun application id's suffix), active inside the block;
    None (and rerun not imported) when the target is off. The ``.rrd`` file is complete when the block ends."""
    if not target.enabled:
        yield None
        return
    check_target(target)
    from placerec.viewer.recorder import Recorder

    with Recorder.open(target, name) as rec:
        token = _active.set(rec)
        try:
            yield rec
        finally:
            _active.reset(token)


def active() -> Recorder | None:
    """The recorder of the enclosing `recording` block, or None."""
    return _active.get()
