"""DBoW database (inverse index scores, planted duplicate, exclusion, persistence) and DLoopDetector options."""

import numpy as np
import pytest

from placerec.errors import ArtifactError, ScanDataError
from placerec.retrieval.dbow.database import BowDatabase, candidate_pairs
from placerec.retrieval.dbow.loop_detector import LoopDetectorParams, normalised_results
from placerec.retrieval.dbow.vocabulary import BowVector, l1_score, train_vocabulary


@pytest.fixture(scope="module")
def corpus():
    rng = np.random.default_rng(7)
    pool = rng.integers(0, 256, (3000, 32), dtype=np.uint8)  # "landmarks" shared between images
    images = [pool[rng.choice(pool.shape[0], 150, replace=False)] for _ in range(120)]
    voc = train_vocabulary(images[:60], k=8, L=3, seed=0)
    return voc, images


def test_query_returns_the_planted_duplicate(corpus):
    voc, images = corpus
    db = BowDatabase(voc)
    for i, img in enumerate(images):
        db.add_descriptors(img, entry_id=i)
    rng = np.random.default_rng(1)
    query = images[77][rng.permutation(150)[:120]]  # a partial, reordered copy of image 77
    res = db.query(voc.transform(query), max_results=5)
    assert res.ids[0] == 77 and res.scores[0] > 2 * res.scores[1]
    assert np.all(np.diff(res.scores) <= 0)
    excluded = db.query(voc.transform(query), max_results=5, max_id=70)
    assert 77 not in excluded.ids and np.all(excluded.ids <= 70)


def test_query_scores_equal_the_l1_formula_through_buffer_merges(corpus, monkeypatch):
    import placerec.retrieval.dbow.database as dbmod

    monkeypatch.setattr(dbmod, "_MIN_BUFFER", 500)  # force several CSR merges with entries still buffered
    voc, images = corpus
    db = BowDatabase(voc)
    bows = [voc.transform(img) for img in images]
    for i, b in enumerate(bows):
        db.add(b, entry_id=1000 + i)
    assert db._entry.size > 0 and db._buf_n > 0
    q = bows[5]
    res = db.query(q, max_results=len(bows))
    expected = {1000 + i: l1_score(q, b) for i, b in enumerate(bows) if l1_score(q, b) > 0}
    assert dict(zip(res.ids.tolist(), res.scores.tolist(), strict=True)) == pytest.approx(expected)


def test_hand_made_vectors_and_duplicates():
    voc = train_vocabulary([np.arange(4 * 32, dtype=np.uint8).reshape(4, 32)], k=4, L=1, weighting="tf")
    db = BowDatabase(voc)
    db.add(BowVector(np.array([0, 1], np.int32), np.array([0.5, 0.5])), entry_id=3)
    db.add(BowVector(np.array([1, 2], np.int32), np.array([0.25, 0.75])), entry_id=4)
    res = db.query(BowVector(np.array([1, 2], np.int32), np.array([0.5, 0.5])), max_results=3)
    assert res.ids.tolist() == [4, 3] and res.scores == pytest.approx([0.75, 0.5])
    with pytest.raises(ScanDataError, match="already"):
        db.add(BowVector(np.array([0], np.int32), np.array([1.0])), entry_id=3)
    assert len(db.query(BowVector(np.array([3], np.int32), np.array([1.0])))) == 0


def test_direct_index_pairs_and_persistence(tmp_path, corpus):
    voc, images = corpus
    ia, jb = candidate_pairs(np.array([5, -1, 7, 5]), np.array([7, 5, 5, -1]))
    assert sorted(zip(ia.tolist(), jb.tolist(), strict=True)) == [(0, 1), (0, 2), (2, 0), (3, 1), (3, 2)]
    db = BowDatabase(voc, levels_up=1)
    for i, img in enumerate(images[:10]):
        db.add_descriptors(img, entry_id=i)
    nodes = db.feature_nodes(4)
    assert nodes.shape == (150,) and np.all(voc.depth[nodes[nodes >= 0]] == voc.L - 1)
    path = tmp_path / "db.npz"
    db.save(path)
    again = BowDatabase.load(path, voc)
    q = voc.transform(images[4])
    a, b = db.query(q, 5), again.query(q, 5)
    assert np.array_equal(a.ids, b.ids) and np.allclose(a.scores, b.scores)
    assert np.array_equal(again.feature_nodes(4), nodes)
    other = train_vocabulary(images[60:80], k=8, L=2, seed=0)
    with pytest.raises(ArtifactError, match="vocabulary"):
        BowDatabase.load(path, other)


def test_normalised_score_and_alpha():
    p = LoopDetectorParams(use_nss=True, alpha=0.3)
    ids, scores = np.array([50, 51, 200]), np.array([0.2, 0.1, 0.05])
    assert normalised_results(p, ids, scores, eta=0.001).status == "low_nss_factor"
    assert normalised_results(p, ids, scores, eta=None).status == "low_nss_factor"
    assert normalised_results(p, ids, scores, eta=1.0).status == "low_scores"
    # normalised by eta = 0.25: 0.8, 0.4, 0.2 -> 200 is cut by alpha
    r = normalised_results(p, ids, scores, eta=0.25)
    assert r.status == "ok" and r.ids.tolist() == [50, 51] and r.scores.tolist() == pytest.approx([0.8, 0.4])
    assert normalised_results(p, ids[:0], scores[:0], eta=0.25).status == "no_db_results"
    r = normalised_results(LoopDetectorParams(), ids, scores)
    assert r.status == "ok" and r.ids.tolist() == ids.tolist() and not LoopDetectorParams().enabled
