"""Vocabulary files: binary and ORB-SLAM2 text round trips, float16 storage, malformed files, shipped files."""

from pathlib import Path

import numpy as np
import pytest

from placerec.errors import ArtifactError
from placerec.retrieval.dbow.io import (
    load_vocabulary,
    read_text_vocabulary,
    save_vocabulary,
    write_text_vocabulary,
)
from placerec.retrieval.dbow.vocabulary import train_vocabulary

VOCAB_DIR = Path(__file__).resolve().parents[1] / "placerec" / "vocab"


@pytest.fixture(scope="module", params=["binary", "float"])
def vocab(request):
    rng = np.random.default_rng(2)
    if request.param == "binary":
        parts = [rng.integers(0, 256, (80, 32), dtype=np.uint8) for _ in range(30)]
    else:
        parts = [rng.standard_normal((80, 64)).astype(np.float32) for _ in range(30)]
    return train_vocabulary(parts, k=6, L=3, seed=0, meta={"note": "test"}), parts


def _same(a, b):
    assert (a.k, a.L, a.weighting, a.scoring) == (b.k, b.L, b.weighting, b.scoring)
    assert np.array_equal(a.parents, b.parents)
    assert a.centres.dtype == b.centres.dtype and np.array_equal(a.centres, b.centres)
    assert np.array_equal(a.weights, b.weights)


def test_binary_round_trip_is_identical(tmp_path, vocab):
    voc, parts = vocab
    save_vocabulary(voc, tmp_path / "v.dbow")
    again = load_vocabulary(tmp_path / "v.dbow")
    _same(voc, again)
    assert again.meta["note"] == "test" and again.fingerprint == voc.fingerprint
    assert np.array_equal(voc.words_of(parts[0]), again.words_of(parts[0]))


def test_text_round_trip_is_identical(tmp_path, vocab):
    voc, parts = vocab
    write_text_vocabulary(voc, tmp_path / "v.txt")
    first = (tmp_path / "v.txt").read_text().splitlines()[0]
    assert first.split() == ["6", "3", "0", "0"]  # k L scoring(L1) weighting(TF-IDF)
    again = read_text_vocabulary(tmp_path / "v.txt")
    _same(voc, again)
    assert load_vocabulary(tmp_path / "v.txt").n_nodes == voc.n_nodes  # load_vocabulary detects text


def test_float16_storage(tmp_path, vocab):
    voc, parts = vocab
    if voc.binary:
        with pytest.raises(ArtifactError):
            save_vocabulary(voc, tmp_path / "x.dbow", "float16")
        return
    save_vocabulary(voc, tmp_path / "h.dbow", "float16")
    half = load_vocabulary(tmp_path / "h.dbow")
    assert half.centres.dtype == np.float32 and np.allclose(half.centres, voc.centres, atol=2e-3)
    assert (tmp_path / "h.dbow").stat().st_size < 0.6 * voc.centres.nbytes + 4096


def test_compressed_and_int8_storage(tmp_path, vocab):
    voc, _ = vocab
    save_vocabulary(voc, tmp_path / "z.dbow", compress=True)
    _same(voc, load_vocabulary(tmp_path / "z.dbow"))
    if not voc.binary:
        save_vocabulary(voc, tmp_path / "q.dbow", "int8")
        q = load_vocabulary(tmp_path / "q.dbow")
        step = np.abs(voc.centres).max() / 127
        assert np.abs(q.centres - voc.centres).max() <= 0.5 * step + 1e-6


def test_orb_slam2_text_with_hand_written_tree(tmp_path):
    # root -> nodes 1, 2; node 1 -> leaves 3, 4; node 2 is a leaf; descriptors of 32 bytes
    rows = [
        (0, 0, 0x00, 0.0),
        (0, 1, 0xFF, 1.5),
        (1, 1, 0x01, 0.7),
        (1, 1, 0x03, 0.9),
    ]
    text = "10 6  0 0\n" + "\n".join(
        " ".join([str(p), str(leaf)] + [str(b)] * 32 + [str(w)]) for p, leaf, b, w in rows
    )
    (tmp_path / "orb.txt").write_text(text + "\n")
    voc = read_text_vocabulary(tmp_path / "orb.txt")
    assert voc.binary and voc.n_nodes == 5 and voc.node_of_word.tolist() == [2, 3, 4]
    d = np.vstack([np.full(32, 0xFF, np.uint8), np.full(32, 0x01, np.uint8), np.full(32, 0x03, np.uint8)])
    assert voc.words_of(d).tolist() == [0, 1, 2]
    assert voc.word_weights.tolist() == pytest.approx([1.5, 0.7, 0.9])


@pytest.mark.parametrize(
    "content, match",
    [
        ("hello\n", "first line"),
        ("10 6 0 0\n", "no nodes"),
        ("10 6 0 0\n0 1 1 2 3 0.5\n0 1 1 2 0.5\n", "malformed"),
        ("10 6 0 0\n0 1 1 2 x 0.5\n", "malformed"),
        ("10 6 9 0\n0 1 1 2 3 0.5\n", "implausible"),
    ],
)
def test_malformed_text_files(tmp_path, content, match):
    (tmp_path / "bad.txt").write_text(content)
    with pytest.raises(ArtifactError, match=match):
        read_text_vocabulary(tmp_path / "bad.txt")


def test_corrupt_and_missing_binary_files(tmp_path, vocab):
    voc, _ = vocab
    path = tmp_path / "v.dbow"
    save_vocabulary(voc, path)
    data = bytearray(path.read_bytes())
    data[-100] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(ArtifactError, match="checksum"):
        load_vocabulary(path)
    path.write_bytes(bytes(data[: len(data) // 2]))
    with pytest.raises(ArtifactError, match="truncated|checksum"):
        load_vocabulary(path)
    with pytest.raises(ArtifactError, match="no such"):
        load_vocabulary(tmp_path / "missing.dbow")


@pytest.mark.parametrize(
    "name, kind, size, levels",
    [("orb_k10L5.dbow", "binary", 32, 5), ("surf_k10L4.dbow", "float", 64, 4)],
)
def test_shipped_vocabularies_load_and_transform(name, kind, size, levels):
    path = VOCAB_DIR / name
    assert path.is_file(), f"{path} is missing (see placerec/vocab/README.md)"
    voc = load_vocabulary(path)
    assert voc.kind == kind and voc.descriptor_size == size and (voc.k, voc.L) == (10, levels)
    assert voc.n_words > 5000 and voc.meta["n_images"] == 3000
    assert path.stat().st_size < 10e6
    rng = np.random.default_rng(0)
    if kind == "binary":
        d = rng.integers(0, 256, (300, 32), dtype=np.uint8)
    else:
        d = rng.standard_normal((300, 64)).astype(np.float32)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
    bow = voc.transform(d)
    assert len(bow) > 0 and bow.values.sum() == pytest.approx(1.0)


def test_an_unreadable_vocabulary_is_an_artifact_error(tmp_path, monkeypatch):
    import builtins

    from placerec.errors import ArtifactError
    from placerec.retrieval.dbow.io import load_vocabulary

    path = tmp_path / "voc.bin"
    path.write_bytes(b"x" * 100)
    real_open = builtins.open

    def denied(file, *args, **kwargs):
        if str(file) == str(path):
            raise PermissionError(13, "Permission denied", str(file))
        return real_open(file, *args, **kwargs)

    monkeypatch.setattr(builtins, "open", denied)
    with pytest.raises(
        ArtifactError, match=r"voc.bin: cannot read the vocabulary file \(Permission denied\)"
    ):
        load_vocabulary(path)
