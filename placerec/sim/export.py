"""Write simulated sequences as KITTI-odometry-style folders (readable by placerec and by KITTI tools).

Layout of ``out_dir``::

    velodyne/000000.bin   float32 records (x, y, z, intensity), sensor frame; invalid returns dropped (as KITTI);
                          intensity = raw / intensity_max in [0, 1] (KITTI's convention for reflectance)
    ring/000000.npy       int16 ring (beam) index of every point of the .bin, 0 = top beam
    column/000000.npy     uint16 azimuth column of every point (with ring, rebuilds the organised image; spinning
                          sensors only)
    poses.txt             one ground-truth T_world_sensor per line, first 3 rows, 12 numbers (KITTI format)
    times.txt             one timestamp (s) per line
    calib.txt             identity ``Tr`` (poses are already in the LiDAR frame) and dummy P0..P3, for KITTI tools
    sensor.yaml           the beam layout: name, beam_elevations_deg, columns, intensity_max, min_range,
                          max_range (exactly the `placerec.types.SensorInfo` fields; raw = bin * intensity_max)
    simulation.yaml       how it was made (preset, sensor, seed, route, revisits, per-beam response ground truth)
    odometry_poses.txt    drifting odometry (only with ``odometry_drift``)

The intensity stored in the .bin is scaled to [0, 1] so that KITTI tools and loaders that expect KITTI's
reflectance work unchanged; multiply by ``intensity_max`` from sensor.yaml to get the sensor's raw units back.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np
import yaml

from placerec.io.atomic import atomic_write
from placerec.sim.sequence import SimulatedSequence
from placerec.types import Sequence

__all__ = ["write_kitti_sequence", "simulate", "format_poses"]

log = logging.getLogger(__name__)


def format_poses(poses: np.ndarray) -> str:
    """KITTI poses text: the first three rows of each 4x4 pose, row-major, one pose per line."""
    rows = np.asarray(poses, dtype=np.float64)[:, :3, :].reshape(len(poses), 12)
    return "".join(" ".join(f"{v:.9e}" for v in r) + "\n" for r in rows)


def _write_text(path: Path, text: str) -> None:
    with atomic_write(path) as fh:
        fh.write(text.encode("utf-8"))


def _write_bytes(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        fh.write(data)
    os.replace(tmp, path)


def _npy_bytes(arr: np.ndarray) -> bytes:
    import io

    buf = io.BytesIO()
    np.save(buf, arr, allow_pickle=False)
    return buf.getvalue()


def write_kitti_sequence(seq: Sequence, out_dir: str | Path, progress: bool = True) -> Path:
    """Render every scan of ``seq`` and write the folder described in the module docstring. Returns ``out_dir``.

    Works for any `Sequence` whose scans carry ``ring`` and a `SensorInfo` with ``intensity_max``; the simulator's
    extras (``simulation.yaml``, odometry) are written when ``seq`` is a `SimulatedSequence`.
    """
    out = Path(out_dir)
    for sub in ("velodyne", "ring", "column"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    n = len(seq)
    info = None

    def write_one(i: int) -> None:
        nonlocal info
        scan = seq[i]
        info = scan.sensor
        imax = float(scan.sensor.intensity_max or 1.0)
        valid = np.any(scan.xyz != 0.0, axis=1)
        rec = np.empty((int(valid.sum()), 4), np.float32)
        rec[:, :3] = scan.xyz[valid]
        rec[:, 3] = scan.intensity[valid] / np.float32(imax)
        _write_bytes(out / "velodyne" / f"{i:06d}.bin", rec.tobytes())
        if scan.ring is not None:
            _write_bytes(out / "ring" / f"{i:06d}.npy", _npy_bytes(scan.ring[valid].astype(np.int16)))
        if scan.shape is not None:
            col = np.tile(np.arange(scan.shape[1], dtype=np.uint16), scan.shape[0])[valid]
        elif scan.sensor.columns and scan.sensor.is_spinning:  # rays lie exactly on their column's azimuth
            az = np.arctan2(scan.xyz[valid, 1], scan.xyz[valid, 0]).astype(np.float64)
            col = (np.floor((np.pi - az) / (2 * np.pi) * scan.sensor.columns) % scan.sensor.columns).astype(
                np.uint16
            )
        else:
            col = None
        if col is not None:
            _write_bytes(out / "column" / f"{i:06d}.npy", _npy_bytes(col))

    if progress:
        from rich.progress import Progress

        with Progress() as bar:
            task = bar.add_task(f"simulating {getattr(seq, 'name', 'sequence')}", total=n)
            for i in range(n):
                write_one(i)
                bar.advance(task)
    else:
        for i in range(n):
            write_one(i)
    if seq.poses is not None:
        _write_text(out / "poses.txt", format_poses(seq.poses))
    times = seq.timestamps if seq.timestamps is not None else np.arange(n, dtype=np.float64) * 0.1
    _write_text(out / "times.txt", "".join(f"{t:.6f}\n" for t in times))
    eye = "1 0 0 0 0 1 0 0 0 0 1 0"
    _write_text(out / "calib.txt", "".join(f"P{k}: {eye}\n" for k in range(4)) + f"Tr: {eye}\n")
    if isinstance(seq, SimulatedSequence):
        info = seq.sensor_info
        _write_text(out / "simulation.yaml", yaml.safe_dump(_simulation_meta(seq), sort_keys=False))
        if seq.odometry_poses is not None:
            _write_text(out / "odometry_poses.txt", format_poses(seq.odometry_poses))
    if info is not None:
        _write_text(out / "sensor.yaml", yaml.safe_dump(info.to_dict(), sort_keys=False))
    log.info("wrote %d scans to %s", n, out)
    return out


def _simulation_meta(seq: SimulatedSequence) -> dict:
    r = seq.beam_response
    return {
        "generator": "placerec.sim",
        "spec": seq.spec.as_dict(),
        "bin_intensity": "raw / intensity_max (multiply by sensor.yaml intensity_max for raw units)",
        "sensor_preset": {
            "family": seq.sensor.family,
            "intensity_bits": seq.sensor.intensity_bits,
            "range_compensated": seq.sensor.range_compensated,
            "organized": seq.sensor.organized,
        },  # fmt: skip
        "route": seq.route.describe(),
        "beam_response": {
            "model": "raw = S(gain * f(x)) + offset, f(x) = x**gamma (x<=1) else 1+gamma*(x-1); see placerec.sim.intensity",
            "gain": r.gain.round(6).tolist(),
            "gamma": r.gamma.round(6).tolist(),
            "offset": r.offset.round(6).tolist(),
        },  # fmt: skip
    }


def simulate(
    preset: str, sensor: str, n_scans: int | None, seed: int, out_dir: str | Path, progress: bool = True
) -> Path:
    """Simulate ``n_scans`` scans of ``sensor`` along the default route of world ``preset`` and write them to
    ``out_dir`` (the ``placerec simulate --preset P --sensor S --scans N --seed K --out DIR`` command)."""
    seq = SimulatedSequence(world=preset, sensor=sensor, n_scans=n_scans, seed=seed)
    return write_kitti_sequence(seq, out_dir, progress=progress)
