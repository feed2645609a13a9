"""No float setting takes NaN or infinity, and the counts that set how much work a run does are capped (#27)."""

from __future__ import annotations

import pytest

from placerec.config import load_config
from placerec.errors import ConfigError
from placerec.slam_app.config import load_slam_config


@pytest.mark.parametrize(
    ("override", "key"),
    [
        ("evaluation.localize.success_distance=.inf", "evaluation.localize.success_distance"),
        ("evaluation.gt_distance=.nan", "evaluation.gt_distance"),
        ("preprocess.min_range=-.inf", "preprocess.min_range"),
        ("evaluation.localize.n_queries=1000000000", "evaluation.localize.n_queries"),
        ("execution.workers=1000000000000", "execution.workers"),
    ],
)
def test_experiment_settings_refuse_non_finite_values_and_huge_counts(override, key):
    with pytest.raises(ConfigError, match=rf"{key}: "):
        load_config("configs/localize.yaml", [override])


@pytest.mark.parametrize(
    ("override", "key"),
    [
        ("loops.threshold=.nan", "loops.threshold"),
        ("graph.loop_sigma_translation=.inf", "graph.loop_sigma_translation"),
        ("odometry.drift.translation=.nan", "odometry.drift.translation"),
        ("robustness.false_loops=1000000000", "robustness.false_loops"),
    ],
)
def test_slam_settings_refuse_non_finite_values_and_huge_counts(override, key):
    with pytest.raises(ConfigError, match=rf"{key}: "):
        load_slam_config("configs/slam_demo.yaml", [override])


def test_pipeline_parameters_refuse_non_finite_values():
    from placerec.recognizer import make_pipeline

    with pytest.raises(ConfigError, match=r"search\.tau_max: Input should be a finite number"):
        make_pipeline("ishot-votes", {"search": {"tau_max": float("nan")}})


@pytest.mark.parametrize(
    ("override", "key"),
    [
        ("preprocess.min_z=3.0", "min_z"),
        ("preprocess.max_range=0.2", "min_range"),
    ],  # max_z 2.0 / min_range 0.5
)
def test_a_preprocess_window_that_drops_every_point_is_refused(override, key):
    with pytest.raises(ConfigError, match=rf"preprocess: .*{key} .* every point would be dropped"):
        load_config(None, [override, "preprocess.max_z=2.0"])


def test_a_cache_dir_that_is_a_file_is_a_config_error(tmp_path):
    from placerec.experiment.cache import DescriptionCache

    (tmp_path / "cache").write_text("not a folder")
    with pytest.raises(ConfigError, match="output.cache_dir .* is a file"):
        DescriptionCache(tmp_path / "cache", "key")


def test_unsorted_tau_edges_are_refused_naming_the_key():
    """Unsorted inline ``tau_edges`` were reported as a count mismatch of sigma and lambda values."""
    from placerec.params import resolve
    from placerec.recognizer import make_pipeline
    from placerec.three_d.vote_model import VoteModel, VoteModelParams

    edges = [0.0, 0.7, 0.9, 0.8, 0.85, 0.95, 1.0]
    with pytest.raises(
        ConfigError, match=r"model\.tau_edges: tau_edges must increase strictly: edge 3 is 0.8"
    ):
        make_pipeline("ishot-prob", {"model": {"tau_edges": edges}})
    with pytest.raises(ConfigError, match=r"params\.model: 3 tau_edges make 2 ranges: sigma and lam need 2"):
        make_pipeline("ishot-prob", {"model": {"tau_edges": [0.0, 0.8, 1.0]}})
    with pytest.raises(ConfigError, match=r"fit: tau_edges: tau_edges must increase strictly: edge 2 is 0.5"):
        resolve(VoteModelParams, {"tau_edges": [0.0, 0.9, 0.5]}, where="fit")
    with pytest.raises(
        ConfigError, match="vote model: tau_edges must increase strictly: edge 2 is 0.5 after 0.9"
    ):
        VoteModel([0.0, 0.9, 0.5], [1.0, 1.0], [0.5, 0.5], 10.0)
