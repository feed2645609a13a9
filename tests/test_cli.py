import json
import subprocess
import sys

import pytest
from typer.testing import CliRunner

from placerec.cli import app

runner = CliRunner()


def test_version_lists_native_dependencies():
    result = runner.invoke(app, ["--version"])
    assert result.exit_code == 0, result.output
    for name in ("placerec", "numpy", "OpenCV", "Open3D"):
        assert name in result.output


def test_help_does_not_import_heavy_modules():
    code = (
        "import sys\n"
        "from typer.testing import CliRunner\n"
        "from placerec.cli import app\n"
        "r = CliRunner().invoke(app, ['--help'])\n"
        "assert r.exit_code == 0, r.output\n"
        "print([m for m in ('open3d', 'torch', 'cv2', 'placerec.sim') if m in sys.modules])\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_dump_config_is_loadable(tmp_path):
    out = tmp_path / "d.yaml"
    result = runner.invoke(app, ["dump-config", "--out", str(out)])
    assert result.exit_code == 0, result.output
    from placerec.config import ExperimentConfig, load_config

    assert load_config(out) == ExperimentConfig()


def test_info_on_generated_scan(tmp_path):
    import numpy as np

    from placerec.io import write_scan
    from placerec.types import Scan

    rng = np.random.default_rng(0)
    path = tmp_path / "s.pcd"
    write_scan(path, Scan(rng.normal(size=(500, 3)) * 10, rng.random(500), ring=rng.integers(0, 16, 500)))
    result = runner.invoke(app, ["info", str(path), "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.output)
    assert summary["points"] == 500 and summary["beams"] == 16 and "ring" in summary["fields"]


def test_info_reports_bad_files_cleanly(tmp_path):
    bad = tmp_path / "bad.bin"
    bad.write_bytes(b"\x00" * 10)
    result = runner.invoke(app, ["info", str(bad)])
    assert result.exit_code == 2
    assert "bad.bin" in result.output and "Traceback" not in result.output


def test_run_rejects_unknown_config_keys(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("evaluation:\n  gt_distnace: 3\n")
    result = runner.invoke(app, ["run", str(cfg)])
    assert result.exit_code == 2
    assert "gt_distnace" in result.output and "gt_distance" in result.output


@pytest.mark.parametrize("name", ["000094.bin"])
def test_info_on_real_kitti(real_data, name):
    result = runner.invoke(app, ["info", str(real_data / "kitti00_frames" / name), "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.output)
    assert summary["points"] > 100_000
    assert 50 <= summary["beams"] <= 70  # HDL-64 estimated from elevation peaks


def test_simulate_writes_a_kitti_folder_placerec_reads_back(tmp_path):
    out = tmp_path / "sim"
    result = runner.invoke(
        app, ["simulate", "--preset", "town", "--sensor", "vlp16", "--scans", "3", "--out", str(out)]
    )
    assert result.exit_code == 0, result.output
    from placerec.io import open_sequence

    seq = open_sequence(out)
    assert len(seq) == 3 and seq.poses.shape == (3, 4, 4)
    scan = seq[0]
    assert scan.ring is not None and scan.sensor.n_beams == 16 and len(scan) > 1000
    bad = runner.invoke(app, ["simulate", "--sensor", "nope", "--scans", "1", "--out", str(tmp_path / "x")])
    assert bad.exit_code == 2 and "nope" in bad.output


def test_simulated_export_round_trips_raw_intensity(tmp_path):
    import numpy as np

    from placerec.io import open_sequence
    from placerec.sim import SimulatedSequence, write_kitti_sequence

    seq = SimulatedSequence(world="town", sensor="vlp16", n_scans=2, seed=4)
    write_kitti_sequence(seq, tmp_path / "out", progress=False)
    loaded, original = open_sequence(tmp_path / "out")[1], seq[1]
    valid = np.any(original.xyz != 0, axis=1)
    assert loaded.sensor.intensity_max == original.sensor.intensity_max == 255
    assert np.allclose(np.sort(loaded.intensity), np.sort(original.intensity[valid]), atol=0.01)


@pytest.mark.parametrize("name", ["orb-dbow", "ishot-votes", "surf-dbow"])
def test_pipeline_parameter_names_are_never_cut_on_an_80_column_terminal(name):
    from placerec.params import param_rows
    from placerec.recognizer import pipeline_params

    result = runner.invoke(app, ["pipelines", name], env={"COLUMNS": "80"})
    assert result.exit_code == 0, result.output
    assert max(map(len, result.output.splitlines())) <= 80
    assert "…" not in result.output
    names = {line.split(" = ")[0] for line in result.output.splitlines() if " = " in line and line[0] != " "}
    assert {row[0] for row in param_rows(pipeline_params(name))} <= names


def test_info_table_never_cuts_a_long_value(tmp_path, monkeypatch):
    """A long path wraps in ``placerec info``'s table rather than ending in '…' (#32: output that fits)."""
    import numpy as np

    from placerec.io import write_scan
    from placerec.types import Scan

    deep = tmp_path / ("a_rather_long_folder_name_" * 4)
    deep.mkdir()
    path = deep / "scan.pcd"
    write_scan(path, Scan(np.random.default_rng(0).normal(size=(50, 3)), np.ones(50)))
    monkeypatch.setenv("COLUMNS", "80")
    result = runner.invoke(app, ["info", str(path)])
    assert result.exit_code == 0, result.output
    assert "…" not in result.output and "scan.pcd" in result.output.replace("\n", "").replace(" ", "")
    assert max(len(line) for line in result.output.splitlines()) <= 80
