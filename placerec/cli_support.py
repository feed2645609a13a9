"""What the ``placerec`` commands (`placerec.cli`) share: one-line errors, progress bars, ``--set`` overrides, the
scans of "a SEQUENCE path or ``--sim-world``", and the tables they print. Heavy modules are imported inside the
functions, so ``placerec --help`` stays instant."""

from __future__ import annotations

import functools
import json
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import typer

if TYPE_CHECKING:
    from placerec.artifacts.sources import SequenceSource, SimWorld
    from placerec.params import Params
    from placerec.recognizer import PipelineEntry

P = TypeVar("P", bound="Params")

__all__ = [
    "native_versions",
    "error_line",
    "fail",
    "reports_errors",
    "progress_bar",
    "with_overrides",
    "sim_world",
    "sequence_source",
    "summarise",
    "print_summary",
    "print_pipelines",
    "print_pipeline_params",
]


def native_versions() -> dict[str, str]:
    """Versions of the native dependencies; raises DependencyError naming the one that fails to import."""
    from placerec.errors import DependencyError

    versions = {}
    for module, label in (("numpy", "numpy"), ("cv2", "OpenCV"), ("open3d", "Open3D")):
        try:
            mod = __import__(module)
        except Exception as exc:  # ImportError, OSError from a missing shared library
            hint = (
                " (open3d needs the system library libusb-1.0-0: apt-get install libusb-1.0-0)"
                if module == "open3d"
                else ""
            )
            raise DependencyError(f"cannot import {label}: {exc}{hint}") from exc
        versions[label] = getattr(mod, "__version__", "unknown")
    return versions


def error_line(exc: Exception) -> str:
    """A placerec error as one line: the lines of its message joined by "; " (by a space after a colon)."""
    line = ""
    for part in (" ".join(p.split()) for p in str(exc).splitlines()):
        if part:
            line = f"{line}{' ' if not line or line.endswith(':') else '; '}{part}"
    return f"error:{line}"


def fail(exc: Exception) -> None:
    """Print a placerec error as one line on stderr and exit with status 2."""
    typer.echo(error_line(exc), err=True)
    raise typer.Exit(2)


def reports_errors(command: Callable[..., None]) -> Callable[..., None]:
    """``command`` (same signature, help and options) with its placerec errors ending as `fail` ends them, and
    Ctrl-C as one line ``interrupted`` on stderr, status 130."""

    @functools.wraps(command)
    def run(*args: Any, **kwargs: Any) -> None:
        from placerec.errors import PlacerecError

        try:
            command(*args, **kwargs)
        except PlacerecError as exc:
            fail(exc)
        except KeyboardInterrupt:
            typer.echo("interrupted", err=True)
            raise typer.Exit(130) from None

    return run


@contextmanager
def progress_bar(label: str) -> Iterator[Callable[[int, int], None]]:
    """A transient progress bar labelled ``label``, as a ``progress(done, total)`` callback; the bar starts at the
    first call, so a builder that fails while reading its inputs prints nothing but its error."""
    from rich.progress import Progress

    bar = Progress(transient=True)
    task = None

    def update(done: int, total: int) -> None:
        nonlocal task
        if task is None:
            bar.start()
            task = bar.add_task(label, total=None)
        bar.update(task, completed=done, total=total)

    try:
        yield update
    finally:
        if task is not None:
            bar.stop()


def with_overrides(cls: type[P], values: dict[str, Any], overrides: list[str] | None, where: str) -> P:
    """``cls`` from the options' ``values`` with the ``--set key=value`` ``overrides`` applied."""
    from placerec.config import apply_overrides
    from placerec.params import resolve

    return resolve(cls, apply_overrides(values, overrides or []), where=where)


def sim_world(world: str | None, sensor: str, scans: int | None, seed: int) -> SimWorld | None:
    """The simulated world of ``--sim-world``, ``--sim-sensor``, ``--sim-scans`` and ``--seed`` (None: none)."""
    from placerec.artifacts.sources import SimWorld

    return None if world is None else SimWorld(world=world, sensor=sensor, scans=scans, seed=seed)


def sequence_source(
    sequence: Path | None, format: str | None, poses: Path | None, sim: SimWorld | None
) -> SequenceSource:
    """The scans of SEQUENCE (read with ``--format``, ``--poses``) or of the simulated world; `ConfigError`
    unless exactly one is given."""
    from placerec.artifacts.sources import SequenceSource

    return SequenceSource(path=sequence, format=format, poses=poses, sim=sim).check()


def summarise(path: Path, format: str | None, dataset: str | None = None, check: bool = False) -> dict:
    """``placerec info``'s summary of a scan file, a map folder (``check``: hash every file of it), or a sequence
    (a folder, a bag, or ``dataset`` given)."""
    from placerec.io import open_sequence, read_scan
    from placerec.io.atomic import peek_artifact
    from placerec.maps import MapArtifact, is_map_folder
    from placerec.summary import artifact_summary, scan_summary, sequence_summary

    if is_map_folder(path) and not format and not dataset:
        return MapArtifact.open(path, check_hashes=check).summary()
    if path.suffix.lower() == ".npz" and path.is_file() and not format and not dataset:
        artifact = peek_artifact(path)
        if artifact is not None:
            return artifact_summary(path, *artifact)
    if dataset or path.is_dir() or path.suffix.lower() in {".bag", ".db3", ".mcap", ".pcap"}:
        kwargs = {k: v for k, v in (("format", format), ("dataset", dataset)) if v}
        return sequence_summary(open_sequence(path, **kwargs))
    return scan_summary(read_scan(path, format=format))


def print_summary(summary: dict) -> None:
    """A summary as a two-column table: dotted keys, values (a dict of floats on one row)."""
    from rich.console import Console
    from rich.table import Table

    table = Table(show_header=False, box=None)
    table.add_column(style="bold cyan", no_wrap=True)
    table.add_column(overflow="fold")  # a long path wraps onto the next line, never cut with '...'

    def add(prefix: str, value: object) -> None:
        if isinstance(value, dict):
            if all(isinstance(v, float) for v in value.values()) and value:
                table.add_row(prefix, "  ".join(f"{k}={v:.3g}" for k, v in value.items()))
            else:
                for k, v in value.items():
                    add(f"{prefix}.{k}" if prefix else k, v)
        else:
            table.add_row(prefix, printable(str(value)))

    add("", summary)
    Console().print(table)


def printable(text: str) -> str:
    """``text`` with the undecodable bytes of a file name (Python's surrogate escapes) shown as ``\\xNN``: a
    terminal cannot encode them."""
    return text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")


def print_pipelines() -> None:
    """The registered pipelines with their operating thresholds and summaries."""
    from rich.console import Console
    from rich.table import Table

    from placerec.recognizer import PIPELINES

    table = Table(title="registered pipelines (placerec pipelines NAME: parameters)")
    table.add_column("pipeline", no_wrap=True)
    table.add_column("threshold", no_wrap=True)
    table.add_column("description", overflow="fold")
    for key, entry in PIPELINES.items():
        table.add_row(key, _thresholds_text(entry, "\n"), entry.summary)
    Console().print(table)
    typer.echo(
        "threshold: the operating threshold on the candidate score, chosen on the tuning split (docs/protocol.md);"
        " 'sensor: value' where a sensor's own tuning cells picked another"
    )


def _changed(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """The entries of ``over`` (nested mappings compared key by key) that ``base`` lacks or holds otherwise."""
    out: dict[str, Any] = {}
    for key, value in over.items():
        old = base.get(key)
        if isinstance(value, Mapping) and isinstance(old, Mapping):
            inner = _changed(old, value)
            if inner:
                out[key] = inner
        elif key not in base or old != value:
            out[key] = value
    return out


def _thresholds_text(entry: PipelineEntry, sep: str) -> str:
    """A registry entry's operating threshold, then each sensor's own ('vlp16: 0.25'), joined by ``sep``."""
    if entry.threshold is None:
        return "-"
    own = [f"{s}: {p.threshold:g}" for s, p in entry.sensors.items() if p.threshold is not None]
    return sep.join([f"{entry.threshold:g}", *own])


def print_pipeline_params(name: str) -> None:
    """Every parameter of pipeline ``name``, one per entry: ``dotted.path = default  (type)``, then its description
    wrapped on indented lines to the terminal's width (readable at 80 columns), then its operating threshold."""
    import shutil
    import textwrap

    from placerec.params import param_rows
    from placerec.recognizer import PIPELINES, pipeline_params

    params = pipeline_params(name)
    width = max(40, min(shutil.get_terminal_size().columns, 100))
    title = f"{name} parameters: path = default  (type), then what it is / where it comes from"
    lines = [*textwrap.wrap(title, width), ""]
    for key, value, kind, description in param_rows(params):
        head = f"{key} = {value!r}  ({kind})"
        lines += textwrap.wrap(head, width, subsequent_indent="    ", break_on_hyphens=False) or [head]
        lines += textwrap.wrap(description, width, initial_indent="    ", subsequent_indent="    ")
    entry = PIPELINES.get(name)
    if entry is not None and entry.threshold is not None:
        text = f"operating threshold: {_thresholds_text(entry, ', ')} (chosen on the tuning split, docs/protocol.md)"
        lines += ["", *textwrap.wrap(text, width)]
    for sensor, preset in (entry.sensors if entry is not None else {}).items():
        if preset.params:
            text = f"on {sensor} scans (sensor={sensor!r}): {json.dumps(preset.params)} (placerec.sensor_presets)"
            lines += textwrap.wrap(text, width, subsequent_indent="    ")
        if preset.odometry is not None:
            o = preset.odometry
            # what the gate's settings change, on top of the sensor's own where it has them
            added = json.dumps(_changed(preset.params, o.params))
            text = (
                f"on {sensor} scans with the odometry gate (odometry_gate=...): threshold {o.threshold:g}, "
                f"{'those and ' if preset.params else ''}{added} (placerec.sensor_presets)"
            )
            lines += textwrap.wrap(text, width, subsequent_indent="    ")
    typer.echo("\n".join(lines))
