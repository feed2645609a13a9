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
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING

from placerec.viewer.target import INSTALL_HINT, ViewerTarget, check_target, viewer_executable

if TYPE_CHECKING:
    from placerec.viewer.recorder import Recorder

__all__ = ["ViewerTarget", "check_target", "recording", "active", "viewer_executable", "INSTALL_HINT"]

_active: contextvars.ContextVar[Recorder | None] = contextvars.ContextVar("placerec_viewer", default=None)


@contextmanager
def recording(target: ViewerTarget, name: str) -> Iterator[Recorder | None]:
    """The recorder of ``target`` named ``name`` (the recording's name in the viewer), active inside the block;
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
