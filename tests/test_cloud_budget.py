"""The RAM budget of verification clouds (issue #27 item 4): stored clouds beyond it move to a spill file and read
back bit for bit, prepared ICP targets stay within it, and pipelines give the same answers with any budget."""

from __future__ import annotations

import os

import numpy as np
import pytest

from placerec.errors import ConfigError, ScanDataError
from placerec.recognizer import make_pipeline
from placerec.sim import SimulatedSequence
from placerec.verify.candidates import CloudStore, VerifiedParams
from placerec.verify.spill import SpillFile, SpillRef


def _clouds(n: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [(rng.normal(0, 20, (int(rng.integers(300, 900)), 3))).astype(np.float32) for _ in range(n)]


@pytest.mark.parametrize("form", ["float32", "int16", "int16-zlib"])
def test_clouds_over_the_budget_move_to_the_spill_file_and_read_back_bit_for_bit(form):
    clouds = _clouds(40)
    budget_mb = 0.05
    small, unlimited = CloudStore(dtype=form, budget_mb=budget_mb), CloudStore(dtype=form)
    for i, c in enumerate(clouds):
        small.add(i, c)
        unlimited.add(i, c)
        assert small.nbytes <= budget_mb * 1e6 / 2  # never over its share of the budget after an add
    n_spilled, spilled_bytes = small.spilled
    assert 20 < n_spilled < 40 and spilled_bytes > 0
    assert unlimited.spilled == (0, 0) and unlimited.nbytes > budget_mb * 1e6
    for i in range(len(clouds)):
        np.testing.assert_array_equal(small.cloud(i), unlimited.cloud(i))
    assert small._clouds[0].__class__.__name__ == "_Spill"  # the oldest went first
    assert small._clouds[39].__class__.__name__ != "_Spill"


def test_re_adding_an_entry_frees_its_old_bytes():
    store = CloudStore(dtype="int16", budget_mb=10)
    a, b = _clouds(2)
    store.add(0, a)
    store.add(0, b)
    fresh = CloudStore(dtype="int16")
    fresh.add(0, b)
    assert store.nbytes == fresh.nbytes and len(store) == 1
    np.testing.assert_array_equal(store.cloud(0), fresh.cloud(0))


def test_prepared_targets_stay_within_a_quarter_of_the_budget():
    clouds = _clouds(12, seed=3)
    store = CloudStore(dtype="int16-zlib", budget_mb=0.8)
    for i, c in enumerate(clouds):
        store.add(i, c)
    for i in range(len(clouds)):
        store.target(i)
        assert store.prepared_bytes <= 0.2e6 or len(store._prepared) == 1
    assert 1 <= len(store._prepared) < len(clouds)
    last = store.target(len(clouds) - 1)
    assert store.target(len(clouds) - 1) is last  # the most recent one is kept
    unlimited = CloudStore(dtype="int16-zlib")
    for i, c in enumerate(clouds):
        unlimited.add(i, c)
        unlimited.target(i)
    assert len(unlimited._prepared) == len(clouds)


def test_spill_file_is_unnamed_and_a_bad_folder_is_a_config_error(tmp_path):
    spill = SpillFile(str(tmp_path))
    ref = spill.write(b"abc")
    assert spill.write(b"defgh") == SpillRef(3, 5)
    assert spill.read(ref) == b"abc" and spill.read(SpillRef(3, 5)) == b"defgh"
    if os.name == "posix":
        assert list(tmp_path.iterdir()) == []  # no directory entry: nothing is left behind
    with pytest.raises(ScanDataError, match="outside the spill file"):
        spill.read(SpillRef(6, 5))
    spill.close()
    missing = SpillFile(str(tmp_path / "no" / "such"))
    with pytest.raises(ConfigError, match="verify.cloud_spill_dir"):
        missing.write(b"x")
    store = CloudStore(dtype="float32", budget_mb=1e-4, spill_dir=str(tmp_path / "nope"))
    with pytest.raises(ConfigError, match="verify.cloud_spill_dir"):
        store.add(0, _clouds(1)[0])


def test_budget_is_bounded_and_not_recorded_in_a_saved_database():
    for bad in (0, -1.0, 1e7):
        with pytest.raises(ConfigError, match="cloud_budget_mb"):
            VerifiedParams(cloud_budget_mb=bad)
    a = VerifiedParams(cloud_budget_mb=1.0, cloud_spill_dir="/tmp")
    b = VerifiedParams(cloud_budget_mb=None)
    assert a.saved_dump() == b.saved_dump() and "cloud_budget_mb" not in a.saved_dump()
    assert a.model_dump()["cloud_budget_mb"] == 1.0


@pytest.fixture(scope="module")
def scans():
    seq = SimulatedSequence(world="town", sensor="os1-64", n_scans=40, seed=5, clutter=False)
    return [seq[i] for i in (0, 1, 2, 3, 30, 31)]


@pytest.mark.parametrize("name", ["orb-hbst", "scan-context"])
def test_pipelines_give_the_same_answers_and_save_the_same_database_with_any_budget(scans, tmp_path, name):
    runs = {}
    for budget in (None, 0.05):
        rec = make_pipeline(name, {"verify": {"cloud_budget_mb": budget}})
        descs = [rec.describe(s) for s in scans]
        for i, d in enumerate(descs[:4]):
            rec.add_description(i, d)
        answers = [
            rec.query_description(d, k=3, query_id=10 + j) for j, d in enumerate(descs[4:] + descs[:1])
        ]
        if budget is not None:
            assert rec._clouds.spilled[0] >= 2  # most clouds are in the spill file
            if name == "orb-hbst":  # and the keypoints, their points and descriptors of most entries
                assert rec._descriptors.nbytes <= 0.05e6 / 12 and len(rec._descriptors) == 4
        rec.save(tmp_path / f"{budget}.npz")
        runs[budget] = answers
    for a, b in zip(runs[None], runs[0.05], strict=True):
        assert [(c.match_id, c.score, c.accepted) for c in a] == [
            (c.match_id, c.score, c.accepted) for c in b
        ]
        for ca, cb in zip(a, b, strict=True):
            np.testing.assert_array_equal(ca.relative_pose, cb.relative_pose)
    assert any(c.accepted for answer in runs[None] for c in answer)
    with np.load(tmp_path / "None.npz") as za, np.load(tmp_path / "0.05.npz") as zb:
        np.testing.assert_array_equal(za["cloud_xyz"], zb["cloud_xyz"])
    # a database saved under one budget loads under another (the budget is a run-time setting)
    other = make_pipeline(name, {"verify": {"cloud_budget_mb": 1000}})
    other.load(tmp_path / "0.05.npz")
    assert len(other._clouds) == 4


def test_placerec_info_reports_what_a_saved_database_entry_costs(scans, tmp_path):
    import json

    from typer.testing import CliRunner

    from placerec.cli import app

    rec = make_pipeline("orb-hbst")
    for i, s in enumerate(scans[:3]):
        rec.add_description(i, rec.describe(s))
    rec.save(tmp_path / "db.npz")
    result = CliRunner().invoke(app, ["info", str(tmp_path / "db.npz"), "--json"])
    assert result.exit_code == 0, result.output
    info = json.loads(result.output)
    assert info["kind"] and info["format_version"] >= 1
    assert info["entries"] == 3
    clouds = info["clouds"]
    points = sum(len(rec._clouds.cloud(i)) for i in range(3)) / 3
    assert clouds["points_per_entry"] == pytest.approx(points, abs=0.1)
    assert clouds["cloud_store"] == "int16-zlib"
    # the packed size measured on the saved clouds: what the store holds in RAM for them
    assert clouds["ram_kib_per_entry_built"] == pytest.approx(rec._clouds.nbytes / 3 / 1024, rel=0.02)
    assert abs(clouds["entries_in_ram_within_budget"] - 64e6 / (rec._clouds.nbytes / 3)) <= 1
    # a scan .npz is still summarised as a scan
    np.savez(tmp_path / "scan.npz", xyz=np.random.default_rng(0).normal(size=(100, 3)).astype(np.float32))
    result = CliRunner().invoke(app, ["info", str(tmp_path / "scan.npz"), "--json"])
    assert result.exit_code == 0 and "points" in json.loads(result.output)


def test_spilled_arrays_keep_their_budget_and_read_back_bit_for_bit():
    from placerec.verify.spill import SpilledArrays

    rng = np.random.default_rng(4)
    arrays = [rng.integers(0, 255, (int(rng.integers(1, 300)), 32), dtype=np.uint8) for _ in range(50)]
    m = SpilledArrays(20_000, SpillFile())
    for i, a in enumerate(arrays):
        m[i] = a
        assert m.nbytes <= 20_000
    assert len(m) == 50 and 0 in m and list(m) == list(range(50))
    for i, a in enumerate(arrays):
        np.testing.assert_array_equal(m[i], a)
        assert m[i].dtype == a.dtype
    m[0] = arrays[1]  # replacing an entry
    np.testing.assert_array_equal(m[0], arrays[1])
    unlimited = SpilledArrays(None, SpillFile())
    for i, a in enumerate(arrays):
        unlimited[i] = a
    assert unlimited.nbytes == sum(a.nbytes for a in arrays)
