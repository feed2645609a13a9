"""Which pipelines a map should hold for global search: measured on the tuning split only.

For each session kind (`placerec.sim.sessions`: ``revisit``, ``partial``, ``opposite``) of ``--world`` at ``--seed``
(default: the tuning split's town, seed 0; test seeds are refused), a map of session 1 (the same for every kind) is
built once from its true poses with ORB-HBST and Scan Context, and every ``--every``-th scan of session 2 inside the overlap is localised by global
search alone (no prior: what the first fix and a kidnap need) with `placerec.maps.Localizer` asking ORB-HBST only,
Scan Context only, and each in turn (``pipeline: None``). A fix is correct within 1 m / 5 deg; accepted fixes only.
The last line printed is one JSON object.

    python tools/tune_map_pipelines.py
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from placerec.artifacts.map import MapBuild, write_map
from placerec.eval.pose_error import pose_errors
from placerec.experiment.protocol import is_test_seed
from placerec.maps import Localizer, LocalizerParams, MapArtifact
from placerec.sim.sessions import make_session_pair
from placerec.slam_app.localize import CORRECT_DEG, CORRECT_M

SEARCHES = {"orb-hbst": "orb-hbst", "scan-context": "scan-context", "orb-hbst, then scan-context": None}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--world", default="town")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--every", type=int, default=4)
    ap.add_argument("--kinds", nargs="+", default=["revisit", "partial", "opposite"])
    args = ap.parse_args()
    if is_test_seed(args.seed) or is_test_seed(args.seed + 100_000):
        raise SystemExit(
            f"seed {args.seed}: a test-split seed (placerec.experiment.protocol): nothing is tuned on it"
        )
    rows = []
    m: MapArtifact | None = None
    with tempfile.TemporaryDirectory() as tmp:
        for kind in args.kinds:
            pair = make_session_pair(args.world, "vlp16", seed=args.seed, kind=kind)
            if m is None:  # session 1 is the same drive for every kind: its map is built once
                build = {"source": {"sim": {"world": args.world}}, "out": str(Path(tmp) / "map"),
                         "pipelines": [{"name": "orb-hbst"}, {"name": "scan-context"}]}  # fmt: skip
                m = MapArtifact.open(write_map(pair.map, MapBuild.model_validate(build)))
            idx = np.arange(0, len(pair.query), args.every)
            idx = idx[pair.overlap[idx]]
            for label, pipe in SEARCHES.items():
                loc = Localizer(m, LocalizerParams(pipeline=pipe))
                correct = wrong = 0
                t0 = time.perf_counter()
                for i in idx.tolist():
                    fix = loc.localize(pair.query[i])
                    if fix.accepted:
                        assert fix.T_world_query is not None
                        te, re = pose_errors(fix.T_world_query[None], pair.query.poses[i][None])
                        good = bool(te[0] <= CORRECT_M and re[0] <= CORRECT_DEG)
                        correct, wrong = correct + int(good), wrong + int(not good)
                ms = (time.perf_counter() - t0) / max(len(idx), 1) * 1e3
                rows.append({"kind": kind, "search": label, "scans": len(idx), "correct": correct, "wrong": wrong,
                             "ms_per_scan": round(ms, 1)})  # fmt: skip
                print(f"{kind:9s} {label:28s} correct {correct:3d} / {len(idx)}, wrong {wrong}, {ms:.0f} ms a scan",
                      flush=True)  # fmt: skip
    print(json.dumps({"tool": "tune_map_pipelines", "world": args.world, "seed": args.seed,
                      "load": f"{os.getloadavg()[0]:.2f}", "rows": rows}))  # fmt: skip


if __name__ == "__main__":
    main()
