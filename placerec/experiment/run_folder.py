"""The results folder of a run: its name, the ``latest`` link, and JSON that is strict.

``make_run_dir`` makes ``<output.dir>/<name>_<timestamp>/`` with the resolved config in it; `point_latest` moves
``latest`` to a run once its report is complete; `interruptible` removes (or marks ``INCOMPLETE``) a run stopped
by Ctrl-C; `finite_or_null` and `json_default` make a payload strict JSON
(NaN and infinity become null; numpy values plain ones). Used by every report: loop closure, localisation, the
benchmark and SLAM.
"""

from __future__ import annotations

import os
import re
import shutil
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from placerec.config import config_to_yaml
from placerec.errors import ConfigError
from placerec.io.atomic import atomic_write

if TYPE_CHECKING:
    from placerec.config import ExperimentConfig
    from placerec.detect import DetectConfig
    from placerec.slam_app.config import SlamConfig

__all__ = [
    "abandon_run",
    "finite_or_null",
    "interruptible",
    "json_default",
    "make_run_dir",
    "point_latest",
    "slug",
]

#: The file that marks a results folder whose run was interrupted after some pipelines' results were written.
INCOMPLETE = "INCOMPLETE"


def slug(label: str) -> str:
    """``label`` as a file-name part: runs of other characters than letters, digits, ``_.-`` become ``_``."""
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", label).strip("_") or "pipeline"


def make_run_dir(
    cfg: ExperimentConfig | SlamConfig | DetectConfig, out_dir: str | Path | None = None
) -> Path:
    """A new timestamped folder for a config with ``name`` and ``output.dir`` (an `ExperimentConfig`, a SLAM
    config) with the config written into it (``latest`` is moved to it only
    when its report is complete, by `point_latest`); `ConfigError` when the results root cannot hold it."""
    root = Path(out_dir or cfg.output.dir)
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    run = root / f"{slug(cfg.name)}_{stamp}"
    n = 1
    while run.exists():
        n += 1
        run = root / f"{slug(cfg.name)}_{stamp}-{n}"
    try:
        run.mkdir(parents=True)
    except OSError as exc:
        where = "--out" if out_dir else "output.dir"
        raise ConfigError(f"{where}: cannot make the results folder {run}: {exc.strerror or exc}") from None
    with atomic_write(run / "config.yaml", "w") as fh:
        fh.write(config_to_yaml(cfg))
    return run


def point_latest(run: Path) -> None:
    """Point ``<run's parent>/latest`` at ``run``, atomically (a new link renamed over the old one)."""
    tmp = run.parent / f".latest-{os.getpid()}"
    try:
        if tmp.is_symlink():
            tmp.unlink()
        tmp.symlink_to(run.name, target_is_directory=True)
        os.replace(tmp, run.parent / "latest")
    except OSError:  # filesystems without symlinks, or a real folder named latest: no link
        if tmp.is_symlink():
            tmp.unlink()


def abandon_run(run: Path, labels: Iterable[str] = ()) -> Path | None:
    """Deal with the folder of a run stopped before its report was complete (Ctrl-C); ``latest`` stays where it
    was. With pipeline ``labels``, a pipeline's results are its ``candidates_<label>.csv``; without, any file but
    the config. A folder with no results is removed (returns None); otherwise a file ``INCOMPLETE`` naming what
    was written is added (returns its path). A run that ``latest`` already points at was complete: left alone."""
    latest = run.parent / "latest"
    if latest.is_symlink() and os.readlink(latest) == run.name:
        return None
    labels = list(labels)
    files = sorted(p.name for p in run.iterdir() if p.name != "config.yaml" and not p.name.startswith("."))
    if labels:
        done = [x for x in labels if f"candidates_{slug(x)}.csv" in files]
        missing = [x for x in labels if x not in done]
        what = f"pipelines with results: {', '.join(done)}; without: {', '.join(missing) or 'none'}"
    else:
        done, what = files, f"files written: {', '.join(files)}"
    if not done:
        shutil.rmtree(run, ignore_errors=True)
        return None
    marker = run / INCOMPLETE
    marker.write_text(f"interrupted before the report was complete; {what}\n")
    return marker


@contextmanager
def interruptible(run: Path, labels: Iterable[str] = ()) -> Iterator[Path]:
    """The body of a run into ``run``: on KeyboardInterrupt the folder is `abandon_run`'s, then the interrupt goes
    on (the command line ends it with status 130)."""
    try:
        yield run
    except KeyboardInterrupt:
        abandon_run(run, labels)
        raise


def finite_or_null(value: Any) -> Any:
    """``value`` with every NaN or infinite float (numpy ones included) replaced by None, recursively."""
    if isinstance(value, dict):
        return {k: finite_or_null(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [finite_or_null(v) for v in value]
    if isinstance(value, float | np.floating):
        return float(value) if np.isfinite(value) else None
    return value


def json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)
