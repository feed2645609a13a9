"""What the input checks cost in the demo run: the share of its time spent validating.

Runs ``placerec run configs/demo.yaml`` (the README's demo) in this process under cProfile, then adds up the time of
the checks: every placerec function whose name says it validates (``check_*``, ``_check*``, ``validate*``,
``*_problem`` such as `placerec.types.rigid_problem`, the SuperPoint provenance and probe checks, the artifact
schema) and the construction of every `placerec.params.Params` (configs and pipeline parameters, validated by
pydantic). A check called from another check is counted once, inside its caller (per caller, from cProfile's
caller table), and so is one called by pydantic while it builds a Params. The profiler slows Python code more than the native code around it, so the share printed is an
upper bound of the share without it.

The last line printed is one JSON object. Example (~4 min on 2 idle cores)::

    python tools/bench_validation.py                     # the demo
    python tools/bench_validation.py --set dataset.simulator.n_scans=200
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import re
import tempfile
import time

CHECK_NAME = re.compile(
    r"^(_?check|_?validate|_?verify_provenance|_?probe)|_problem$|^__init__$|^model_validate$"
)


def is_check(func: tuple[str, int, str]) -> bool:
    """Whether a cProfile function key (file, line, name) is one of placerec's checks."""
    filename, _, name = func
    if "placerec" not in filename or "/tools/" in filename:
        return False
    if name in ("__init__", "model_validate"):
        return filename.endswith("placerec/params.py")  # Params construction: pydantic's validation
    return bool(CHECK_NAME.search(name))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default="configs/demo.yaml")
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="key.path=value")
    ap.add_argument("--top", type=int, default=12, help="checks listed")
    args = ap.parse_args()
    from placerec.cli import app

    with tempfile.TemporaryDirectory() as out:
        argv = ["run", args.config, "--out", out]
        for o in args.overrides:
            argv += ["--set", o]
        prof = cProfile.Profile()
        t0 = time.perf_counter()
        prof.enable()
        try:
            app(argv, standalone_mode=False)
        finally:
            prof.disable()
        wall = time.perf_counter() - t0
    stats = pstats.Stats(prof)
    table = stats.stats  # type: ignore[attr-defined]
    per_check: dict[str, float] = {}
    for func, (_, _, _, _, callers) in table.items():
        if not is_check(func):
            continue
        # calls from another check, or from pydantic inside a Params construction (nested sections, field
        # validators), are inside a check counted already
        outer = sum(
            ct
            for caller, (_, _, _, ct) in callers.items()
            if not is_check(caller) and "pydantic" not in caller[0]
        )
        if outer > 0:
            per_check[f"{func[0].split('placerec/')[-1]}:{func[1]} {func[2]}"] = outer
    total = stats.total_tt  # type: ignore[attr-defined]
    checks = sum(per_check.values())
    print(f"run under the profiler: {wall:.1f} s wall, {total:.1f} s profiled")
    print(f"checks: {checks:.3f} s = {100 * checks / total:.2f} % of the run")
    for name, t in sorted(per_check.items(), key=lambda kv: -kv[1])[: args.top]:
        print(f"  {t * 1e3:9.1f} ms  {name}")
    print(
        json.dumps(
            {
                "bench": "validation",
                "config": args.config,
                "overrides": args.overrides,
                "run_s": round(total, 2),
                "checks_s": round(checks, 3),
                "checks_share_pct": round(100 * checks / total, 3),
            }
        )
    )


if __name__ == "__main__":
    main()
