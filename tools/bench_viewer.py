"""What the report's evidence and a Rerun recording cost, and whether the report opens cleanly in a browser.

Runs ``placerec run CONFIG`` (default: the demo) three ways, interleaved over ``--repeats`` rounds, with the
description cache off so every run computes what a first run computes:

* ``plain``: ``output.evidence=false`` (the report as it was before the galleries),
* ``evidence``: the default report (per-closure galleries, rejection summaries, interactive figures),
* ``rrd``: the default report plus ``--rrd FILE`` (a Rerun recording; needs ``placerec[viewer]``).

It prints wall and CPU seconds per arm (median over the rounds), the ratios evidence / plain (target <= 1.15) and
rrd / evidence (target <= 1.10), the recording's size, then opens the evidence run's ``index.html`` in headless
Chromium (`placerec.experiment.browser.check_report`: console errors, images that did not load, failed requests)
and ends with one JSON line.

    .venv/bin/python tools/bench_viewer.py [--config configs/demo.yaml] [--set key=value ...] [--repeats 1]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ARMS = {
    "plain": ["--set", "output.evidence=false"],
    "evidence": [],
    "rrd": ["--rrd", "{rrd}"],
}


def run_arm(config: str, sets: list[str], arm: str, out: Path) -> dict[str, float]:
    """One ``placerec run`` of ``arm`` into ``out``: wall and CPU seconds (the child's user + system time)."""
    out.mkdir(parents=True, exist_ok=True)
    rrd = out / "run.rrd"
    extra = [a.replace("{rrd}", str(rrd)) for a in ARMS[arm]]
    cmd = [str(Path(sys.executable).with_name("placerec")), "run", config, "--out", str(out), "--set", "output.progress=false",
           "--set", "output.cache_dir=null", *[x for s in sets for x in ("--set", s)], *extra]  # fmt: skip
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        sys.exit(f"{arm}: placerec run failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"wall_s": wall, "cpu_s": cpu, "rrd_mb": rrd.stat().st_size / 2**20 if rrd.exists() else 0.0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="configs/demo.yaml")
    ap.add_argument("--set", action="append", default=[], help="config override key.path=value")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--keep", help="folder to keep the runs in (default: a temporary one)")
    args = ap.parse_args()

    root = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="placerec-bench-viewer-"))
    times: dict[str, list[dict[str, float]]] = {arm: [] for arm in ARMS}
    for r in range(args.repeats):
        for arm in ARMS:
            out = root / f"{arm}-{r}"
            times[arm].append(run_arm(args.config, args.set, arm, out))
            t = times[arm][-1]
            print(f"round {r} {arm:>8}: {t['wall_s']:.1f} s wall, {t['cpu_s']:.1f} s CPU", flush=True)

    def med(arm: str, key: str) -> float:
        return statistics.median(t[key] for t in times[arm])

    ratio_evidence = med("evidence", "wall_s") / med("plain", "wall_s")
    ratio_rrd = med("rrd", "wall_s") / med("evidence", "wall_s")
    print(f"evidence / plain: {ratio_evidence:.3f} wall (target <= 1.15), "
          f"{med('evidence', 'cpu_s') / med('plain', 'cpu_s'):.3f} CPU")  # fmt: skip
    print(f"rrd / evidence:   {ratio_rrd:.3f} wall (target <= 1.10), "
          f"{med('rrd', 'cpu_s') / med('evidence', 'cpu_s'):.3f} CPU; recording {med('rrd', 'rrd_mb'):.1f} MB")  # fmt: skip

    from placerec.experiment.browser import check_report

    report = next((root / "evidence-0").glob("*/index.html"))
    check = check_report(report)
    print(f"browser: {check.n_images} images, {check.n_plots_drawn}/{check.n_plots} plots drawn, "
          f"{len(check.problems)} problems, {check.load_s:.1f} s")  # fmt: skip
    for line in check.problems:
        print(f"  {line}")
    load = os.getloadavg()[0]
    print(json.dumps({
        "bench": "viewer", "config": args.config, "repeats": args.repeats,
        "wall_s": {arm: round(med(arm, "wall_s"), 2) for arm in ARMS},
        "cpu_s": {arm: round(med(arm, "cpu_s"), 2) for arm in ARMS},
        "ratio_evidence_over_plain": round(ratio_evidence, 3), "ratio_rrd_over_evidence": round(ratio_rrd, 3),
        "rrd_mb": round(med("rrd", "rrd_mb"), 1), "report_ok": check.ok, "report_problems": check.problems,
        "report_images": check.n_images, "report_plots_drawn": f"{check.n_plots_drawn}/{check.n_plots}",
        "load_1min_at_end": round(load, 2), "cores": os.cpu_count(), "python": platform.python_version(),
    }))  # fmt: skip
    if not args.keep:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
