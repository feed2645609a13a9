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
}


@pytest.mark.parametrize("name", sensor_names())
def test_simulated_presets_from_record_and_from_structure(name: str) -> None:
    scan = SimulatedSequence(world="town", sensor=name, seed=0)[0]
    known = identify_sensor(scan)
    assert known.how == "metadata" and known.model is not None and known.model.startswith(_EXPECTED_SIM[name])
    bare = identify_sensor(replace(scan, sensor=SensorInfo(), ring=None))
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
