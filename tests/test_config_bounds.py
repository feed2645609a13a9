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
