"""Executors: worker counts of 0 and 10^12, chunks of 0, malformed Dask scheduler addresses. A malformed address
must be a `ConfigError` naming ``execution.scheduler`` (at load, or when the pool starts), never a traceback from
inside Dask; an unreachable one the same, after Dask's timeout (those cases are ``slow``)."""

from __future__ import annotations

from typing import Any

from fuzz.corpus import Case
from placerec.errors import ConfigError


def _pool(overrides: list[str]) -> Any:
    from placerec.config import load_config
    from placerec.experiment.parallel import task_pool

    cfg = load_config(None, overrides)
    with task_pool(cfg.execution) as submit:
        return submit(abs, [(-3,)], lambda r: None)


def _loads(overrides: list[str]) -> Any:
    from placerec.config import load_config

    return load_config(None, overrides)


MALFORMED = {
    "empty": "''",
    "spaces": "'   '",
    "words": "'not an address'",
    "scheme-only": "'tcp://'",
    "port-text": "'tcp://127.0.0.1:port'",
    "port-negative": "'tcp://127.0.0.1:-5'",
    "port-too-big": "'tcp://127.0.0.1:99999'",
    "bracket-open": "'tcp://[::1'",
    "unknown-scheme": "'gopher://127.0.0.1:8786'",
    "newline": "'tcp://127.0.0.1:8786\\nrm -rf'",
    "number": "8786",
    "list": "['tcp://127.0.0.1:8786']",
}
UNREACHABLE = {"closed-port": "'tcp://127.0.0.1:1'", "bad-ip": "'tcp://256.256.256.256:8786'"}


def cases() -> list[Case]:
    out: list[Case] = []
    for name, value in (
        ("0", "0"),
        ("-1", "-1"),
        ("1e12", "1000000000000"),
        ("1.5", "1.5"),
        ("text", "'two'"),
    ):
        for executor in ("local", "dask"):
            out.append(
                Case(
                    "executors",
                    f"workers-{name}/{executor}",
                    lambda t, v=value, e=executor: [
                        f"execution.workers={v}",
                        f"execution.executor={e}",
                    ],  # fmt: skip
                    _loads,
                    names="execution.workers",
                    error=ConfigError,
                )
            )
    out.append(Case("executors", "chunk-0", lambda t: ["execution.chunk=0"], _loads, names="execution.chunk", error=ConfigError))  # fmt: skip
    out.append(Case("executors", "scheduler-without-dask", lambda t: ["execution.scheduler='tcp://127.0.0.1:8786'"],
                    _loads, names="execution.scheduler", error=ConfigError))  # fmt: skip
    # malformed addresses are refused at once; unreachable ones after distributed's timeout (slow)
    for name, value, slow in [(n, v, False) for n, v in MALFORMED.items()] + [
        (n, v, True) for n, v in UNREACHABLE.items()
    ]:
        out.append(
            Case(
                "executors",
                f"scheduler-{name}",
                lambda t, v=value: ["execution.executor=dask", f"execution.scheduler={v}"],  # fmt: skip
                _pool,
                names="execution.scheduler",
                error=ConfigError,
                slow=slow,
            )
        )
    return out
