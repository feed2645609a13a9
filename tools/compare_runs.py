"""Whether two results folders hold the same answers: the check that a refactor changed no behaviour.

Walks folder A (a ``placerec run`` / ``placerec slam`` / ``placerec bench`` / ``tools/eval_localization.py``
output) and compares every file of the same relative path in folder B, run folders matched by their name without
the timestamp (``demo_20261127-002059`` ~ ``demo_20261127-013514``):

* ``candidates_*.csv``, ``*_kitti.txt``, ``*_tum.txt``, ``loops.csv``, ``graph.g2o``, ``poses.txt``: byte for byte;
* ``metrics.json`` / ``benchmark.json`` / ``cell.json``: equal once every key naming a time, a load or a date is
  left out (``time_ms``, ``*_ms``, ``seconds``, ``runtime_s``, ``load_avg``, ``peak_memory_mb``, ...);
* ``*.npz``: equal arrays (headers, with their creation times and paths, left out).

    python tools/compare_runs.py results_before/ results_after/

Prints each difference and one JSON line (files compared, differences); exits 1 when there is a difference.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path
from typing import Any

import numpy as np

BYTES = ("candidates_*.csv", "*_kitti.txt", "*_tum.txt", "loops.csv", "graph.g2o", "poses.txt")
JSON = ("metrics.json", "benchmark.json", "cell.json")
#: keys whose values are timings, machine load or dates, not answers
_TIMING = re.compile(
    r"(^|_)(ms|s|time|times|seconds|runtime|load|load_avg|memory|mb|created|date|wall)(_|$)|time_ms"
)
_STAMP = re.compile(r"_\d{8}-\d{6}(-\d+)?$")


def _key(path: Path, root: Path) -> str:
    """``path`` relative to ``root`` with run-folder timestamps dropped."""
    return "/".join(_STAMP.sub("", part) for part in path.relative_to(root).parts)


def _files(root: Path) -> dict[str, Path]:
    out: dict[str, Path] = {}
    for pattern in (*BYTES, *JSON, "*.npz"):
        for p in root.rglob(pattern):
            if "latest" not in p.relative_to(root).parts and "cache" not in str(p.relative_to(root)):
                out[_key(p, root)] = p
    return out


def json_differences(a: Any, b: Any, path: str = "") -> list[str]:
    """Where two JSON values differ, timing keys left out (NaN equals NaN)."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b)):
            if _TIMING.search(str(k)):
                continue
            if k not in a or k not in b:
                out.append(f"{path}/{k}: only in {'A' if k in a else 'B'}")
            else:
                out += json_differences(a[k], b[k], f"{path}/{k}")
        return out
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{path}: {len(a)} items != {len(b)}"]
        return [
            d
            for i, (x, y) in enumerate(zip(a, b, strict=True))
            for d in json_differences(x, y, f"{path}[{i}]")
        ]
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return []
    return [] if a == b else [f"{path}: {a!r} != {b!r}"]


def compare(a: Path, b: Path) -> tuple[int, list[str]]:
    """(files compared, differences) of two results folders."""
    fa, fb = _files(a), _files(b)
    diffs = [f"{k}: only in {'A' if k in fa else 'B'}" for k in sorted(set(fa) ^ set(fb))]
    for k in sorted(set(fa) & set(fb)):
        pa, pb = fa[k], fb[k]
        if pa.suffix == ".npz":
            with np.load(pa) as x, np.load(pb) as y:
                names = [n for n in x.files if not n.startswith("__")]
                if sorted(names) != sorted(n for n in y.files if not n.startswith("__")):
                    diffs.append(f"{k}: other arrays")
                diffs += [
                    f"{k}: {n} differs" for n in names if n in y.files and not np.array_equal(x[n], y[n])
                ]
        elif pa.name in JSON:
            diffs += [
                f"{k}{d}" for d in json_differences(json.loads(pa.read_text()), json.loads(pb.read_text()))
            ]
        elif pa.read_bytes() != pb.read_bytes():
            diffs.append(f"{k}: differs")
    return len(set(fa) & set(fb)), diffs


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("a", type=Path)
    ap.add_argument("b", type=Path)
    args = ap.parse_args(argv)
    n, diffs = compare(args.a, args.b)
    for d in diffs:
        print(d)
    print(json.dumps({"tool": "compare_runs", "files": n, "differences": len(diffs)}))
    return 1 if diffs else 0


if __name__ == "__main__":
    sys.exit(main())
