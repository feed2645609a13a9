"""Hostile files shared by the surfaces: sparse files, FIFOs, directories in a file's place, non-UTF-8 names,
files that cannot be opened (permission denied; emulated when running as root, who may read anything)."""

from __future__ import annotations

import builtins
import contextlib
import io
import os
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any
from unittest import mock

import numpy as np
import pytest

__all__ = ["sparse", "fifo", "non_utf8", "unreadable", "denied", "can_make_fifo"]

can_make_fifo = hasattr(os, "mkfifo")


def sparse(path: Path, size: int, head: bytes = b"") -> Path:
    """``path`` of ``size`` bytes declared (``head``, then a hole): nothing but ``head`` is stored."""
    with open(path, "wb") as fh:
        fh.write(head)
        fh.truncate(size)
    return path


def fifo(path: Path) -> Path:
    """A FIFO at ``path``. A daemon thread opens its write end and closes it again, so a reader that (wrongly)
    opens it gets end-of-file instead of blocking the test run forever."""
    if not can_make_fifo:
        pytest.skip("no FIFOs on this platform")
    os.mkfifo(path)

    def writer() -> None:
        with contextlib.suppress(OSError), open(path, "wb"):
            pass

    threading.Thread(target=writer, daemon=True).start()
    return path


def non_utf8(folder: Path, stem: bytes, suffix: str) -> Path:
    """A path in ``folder`` whose name is not UTF-8 (``stem`` holds bytes like 0xff), as Python spells it."""
    name = os.fsdecode(stem + suffix.encode())
    try:
        (folder / name).touch()
    except (OSError, UnicodeEncodeError):
        pytest.skip("the file system refuses non-UTF-8 names")
    return folder / name


def _same(a: Any, target: Path) -> bool:
    if isinstance(a, int):  # a file descriptor
        return False
    with contextlib.suppress(TypeError, ValueError, OSError):
        return Path(os.fsdecode(a)).resolve() == target
    return False


@contextlib.contextmanager
def denied(path: Path) -> Iterator[None]:
    """Reading ``path`` fails with PermissionError: by its mode when not root, else by patching the ways
    placerec opens files (``open``, ``io.open``, ``os.open``, ``np.fromfile``, ``np.memmap``) for that path."""
    target = path.resolve()
    if os.geteuid() != 0:
        mode = path.stat().st_mode
        path.chmod(0)
        try:
            yield
        finally:
            path.chmod(mode)
        return

    def refuse(real: Callable[..., Any]) -> Callable[..., Any]:
        def wrapped(file: Any, *args: Any, **kwargs: Any) -> Any:
            if _same(file, target):
                raise PermissionError(13, "Permission denied", str(file))
            return real(file, *args, **kwargs)

        return wrapped

    with contextlib.ExitStack() as stack:
        stack.enter_context(mock.patch.object(builtins, "open", refuse(builtins.open)))
        stack.enter_context(mock.patch.object(io, "open", refuse(io.open)))
        stack.enter_context(mock.patch.object(os, "open", refuse(os.open)))
        stack.enter_context(mock.patch.object(np, "fromfile", refuse(np.fromfile)))
        stack.enter_context(mock.patch.object(np, "memmap", refuse(np.memmap)))
        yield


def unreadable(fn: Callable[[Path], Any]) -> Callable[[Path], Any]:
    """``fn(path)`` run while ``path`` cannot be opened (`denied`)."""

    def run(path: Path) -> Any:
        with denied(path):
            return fn(path)

    return run
