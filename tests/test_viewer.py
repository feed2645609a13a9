"""Rerun recordings (`placerec.viewer`, docs/viewer.md): tiny runs with ``--rrd`` read back with Rerun's own
reader and compared with the run's own files; rerun never imported without the flags; bad flags refused before
a run starts."""

import json
import os
import subprocess
import sys
from collections import defaultdict

import numpy as np
import pytest
from typer.testing import CliRunner

from placerec.cli import app
from placerec.experiment.candidates import read_candidates

rr_recording = pytest.importorskip(
    "rerun.recording", reason="the viewer extra: pip install 'placerec[viewer]'"
)

#: the block loop driven twice at 3 m (57 scans a lap): from scan 57 on every query revisits
TINY_RUN = """
name: tiny
dataset:
  simulator: {world: town, sensor: vlp16, route: loop, spacing: 3.0, seed: 3, n_scans: 66}
pipelines:
  - name: scan-context
  - name: orb-hbst
evaluation:
  exclusion: {frames: 30}
output:
  cache_dir: null
  progress: false
"""
TINY_SLAM = [
    "dataset.simulator.sensor=vlp16", "dataset.simulator.route=loop", "dataset.simulator.spacing=3.0",
    "dataset.simulator.seed=3", "dataset.simulator.n_scans=66", "loops.exclusion.frames=30", "output.progress=false",
]  # fmt: skip
GREEN = 0x28C850FF  # placerec.viewer.recorder.ACCEPTED as Rerun packs it (RGBA)


_SKIP = {"log_time", "log_tick", "scan_time"}  # columns the checks never read
ROW_ID = (
    "rerun.controls.RowId"  # big-endian log time first: orders rows logged at the same scan as Rerun does
)


def read_rrd(path):
    """Entity path -> [(scan, row as a dict of python values)], every chunk merged, in the order Rerun's
    latest-at queries use (scan, then row id); static rows get scan -1."""
    rows = defaultdict(list)
    for chunk in rr_recording.load_recording(path).chunks():
        batch = chunk.to_record_batch()
        keep = [f.name for f in batch.schema if f.name not in _SKIP]
        table = batch.select(keep).to_pydict()
        n = chunk.num_rows
        times = table.get("scan", [-1] * n)
        for i in range(n):
            rows[str(chunk.entity_path)].append((times[i], {k: v[i] for k, v in table.items()}))
    return {k: sorted(v, key=lambda r: (r[0], r[1][ROW_ID])) for k, v in rows.items()}


def _with(rows, component):
    return [(t, r) for t, r in rows if r.get(component) is not None]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp("viewer")
    cfg = root / "tiny.yaml"
    cfg.write_text(TINY_RUN)
    rrd = root / "tiny.rrd"
    result = CliRunner().invoke(app, ["run", str(cfg), "--out", str(root / "results"), "--rrd", str(rrd)])
    assert result.exit_code == 0, result.output
    return root / "results" / "latest", read_rrd(rrd)


def test_the_recording_passes_rerun_rrd_verify(run):
    from placerec.viewer import viewer_executable

    exe = viewer_executable()
    if exe is None:
        pytest.skip("rerun-sdk's command line is not installed")
    rrd = run[0].parent.parent / "tiny.rrd"
    p = subprocess.run([str(exe), "rrd", "verify", str(rrd)], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert [f.name for f in rrd.parent.iterdir() if f.name.startswith(".")] == []  # no temporary folder left


def test_every_scan_is_logged_once(run):
    folder, rec = run
    n = len(read_candidates(folder / "candidates_orb-hbst.csv").query_ids)
    scans = _with(rec["/world/scan"], "Points3D:positions")
    assert [t for t, _ in scans] == list(range(n))
    assert all(0 < len(r["Points3D:positions"]) <= 4000 for _, r in scans)
    assert len(_with(rec["/scan/image"], "EncodedImage:blob")) == n  # one visual front end: one image a scan
    assert len(rec["/world/trajectory/gt"][0][1]["LineStrips3D:strips"][0]) == n


@pytest.mark.parametrize("pipeline", ["scan-context", "orb-hbst"])
def test_candidates_and_closures_match_the_run(run, pipeline):
    folder, rec = run
    table = read_candidates(folder / f"candidates_{pipeline}.csv")
    logged = sum(
        len(_with(rows, "TextDocument:text"))
        for path, rows in rec.items()
        if path.startswith(f"/pipelines/{pipeline}/candidates/") and path.endswith("/verification")
    )
    assert logged == int((table.match_ids >= 0).sum()) > 0
    top = table.accepted[:, 0]
    assert (top != -1).sum() == (table.match_ids[:, 0] >= 0).sum()  # both pipelines verify their candidates
    for kind, value in (("accepted", 1), ("rejected", 0)):
        strips = rec[f"/world/loops/{pipeline}/{kind}"][-1][1]["LineStrips3D:strips"]
        assert len(strips) == int((top == value).sum()) > 0, kind


def test_the_pairs_show_the_inliers_of_verification(run):
    folder, rec = run
    table = read_candidates(folder / "candidates_orb-hbst.csv")
    lines = _with(rec["/pipelines/orb-hbst/candidates/0/pair/correspondences"], "LineStrips2D:strips")
    assert len(lines) == len(_with(rec["/pipelines/orb-hbst/candidates/0/pair"], "EncodedImage:blob")) > 10
    for t, r in lines:
        green = sum(c == GREEN for c in r["LineStrips2D:colors"])
        assert green == table.inliers[t, 0], t
        ends = np.array(r["LineStrips2D:strips"], dtype=np.float32)
        assert (
            ends.shape[1:] == (2, 2) and (ends[:, 1, 1] >= ends[:, 0, 1]).all()
        )  # match image below the query


def test_the_aligned_clouds_are_the_query_moved_by_the_candidate_pose(run):
    folder, rec = run
    table = read_candidates(folder / "candidates_orb-hbst.csv")
    scans = dict(_with(rec["/world/scan"], "Points3D:positions"))
    aligned = _with(rec["/pipelines/orb-hbst/candidates/0/alignment/query"], "Points3D:positions")
    assert aligned
    for t, r in aligned[:5]:
        T = table.relative_poses[t, 0]
        query = np.array(scans[t]["Points3D:positions"], np.float64)[::2]
        np.testing.assert_allclose(
            np.array(r["Points3D:positions"]), query @ T[:3, :3].T + T[:3, 3], atol=1e-3
        )


def test_slam_recording_matches_its_loops(tmp_path):
    rrd = tmp_path / "slam.rrd"
    result = CliRunner().invoke(
        app,
        ["slam", "--out", str(tmp_path / "out"), "--rrd", str(rrd)]
        + [a for s in TINY_SLAM for a in ("--set", s)],
    )
    assert result.exit_code == 0, result.output
    metrics = json.loads((tmp_path / "out" / "latest" / "metrics.json").read_text())
    rec = read_rrd(rrd)
    assert [t for t, _ in _with(rec["/world/scan"], "Points3D:positions")] == list(range(metrics["n_scans"]))
    accepted = rec["/world/loops/orb-hbst/accepted"][-1][1]["LineStrips3D:strips"]
    assert len(accepted) == metrics["loops"]["accepted"] > 0
    final = rec["/world/trajectory/optimized"][-1][1]["LineStrips3D:strips"][0]
    poses = np.loadtxt(tmp_path / "out" / "latest" / "poses_kitti.txt").reshape(-1, 3, 4)
    np.testing.assert_allclose(np.array(final), poses[:, :, 3], atol=1e-6)
    # the edges were moved onto the optimised poses at the end
    ends = np.array(accepted, np.float64).reshape(-1, 3)
    assert np.min(np.linalg.norm(ends[:, None] - poses[None, :, :, 3], axis=2), axis=1).max() < 1e-6


def test_the_ishot_posterior_is_logged_batch_by_batch(tmp_path):
    from placerec.pipelines.probabilistic_voting import PosteriorStep
    from placerec.viewer import ViewerTarget, recording

    steps = [
        PosteriorStep(7, 16 * (k + 1), 64, np.arange(4), np.array([0.1, 0.2, 0.3, 0.4]) ** (k + 1))
        for k in range(3)
    ]
    with recording(ViewerTarget(rrd=tmp_path / "p.rrd"), "posterior") as rec:
        observe = rec.posterior_observer("ishot-prob")
        for s in steps:
            observe(s)
    rows = read_rrd(tmp_path / "p.rrd")["/pipelines/ishot-prob/posterior"]
    assert [r["ishot_batch"] for _, r in rows] == [1, 2, 3]
    for (_, r), s in zip(rows, steps, strict=True):
        np.testing.assert_allclose(r["BarChart:values"][0]["buffer"], s.probabilities)


def test_probabilistic_voting_calls_its_observer(ishot_recognizer_and_query):
    rec, desc = ishot_recognizer_and_query
    seen = []
    rec.posterior_observer = seen.append
    try:
        rec.query_description(desc, k=1, query_id=99)
    finally:
        rec.posterior_observer = None
    assert seen and all(s.query_id == 99 for s in seen)
    assert [s.matched for s in seen] == sorted(s.matched for s in seen)
    for s in seen:
        assert len(s.ids) == len(s.probabilities) and np.isclose(s.probabilities.sum(), 1.0)


@pytest.fixture(scope="module")
def ishot_recognizer_and_query():
    from placerec.recognizer import make_pipeline
    from placerec.sim import SimulatedSequence

    seq = SimulatedSequence(world="town", sensor="vlp16", n_scans=4, seed=0, spacing=3.0)
    rec = make_pipeline("ishot-prob", {"verify": {"enabled": False}})
    for i in range(3):
        rec.add(i, seq[i], seq.poses[i])
    return rec, rec.describe(seq[3])


def _cli(args, block_rerun=False):
    """``placerec ARGS`` in a fresh interpreter; with ``block_rerun`` as if rerun-sdk were not installed. Returns
    (exit code, output, whether rerun got imported)."""
    code = (
        "import sys\n"
        + ("sys.modules['rerun'] = None\n" if block_rerun else "")
        + "from typer.testing import CliRunner\nfrom placerec.cli import app\n"
        + f"r = CliRunner().invoke(app, {args!r})\n"
        + "print(r.output)\nprint('rerun imported:', 'rerun' in sys.modules and sys.modules['rerun'] is not None)\n"
        + "sys.exit(r.exit_code)\n"
    )
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    return p.returncode, p.stdout + p.stderr, "rerun imported: True" in p.stdout


TINY_ARGS = ["--set", "dataset.simulator.n_scans=4", "--set", "pipelines=[{name: scan-context}]",
             "--set", "evaluation.exclusion.frames=1", "--set", "output.cache_dir=null"]  # fmt: skip


def test_a_run_without_the_flags_never_imports_rerun(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(TINY_RUN)
    code, out, imported = _cli(["run", str(cfg), "--out", str(tmp_path / "o"), *TINY_ARGS])
    assert code == 0, out
    assert not imported


@pytest.mark.parametrize("flag", [["--viewer"], ["--rrd", "x.rrd"]])
def test_the_flags_without_the_extra_name_it(tmp_path, flag):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(TINY_RUN)
    code, out, _ = _cli(["run", str(cfg), "--out", str(tmp_path / "o"), *flag], block_rerun=True)
    assert code == 2 and "pip install 'placerec[viewer]'" in out, out
    assert not (tmp_path / "o").exists()


def _unwritable(tmp_path, kind):
    if kind == "missing folder":
        return tmp_path / "nowhere" / "x.rrd"
    if kind == "a folder":
        (tmp_path / "dir.rrd").mkdir()
        return tmp_path / "dir.rrd"
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    return ro / "x.rrd"


@pytest.mark.parametrize("kind", ["missing folder", "a folder", "read-only folder"])
@pytest.mark.parametrize("command", ["run", "slam"])
def test_an_unwritable_recording_fails_before_the_run(tmp_path, kind, command):
    if kind == "read-only folder" and os.geteuid() == 0:
        pytest.skip("root writes into read-only folders")
    rrd = _unwritable(tmp_path, kind)
    cfg = tmp_path / "c.yaml"
    cfg.write_text(TINY_RUN)
    args = (
        [command]
        + ([str(cfg)] if command == "run" else [])
        + ["--out", str(tmp_path / "o"), "--rrd", str(rrd)]
    )
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 2, result.output
    assert str(rrd) in result.output
    assert not (tmp_path / "o").exists()  # nothing ran


def test_localize_refuses_an_unwritable_recording_before_opening_the_map(tmp_path):
    rrd = _unwritable(tmp_path, "missing folder")
    result = CliRunner().invoke(
        app, ["localize", str(tmp_path / "no-map"), str(tmp_path / "no-seq"), "--rrd", str(rrd)]
    )
    assert result.exit_code == 2 and str(rrd) in result.output, result.output


TINY_LOCALIZE = """
name: loc
dataset:
  simulator: {world: town, sensor: vlp16, seed: 0, n_scans: 40}
pipelines:
  - name: ishot-prob
evaluation:
  mode: localize
  localize: {n_queries: 3}
output:
  cache_dir: null
  progress: false
"""


def test_localize_mode_logs_the_fixes_on_the_map_and_the_posterior(tmp_path):
    cfg = tmp_path / "loc.yaml"
    cfg.write_text(TINY_LOCALIZE)
    rrd = tmp_path / "loc.rrd"
    result = CliRunner().invoke(app, ["run", str(cfg), "--out", str(tmp_path / "out"), "--rrd", str(rrd)])
    assert result.exit_code == 0, result.output
    folder = tmp_path / "out" / "latest"
    table = read_candidates(folder / "candidates_ishot-prob.csv")
    map_poses = np.loadtxt(folder / "map_poses.txt").reshape(-1, 3, 4)
    rec = read_rrd(rrd)
    assert [t for t, _ in _with(rec["/world/scan"], "Points3D:positions")] == list(
        range(len(table.query_ids))
    )
    assert len(rec["/world/trajectory/map"][0][1]["LineStrips3D:strips"][0]) == len(map_poses)
    logged = sum(
        len(_with(rows, "TextDocument:text")) for p, rows in rec.items() if p.endswith("/verification")
    )
    assert logged == int((table.match_ids >= 0).sum())
    # the fixes: each accepted best candidate's T_world_query, i.e. its map pose moved by relative_pose
    fixed = [q for q in range(len(table.query_ids)) if table.accepted[q, 0] == 1]
    expected = []
    for q in fixed:
        T_map = np.vstack([map_poses[table.match_ids[q, 0]], [0, 0, 0, 1]])
        expected.append((T_map @ table.relative_poses[q, 0])[:3, 3])
    fixes = rec["/world/fixes/ishot-prob"][-1][1]["Points3D:positions"]
    assert len(fixed) > 0
    np.testing.assert_allclose(np.array(fixes), np.array(expected), atol=1e-3)
    posterior = _with(rec["/pipelines/ishot-prob/posterior"], "BarChart:values")
    assert len(posterior) >= len(table.query_ids)  # at least one batch a query
    sizes = set()
    for _, r in posterior:
        values = np.array(r["BarChart:values"][0]["buffer"])
        sizes.add(len(values))
        assert np.isclose(values.sum(), 1.0)
    assert len(sizes) == 1 and 1 < sizes.pop() <= len(map_poses)  # one probability per place of the map


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the display check is Linux's")
def test_viewer_without_a_display_fails_before_the_run(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(TINY_RUN)
    env = {"DISPLAY": "", "WAYLAND_DISPLAY": "", "WAYLAND_SOCKET": ""}
    result = CliRunner(env=env).invoke(app, ["run", str(cfg), "--out", str(tmp_path / "o"), "--viewer"])
    assert result.exit_code == 2 and "no display" in result.output and "--rrd" in result.output, result.output
    assert not (tmp_path / "o").exists()


def test_the_viewer_executable_is_found_beside_python_off_path(monkeypatch):
    from placerec.viewer import viewer_executable

    beside = os.path.join(os.path.dirname(sys.executable), "rerun")
    if not os.access(beside, os.X_OK):
        pytest.skip("rerun-sdk's viewer is not installed beside this Python")
    monkeypatch.setenv("PATH", "/nonexistent")
    assert str(viewer_executable()) == beside


def test_growing_entities_are_logged_a_linear_number_of_items():
    from placerec.viewer.recorder import _Growing

    g, items_logged, logs = _Growing(), 0, 0
    for i in range(5000):
        if g.add(i):
            logs += 1
            items_logged += len(g.items)
            g.logged = len(g.items)
    assert (
        logs < 150 and items_logged < 25 * 5000
    )  # every addition logged again would be 5000 logs, 12.5M items
    assert len(g.items) - g.logged <= g.logged // 20  # what the end of the recording still has to log


def test_placerec_localize_logs_its_fixes_on_the_map(tmp_path):
    import csv

    runner = CliRunner()
    build = ["map", "build", "--sim-world", "town", "--sim-sensor", "vlp16", "--sim-scans", "20"]
    result = runner.invoke(app, [*build, "--pipeline", "scan-context", "--out", str(tmp_path / "map")])
    assert result.exit_code == 0, result.output
    sim = ["simulate", "--preset", "town", "--sensor", "vlp16", "--scans", "5", "--seed", "0"]
    assert runner.invoke(app, [*sim, "--out", str(tmp_path / "seq")]).exit_code == 0
    rrd = tmp_path / "loc.rrd"
    args = ["localize", str(tmp_path / "map"), str(tmp_path / "seq"), "--out", str(tmp_path / "out")]
    result = runner.invoke(app, [*args, "--rrd", str(rrd)])
    assert result.exit_code == 0, result.output
    with open(tmp_path / "out" / "fixes.csv") as fh:
        rows = list(csv.DictReader(fh))
    rec = read_rrd(rrd)
    assert len(rec["/world/map/keyframes"][0][1]["Points3D:positions"]) == 20
    assert [t for t, _ in _with(rec["/world/scan"], "Points3D:positions")] == list(range(len(rows)))
    assert len(_with(rec["/localize/localizer"], "TextDocument:text")) == len(rows)
    fixed = [[float(r[k]) for k in "xyz"] for r in rows if r["accepted"] == "1"]
    assert fixed
    np.testing.assert_allclose(rec["/world/fixes/localizer"][-1][1]["Points3D:positions"], fixed, atol=1e-4)


def test_a_run_that_fails_leaves_no_recording(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(TINY_RUN.replace("name: orb-hbst", "name: no-such-pipeline"))
    (tmp_path / "rec").mkdir()
    rrd = tmp_path / "rec" / "x.rrd"
    result = CliRunner().invoke(app, ["run", str(cfg), "--out", str(tmp_path / "o"), "--rrd", str(rrd)])
    assert result.exit_code == 2 and "no-such-pipeline" in result.output, result.output
    assert list((tmp_path / "rec").iterdir()) == []  # neither the file nor the temporary folder
