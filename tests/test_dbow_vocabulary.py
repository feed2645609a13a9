"""DBoW vocabulary: L1 score and IDF by hand, transform against a per-descriptor descent, cluster recovery."""

import numpy as np
import pytest

from placerec.errors import ConfigError, ScanDataError
from placerec.retrieval.dbow.vocabulary import BowVector, Vocabulary, l1_score, train_vocabulary


def _bow(d: dict[int, float]) -> BowVector:
    words = np.array(sorted(d), np.int32)
    return BowVector(words, np.array([d[w] for w in sorted(d)], np.float64))


def test_l1_score_matches_hand_computed_vectors():
    v = _bow({1: 0.5, 2: 0.5})
    w = _bow({2: 0.25, 3: 0.75})
    # |v - w|_1 = 0.5 + 0.25 + 0.75 = 1.5  ->  s = 1 - 0.75
    assert l1_score(v, w) == pytest.approx(0.25)
    assert l1_score(v, v) == pytest.approx(1.0)
    assert l1_score(v, _bow({7: 1.0})) == 0.0
    a = _bow({0: 0.1, 4: 0.2, 9: 0.3, 11: 0.4})
    b = _bow({4: 0.5, 9: 0.1, 12: 0.4})
    dense_a, dense_b = np.zeros(13), np.zeros(13)
    dense_a[a.words], dense_b[b.words] = a.values, b.values
    assert l1_score(a, b) == pytest.approx(1 - 0.5 * np.abs(dense_a - dense_b).sum())


def _toy_vocabulary(weighting: str = "tf-idf") -> tuple[Vocabulary, list[np.ndarray]]:
    """Three far-apart 'words' (bytes 0x00, 0x0F, 0xF0 repeated) and a toy corpus of four images."""
    a, b, c = (np.full((1, 32), v, np.uint8) for v in (0x00, 0x0F, 0xF0))
    images = [
        np.vstack([a, a, b]),  # words A, B
        np.vstack([a]),  # A
        np.vstack([a, c, c]),  # A, C
        np.vstack([a, b]),  # A, B
    ]
    return train_vocabulary(images, k=3, L=1, weighting=weighting), images


def test_idf_on_a_toy_corpus():
    voc, images = _toy_vocabulary()
    assert voc.n_words == 3
    wa, wb, wc = voc.words_of(np.vstack([images[1], images[0][2:], images[2][1:2]]))
    idf = voc.word_weights
    assert idf[wa] == pytest.approx(0.0)  # in every image: ln(4/4), a stopped word
    assert idf[wb] == pytest.approx(np.log(4 / 2))
    assert idf[wc] == pytest.approx(np.log(4 / 1))
    # TF-IDF vector of image 2 (A, C, C): A is stopped; C alone -> 1 after L1 normalisation
    bow = voc.transform(images[2])
    assert bow.words.tolist() == [wc] and bow.values.tolist() == [1.0]
    # image with B once and C twice: values 1 ln2 and 2 ln4, normalised
    bow = voc.transform(np.vstack([images[0][2:], images[2][1:]]))
    raw = {wb: np.log(2), wc: 2 * np.log(4)}
    total = sum(raw.values())
    assert dict(zip(bow.words.tolist(), bow.values.tolist(), strict=True)) == pytest.approx(
        {w: x / total for w, x in raw.items()}
    )


def test_binary_weighting_counts_a_word_once():
    voc, images = _toy_vocabulary("binary")
    assert np.all(voc.word_weights == 1.0)
    bow = voc.transform(images[2])
    assert bow.values.tolist() == [0.5, 0.5]


def _reference_words(voc: Vocabulary, desc: np.ndarray) -> list[int]:
    """Per-descriptor descent written plainly (first child wins ties)."""
    out = []
    for d in desc:
        node = 0
        while (voc.children[node] >= 0).any():
            kids = voc.children[node][voc.children[node] >= 0]
            if voc.binary:
                dist = [np.unpackbits(voc.centres[c] ^ d).sum() for c in kids]
            else:
                dist = [np.sum((voc.centres[c].astype(np.float64) - d) ** 2) for c in kids]
            node = int(kids[int(np.argmin(dist))])
        out.append(int(voc.word_of_node[node]))
    return out


@pytest.mark.parametrize("kind", ["binary", "float"])
def test_vectorised_transform_matches_plain_descent(kind):
    rng = np.random.default_rng(3)
    if kind == "binary":
        parts = [rng.integers(0, 256, (60, 32), dtype=np.uint8) for _ in range(20)]
    else:
        parts = [rng.standard_normal((60, 16)).astype(np.float32) for _ in range(20)]
    voc = train_vocabulary(parts, k=4, L=3, seed=1)
    query = parts[0][:40] if kind == "binary" else rng.standard_normal((40, 16)).astype(np.float32)
    assert voc.words_of(query).tolist() == _reference_words(voc, query)
    # direct index: node at depth L - levels_up is an ancestor of each descriptor's leaf
    _, nodes = voc.transform(query, levels_up=1)
    leaves = voc.node_of_word[voc.words_of(query)]
    for leaf, node in zip(leaves, nodes, strict=True):
        if node < 0:
            continue
        while leaf != node and leaf > 0:
            leaf = voc.parents[leaf]
        assert leaf == node


def _clusters(kind: str, n_clusters: int, per: int, rng: np.random.Generator):
    if kind == "binary":
        centres = rng.integers(0, 256, (n_clusters, 32), dtype=np.uint8)
        labels = np.repeat(np.arange(n_clusters), per)
        # exact copies: DBoW2's binary k-means++ draws seeds proportionally to the Hamming distance (not its
        # square), so with noisy copies two seeds can fall in one cluster; with copies they never do
        return centres[labels], labels
    centres = rng.standard_normal((n_clusters, 8)).astype(np.float32) * 10
    labels = np.repeat(np.arange(n_clusters), per)
    return (centres[labels] + 0.1 * rng.standard_normal((labels.size, 8))).astype(np.float32), labels


@pytest.mark.parametrize("kind", ["binary", "float"])
def test_well_separated_clusters_are_recovered(kind):
    rng = np.random.default_rng(0)
    data, labels = _clusters(kind, 10, 40, rng)
    perm = rng.permutation(labels.size)
    data, labels = data[perm], labels[perm]
    voc = train_vocabulary(np.array_split(data, 8), k=10, L=2, seed=0)
    top = voc.children[0][voc.children[0] >= 0]
    assert top.size == 10
    _, node = voc.descend(data, node_depth=1)
    # every cluster lands in exactly one top-level node and every node holds exactly one cluster
    pairs = {(int(lab), int(n)) for lab, n in zip(labels, node, strict=True)}
    assert len(pairs) == 10 and {p[0] for p in pairs} == set(range(10)) and {p[1] for p in pairs} == set(top)
    if kind == "binary":  # majority centres of identical members are the members
        assert {bytes(c) for c in voc.centres[top]} == {bytes(c) for c in data}


def test_nodes_with_at_most_k_descriptors_get_one_child_each():
    d = np.arange(5 * 32, dtype=np.uint8).reshape(5, 32)
    voc = train_vocabulary([d], k=10, L=3)
    assert voc.n_nodes == 6 and voc.n_words == 5
    assert np.array_equal(np.sort(voc.centres[1:], axis=0), np.sort(d, axis=0))


def test_bad_inputs_raise():
    with pytest.raises(ConfigError):
        train_vocabulary([np.zeros((3, 32), np.uint8)], k=1)
    with pytest.raises(ScanDataError):
        train_vocabulary([])
    voc, _ = _toy_vocabulary()
    with pytest.raises(ScanDataError, match="size 32"):
        voc.transform(np.zeros((3, 16), np.uint8))
    with pytest.raises(ScanDataError, match="binary"):
        voc.transform(np.zeros((3, 32), np.float32))
