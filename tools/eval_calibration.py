"""Verify the per-beam intensity calibration on the simulator, whose per-beam response curves are ground truth.

Usage::

    python tools/eval_calibration.py [--sensors vlp16 hdl64] [--seed 0] [--eval-scans 40] [--no-figures]

For each sensor: simulate a drive through the town (VLP-16: the whole default route at 1 m; HDL-64: 150 scans at
2 m), calibrate with the default `CalibrationParams` (`placerec.calibration.calibrate_sequence`), then evaluate on
a *different* drive (another world seed) with the *same* sensor unit (same per-beam curves): every point within
[1, 30] m (the intensity cut-off).

Ground truth. The simulator's raw value is ``S(g_b f_b(x)) + o_b`` of the *apparent* reflectance ``x`` (the
range-compensated surface response, incidence included; `placerec.sim.intensity`), and
``BeamResponse.to_apparent(raw, beam)`` inverts the true curve of the beam. A per-beam table can recover ``x`` and
nothing more: material reflectance also depends on the incidence angle, which no lookup of (beam, raw) can undo.
The calibration reports reflectance on the scale of "the average beam" (its gauge: the mean response curve over
beams is the identity), so the target is ``y = mean_b expected_raw(x, b) / saturation`` (for the VLP-16 preset the
mean curve is close to ``100 x``, so ``y ~ x``). Metrics, raw (``raw / saturation``) vs calibrated, per beam and
overall: Pearson correlation and mean absolute error with ``y``, and a gauge-free error: the MAE with ``x`` after
the best monotone map common to all beams (isotonic regression), which scores only the per-beam consistency.

Writes ``docs/figures/calibration_<sensor>.png`` (a Fig. 7 of the ISHOT paper with the true curves beside the
estimated ones, a few beams overlaid, per-beam errors before/after), prints a table per sensor and ends with
exactly one JSON line of headline figures.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SETUPS = {"vlp16": {"n_scans": None, "spacing": 1.0}, "hdl64": {"n_scans": 150, "spacing": 2.0}}


def gauge_free_mae(values: np.ndarray, truth: np.ndarray, bins: int = 200) -> float:
    """MAE after the best non-decreasing map from ``values`` to ``truth`` (isotonic regression on quantile bins)."""
    from placerec.calibration.levinson import _isotonic

    q = np.quantile(values, np.linspace(0, 1, bins + 1))
    idx = np.clip(np.searchsorted(q, values, side="right") - 1, 0, bins - 1)
    n = np.bincount(idx, minlength=bins)
    ok = n > 0
    mean_t = np.bincount(idx, truth, bins)[ok] / n[ok]
    mean_v = np.bincount(idx, values, bins)[ok] / n[ok]
    fitted = _isotonic(mean_t, n[ok].astype(np.float64))
    return float(np.abs(np.interp(values, mean_v, fitted) - truth).mean())


def evaluation_points(sensor: str, seed: int, n_scans: int) -> tuple[np.ndarray, np.ndarray]:
    """Raw intensity and ring of every point within [1, 30] m of a drive through another world, same unit."""
    from placerec.sim import SimulatedSequence

    seq = SimulatedSequence(
        world="town", sensor=sensor, n_scans=n_scans, seed=seed + 1, unit_seed=seed, spacing=2.0
    )
    raw, ring = [], []
    for i in range(len(seq)):
        s = seq[i]
        keep = (s.ranges >= 1.0) & (s.ranges <= 30.0)
        raw.append(s.intensity[keep])
        ring.append(s.ring[keep])
    return np.concatenate(raw).astype(np.float64), np.concatenate(ring).astype(np.int64)


def true_curves(response, saturation: float, raw_axis: np.ndarray) -> tuple[np.ndarray, callable]:
    """Per-beam true tables on the calibration's gauge (n_beams, len(raw_axis)) and the map apparent -> gauge."""
    grid = np.linspace(0.0, 3.0, 6001)
    mean_curve = np.mean(
        [response.expected_raw(grid, b, clip=False) for b in range(response.n_beams)], axis=0
    )

    def to_gauge(apparent: np.ndarray) -> np.ndarray:
        return np.clip(np.interp(apparent, grid, mean_curve) / saturation, 0.0, 1.0)

    curves = np.stack([to_gauge(response.to_apparent(raw_axis, b)) for b in range(response.n_beams)])
    return curves, to_gauge


def evaluate(sensor: str, seed: int, eval_scans: int) -> dict:
    from placerec.calibration import CalibrationParams, calibrate_sequence
    from placerec.sim import SimulatedSequence

    setup = SETUPS[sensor]
    seq = SimulatedSequence(world="town", sensor=sensor, seed=seed, **setup)
    t0 = time.perf_counter()
    table = calibrate_sequence(seq, CalibrationParams())
    calib_s = time.perf_counter() - t0
    truth = seq.beam_response
    sat = float(table.meta["saturation"])
    raw, ring = evaluation_points(sensor, seed, eval_scans)
    apparent = truth.to_apparent(raw, ring)
    _, to_gauge = true_curves(truth, sat, np.arange(2.0))
    target = to_gauge(apparent)
    x01 = np.clip(apparent, 0.0, 1.0)
    values = {"raw": np.clip(raw / sat, 0.0, 1.0), "calibrated": table.lookup(raw, ring).astype(np.float64)}
    per_beam = {k: {"mae": [], "corr": []} for k in values}
    for b in range(truth.n_beams):
        m = ring == b
        for k, v in values.items():
            per_beam[k]["mae"].append(float(np.abs(v[m] - target[m]).mean()) if m.any() else float("nan"))
            ok = m.sum() > 2 and np.std(v[m]) > 0
            per_beam[k]["corr"].append(float(np.corrcoef(v[m], target[m])[0, 1]) if ok else float("nan"))
    overall = {
        k: {
            "corr": float(np.corrcoef(v, target)[0, 1]),
            "mae": float(np.abs(v - target).mean()),
            "gauge_free_mae": gauge_free_mae(v, x01),
        }
        for k, v in values.items()
    }
    improved = int(np.sum(np.array(per_beam["calibrated"]["mae"]) < np.array(per_beam["raw"]["mae"])))
    return {
        "sensor": sensor,
        "table": table,
        "truth": truth,
        "saturation": sat,
        "calib_scans": len(seq),
        "calib_s": calib_s,
        "eval_points": int(raw.size),
        "overall": overall,
        "per_beam": per_beam,
        "beams_improved": improved,
        "beam_counts": np.bincount(ring, minlength=truth.n_beams),
    }


def plot(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    table, truth, sat = res["table"], res["truth"], res["saturation"]
    B = table.n_beams
    top = int(min(table.n_raw - 1, round(sat)))
    a = np.arange(top + 1, dtype=np.float64)
    true, _ = true_curves(truth, sat, a)
    est = table.values[:, : top + 1]
    counts = table.counts[:, : top + 1]
    cmap = plt.get_cmap("viridis")
    colours = [cmap(i / max(B - 1, 1)) for i in range(B)]
    fig, axes = plt.subplots(1, 4, figsize=(19, 4.8), gridspec_kw={"width_ratios": [1, 1, 1, 1.25]})
    for ax, curves, title in ((axes[0], est, "estimated (unsupervised)"), (axes[1], true, "ground truth")):
        for b in range(B):
            ax.plot(a, curves[b], color=colours[b], lw=1.1)
        ax.plot(a, a / sat, "k--", lw=1, label="raw / saturation (uncalibrated)")
        ax.set(xlim=(0, top), ylim=(0, 1.02), xlabel="raw intensity", title=f"{title}: all {B} beams")
        ax.legend(loc="upper left", fontsize=8)
    axes[0].set_ylabel("calibrated intensity (average-beam scale)")
    sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(0, B - 1))
    fig.colorbar(sm, ax=axes[1], fraction=0.05, pad=0.02).set_label("beam (ring; 0 = top)")
    pick = np.argsort([np.average(np.abs(a / sat - true[b]), weights=counts[b] + 1e-9) for b in range(B)])[
        -4:
    ]
    for k, b in enumerate(pick):
        c = plt.get_cmap("tab10")(k)
        obs = counts[b] >= 5
        axes[2].plot(a, true[b], "--", color=c, lw=1.3)
        axes[2].plot(a, np.where(obs, est[b], np.nan), "-", color=c, lw=1.6, label=f"beam {b}")
        axes[2].plot(a, np.where(obs, np.nan, est[b]), ":", color=c, lw=1.2)
    axes[2].plot(a, a / sat, "k--", lw=0.8, alpha=0.5)
    axes[2].set(xlim=(0, top), ylim=(0, 1.02), xlabel="raw intensity",
                title="most distorted beams: estimate (solid), truth (dashed)")  # fmt: skip
    axes[2].legend(loc="upper left", fontsize=8)
    pb = res["per_beam"]
    x = np.arange(B)
    axes[3].bar(
        x - 0.2, pb["raw"]["mae"], 0.4, label=f"raw (MAE {res['overall']['raw']['mae']:.4f})", color="0.6"
    )
    axes[3].bar(x + 0.2, pb["calibrated"]["mae"], 0.4, color="tab:blue",
                label=f"calibrated (MAE {res['overall']['calibrated']['mae']:.4f})")  # fmt: skip
    axes[3].set(xlabel="beam (ring; 0 = top)", ylabel="mean |intensity - truth|",
                title=f"held-out drive: error per beam ({res['beams_improved']}/{B} improved)")  # fmt: skip
    if B > 16:
        axes[3].set_xticks(x[::8])
    else:
        axes[3].set_xticks(x)
    axes[3].set_ylim(0, 1.3 * np.nanmax(pb["raw"]["mae"]))
    axes[3].legend(fontsize=8, loc="upper left")
    fig.suptitle(
        f"Per-beam intensity calibration on the simulated {res['sensor'].upper()} "
        f"({res['calib_scans']} scans, EM: {table.meta['em_iterations']} iterations)",
        fontsize=12,
    )
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sensors", nargs="*", default=["vlp16", "hdl64"], choices=sorted(SETUPS))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--eval-scans", type=int, default=40, help="scans of the held-out drive (2 m apart)")
    ap.add_argument("--figures", default=str(ROOT / "docs" / "figures"))
    ap.add_argument("--no-figures", action="store_true")
    args = ap.parse_args()

    from rich.console import Console
    from rich.table import Table

    console = Console(stderr=True)
    headline: dict[str, dict] = {}
    for sensor in args.sensors:
        res = evaluate(sensor, args.seed, args.eval_scans)
        o, pb = res["overall"], res["per_beam"]
        t = Table(title=f"{sensor}: {res['calib_scans']} scans calibrated in {res['calib_s']:.1f} s, "
                        f"{res['eval_points']} held-out points")  # fmt: skip
        for col in ("beam", "points", "corr raw", "corr cal", "MAE raw", "MAE cal"):
            t.add_column(col, justify="right")
        for b in range(res["table"].n_beams):
            t.add_row(str(b), str(res["beam_counts"][b]), f"{pb['raw']['corr'][b]:.4f}",
                      f"{pb['calibrated']['corr'][b]:.4f}", f"{pb['raw']['mae'][b]:.4f}",
                      f"{pb['calibrated']['mae'][b]:.4f}")  # fmt: skip
        t.add_row("all", str(res["eval_points"]), f"{o['raw']['corr']:.4f}", f"{o['calibrated']['corr']:.4f}",
                  f"{o['raw']['mae']:.4f}", f"{o['calibrated']['mae']:.4f}", style="bold")  # fmt: skip
        console.print(t)
        console.print(f"gauge-free MAE: raw {o['raw']['gauge_free_mae']:.4f}, "
                      f"calibrated {o['calibrated']['gauge_free_mae']:.4f}")  # fmt: skip
        if not args.no_figures:
            path = Path(args.figures) / f"calibration_{sensor}.png"
            plot(res, path)
            console.print(f"wrote {path}")
        headline[sensor] = {
            "corr_raw": round(o["raw"]["corr"], 4),
            "corr_cal": round(o["calibrated"]["corr"], 4),
            "mae_raw": round(o["raw"]["mae"], 4),
            "mae_cal": round(o["calibrated"]["mae"], 4),
            "gauge_free_mae_raw": round(o["raw"]["gauge_free_mae"], 4),
            "gauge_free_mae_cal": round(o["calibrated"]["gauge_free_mae"], 4),
            "beams_improved": f"{res['beams_improved']}/{res['table'].n_beams}",
            "worst_beam_mae_raw": round(float(np.nanmax(pb["raw"]["mae"])), 4),
            "worst_beam_mae_cal": round(float(np.nanmax(pb["calibrated"]["mae"])), 4),
            "calib_scans": res["calib_scans"],
            "calib_s": round(res["calib_s"], 1),
        }
    print(json.dumps(headline))


if __name__ == "__main__":
    main()
