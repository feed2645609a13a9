"""Artifact builders (`placerec.artifacts`): the registry, the sources they read, the checks the CLI and the Python
API share, and the CLI's shared helpers (one-line errors, "a SEQUENCE path or --sim-world")."""

from __future__ import annotations

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from placerec import cli_support
from placerec.artifacts import BUILDERS, build, builder, config_type
from placerec.artifacts.calibration import CalibrationBuild, build_calibration
from placerec.artifacts.places import PlacesBuild, build_places_db
from placerec.artifacts.sources import SequenceSource, SimWorld, require_one_source
from placerec.artifacts.votes import VoteModelBuild, build_vote_model
from placerec.errors import ArtifactError, ConfigError, ScanDataError
from placerec.params import Params
from placerec.three_d.places import PlacesDatabase, PlacesParams
from placerec.three_d.vote_model import VoteModel


def test_every_registered_builder_takes_its_settings_class_and_returns_a_path():
    assert set(BUILDERS) >= {"calibration", "places-db", "vote-model", "vocabulary"}
    for name in BUILDERS:
        if name == "superpoint-weights":
            pytest.importorskip("torch", reason="SuperPoint training needs torch")
        assert issubclass(config_type(name), Params)
    assert builder("places-db") is build_places_db and config_type("places-db") is PlacesBuild
    assert builder("calibration") is build_calibration and config_type("calibration") is CalibrationBuild
    assert builder("vote-model") is build_vote_model and config_type("vote-model") is VoteModelBuild
    with pytest.raises(ConfigError, match="unknown artifact 'nope'.*places-db"):
        builder("nope")


def test_build_resolves_a_mapping_strictly(tmp_path):
    with pytest.raises(ConfigError, match="places-db settings: params.window: unknown key"):
        build("places-db", {"source": {"sim": {"world": "town"}}, "out": str(tmp_path / "p.npz"),
                            "params": {"window": 0}})  # fmt: skip
    assert not (tmp_path / "p.npz").exists()


@pytest.mark.parametrize("given, sim", [(False, None), (True, SimWorld(world="town"))])
def test_a_source_needs_exactly_one_of_a_path_and_a_simulated_world(tmp_path, given, sim):
    with pytest.raises(ConfigError, match=r"give either a SEQUENCE path or --sim-world \(not both\)"):
        require_one_source(given, sim)
    source = SequenceSource(path=tmp_path if given else None, sim=sim)
    with pytest.raises(ConfigError, match="give either a SEQUENCE path"):
        source.route()
    with pytest.raises(ConfigError, match="give either a SEQUENCE path"):
        build_places_db(PlacesBuild(source=source, out=tmp_path / "p.npz"))
    assert not (tmp_path / "p.npz").exists()


def test_source_paths_accept_strings_and_paths(tmp_path):
    assert SequenceSource(path=str(tmp_path)).path == tmp_path == SequenceSource(path=tmp_path).path
    with pytest.raises(ConfigError, match="path"):
        SequenceSource(path=3)


def _tiny_places(path, n_scans: int = 3) -> PlacesDatabase:
    """Two described places of a straight 3-scan map (enough for the vote model's map check)."""
    poses = np.tile(np.eye(4), (n_scans, 1, 1))
    poses[:, 0, 3] = np.arange(n_scans) * 5.0
    rng = np.random.default_rng(0)
    db = PlacesDatabase(
        ids=np.array([0, 2]),
        poses=poses[[0, 2]],
        sources=[np.array([0, 1]), np.array([1, 2])],
        kp_offsets=np.array([0, 4, 8]),
        keypoints=rng.normal(size=(8, 3)).astype(np.float32),
        descriptors=rng.normal(size=(8, 352)).astype(np.float32),
        params=PlacesParams(descriptor_store="float32", store_clouds=False),
        scan_poses=poses,
        sequence="tiny",
    )
    db.save(path)
    return db


def test_the_vote_model_api_refuses_a_simulated_map_other_than_the_places_map(tmp_path):
    """The map check ``placerec fit-votes`` reports is the API's: `build_vote_model` raises `ConfigError`."""
    places = tmp_path / "places.npz"
    _tiny_places(places)
    config = VoteModelBuild(places=places, out=tmp_path / "votes.npz", sim={"world": "town", "scans": 4},
                            n_training=1)  # fmt: skip
    with pytest.raises(ConfigError, match=r"places.npz was built from another map \(tiny, 3 scans\) than the "
                                          r"simulated sim-town-vlp16-default-s0 \(4 scans\)"):  # fmt: skip
        build_vote_model(config)
    with pytest.raises(ConfigError, match="another map"):
        build("vote-model", {"places": str(places), "out": str(tmp_path / "votes.npz"),
                             "sim": {"world": "town", "scans": 4}, "n_training": 1})  # fmt: skip
    assert not (tmp_path / "votes.npz").exists()


def test_the_vote_model_needs_training_paths_or_a_simulated_world_and_a_places_database(tmp_path):
    places = tmp_path / "places.npz"
    _tiny_places(places)
    for extra in ({}, {"training": [tmp_path], "sim": SimWorld(world="town")}):
        with pytest.raises(ConfigError, match=r"give either TRAINING sequence paths or --sim-world"):
            build_vote_model(VoteModelBuild(places=places, out=tmp_path / "v.npz", **extra))
    with pytest.raises(ArtifactError, match="missing.npz: no such artifact file"):
        build_vote_model(VoteModelBuild(places=tmp_path / "missing.npz", out=tmp_path / "v.npz"))


def test_places_and_vote_model_built_through_the_registry(tmp_path):
    sim = {"world": "town", "scans": 8}
    places = build("places-db", {"source": {"sim": sim}, "out": str(tmp_path / "places.npz"),
                                 "params": {"window_m": 0}})  # fmt: skip
    db = PlacesDatabase.load(places)
    assert places == tmp_path / "places.npz" and len(db) > 1 and db.params.window_m == 0
    seen = []
    votes = build("vote-model", {"places": str(places), "out": str(tmp_path / "votes.npz"), "sim": sim,
                                 "n_training": 1, "params": {"min_votes": 5, "tau_edges": [0, 1]}},
                  progress=lambda done, total: seen.append((done, total)))  # fmt: skip
    model = VoteModel.load(votes)
    assert model.provenance["places_file"] == str(places) and model.n_ranges == 1
    assert seen and seen[-1][0] == seen[-1][1] == model.provenance["n_training_scans"]


# ----------------------------------------------------------------------------- the CLI's shared helpers


def _app_with(command) -> typer.Typer:
    app = typer.Typer()
    app.command("go")(lambda: None)  # two commands, so "boom" is a sub-command name
    app.command("boom")(cli_support.reports_errors(command))
    return app


def test_a_placerec_error_in_a_command_is_one_line_on_stderr_with_status_2():
    def boom() -> None:
        raise ScanDataError("scan.bin: first line\n  second line")

    result = CliRunner().invoke(_app_with(boom), ["boom"])
    assert result.exit_code == 2 and result.output.strip() == "error: scan.bin: first line; second line"


def test_other_exceptions_are_not_caught_by_the_command_wrapper():
    def boom() -> None:
        raise RuntimeError("a bug")

    result = CliRunner().invoke(_app_with(boom), ["boom"])
    assert result.exit_code == 1 and isinstance(result.exception, RuntimeError)


def test_the_wrapper_keeps_the_commands_options_and_help():
    def boom(count: int = typer.Option(3, help="How many.")) -> None:
        """Explode COUNT times."""
        typer.echo(f"count {count}")

    app = _app_with(boom)
    assert CliRunner().invoke(app, ["boom", "--count", "4"]).output == "count 4\n"
    help_text = CliRunner().invoke(app, ["boom", "--help"]).output
    assert "Explode COUNT times." in help_text and "How many." in help_text


def test_cli_sources_need_exactly_one_of_a_sequence_and_a_simulated_world(tmp_path):
    sim = cli_support.sim_world("town", "vlp16", 5, 2)
    assert sim == SimWorld(world="town", sensor="vlp16", scans=5, seed=2)
    assert cli_support.sim_world(None, "vlp16", 5, 2) is None
    assert cli_support.sequence_source(None, None, None, sim).sim == sim
    assert cli_support.sequence_source(tmp_path, "kitti", None, None).path == tmp_path
    for sequence, world in ((None, None), (tmp_path, sim)):
        with pytest.raises(ConfigError, match=r"give either a SEQUENCE path or --sim-world \(not both\)"):
            cli_support.sequence_source(sequence, None, None, world)


def test_cli_overrides_are_checked_by_the_settings_class():
    params = cli_support.with_overrides(PlacesParams, {"window_m": 3.0}, ["spacing_m=2"], "places parameters")
    assert (params.window_m, params.spacing_m) == (3.0, 2.0)
    with pytest.raises(ConfigError, match="places parameters: nope: unknown key"):
        cli_support.with_overrides(PlacesParams, {}, ["nope=1"], "places parameters")
