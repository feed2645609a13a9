"""How many threads placerec's own work may use, and the helper thread that runs a scan's independent steps side
by side.

* `available_threads`: ``OMP_NUM_THREADS`` when it is a positive number (a Dask worker sets it to 1), else the
  cores this process may use. The default of the thread counts placerec chooses itself (a cloud's ICP
  preparation, `side_by_side`).
* `import_openmp` imports a module whose OpenMP runtime placerec drives (small_gicp, faiss and ouster-sdk share
  one vendored libgomp) with ``OMP_WAIT_POLICY=passive`` while the runtime loads (it reads the variable once, then)
  unless the user set it: idle OpenMP threads then sleep instead of spinning, which otherwise burns up to ~10 ms
  of a core after every parallel region (a real HDL-64 match prepared on 2 threads: 17.4 ms CPU spinning, 14.7
  sleeping, 12.5 on one thread). The variable is removed again, so other runtimes (PyTorch's) and child processes
  keep the user's environment.
* `side_by_side` starts a function on one helper thread and returns its `concurrent.futures.Future`; the
  caller does the other step meanwhile and then takes ``.result()``. It pays where both steps spend their time in
  code that releases the GIL (numba kernels compiled ``nogil``, OpenCV, small_gicp's OpenMP loops): a visual
  front end forms its intensity image and features beside the ICP cloud's voxel grid (a real HDL-64 scan 19.4 ->
  15.0 ms). Each step computes what it would compute alone, so results do not depend on it. With one thread
  available, or when called from the helper thread itself, the function runs at once in the caller.
"""

from __future__ import annotations

import importlib
import os
import sys
import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from types import ModuleType
from typing import Any, TypeVar

__all__ = ["available_threads", "import_openmp", "side_by_side"]

T = TypeVar("T")

_lock = threading.Lock()
_pool: ThreadPoolExecutor | None = None
_PREFIX = "placerec-side"


def available_threads() -> int:
    """``OMP_NUM_THREADS`` when it is a positive number, else the cores this process may use (at least 1)."""
    env = os.environ.get("OMP_NUM_THREADS", "").strip()
    if env.isdigit() and int(env) > 0:
        return int(env)
    affinity = getattr(os, "sched_getaffinity", None)  # Linux; elsewhere all the machine's cores
    return max(len(affinity(0)) if affinity else os.cpu_count() or 1, 1)


def import_openmp(name: str) -> ModuleType:
    """``importlib.import_module(name)`` with idle OpenMP threads sleeping (see the module docstring); ImportError
    as the import raises it."""
    module = sys.modules.get(name)
    if module is not None:
        return module
    with _lock:
        ours = "OMP_WAIT_POLICY" not in os.environ
        if ours:
            os.environ["OMP_WAIT_POLICY"] = "passive"
        try:
            return importlib.import_module(name)
        finally:
            if ours:
                os.environ.pop("OMP_WAIT_POLICY", None)


def side_by_side(fn: Callable[..., T], *args: Any) -> Future[T]:
    """``fn(*args)`` on the helper thread (see the module docstring); its exception is raised by ``.result()``."""
    if available_threads() < 2 or threading.current_thread().name.startswith(_PREFIX):
        done: Future[T] = Future()
        try:
            done.set_result(fn(*args))
        except BaseException as exc:  # handed to the caller by .result(), as the helper thread would
            done.set_exception(exc)
        return done
    return _helper().submit(fn, *args)


def _helper() -> ThreadPoolExecutor:
    global _pool
    with _lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix=_PREFIX)
        return _pool
