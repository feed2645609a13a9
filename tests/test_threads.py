"""`placerec.threads`: the thread count placerec chooses, OpenMP runtimes loaded with sleeping idle threads, and
the helper thread that runs a scan's independent steps side by side."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import types

import pytest

from placerec import threads
from placerec.threads import available_threads, import_openmp, side_by_side


def test_import_openmp_sets_the_policy_only_while_importing(monkeypatch):
    seen = []

    def fake_import(name):
        seen.append((name, os.environ.get("OMP_WAIT_POLICY")))
        return types.ModuleType(name)

    monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)
    monkeypatch.setattr(threads.importlib, "import_module", fake_import)
    assert import_openmp("not_loaded_yet_1").__name__ == "not_loaded_yet_1"
    assert seen == [("not_loaded_yet_1", "passive")]
    assert "OMP_WAIT_POLICY" not in os.environ  # removed again: other runtimes and children keep the user's
    monkeypatch.setenv("OMP_WAIT_POLICY", "active")  # the user's own setting wins
    import_openmp("not_loaded_yet_2")
    assert seen[-1] == ("not_loaded_yet_2", "active") and os.environ["OMP_WAIT_POLICY"] == "active"


def test_import_openmp_of_a_loaded_module_and_a_missing_one(monkeypatch):
    assert import_openmp("os") is os
    monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)
    with pytest.raises(ImportError):
        import_openmp("placerec_no_such_module")
    assert "OMP_WAIT_POLICY" not in os.environ


SPIN = """
import time, numpy as np
from placerec.verify.icp import _small_gicp
sg = _small_gicp()
c = sg.voxelgrid_sampling(np.random.default_rng(0).normal(0, 10, (20000, 3)), 0.3)
tree = sg.KdTree(c, num_threads=2)
sg.estimate_normals_covariances(c, tree, 10, num_threads=2)
c0 = time.process_time(); time.sleep(0.2); print((time.process_time() - c0) * 1e3)
"""


def test_idle_openmp_threads_of_small_gicp_sleep():
    """After a parallel region small_gicp's OpenMP threads do not spin (with the policy 'active' they burn a
    core for the whole 0.2 s; placerec's import leaves them asleep: well under a millisecond measured)."""
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "OMP_NUM_THREADS")}
    out = subprocess.run([sys.executable, "-c", SPIN], env=env, capture_output=True, text=True, check=True)
    assert float(out.stdout.split()[-1]) < 50.0
    spin = subprocess.run(
        [sys.executable, "-c", SPIN], env=env | {"OMP_WAIT_POLICY": "active"}, capture_output=True, text=True
    )
    assert float(spin.stdout.split()[-1]) > 100.0  # the check can tell spinning from sleeping


def test_available_threads(monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert available_threads() == 3
    for junk in ("0", "x", ""):
        monkeypatch.setenv("OMP_NUM_THREADS", junk)
        assert available_threads() == len(os.sched_getaffinity(0))


def test_side_by_side_runs_on_the_helper_thread(monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    job = side_by_side(lambda: threading.current_thread().name)
    assert job.result().startswith("placerec-side")
    # from the helper thread itself: at once (waiting on a job queued behind itself would never end)
    nested = side_by_side(lambda: side_by_side(lambda: threading.current_thread().name).result())
    assert nested.result().startswith("placerec-side")


def test_side_by_side_inline_on_one_thread_and_errors(monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert side_by_side(lambda: threading.current_thread().name).result() == threading.current_thread().name

    def boom():
        raise ValueError("from the job")

    for n in ("1", "2"):
        monkeypatch.setenv("OMP_NUM_THREADS", n)
        with pytest.raises(ValueError, match="from the job"):
            side_by_side(boom).result()


@pytest.mark.parametrize("pipeline", ["orb-hbst", "superpoint-dbow"])
def test_visual_pipelines_give_the_sequential_results(monkeypatch, pipeline):
    """Descriptions (image and features beside the ICP cloud) and verified candidates (float descriptors matched on
    two threads) are those of the one-thread path, byte for byte."""
    import numpy as np

    from placerec.recognizer import make_pipeline
    from placerec.sim import SimulatedSequence

    seq = SimulatedSequence("town", "os1-64", seed=3, n_scans=14)
    scans = [seq[i] for i in (*range(8), 3, 4, 5)]  # the last three revisit scans 3-5

    def run(n_threads):
        monkeypatch.setenv("OMP_NUM_THREADS", n_threads)
        rec = make_pipeline(pipeline, {"verify": {"top_k": 6}})
        descriptions, found = [], []
        for k, scan in enumerate(scans):
            d = rec.describe(scan)
            descriptions.append({key: np.asarray(v).tobytes() for key, v in d.items()})
            if k > 3:
                for c in rec.query_description(d, 5, max_id=k - 3, query_id=k):
                    pose = None if c.relative_pose is None else c.relative_pose.tobytes()
                    found.append(
                        (c.match_id, c.score, c.accepted, c.rejection, pose, np.asarray(c.matches).tobytes())
                    )
            rec.add_description(k, d)
        return descriptions, found

    one, two = run("1"), run("2")
    assert one[0] == two[0]
    assert len(one[1]) > 10 and any(f[2] for f in one[1])  # revisits found and verified
    assert one[1] == two[1]
