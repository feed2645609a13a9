"""Intensity calibration (Levinson & Thrun EM): recovery of known per-beam curves, gauge, table I/O, apply(),
errors, range cut-off, preprocessing hook, CLI, and a small simulator check against the ground-truth curves."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from placerec.calibration import (
    CalibrationParams,
    CalibrationTable,
    RawBinning,
    calibrate_observations,
    calibrate_sequence,
    fit_levinson,
    group_observations,
    incidence_cosine,
    load_calibration,
)
from placerec.errors import ArtifactError, ConfigError, ScanDataError
from placerec.preprocess import PreprocessParams, preprocess_scan
from placerec.types import Scan, SensorInfo

VLP = SensorInfo(name="vlp16", beam_elevations_deg=tuple(np.linspace(15, -15, 16)), intensity_max=255.0)
BINS = RawBinning(256, 1.0)


def _responses(n_beams: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    gain = np.exp(rng.normal(0.0, 0.15, n_beams))
    gamma = np.clip(rng.normal(1.0, 0.15, n_beams), 0.7, 1.4)
    offset = rng.normal(0.0, 2.0, n_beams)
    return gain, gamma, offset


def _synthetic(n_beams=16, n_cells=6000, per_cell=6, noise=0.06, seed=0, identical=False):
    """Cells of known reflectance, each read by random beams with different monotone responses."""
    rng = np.random.default_rng(seed)
    gain, gamma, offset = _responses(n_beams, seed + 1)
    if identical:
        gain, gamma, offset = np.ones(n_beams), np.ones(n_beams), np.zeros(n_beams)
    x = np.clip(rng.beta(1.6, 3.0, n_cells), 0.0, 1.0)
    cell = np.repeat(np.arange(n_cells), per_cell)
    beam = rng.integers(0, n_beams, cell.size)
    seen = x[cell] * np.exp(rng.normal(0.0, noise, cell.size))
    raw = np.clip(
        np.rint(100 * gain[beam] * seen ** gamma[beam] + offset[beam] + rng.normal(0, 0.5, cell.size)), 0, 255
    )
    obs = group_observations(cell, beam, BINS.index(raw), n_beams, BINS)
    truth = np.clip(np.maximum(raw - offset[beam], 0) / (100 * gain[beam]), 0, None) ** (1 / gamma[beam])
    # the same truth on the calibration's scale: the mean response over beams is the identity (the gauge)
    grid = np.linspace(0, 1.5, 3001)
    mean_resp = np.mean([100 * gain[b] * grid ** gamma[b] + offset[b] for b in range(n_beams)], axis=0)
    return obs, raw, beam, np.clip(np.interp(truth, grid, mean_resp) / 100, 0, 1)


@pytest.fixture(scope="module")
def synthetic():
    obs, raw, beam, truth = _synthetic()
    return obs, raw, beam, truth, calibrate_observations(obs, CalibrationParams(), "vlp16")


def test_em_recovers_known_per_beam_curves(synthetic):
    obs, raw, beam, truth, table = synthetic
    cal = table.lookup(raw, beam)
    raw01 = np.clip(raw / 100.0, 0, 1)
    mae_raw, mae_cal = np.abs(raw01 - truth).mean(), np.abs(cal - truth).mean()
    assert mae_cal < 0.01 and mae_cal < 0.2 * mae_raw, (mae_raw, mae_cal)
    assert np.corrcoef(cal, truth)[0, 1] > 0.995 > np.corrcoef(raw01, truth)[0, 1] + 0.02
    assert table.values.dtype == np.float32 and table.values.shape == (16, 256)
    assert np.all(np.diff(table.values, axis=1) >= 0)  # monotone per beam
    assert table.values[:, 101:].min() == 1.0 and table.meta["saturation"] == 100.0  # raw > 100 -> 1


def test_gauge_mean_response_is_identity():
    obs, *_ = _synthetic(n_cells=3000)
    fit = fit_levinson(obs, CalibrationParams())
    used = (fit.levels > 5) & (fit.levels < 60)  # where the data are
    assert used.sum() > 40
    assert np.allclose(fit.response.mean(axis=0)[used], fit.levels[used], atol=0.5)
    fit3 = fit_levinson(obs, CalibrationParams(gauge=3))
    assert np.allclose(fit3.response[3][used], fit3.levels[used], atol=0.5)
    table = calibrate_observations(obs, CalibrationParams(gauge=3), "vlp16")
    assert table.meta["gauge"] == "beam 3 = identity"
    a = np.arange(10, 50)
    assert np.abs(table.values[3, a] - a / 100.0).max() < 0.01  # the reference beam is left as it is


def test_identical_beams_give_the_identity_table():
    obs, *_ = _synthetic(n_cells=3000, identical=True)
    table = calibrate_observations(obs, CalibrationParams(), "vlp16")
    a = np.arange(10, 80)
    assert np.abs(table.values[:, a] - a / 100.0).max() < 0.02


def test_save_load_round_trip(tmp_path, synthetic):
    table = synthetic[-1]
    path = tmp_path / "calib.npz"
    table.save(path)
    back = CalibrationTable.load(path)
    assert np.array_equal(back.values, table.values) and np.array_equal(back.counts, table.counts)
    assert (back.sensor, back.raw_step, back.max_range) == ("vlp16", 1.0, 30.0)
    assert back.meta["params"] == CalibrationParams().model_dump(mode="json")
    assert back.meta["saturation"] == table.meta["saturation"]
    assert load_calibration(path) is load_calibration(path)  # cached
    assert not list(tmp_path.glob(".*.tmp"))  # atomic write left no temporary file


def _scan(n=200, ring=True, sensor=VLP, seed=0):
    rng = np.random.default_rng(seed)
    r = np.linspace(2.0, 40.0, n)
    az = rng.uniform(-np.pi, np.pi, n)
    xyz = np.stack([r * np.cos(az), r * np.sin(az), np.zeros(n)], axis=1)
    return Scan(xyz, rng.integers(0, 120, n).astype(np.float32), ring=rng.integers(0, 16, n) if ring else None,
                sensor=sensor, source="test.bin")  # fmt: skip


def _table(max_range=30.0):
    values = np.clip(np.arange(256)[None, :] * (1 + 0.01 * np.arange(16))[:, None] / 100.0, 0, 1)
    return CalibrationTable(values, sensor="vlp16", max_range=max_range)


def test_apply_maps_raw_through_the_beam_table_and_cuts_range():
    scan, table = _scan(), _table()
    out = table.apply(scan)
    near = scan.ranges <= 30.0
    expected = np.clip(scan.intensity * (1 + 0.01 * scan.ring) / 100.0, 0, 1)
    assert np.allclose(out.intensity[near], expected[near], atol=1e-6)
    assert np.isnan(out.intensity[~near]).all() and (~near).any()
    assert len(table.apply(scan, beyond="drop")) == near.sum()
    assert np.all(table.apply(scan, beyond="zero").intensity[~near] == 0)
    assert np.isfinite(table.apply(scan, max_range=None).intensity).all()
    assert np.allclose(table.lookup([10.5], [0]), [0.105])  # linear between bins


def test_apply_keeps_no_return_points_of_organised_scans_at_zero():
    xyz = np.zeros((16 * 4, 3), np.float32)
    xyz[::2, 0] = 5.0
    scan = Scan(xyz, np.full(64, 50.0), ring=np.repeat(np.arange(16), 4), shape=(16, 4), sensor=VLP)
    out = _table().apply(scan)
    assert out.shape == (16, 4) and np.all(out.intensity[1::2] == 0) and np.all(out.intensity[::2] > 0.4)


def test_apply_errors():
    table = _table()
    with pytest.raises(ScanDataError, match="test.bin.*ring"):
        table.apply(_scan(ring=False))
    hdl = SensorInfo(name="hdl64", beam_elevations_deg=tuple(np.linspace(2, -24.9, 64)))
    with pytest.raises(ScanDataError, match="64 beams.*16"):
        table.apply(_scan(sensor=hdl))
    bad = Scan(np.ones((3, 3)), [1, 2, 3], ring=[0, 1, 20], source="odd.bin")
    with pytest.raises(ScanDataError, match="odd.bin: ring index 20"):
        table.apply(bad)


def test_corrupt_or_wrong_files_raise_artifact_errors(tmp_path):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(ArtifactError, match="bad.npz"):
        CalibrationTable.load(bad)
    with pytest.raises(ArtifactError, match="no such"):
        load_calibration(tmp_path / "missing.npz")
    from placerec.io.atomic import save_artifact

    other = tmp_path / "other.npz"
    save_artifact(other, "vocabulary", 1, {"values": np.zeros((2, 2))})
    with pytest.raises(ArtifactError, match="vocabulary"):
        CalibrationTable.load(other)
    partial = tmp_path / "partial.npz"
    save_artifact(
        partial, "intensity-calibration", 1, {"values": np.zeros((2, 4))}, {"sensor": "x", "n_beams": 2}
    )
    with pytest.raises(ArtifactError, match="partial.npz.*'counts'"):
        CalibrationTable.load(partial)
    wrong = tmp_path / "wrong.npz"
    save_artifact(wrong, "intensity-calibration", 1,
                  {"values": np.full((2, 4), 3.0), "counts": np.zeros((2, 4), np.int64)},
                  {"sensor": "x", "n_beams": 2, "n_raw": 4, "raw_step": 1.0})  # fmt: skip
    with pytest.raises(ArtifactError, match="wrong.npz.*\\[0, 1\\]"):
        CalibrationTable.load(wrong)


def test_preprocess_applies_the_table_and_drops_points_beyond_the_cut_off(tmp_path):
    path = tmp_path / "t.npz"
    _table().save(path)
    scan = _scan()
    out = preprocess_scan(scan, PreprocessParams(min_range=0.5, intensity={"calibration": str(path)}))
    near = scan.ranges <= 30.0
    assert len(out) == near.sum() and np.isfinite(out.intensity).all()
    assert np.allclose(out.intensity, _table().apply(scan).intensity[near])
    plain = preprocess_scan(scan, PreprocessParams(min_range=0.5))  # VLP-16 default: raw / 100, not dropped
    assert len(plain) == len(scan)


def test_incidence_cosine_of_a_plane_seen_from_above():
    g = np.stack(np.meshgrid(np.linspace(-2, 2, 41), np.linspace(-2, 2, 41)), -1).reshape(-1, 2)
    xyz = np.c_[g, np.zeros(len(g))]
    origin = np.array([0.0, 0.0, 3.0])
    cos = incidence_cosine(xyz, np.broadcast_to(origin, xyz.shape))
    expected = 3.0 / np.linalg.norm(xyz - origin, axis=1)
    ok = np.isfinite(cos)  # edge cells with fewer than 8 points have no normal
    assert ok.mean() > 0.8 and np.allclose(cos[ok], expected[ok], atol=1e-6)
    blob = np.random.default_rng(0).normal(size=(500, 3)) * 0.1  # not planar: no normal
    assert np.isnan(incidence_cosine(blob, np.zeros_like(blob))).all()


def test_cells_seen_by_a_single_beam_are_dropped():
    obs = group_observations([7, 7, 7, 9, 9], [0, 1, 1, 2, 2], [10, 11, 11, 5, 6], 4, BINS)
    assert obs.n_cells == 1 and obs.count.tolist() == [1, 2] and obs.beam.tolist() == [0, 1]
    with pytest.raises(ScanDataError, match="no map cell"):
        fit_levinson(group_observations([1, 2], [0, 1], [3, 4], 4, BINS))


def test_simulator_calibration_tracks_the_true_response_curves(tmp_path):
    from placerec.sim import SimulatedSequence

    seq = SimulatedSequence(world="town", sensor="vlp16", n_scans=60, seed=0, spacing=3.0)
    table = calibrate_sequence(seq, CalibrationParams())
    truth = seq.beam_response
    test = SimulatedSequence(
        world="town", sensor="vlp16", n_scans=3, seed=1, unit_seed=0
    )  # same unit, new world
    scans = [test[i] for i in range(3)]
    keep = [(s.ranges >= 1.0) & (s.ranges <= 30.0) for s in scans]
    raw = np.concatenate([s.intensity[k] for s, k in zip(scans, keep, strict=True)])
    ring = np.concatenate([s.ring[k] for s, k in zip(scans, keep, strict=True)]).astype(np.int64)
    apparent = truth.to_apparent(raw, ring)  # the inverse of the true per-beam curves
    grid = np.linspace(0.0, 2.0, 2001)
    gauge = np.mean([truth.expected_raw(grid, b, clip=False) for b in range(16)], axis=0)
    target = np.clip(np.interp(apparent, grid, gauge) / 100.0, 0, 1)
    cal, raw01 = table.lookup(raw, ring), np.clip(raw / 100.0, 0, 1)
    mae_raw, mae_cal = np.abs(raw01 - target).mean(), np.abs(cal - target).mean()
    assert mae_cal < 0.7 * mae_raw, (mae_raw, mae_cal)
    assert np.corrcoef(cal, target)[0, 1] > np.corrcoef(raw01, target)[0, 1] + 0.02


def test_observations_take_their_settings_from_calibration_params():
    """`collect_observations` reads `CalibrationParams` (no keyword options with defaults of their own)."""
    from placerec.calibration import collect_observations
    from placerec.sim import SimulatedSequence

    seq = SimulatedSequence(world="town", sensor="vlp16", n_scans=6, seed=0, spacing=3.0)
    obs = collect_observations(seq)
    assert obs.n_inc == CalibrationParams().incidence_bins == 6
    fewer = collect_observations(seq, CalibrationParams(incidence_bins=2, step=2, min_beams=3))
    assert fewer.n_inc == 2 and fewer.n_points < obs.n_points and fewer.n_cells < obs.n_cells
    assert collect_observations(seq, CalibrationParams(min_cos_incidence=None)).n_inc == 1


def test_cli_calibrate_on_the_simulator(tmp_path):
    from placerec.cli import app

    out = tmp_path / "calib.npz"
    args = [
        "calibrate",
        "--sim-world",
        "town",
        "--sim-scans",
        "25",
        "--out",
        str(out),
        "--set",
        "min_count=3",
    ]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    table = load_calibration(out)
    assert table.n_beams == 16 and table.sensor == "vlp16" and table.meta["params"]["min_count"] == 3
    res = CliRunner().invoke(app, ["calibrate", "--out", str(out)])
    assert res.exit_code == 2 and "SEQUENCE" in res.output


def test_calibration_params_use_the_strict_parameter_mechanism():
    """Unknown keys and bad values are `ConfigError`s naming the key (and the allowed keys for a typo)."""
    with pytest.raises(ConfigError, match="voxel_sise: unknown key; allowed keys there: .*voxel_size"):
        CalibrationParams(voxel_sise=0.3)
    with pytest.raises(ConfigError, match="levels"):
        CalibrationParams(levels=2)
    assert CalibrationParams(max_range=20).max_range == 20.0


def test_calibrate_command_reports_bad_parameters_with_the_one_formatter(tmp_path):
    """``placerec calibrate`` checks its parameters before reading any scan; errors name the key and the
    allowed keys (`placerec.params.format_errors`), on one line with status 2."""
    from typer.testing import CliRunner

    from placerec.cli import app

    out = tmp_path / "t.npz"
    args = ["calibrate", "--sim-world", "town", "--out", str(out)]
    result = CliRunner().invoke(app, [*args, "--set", "levls=64"])
    assert result.exit_code == 2, result.output
    assert (
        "calibration parameters: levls: unknown key; allowed keys there: estimate, fit_range" in result.output
    )
    result = CliRunner().invoke(app, [*args, "--voxel-size", "-1"])
    assert result.exit_code == 2, result.output
    assert "calibration parameters: voxel_size: Input should be greater than 0 (got -1.0)" in result.output
    assert not out.exists()
