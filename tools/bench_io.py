"""Benchmark placerec.io on the real samples in ../shared/data/real.

Median load times of a real KITTI ``.bin`` frame (with plain ``np.fromfile`` as the floor), a real binary PCD
frame, a binary_compressed PCD made from the KITTI frame (write and read), the NCLT frame, the organised OS1-64
frame, and, when ``placerec.preprocess.voxel_downsample`` exists, voxelisation at 0.4 m. Prints a table, then
exactly one JSON line of headline figures. Exits 0 with a message when the real data are absent.

    python tools/bench_io.py [--repeats 9]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from placerec.io import read_scan, write_scan

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"


def median_ms(fn: Callable[[], object], repeats: int) -> float:
    fn()  # warm the page cache and imports
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=9)
    args = ap.parse_args()
    if not REAL.is_dir():
        print(f"bench_io: real sample data not found at {REAL}; nothing to benchmark (skipped)")
        return 0
    r = args.repeats
    kitti = REAL / "kitti00_frames" / "000094.bin"
    pcd = REAL / "kitti_raw_hdl64_sequence" / "0000000000.pcd"
    nclt = REAL / "nclt_hdl32_frame" / "1326652795280148.bin"
    os1 = REAL / "ouster_os1_64_revisit_pair" / "32line_1.bin"
    rows: list[tuple[str, float, str]] = []
    res: dict[str, float | None] = {}

    scan = read_scan(kitti)
    res["kitti_bin_fromfile_floor_ms"] = median_ms(lambda: np.fromfile(kitti, dtype="<f4").reshape(-1, 4), r)
    res["kitti_bin_load_ms"] = median_ms(lambda: read_scan(kitti), r)
    rows += [
        ("np.fromfile of the KITTI frame (floor)", res["kitti_bin_fromfile_floor_ms"], f"{len(scan)} pts"),
        ("read_scan KITTI .bin", res["kitti_bin_load_ms"], f"{len(scan)} pts"),
    ]
    n_pcd = len(read_scan(pcd))
    res["pcd_binary_load_ms"] = median_ms(lambda: read_scan(pcd), r)
    rows.append(("read_scan binary PCD", res["pcd_binary_load_ms"], f"{n_pcd} pts"))
    with tempfile.TemporaryDirectory() as d:
        comp = Path(d) / "frame.pcd"
        res["pcd_compressed_write_ms"] = median_ms(
            lambda: write_scan(comp, scan, data="binary_compressed"), r
        )
        ratio = comp.stat().st_size / kitti.stat().st_size
        res["pcd_compressed_load_ms"] = median_ms(lambda: read_scan(comp), r)
        assert np.array_equal(read_scan(comp).xyz, scan.xyz)
    rows += [
        ("write binary_compressed PCD", res["pcd_compressed_write_ms"], f"size {ratio:.2f} x raw"),
        ("read_scan binary_compressed PCD", res["pcd_compressed_load_ms"], "LZF + column blocks"),
    ]
    res["nclt_load_ms"] = median_ms(lambda: read_scan(nclt, format="nclt"), r)
    rows.append(("read_scan NCLT velodyne_sync", res["nclt_load_ms"], "23,546 pts"))
    res["os1_organised_load_ms"] = median_ms(
        lambda: read_scan(os1, organized=True, layout=(64, 1024, "column-major")), r
    )
    rows.append(
        ("read_scan OS1-64 organised 64x1024", res["os1_organised_load_ms"], "column-major -> row-major")
    )
    try:
        from placerec.preprocess import voxel_downsample
    except ImportError:
        voxel_downsample = None
    if voxel_downsample is None:
        print("note: placerec.preprocess.voxel_downsample not available; voxelisation not timed")
        res["voxel_0p4_ms"] = None
    else:
        n_vox = len(voxel_downsample(scan, 0.4))
        res["voxel_0p4_ms"] = median_ms(lambda: voxel_downsample(scan, 0.4), r)
        rows.append(("voxel_downsample 0.4 m (KITTI frame)", res["voxel_0p4_ms"], f"-> {n_vox} pts"))

    width = max(len(n) for n, _, _ in rows)
    print(f"{'operation':<{width}}  {'median ms':>10}  notes")
    for name, ms, note in rows:
        print(f"{name:<{width}}  {ms:>10.2f}  {note}")
    print(json.dumps({k: (None if v is None else round(v, 3)) for k, v in res.items()}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
