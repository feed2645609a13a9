"""Description in worker processes (`placerec.experiment.parallel`): local processes and a 2-worker Dask
LocalCluster give exactly the candidates of a serial run."""

from __future__ import annotations

import numpy as np
import pytest

from placerec.config import load_config
from placerec.errors import ConfigError
from placerec.experiment.runner import run_loop

BASE = [
    "dataset.simulator.world=town",
    "dataset.simulator.sensor=vlp16",
    "dataset.simulator.n_scans=36",
    "dataset.simulator.spacing=3.0",
    "pipelines=[{name: scan-context}, {name: orb-hbst}]",
    "evaluation.exclusion.frames=10",
    "evaluation.top_n=3",
    "output.progress=false",
]


def _candidates(records) -> list:
    return [
        [[(c.match_id, round(float(c.score), 12)) for c in cands] for cands in r.candidates] for r in records
    ]


@pytest.fixture(scope="module")
def serial(warm_kernels):
    cfg = load_config(None, [*BASE, "output.cache_dir=null"])
    return _candidates(run_loop(cfg)[1])


@pytest.mark.parametrize(
    "execution",
    [["execution.executor=dask", "execution.workers=2"], ["execution.workers=2"]],
    ids=["dask", "local"],
)
def test_parallel_description_gives_the_serial_results(serial, tmp_path, execution):
    pytest.importorskip("distributed", reason="the Dask executor needs dask and distributed (extra 'dask')")
    cfg = load_config(None, [*BASE, f"output.cache_dir={tmp_path}", "execution.chunk=6", *execution])
    seq, records = run_loop(cfg)
    assert _candidates(records) == serial
    assert sum(len(c) > 0 for c in serial[0]) > 10  # the comparison covers real answers
    # every description was made by a worker: the cache holds one entry per scan and front end
    entries = list(tmp_path.rglob("*.npz"))
    assert len(entries) == 2 * len(seq)
    assert all(np.isfinite(r.timing_ms["describe"]).all() for r in records)


def test_a_scheduler_needs_the_dask_executor():
    with pytest.raises(ConfigError, match="execution.scheduler needs execution.executor: dask"):
        load_config(None, ["execution.scheduler=tcp://127.0.0.1:8786"])


def test_localize_map_described_in_worker_processes(real_data, tmp_path):
    """Localize mode: the map (a KITTI layout of real frames) is described by 2 local processes into the cache;
    the candidates are those of a serial run."""
    import shutil

    from placerec.experiment.runner import run_localize

    seq = tmp_path / "seq"
    (seq / "velodyne").mkdir(parents=True)
    frames = sorted((real_data / "kitti00_frames").glob("*.bin"))
    for k, f in enumerate(frames):
        shutil.copy(f, seq / "velodyne" / f"{k:06d}.bin")
    lines = (real_data / "kitti00_frames" / "poses_00.txt").read_text().splitlines()
    (seq / "poses.txt").write_text("\n".join(lines[int(f.stem)] for f in frames) + "\n")
    base = [
        "evaluation.mode=localize",
        f"evaluation.localize.map={{source: path, path: '{seq}'}}",
        f"evaluation.localize.queries={{source: path, path: '{seq}'}}",
        "pipelines=[{name: scan-context, params: {verify: {enabled: false}}}]",
        "evaluation.top_n=2",
        "output.progress=false",
    ]
    serial = run_localize(load_config(None, [*base, "output.cache_dir=null"]))[2]
    parallel = run_localize(
        load_config(None, [*base, f"output.cache_dir={tmp_path / 'cache'}", "execution.workers=2"])
    )[2]
    assert _candidates(parallel) == _candidates(serial)
    assert [c[0][0] for c in _candidates(serial)[0]] == [0, 1, 2, 3]  # every real frame finds itself
    assert len(list((tmp_path / "cache").rglob("*.npz"))) == len(frames)


@pytest.mark.parametrize(
    ("address", "why"),
    [
        ("'tcp://::::'", "is not a Dask scheduler address"),
        ("tcp://host", "is not a Dask scheduler address"),
        ("tcp://10.0.0.5:99999", "port 99999 is not in 1-65535"),
        ("tcp://[::zz]:8786", r"\[::zz\] is not an IPv6 address"),
        ("http://10.0.0.5:8786", "is not a Dask scheduler address"),
    ],
)
def test_a_malformed_scheduler_address_is_a_config_error(address, why):
    """A malformed address reached `distributed`, which raised a bare ValueError."""
    with pytest.raises(ConfigError, match=rf"execution\.scheduler: .*{why}"):
        load_config(None, ["execution.executor=dask", f"execution.scheduler={address}"])
    for ok in (
        "tcp://10.0.0.5:8786",
        "tcp://[::1]:8786",
        "scheduler.local:8786",
        "tls://node-1.example:8786",
    ):
        assert load_config(None, ["execution.executor=dask", f"execution.scheduler={ok}"]).execution.scheduler


def test_a_scheduler_that_cannot_be_reached_is_a_config_error(monkeypatch):
    """Whatever `distributed` raises for an address it cannot use is a ConfigError naming the address."""
    pytest.importorskip("distributed")
    import distributed

    from placerec.experiment.parallel import task_pool

    def refuse(address, **kwargs):
        raise ValueError(f"invalid address {address!r}")

    monkeypatch.setattr(distributed, "Client", refuse)
    cfg = load_config(None, ["execution.executor=dask", "execution.scheduler=tcp://10.0.0.5:8786"])
    with pytest.raises(
        ConfigError, match=r"execution\.scheduler: cannot reach the Dask scheduler 'tcp://10\.0\.0\.5:8786'"
    ):
        with task_pool(cfg.execution):
            pass


def test_workers_are_capped_on_the_command_line_too():
    from typer.testing import CliRunner

    from placerec.artifacts.vocabulary import load_training_config
    from placerec.cli import app

    result = CliRunner().invoke(app, ["run", "configs/demo.yaml", "--workers", "1000000000000"])
    assert result.exit_code == 2 and "execution.workers" in result.output and result.exception is not None
    with pytest.raises(ConfigError, match="workers"):
        load_training_config(None, workers=10**12)
