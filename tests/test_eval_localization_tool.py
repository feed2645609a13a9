"""tools/eval_localization.py: the config it runs (world, pipelines subset) and the vote model's draw check."""

from pathlib import Path

import pytest
from tool_modules import load_tool

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def tool():
    return load_tool("eval_localization", "eval_localization_tool")


def test_another_world_reads_its_own_places_and_towns_vote_model(tool):
    data = tool.config_data(str(ROOT / "configs" / "localize.yaml"), "campus", ["ishot-prob", "scan-context"])
    assert data["dataset"]["simulator"]["world"] == "campus"
    assert [s.get("label", s["name"]) for s in data["pipelines"]] == ["ishot-prob", "scan-context"]
    params = data["pipelines"][0]["params"]
    assert params["places"]["database"] == ".cache/localize/places_campus_vlp16_sq8.npz"
    assert params["vote_model"] == ".cache/localize/votes_town_vlp16.npz"
    town = tool.config_data(str(ROOT / "configs" / "localize.yaml"), "town", None)
    assert town["pipelines"][0]["params"]["places"]["database"] == ".cache/localize/places_town_vlp16_sq8.npz"
    assert len(town["pipelines"]) > 2


def test_an_unknown_pipeline_label_is_refused(tool):
    with pytest.raises(SystemExit, match="ishot-porb"):
        tool.config_data(str(ROOT / "configs" / "localize.yaml"), "town", ["ishot-prob", "ishot-porb"])


def test_the_vote_models_training_draws_are_kept_apart_from_the_evaluated_draw(tool):
    names = [f"sim-town-vlp16-default-s0-query-{c}-draw1" for c in ("gator", "pole", "occlusion")]
    assert tool.training_draws(names) == {1}
    assert tool.training_draws(["sim-town-vlp16-default-s0-query-pole"]) == {0}
    test = tool.vote_model_draw_check(names, 2, "town")
    assert test == {"vote_model_draws": [1], "vote_model_trained_on_evaluated_draw": False}
    assert tool.vote_model_draw_check(names, 1, "town")["vote_model_trained_on_evaluated_draw"] is True
    assert tool.vote_model_draw_check(names, 1, "campus")["vote_model_trained_on_evaluated_draw"] is False
    on_test = [n.replace("draw1", "draw2") for n in names]
    with pytest.raises(SystemExit, match="fitted on query draw 2"):
        tool.vote_model_draw_check(on_test, 2, "town")
    with pytest.raises(SystemExit, match="not a simulated localisation draw"):
        tool.training_draws(["kitti-00"])
