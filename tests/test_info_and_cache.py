"""``placerec info``'s sensor identification (placerec.summary) and ``placerec cache info|clear``."""

import importlib.util
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from placerec.cli import app
from placerec.cli_support import summarise
from placerec.io import write_scan
from placerec.sim import SimulatedSequence, sensor_names
from placerec.summary import identify_sensor
from placerec.types import Scan, SensorInfo

runner = CliRunner()


def _sensor(path: Path) -> str:
    summary = summarise(path, None)
    return summary.get("first_scan", summary)["sensor"]


@pytest.mark.parametrize(
    "rel, expected",
    [
        ("kitti00_frames/000094.bin", "likely velodyne hdl-64e"),
        ("kitti_raw_hdl64_sequence/0000000000.pcd", "likely velodyne hdl-64e"),
        ("ouster_os1_64_revisit_pair/32line_1.bin", "likely ouster os1-64 (gen1"),
        ("nclt_hdl32_frame/1326652795280148.bin", "velodyne hdl-32e (from metadata: the nclt"),
    ],
)
def test_real_scans_are_identified(real_data: Path, rel: str, expected: str) -> None:
    line = _sensor(real_data / rel)
    assert line.startswith(expected), line
    assert line.endswith("guess)") == line.startswith("likely")


@pytest.mark.skipif(importlib.util.find_spec("ouster") is None, reason="ouster-sdk not installed")
@pytest.mark.parametrize(
    "name, expected",
    [
        ("OS-1-64_1024x10_fw20.pcap", "ouster os1-64 (gen1"),
        ("OS-1-128_v2.3.0_1024x10_lb_n3.pcap", "ouster os1-128"),
    ],
)
def test_ouster_pcaps_from_their_metadata(real_data: Path, name: str, expected: str) -> None:
    line = _sensor(real_data / "ouster_sdk_pcaps" / name)
    assert line.startswith(expected) and "from metadata: the Ouster metadata json" in line, line


def test_info_command_prints_the_sensor_of_the_ouster_pair(real_data: Path) -> None:
    path = real_data / "ouster_os1_64_revisit_pair" / "32line_1.bin"
    result = runner.invoke(app, ["info", str(path), "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.output)
    assert "velodyne" not in summary["sensor"] and summary["sensor_detail"]["how"] == "guess"
    assert summary["sensor_detail"]["model"].startswith("ouster os1-64")
    assert summary["sensor_detail"]["beams"] == 64 and summary["sensor_detail"]["columns"] == 1024


_EXPECTED_SIM = {
    "vlp16": "velodyne vlp-16",
    "hdl64": "velodyne hdl-64e",
    "os1-64": "ouster os1-64 (gen1",
    "os1-64-gen2": "ouster os1-64 (gen2+",
    "os1-128": "ouster os1-128 (gen2+",
    "hdl32": "velodyne hdl-32e",
    "avia": "livox",
    "mid360": "livox",
    "e1r": "robosense e1r",
}


@pytest.mark.parametrize("name", sensor_names())
def test_simulated_presets_from_record_and_from_structure(name: str) -> None:
    scan = SimulatedSequence(world="town", sensor=name, seed=0)[0]
    known = identify_sensor(scan)
    assert known.how == "metadata" and known.model is not None and known.model.startswith(_EXPECTED_SIM[name])
    bare = identify_sensor(replace(scan, sensor=SensorInfo(), ring=None))
    if not scan.sensor.is_spinning:
        # a bare cloud of a scanner that does not spin tells little: a limited horizontal field reads as a
        # non-repetitive (Livox-style) pattern, a 360 deg rosette matches no beam layout
        assert bare.model in ("livox", None)
        return
    assert bare.how == "guess" and bare.model is not None and bare.model.startswith(_EXPECTED_SIM[name])
    assert bare.line().startswith("likely ") and bare.line().endswith("; guess)")


def test_sensor_yaml_beside_a_kitti_bin_is_metadata(tmp_path: Path) -> None:
    scan = SimulatedSequence(world="town", sensor="vlp16", seed=0)[0]
    write_scan(tmp_path / "velodyne" / "000000.bin", scan)
    info = replace(scan.sensor, name="VLP-16 on the roof")
    (tmp_path / "sensor.yaml").write_text(yaml.safe_dump(info.to_dict()))
    line = _sensor(tmp_path / "velodyne" / "000000.bin")
    assert line.startswith("velodyne vlp-16 (from metadata: ") and "sensor.yaml" in line, line


def _write_ascii_pcd(path: Path, fields: list[str], rows: np.ndarray) -> None:
    head = (
        f"VERSION 0.7\nFIELDS {' '.join(fields)}\nSIZE {' '.join('4' for _ in fields)}\n"
        f"TYPE {' '.join('F' for _ in fields)}\nCOUNT {' '.join('1' for _ in fields)}\n"
        f"WIDTH {len(rows)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(rows)}\nDATA ascii\n"
    )
    path.write_text(head + "\n".join(" ".join(f"{v:.4f}" for v in r) for r in rows) + "\n")


def test_livox_from_fields_and_from_its_pattern(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    n = 20000
    az, el = np.radians(rng.uniform(-35, 35, n)), np.radians(rng.uniform(-38, 38, n))
    r = rng.uniform(3, 40, n)
    xyz = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], axis=1)
    rows = np.column_stack([xyz, rng.integers(0, 255, n), rng.integers(0, 4, n), rng.integers(0, 6, n)])
    _write_ascii_pcd(tmp_path / "livox.pcd", ["x", "y", "z", "intensity", "tag", "line"], rows)
    line = _sensor(tmp_path / "livox.pcd")
    assert line.startswith("likely livox (fields line, tag of the Livox driver"), line
    bare = identify_sensor(Scan(xyz=xyz.astype(np.float32), intensity=np.zeros(n, np.float32)))
    assert bare.model == "livox" and "non-repetitive" in bare.line()


def test_a_sensor_no_model_fits_is_unknown() -> None:
    rng = np.random.default_rng(1)
    elev = np.radians(np.repeat(np.linspace(60.0, 40.0, 8), 2000))  # 8 beams, all looking up
    az = rng.uniform(-np.pi, np.pi, elev.size)
    xyz = 10 * np.stack([np.cos(elev) * np.cos(az), np.cos(elev) * np.sin(az), np.sin(elev)], axis=1)
    guess = identify_sensor(Scan(xyz=xyz.astype(np.float32), intensity=np.zeros(elev.size, np.float32)))
    assert (
        guess.model is None and guess.line().startswith("unknown (") and "no known model fits" in guess.line()
    )


# --- the description cache: size limit, info, clear ---------------------------------------------------------------

import logging  # noqa: E402
import os  # noqa: E402
import shutil  # noqa: E402
import time  # noqa: E402

from placerec.errors import ConfigError  # noqa: E402
from placerec.experiment.cache import (  # noqa: E402
    LIMIT_ENV,
    DescriptionCache,
    cache_info,
    cache_limit_mb,
    clear_cache,
    scan_cache,
    trim_cache,
)


def _fill(root: Path, data_key: str, frontend: str, n: int, floats: int = 2500) -> DescriptionCache:
    cache = DescriptionCache(root, data_key)
    for i in range(n):
        cache.put(frontend, i, {"d": np.full(floats, i, np.float32)}, 1.0)
    return cache


def test_cache_limit_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(LIMIT_ENV, raising=False)
    assert cache_limit_mb() == 2000.0
    for off in ("0", "off", "None"):
        monkeypatch.setenv(LIMIT_ENV, off)
        assert cache_limit_mb() is None
    monkeypatch.setenv(LIMIT_ENV, "250.5")
    assert cache_limit_mb() == 250.5
    for bad in ("-1", "big", "inf", "nan"):
        monkeypatch.setenv(LIMIT_ENV, bad)
        with pytest.raises(ConfigError, match=LIMIT_ENV):
            cache_limit_mb()


def test_runs_keep_the_size_limit_evicting_least_recently_used(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    root = tmp_path / "cache"
    monkeypatch.setenv(LIMIT_ENV, "off")
    first = _fill(root, "aaaaaaaaaaaa", "sc-0123456789ab", 10)  # ~10 kB each, 100 kB
    old = time.time() - 3600
    for e in scan_cache(root):
        os.utime(e.path, (old, old + int(e.path.stem)))  # entry 0 used longest ago
    assert first.get("sc-0123456789ab", 3) is not None  # a use: entry 3 becomes the most recent
    monkeypatch.setenv(LIMIT_ENV, "0.15")  # 150 kB
    with caplog.at_level(logging.WARNING, logger="placerec.experiment.cache"):
        _fill(root, "bbbbbbbbbbbb", "sc-0123456789ab", 8)
    total = sum(e.size for e in scan_cache(root))
    assert total <= 0.15e6 * 1.1
    left = {(e.data_key, int(e.path.stem)) for e in scan_cache(root)}
    assert ("aaaaaaaaaaaa", 3) in left and ("aaaaaaaaaaaa", 0) not in left
    assert all(("bbbbbbbbbbbb", i) in left for i in range(8))
    assert "evicted" in caplog.text and LIMIT_ENV in caplog.text
    assert (root / "CACHEDIR.TAG").read_text().startswith("Signature: 8a477f597d28d172789f06886806bc55")


def test_entries_removed_by_another_process_while_listed_are_not_listed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two benchmark workers trim one cache: what the other removes between the listing and the stat (or a
    folder it empties and removes) is simply not there, never an error that ends the run."""
    import placerec.experiment.cache as cache_module

    root = tmp_path / "cache"
    monkeypatch.setenv(LIMIT_ENV, "off")
    _fill(root, "aaaaaaaaaaaa", "sc-0123456789ab", 4)
    _fill(root, "bbbbbbbbbbbb", "sc-0123456789ab", 2)
    real = os.scandir
    gone = root / "aaaaaaaaaaaa" / "sc-0123456789ab" / "000001.npz"
    emptied = root / "bbbbbbbbbbbb" / "sc-0123456789ab"

    class Racing:
        """A listing during which the other process removes ``gone`` (and the folder ``emptied``) after they were
        listed and before this process looks at them."""

        def __init__(self, path):
            self.listing = real(path)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.listing.close()

        def __iter__(self):
            for entry in self.listing:
                if Path(entry.path) == gone:
                    gone.unlink()
                if Path(entry.path) == emptied:
                    shutil.rmtree(emptied)
                yield entry

    def racing(path):
        return real(path) if isinstance(path, int) else Racing(path)  # int: shutil.rmtree's own listing

    monkeypatch.setattr(cache_module.os, "scandir", racing)
    left = {(e.data_key, int(e.path.stem)) for e in scan_cache(root)}
    assert left == {("aaaaaaaaaaaa", i) for i in (0, 2, 3)}
    monkeypatch.setenv(LIMIT_ENV, "0.001")
    assert trim_cache(root, 0.001)[0] >= 1


def test_a_folder_with_foreign_files_is_never_cleared_or_trimmed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    root = tmp_path / "cache"
    monkeypatch.setenv(LIMIT_ENV, "off")
    _fill(root, "aaaaaaaaaaaa", "sc-0123456789ab", 4)
    (root / "aaaaaaaaaaaa" / "notes.txt").write_text("mine")
    (root / "aaaaaaaaaaaa" / "sc-0123456789ab" / "photo.jpg").write_bytes(b"x")
    before = sorted(p for p in root.rglob("*"))
    with pytest.raises(ConfigError, match="does not look like a description cache.*notes.txt"):
        clear_cache(root)
    monkeypatch.setenv(LIMIT_ENV, "0.001")
    with caplog.at_level(logging.WARNING, logger="placerec.experiment.cache"):
        _fill(root, "aaaaaaaaaaaa", "sc-0123456789ab", 6)
    assert "not trimmed" in caplog.text
    assert set(before) <= set(root.rglob("*"))
    result = runner.invoke(app, ["cache", "clear", "--dir", str(root)])
    assert result.exit_code == 2 and result.output.startswith("error:") and "nothing removed" in result.output
    assert (root / "aaaaaaaaaaaa" / "notes.txt").read_text() == "mine"


def test_cache_info_and_clear_commands(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    root = tmp_path / "cache"
    monkeypatch.setenv(LIMIT_ENV, "off")
    _fill(root, "aaaaaaaaaaaa", "scan-context-0123456789ab", 3, floats=10)
    _fill(root, "bbbbbbbbbbbb", "scan-context-0123456789ab", 2, floats=10)
    _fill(root, "aaaaaaaaaaaa", "visual-0123456789ab", 4, floats=10)
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(yaml.safe_dump({"output": {"cache_dir": str(root)}}))
    result = runner.invoke(app, ["cache", "info", "--config", str(cfg), "--json"])
    assert result.exit_code == 0, result.output
    info = json.loads(result.output)
    assert info["entries"] == 9 and info["datasets"] == 2 and info["limit_mb"] == "none"
    assert info["frontends"]["scan-context-0123456789ab"]["entries"] == 5
    assert info["frontends"]["visual-0123456789ab"]["datasets"] == 1
    assert info["oldest_use"] is not None and info["newest_use"] is not None
    for e in scan_cache(root):
        if e.data_key == "bbbbbbbbbbbb":
            os.utime(e.path, (time.time() - 10 * 86400,) * 2)
    result = runner.invoke(app, ["cache", "clear", "--dir", str(root), "--older-than", "5"])
    assert result.exit_code == 0 and result.output.startswith("removed 2 entries"), result.output
    assert not (root / "bbbbbbbbbbbb").exists()  # emptied folders go too
    result = runner.invoke(app, ["cache", "clear", "--dir", str(root), "--frontend", "scan-context"])
    assert result.output.startswith("removed 3 entries")
    assert cache_info(root)["frontends"].keys() == {"visual-0123456789ab"}
    result = runner.invoke(app, ["cache", "clear", "--dir", str(root)])
    assert result.output.startswith("removed 4 entries") and root.is_dir() and scan_cache(root) == []
    result = runner.invoke(app, ["cache", "info", "--dir", str(tmp_path / "none"), "--json"])
    assert result.exit_code == 0 and json.loads(result.output)["exists"] is False
