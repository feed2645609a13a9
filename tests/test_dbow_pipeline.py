"""ORB-DBoW / SURF-DBoW pipelines, vocabulary training from a config and the train-vocab command."""

import json
from dataclasses import replace

import numpy as np
import pytest
import yaml

from placerec.errors import ArtifactError, ConfigError
from placerec.pipelines.dbow import VisualDBoW
from placerec.recognizer import make_pipeline
from placerec.retrieval.dbow.io import load_vocabulary
from placerec.sim import SimulatedSequence


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A small ORB vocabulary trained with the CLI on 4 images of a training world (not the test seed)."""
    from typer.testing import CliRunner

    from placerec.cli import app

    folder = tmp_path_factory.mktemp("vocab")
    cfg = {
        "features": "orb",
        "k": 6,
        "L": 3,
        "n_images": 4,
        "simulator": {"worlds": ["town"], "sensors": ["os1-64"], "seeds": [105]},
        "output": str(folder / "orb_small.dbow"),
    }
    (folder / "cfg.yaml").write_text(yaml.safe_dump(cfg))
    result = CliRunner().invoke(app, ["train-vocab", "--config", str(folder / "cfg.yaml")])
    assert result.exit_code == 0, result.output
    return folder / "orb_small.dbow"


@pytest.fixture(scope="module")
def scans():
    seq = SimulatedSequence(world="town", sensor="os1-64", n_scans=2, seed=5, clutter=False)
    return seq[0], seq[1]


def test_training_writes_vocabulary_and_metadata(trained):
    voc = load_vocabulary(trained)
    assert voc.binary and (voc.k, voc.L) == (6, 3) and voc.n_words > 50
    meta = json.loads(trained.with_suffix(".json").read_text())
    assert (
        meta["n_images"] == 4 and meta["n_descriptors"] > 100 and meta["sequences"] == ["town/os1-64/seed105"]
    )
    assert meta["simulator"]["seeds"] == [105] and meta["placerec_version"] and meta["train_seconds"] >= 0


def _rotated(scan, yaw):
    c, s = np.cos(-yaw), np.sin(-yaw)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], np.float32)
    return replace(scan, xyz=scan.xyz @ R.T, shape=None)


@pytest.mark.parametrize("yaw_deg", [-100.0, 35.0])
def test_dbow_finds_the_place_and_its_yaw(trained, scans, yaw_deg):
    rec = make_pipeline("orb-dbow", {"vocabulary": str(trained)})
    flat0, flat1 = replace(scans[0], shape=None), replace(scans[1], shape=None)
    rec.add(0, flat0)
    rec.add(1, _rotated(flat1, 2.0))
    (cand, *_) = rec.query(_rotated(flat0, np.radians(yaw_deg)), k=2)
    assert cand.match_id == 0 and cand.score > 0.3 and cand.extra["bow_score"] > 0.2
    est = np.degrees(np.arctan2(cand.relative_pose[1, 0], cand.relative_pose[0, 0]))
    assert abs((est - yaw_deg + 180) % 360 - 180) < 2.0


def test_bow_score_and_exclusion(trained, scans):
    rec = make_pipeline(
        "orb-dbow", {"vocabulary": str(trained), "verify": {"enabled": False}, "check": "none"}
    )
    for i, s in enumerate(scans):
        rec.add(10 + i, s)
    (c,) = rec.query(scans[1], k=1)
    assert c.match_id == 11 and c.score == pytest.approx(1.0) and c.relative_pose is None
    assert [x.match_id for x in rec.query(scans[1], k=2, max_id=10)] == [10]
    looped = make_pipeline(
        "orb-dbow",
        {
            "vocabulary": str(trained),
            "verify": {"enabled": False},
            "check": "none",
            "loop": {"use_nss": True},
        },
    )
    looped.add(0, scans[0])
    looped.add(1, scans[1])
    (c,) = looped.query(scans[0], k=1, query_id=2)
    assert c.match_id == 0 and c.extra["status"] == "ok"


def test_frontend_is_shared_with_hbst(trained):
    dbow = make_pipeline("orb-dbow", {"vocabulary": str(trained)})
    assert dbow.frontend_key == make_pipeline("orb-hbst").frontend_key
    assert (
        dbow.frontend_key
        != make_pipeline(
            "orb-dbow", {"vocabulary": str(trained), "feature_params": {"nfeatures": 100}}
        ).frontend_key
    )


def test_save_load_gives_identical_answers(tmp_path, trained, scans):
    rec = make_pipeline("orb-dbow", {"vocabulary": str(trained)})
    rec.add(0, scans[0])
    rec.add(1, scans[1])
    before = rec.query(scans[1], k=2)
    rec.save(tmp_path / "db.npz")
    fresh = make_pipeline("orb-dbow", {"vocabulary": str(trained)})
    fresh.load(tmp_path / "db.npz")
    after = fresh.query(scans[1], k=2)
    assert [(c.match_id, c.score, c.inliers) for c in before] == [
        (c.match_id, c.score, c.inliers) for c in after
    ]
    with pytest.raises(ArtifactError, match="other parameters"):
        make_pipeline("orb-dbow", {"vocabulary": str(trained), "n_check": 3}).load(tmp_path / "db.npz")


def test_missing_or_mismatched_vocabulary(tmp_path, trained):
    with pytest.raises(ArtifactError, match="train-vocab"):
        VisualDBoW(vocabulary=str(tmp_path / "none.dbow"))
    with pytest.raises(ArtifactError, match="does not fit"):
        make_pipeline("surf-dbow", {"vocabulary": str(trained)})
    with pytest.raises(ConfigError, match=r"params\.vocab: unknown key; allowed keys there: .*vocabulary"):
        make_pipeline("orb-dbow", {"vocab": "x"})


def test_descriptor_cache_key_follows_settings_and_data(tmp_path):
    from placerec.artifacts.vocabulary import VocabTrainingConfig, descriptor_cache_key

    folder = tmp_path / "velodyne"
    folder.mkdir()
    (folder / "000000.bin").write_bytes(np.zeros(8, np.float32).tobytes())
    cfg = VocabTrainingConfig(simulator=None, datasets=[{"source": "path", "path": str(folder)}])
    key = descriptor_cache_key(cfg)
    assert descriptor_cache_key(cfg) == key
    assert descriptor_cache_key(cfg.model_copy(update={"k": 7})) == key  # vocabulary shape: same descriptors
    assert descriptor_cache_key(cfg.model_copy(update={"n_images": 10})) != key
    (folder / "000000.bin").write_bytes(np.ones(12, np.float32).tobytes())  # a scan replaced
    assert descriptor_cache_key(cfg) != key
    assert descriptor_cache_key(VocabTrainingConfig()) != key  # the simulator's sources are part of its key


def test_a_queried_description_is_inserted_with_the_queries_bow_vector(trained, scans, monkeypatch):
    """A loop detector queries a scan, then inserts it: the insert takes the query's BoW vector and direct-index
    nodes instead of transforming the descriptors again; any other description is transformed, and the database
    is the one of transforming each."""
    rec = make_pipeline("orb-dbow", {"vocabulary": str(trained), "verify": {"enabled": False}})
    fresh = make_pipeline("orb-dbow", {"vocabulary": str(trained), "verify": {"enabled": False}})
    a, b = (rec.describe(s) for s in scans)
    calls = []
    transform = rec.vocabulary.transform
    monkeypatch.setattr(rec.vocabulary, "transform", lambda *args: calls.append(1) or transform(*args))

    rec.add_description(0, a)  # never queried: transformed
    assert len(calls) == 1
    rec.query_description(b, k=1)
    rec.add_description(1, b)  # the description just queried: its vector reused
    assert len(calls) == 2
    rec.query_description(b, k=1)
    rec.add_description(2, dict(b))  # another description object with the same arrays: transformed
    assert len(calls) == 4

    for i, d in enumerate((a, b, b)):
        fresh.add_description(i, d)
    for i in range(3):
        mine, theirs = rec.db.bow(i), fresh.db.bow(i)
        np.testing.assert_array_equal(mine.words, theirs.words)
        np.testing.assert_array_equal(mine.values, theirs.values)
    assert [q.match_id for q in rec.query_description(a, k=3)] == [
        q.match_id for q in fresh.query_description(a, k=3)
    ]
