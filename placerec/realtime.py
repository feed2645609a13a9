"""The real-time mode of the loop-closure detector: its settings, its counters, and its one worker thread.

`placerec.loop_closure.LoopClosureDetector` with ``realtime=RealtimeParams(...)`` describes each scan in the
caller's thread and hands "query, then add" to a `SerialWorker`: one background thread that runs the jobs one at
a time in the order they were given (a FIFO), so the recognizer's database sees exactly the sequence of
operations of the sequential mode and accepts the same closures, only later. `RealtimeStats` counts what a
budget-minded caller needs: scans over budget, the backlog, closures returned later than their scan's call.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

import numpy as np
from pydantic import Field

from placerec.errors import ConfigError, ScanDataError
from placerec.params import Params

__all__ = ["RealtimeParams", "RealtimeStats", "LateScanError", "SerialWorker"]

R = TypeVar("R")


class RealtimeParams(Params):
    """The real-time mode's budget (`placerec.loop_closure.LoopClosureDetector`, ``loops.realtime``)."""

    budget_ms: float = Field(
        100.0, gt=0, description="time per scan (ms) a process() call should stay within"
    )
    max_backlog: int = Field(
        3,
        ge=0,
        le=1000,
        description="scans the worker may be behind; beyond, process() waits (0: wait for every scan)",
    )


class LateScanError(ScanDataError):
    """An earlier scan's query or insertion failed in the real-time worker; ``scan_id`` names it. Raised at the
    start of the next `process` / `flush` / `close`, before anything of that call's own scan is done (so it can be
    fed again); that earlier scan keeps its id but was not added (as a skipped one)."""

    def __init__(self, scan_id: int, cause: Exception) -> None:
        super().__init__(f"scan {scan_id}: loop-closure query failed in the real-time worker: {cause}")
        self.scan_id = scan_id


@dataclass
class RealtimeStats:
    """Counters of a real-time detector. ``scans``: `process` calls; ``over_budget``: calls that took longer than
    ``budget_ms``, a wait for the worker included; ``waited``: calls that waited for the worker's backlog;
    ``max_backlog``: most places queued or in the worker at once; ``closures``: accepted closures returned;
    ``deferred_closures``: those returned by a later call than their own place's; ``max_delay``: most places fed
    between a closure's place and the call that returned it; ``worker_errors``: places whose query failed in the
    worker (`LateScanError`); ``process_ms``: wall time of each `process` call; ``worker_ms``: the worker's time
    per place (query + verification + insert)."""

    budget_ms: float
    scans: int = 0
    over_budget: int = 0
    waited: int = 0
    max_backlog: int = 0
    closures: int = 0
    deferred_closures: int = 0
    max_delay: int = 0
    worker_errors: int = 0
    process_ms: list[float] = field(default_factory=list)
    worker_ms: list[float] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        """The counters and ``process_ms`` / ``worker_ms`` as median, p95, max (for metrics.json)."""
        out: dict[str, Any] = {
            k: getattr(self, k)
            for k in ("budget_ms", "scans", "over_budget", "waited", "max_backlog", "closures",
                      "deferred_closures", "max_delay", "worker_errors")
        }  # fmt: skip
        for name in ("process_ms", "worker_ms"):
            a = np.asarray(getattr(self, name), np.float64)
            out[name] = (
                {"median": float(np.median(a)), "p95": float(np.percentile(a, 95)), "max": float(a.max())}
                if a.size
                else None
            )
        return out


@dataclass
class _Done(Generic[R]):
    """A finished job: its key, its result or its error, the worker's wall ms."""

    key: int
    result: R | None
    error: Exception | None
    ms: float


class SerialWorker(Generic[R]):
    """One daemon thread running ``run(job)`` for each submitted job, one at a time, in submission order.

    `submit` queues a job (starting the thread on the first one) and returns the backlog (jobs queued or running);
    `wait` blocks until it is at most a number; `take` hands over the finished jobs in order (an exception a job
    raised is kept with it, never lost); `stop` lets the thread finish every queued job, then joins it.
    """

    def __init__(self, run: Callable[[Any], R], name: str = "placerec-loop-closure") -> None:
        self._run = run
        self._name = name
        self._cv = threading.Condition()
        self._jobs: deque[tuple[int, Any]] = deque()
        self._done: list[_Done[R]] = []
        self._backlog = 0
        self._stopping = False
        self._thread: threading.Thread | None = None

    @property
    def closed(self) -> bool:
        """Whether `stop` was called: no more jobs are taken."""
        with self._cv:
            return self._stopping

    def submit(self, key: int, job: Any) -> int:
        """Queue ``job`` under ``key``; returns the backlog with it. `ConfigError` once stopped."""
        with self._cv:
            if self._stopping:
                raise ConfigError("the real-time loop-closure worker is closed: no more scans")
            self._jobs.append((key, job))
            self._backlog += 1
            backlog = self._backlog
            self._cv.notify_all()
        if self._thread is None:
            self._thread = threading.Thread(target=self._loop, name=self._name, daemon=True)
            self._thread.start()
        return backlog

    def wait(self, at_most: int = 0) -> None:
        """Block until at most ``at_most`` jobs are queued or running."""
        with self._cv:
            self._cv.wait_for(lambda: self._backlog <= at_most)

    def take(self) -> list[_Done[R]]:
        """The jobs finished since the last call, in submission order."""
        with self._cv:
            done, self._done = self._done, []
        return done

    def stop(self) -> None:
        """Finish every queued job, then end the thread (idempotent)."""
        with self._cv:
            self._stopping = True
            self._cv.notify_all()
        if self._thread is not None:
            self._thread.join()

    def _loop(self) -> None:
        while True:
            with self._cv:
                self._cv.wait_for(lambda: bool(self._jobs) or self._stopping)
                if not self._jobs:
                    return
                key, job = self._jobs.popleft()
            t0 = time.perf_counter()
            result: R | None = None
            error: Exception | None = None
            try:
                result = self._run(job)
            except Exception as exc:  # kept with the job and re-raised in the caller's thread
                error = exc
            done = _Done(key, result, error, (time.perf_counter() - t0) * 1e3)
            with self._cv:
                self._done.append(done)
                self._backlog -= 1
                self._cv.notify_all()
