"""Where a Rerun recording goes (`ViewerTarget`) and the checks made before a run starts (`check_target`); imports
nothing of Rerun but, to check it is installed, ``rerun`` itself."""

from __future__ import annotations

import os
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

from placerec.errors import ConfigError, DependencyError

__all__ = ["ViewerTarget", "check_target", "viewer_executable", "INSTALL_HINT"]

INSTALL_HINT = "pip install 'placerec[viewer]'"


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
