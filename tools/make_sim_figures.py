"""Make the figures of ``docs/simulator.md`` (PNG files ``docs/figures/sim_*.png``) and print the numbers quoted there.

Usage::

    python tools/make_sim_figures.py [--out docs/figures] [--real ../shared/data/real]

Simulated images use a per-beam projection (row = ring index, column = azimuth column); the HDL-64 figure also
shows the VPR paper's uniform projection (eq. 2), whose empty rows come from the uneven beam spacing. The real
OS1-64 scan (MulRan, via the LiDAR-Iris demo) is read directly with NumPy: KITTI-style float32 x4 records, 65536
points, column-major (each block of 64 consecutive points is one column, rows from +17.8 deg down), zeros invalid.
Real data is optional: without it the comparison figures are skipped.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from placerec.sim import SimulatedSequence, build_world, get_sensor, make_route  # noqa: E402
from placerec.sim.materials import M  # noqa: E402
from placerec.types import Scan  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def ring_image(scan: Scan, field: str = "intensity") -> np.ndarray:
    """(n_beams, columns) image: row = ring, column = azimuth column; nearest return wins; 0 = empty."""
    info = scan.sensor
    rows, cols = info.n_beams, info.columns
    if scan.shape is not None:
        img = scan.ranges if field == "range" else getattr(scan, field)
        return img.reshape(scan.shape).astype(np.float32)
    rng = scan.ranges
    valid = rng > 0
    az = np.arctan2(scan.xyz[valid, 1], scan.xyz[valid, 0])
    c = (np.floor((np.pi - az) / (2 * np.pi) * cols) % cols).astype(int)
    r = scan.ring[valid].astype(int)
    val = rng[valid] if field == "range" else getattr(scan, field)[valid]
    order = np.argsort(-rng[valid])  # nearest written last
    img = np.zeros((rows, cols), np.float32)
    img[r[order], c[order]] = val[order]
    return img


def uniform_image(
    xyz: np.ndarray, value: np.ndarray, fov_up: float, fov_down: float, rows: int = 64, cols: int = 2048
) -> np.ndarray:
    """The VPR paper's eq. 2 projection, assuming uniformly spaced beams (nearest return per pixel)."""
    rng = np.linalg.norm(xyz, axis=1)
    ok = rng > 0
    xyz, value, rng = xyz[ok], value[ok], rng[ok]
    theta = np.arctan2(xyz[:, 1], xyz[:, 0])
    phi = np.arcsin(np.clip(xyz[:, 2] / rng, -1, 1))
    f = np.radians(fov_up + fov_down)
    u = np.clip(np.floor(0.5 * (1 - theta / np.pi) * cols), 0, cols - 1).astype(int)
    v = np.clip(np.floor((1 - (phi + np.radians(fov_down)) / f) * rows), 0, rows - 1).astype(int)
    order = np.argsort(-rng)
    img = np.zeros((rows, cols), np.float32)
    hit = np.zeros((rows, cols), bool)
    img[v[order], u[order]] = value[order]
    hit[v[order], u[order]] = True
    return img, hit


def show(img: np.ndarray, pct: float = 99.0, scale: float | None = None) -> np.ndarray:
    """Scale to [0, 1] by ``scale`` or by the ``pct`` percentile of the unsaturated returns."""
    v = img[img > 0]
    if scale is None and len(v):
        unsat = v[v < 0.9 * v.max()]
        top = np.percentile(unsat if len(unsat) > 0.5 * len(v) else v, pct)
    else:
        top = scale or 1.0
    return np.clip(img / max(top, 1e-9), 0, 1)


def read_mulran(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    a = np.fromfile(path, dtype=np.float32).reshape(1024, 64, 4).transpose(1, 0, 2)
    xyz = a[..., :3]
    return xyz, a[..., 3], np.linalg.norm(xyz, axis=-1)


def orb_count(img8: np.ndarray) -> int:
    import cv2

    orb = cv2.ORB_create(nfeatures=300, scaleFactor=1.2, nlevels=8, edgeThreshold=15, fastThreshold=40)
    return len(orb.detect(img8, None))


def to8(img: np.ndarray, pct: float = 99.0) -> np.ndarray:
    return (255 * show(img, pct)).astype(np.uint8)


def fig_sensors(out: Path, seed: int) -> dict:
    """The same place seen by every sensor preset."""
    names = ["vlp16", "hdl64", "os1-64", "os1-64-gen2", "os1-128"]
    ref = SimulatedSequence("town", "os1-64", seed=seed)
    i = 25
    fig, axes = plt.subplots(len(names), 1, figsize=(16, 12))
    stats = {}
    for ax, name in zip(axes, names, strict=True):
        seq = SimulatedSequence(ref.world, name, seed=seed, route=ref.route)
        scan = seq[i]
        img = ring_image(scan)
        bits = seq.sensor.intensity_bits
        ax.imshow(show(img), cmap="gray", aspect="auto", interpolation="nearest")
        ax.set_title(
            f"{name}: {seq.sensor.n_beams} beams x {seq.sensor.columns} columns, {bits}-bit intensity (shown to its 99th percentile)",
            fontsize=9,
        )
        ax.set_yticks([])
        stats[name] = {"valid_points": int(np.count_nonzero(scan.ranges > 0))}
    fig.suptitle(
        f"Same place (town, default route scan {i}) seen by each sensor preset (rows = rings)", fontsize=11
    )
    fig.tight_layout()
    fig.savefig(out / "sim_sensors_same_place.png", dpi=90)
    plt.close(fig)
    return stats


def fig_hdl64(out: Path, seed: int, real: Path | None) -> dict:
    seq = SimulatedSequence("town", "hdl64", seed=seed)
    scan = seq[25]
    up, down = scan.sensor.vertical_fov_deg
    uni, hit = uniform_image(scan.xyz, scan.intensity, up, down)
    rows = 3 if real is None else 4
    fig, axes = plt.subplots(rows, 1, figsize=(16, 2.6 * rows))
    axes[0].imshow(show(uni), cmap="gray", aspect="auto", interpolation="nearest")
    empty = np.flatnonzero(hit.mean(axis=1) < 0.05)
    axes[0].set_title(
        f"simulated HDL-64, uniform projection (VPR eq. 2): empty rows {empty.tolist()}", fontsize=9
    )
    axes[1].imshow(hit, cmap="gray", aspect="auto", interpolation="nearest")
    axes[1].set_title(
        "pixels hit (white) under the uniform projection: the lower block's 0.52 deg spacing skips rows",
        fontsize=9,
    )
    axes[2].imshow(show(ring_image(scan)), cmap="gray", aspect="auto", interpolation="nearest")
    axes[2].set_title("the same scan projected per beam from the ring index: no empty rows", fontsize=9)
    res = {"sim_empty_rows": empty.tolist()}
    if real is not None and (real / "kitti00_frames" / "000094.bin").is_file():
        k = np.fromfile(real / "kitti00_frames" / "000094.bin", dtype=np.float32).reshape(-1, 4)
        kimg, khit = uniform_image(k[:, :3], k[:, 3], up, down)
        kempty = np.flatnonzero(khit.mean(axis=1) < 0.05)
        axes[3].imshow(show(kimg, scale=0.6), cmap="gray", aspect="auto", interpolation="nearest")
        axes[3].set_title(
            f"real KITTI 00 frame 94 (HDL-64E), same projection: empty rows {kempty.tolist()}", fontsize=9
        )
        res["kitti_empty_rows"] = kempty.tolist()
        pct = [5, 25, 50, 75, 95]
        res["kitti_bin_intensity_pct"] = np.percentile(k[:, 3], pct).round(3).tolist()
        res["kitti_zero_fraction"] = round(float(np.mean(k[:, 3] == 0)), 3)
        res["sim_bin_intensity_pct"] = (
            np.percentile(scan.intensity / scan.sensor.intensity_max, pct).round(3).tolist()
        )
    for ax in axes:
        ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(out / "sim_hdl64_empty_rows.png", dpi=90)
    plt.close(fig)
    return res


def fig_route(out: Path, seed: int) -> dict:
    w = build_world("town", seed)
    r = make_route(w, "long", seed=seed)
    d = make_route(w, "default", seed=seed)
    g = w.ground
    lab = g.labels[::5, ::5]
    shade = np.full(lab.shape, 0.85)
    shade[np.isin(lab, [M.ASPHALT, M.ASPHALT_PATCH])] = 0.55
    shade[lab == M.MARKING] = 1.0
    shade[lab == M.GRASS] = 0.75
    free = w.free.mask
    fx = np.arange(lab.shape[1]) * 0.5 + g.x0
    fy = np.arange(lab.shape[0]) * 0.5 + g.y0
    fi = np.clip(((fy - w.free.y0) / w.free.resolution).astype(int), 0, free.shape[0] - 1)
    fj = np.clip(((fx - w.free.x0) / w.free.resolution).astype(int), 0, free.shape[1] - 1)
    shade[~free[np.ix_(fi, fj)]] = 0.2
    ext = [g.x0, g.x0 + g.labels.shape[1] * g.resolution, g.y0, g.y0 + g.labels.shape[0] * g.resolution]
    fig, axes = plt.subplots(1, 2, figsize=(16, 8))
    colors = {"same": "tab:green", "opposite": "tab:red", "crossing": "tab:orange"}
    for ax, route, title in ((axes[0], d, "default route"), (axes[1], r, "long route")):
        ax.imshow(shade, origin="lower", extent=ext, cmap="gray", vmin=0, vmax=1)
        xy = route.poses[:, :2, 3]
        ax.plot(xy[:, 0], xy[:, 1], "-", color="tab:blue", lw=1.2, label="route")
        for rv in route.revisits:
            ax.plot(
                xy[rv.start : rv.stop, 0],
                xy[rv.start : rv.stop, 1],
                "-",
                color=colors[rv.kind],
                lw=3.5,
                alpha=0.8,
            )
        ax.plot(*xy[0], "k^", ms=9)
        for kind, c in colors.items():
            ax.plot([], [], "-", color=c, lw=3.5, label=f"revisit: {kind}")
        ax.set_title(
            f"town, {title}: {len(route)} scans at 1 m, {len(route.revisits)} revisit segments", fontsize=10
        )
        if route is d:
            pad = 40
            ax.set_xlim(xy[:, 0].min() - pad, xy[:, 0].max() + pad)
            ax.set_ylim(xy[:, 1].min() - pad, xy[:, 1].max() + pad)
        ax.legend(loc="lower left", fontsize=8)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
    fig.tight_layout()
    fig.savefig(out / "sim_route.png", dpi=90)
    plt.close(fig)
    return {"default": d.describe()["revisits"], "default_len": len(d), "long_len": len(r)}


def fig_presets(out: Path, seed: int) -> None:
    fig, axes = plt.subplots(3, 1, figsize=(16, 6.5))
    for ax, preset in zip(axes, ("town", "campus", "industrial"), strict=True):
        seq = SimulatedSequence(preset, "os1-64", seed=seed, n_scans=120)
        ax.imshow(show(ring_image(seq[100])), cmap="gray", aspect="auto", interpolation="nearest")
        ax.set_title(f"{preset} (OS1-64, scan 100 of the default route)", fontsize=9)
        ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(out / "sim_presets.png", dpi=90)
    plt.close(fig)


def fig_real(out: Path, seed: int, real: Path) -> dict:
    """Simulated OS1-64 (reflectivity and raw-signal channel) next to the real MulRan OS1-64 scan."""
    xyz, rint, rrng = read_mulran(real / "ouster_os1_64_revisit_pair" / "32line_1.bin")
    rvalid = rrng > 0
    sig_sensor = dataclasses.replace(get_sensor("os1-64"), range_compensated=False)
    town_ref = SimulatedSequence("town", "os1-64", seed=seed, n_scans=60)
    town_sig = SimulatedSequence(town_ref.world, sig_sensor, seed=seed, route=town_ref.route)[40]
    town = town_ref[40]
    campus_ref = SimulatedSequence("campus", "os1-64", seed=seed, n_scans=120)
    campus_sig = SimulatedSequence(campus_ref.world, sig_sensor, seed=seed, route=campus_ref.route)[60]
    imgs = [
        (
            "real",
            "real OS1-64 (MulRan, 16-bit intensity = signal, not range compensated; raw column order, staggered)",
            rint,
            rrng,
        ),
        (
            "sim town signal",
            "simulated OS1-64, town, signal channel (range_compensated=False, like the real file)",
            ring_image(town_sig),
            ring_image(town_sig, "range"),
        ),
        (
            "sim town reflectivity",
            "simulated OS1-64, town, reflectivity channel (range compensated, the default)",
            ring_image(town),
            ring_image(town, "range"),
        ),
        (
            "sim campus signal",
            "simulated OS1-64, campus, signal channel",
            ring_image(campus_sig),
            ring_image(campus_sig, "range"),
        ),
    ]
    fig, axes = plt.subplots(
        len(imgs), 2, figsize=(20, 2.4 * len(imgs)), gridspec_kw={"width_ratios": [1, 1]}
    )
    stats: dict = {}
    for (key, title, it, rg), row in zip(imgs, axes, strict=True):
        v = rg > 0
        row[0].imshow(show(np.where(v, it, 0)), cmap="gray", aspect="auto", interpolation="nearest")
        row[0].set_title(title, fontsize=8)
        row[1].imshow(rg, cmap="turbo", vmin=0, vmax=40, aspect="auto", interpolation="nearest")
        row[1].set_title("range 0..40 m", fontsize=8)
        stats[key] = {
            "valid_fraction": round(float(v.mean()), 3),
            "intensity_p5_50_95": [float(x) for x in np.percentile(it[v], [5, 50, 95]).round(1)],
            "range_median_m": round(float(np.median(rg[v])), 2),
            "orb_keypoints": orb_count(to8(np.where(v, it, 0))),
        }
        for a in row:
            a.set_yticks([])
    fig.tight_layout()
    fig.savefig(out / "sim_vs_real_os1_64.png", dpi=80)
    plt.close(fig)

    fig, axes = plt.subplots(1, 2, figsize=(14, 4))
    bins = np.linspace(0, 5, 61)
    for (key, _, it, rg), color in zip(imgs, ("k", "tab:blue", "tab:green", "tab:orange"), strict=True):
        v = rg > 0
        axes[0].hist(
            np.log10(np.maximum(it[v], 1.0)),
            bins=bins,
            histtype="step",
            density=True,
            color=color,
            lw=1.5,
            label=key,
        )
        axes[1].hist(
            rg[v], bins=np.linspace(0, 80, 81), histtype="step", density=True, color=color, lw=1.5, label=key
        )
    axes[0].set_xlabel("log10 raw intensity (16-bit units)")
    axes[1].set_xlabel("range (m)")
    for a in axes:
        a.legend(fontsize=8)
        a.set_ylabel("density")
    axes[0].set_title("intensity histogram: real MulRan OS1-64 vs simulated OS1-64", fontsize=9)
    axes[1].set_title("range histogram", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "sim_vs_real_histograms.png", dpi=90)
    plt.close(fig)
    # median intensity per range bin: the real channel falls like the simulated signal channel
    edges = [0, 5, 10, 20, 30, 50, 100]
    prof = {}
    for key, _, it, rg in imgs:
        v = rg > 0
        prof[key] = [
            float(np.median(it[v & (rg >= a) & (rg < b)])) if np.any(v & (rg >= a) & (rg < b)) else None
            for a, b in zip(edges[:-1], edges[1:], strict=True)
        ]
    stats["median_intensity_by_range"] = {"edges_m": edges, **prof}
    stats["real_valid_top_bottom_rows"] = [
        round(float(rvalid[:8].mean()), 2),
        round(float(rvalid[-8:].mean()), 2),
    ]
    return stats


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "figures")
    ap.add_argument("--real", type=Path, default=ROOT.parent / "shared" / "data" / "real")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    real = args.real if args.real.is_dir() else None
    numbers = {
        "sensors": fig_sensors(args.out, args.seed),
        "hdl64": fig_hdl64(args.out, args.seed, real),
        "route": fig_route(args.out, args.seed),
    }
    fig_presets(args.out, args.seed)
    if real is not None:
        numbers["real_vs_sim"] = fig_real(args.out, args.seed, real)
    print(json.dumps(numbers, indent=1))


if __name__ == "__main__":
    main()
