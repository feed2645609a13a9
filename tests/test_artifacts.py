"""Artifacts fail loudly: corrupted copies of real saved artifacts of every kind raise `ArtifactError`, never a bare
exception and never a silent load of other content; saves are atomic, keep the umask and clean up after crashes."""

from __future__ import annotations

import functools
import io
import json
import os
import stat
import struct
import subprocess
import sys
import zipfile
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from fuzz.artifacts import _calibration  # the same small table the fuzz corpus damages

from placerec.calibration.table import CalibrationTable
from placerec.errors import ArtifactError
from placerec.io.atomic import atomic_write, load_artifact, save_artifact
from placerec.recognizer import PIPELINES, make_pipeline
from placerec.retrieval.dbow.database import BowDatabase
from placerec.retrieval.dbow.io import load_vocabulary, save_vocabulary
from placerec.retrieval.dbow.vocabulary import Vocabulary, train_vocabulary
from placerec.retrieval.hbst import HBST
from placerec.three_d.places import PlacesDatabase, PlacesParams

Edit = Callable[[dict[str, np.ndarray], dict], None]  # changes (arrays, header) in place


# ------------------------------------------------------------------------------------------ real artifacts
def _hbst(path: Path) -> None:
    rng = np.random.default_rng(0)
    h = HBST(leaf_size=8)
    for i in range(4):
        h.add(10 + i, rng.integers(0, 256, (30, 32), dtype=np.uint8))
    h.save(path)


def _places(path: Path) -> None:
    rng = np.random.default_rng(1)
    scan_poses = np.tile(np.eye(4), (6, 1, 1))
    scan_poses[:, 0, 3] = np.arange(6) * 3.0
    ids = np.array([0, 2, 4])
    counts = np.array([5, 0, 7])
    sources = [np.array([0, 1]), np.array([1, 2, 3]), np.array([3, 4, 5])]
    clouds = [
        (rng.normal(size=(n, 3)).astype(np.float32), rng.uniform(size=n).astype(np.float32))
        for n in (9, 4, 6)
    ]
    PlacesDatabase(
        ids=ids, poses=scan_poses[ids].copy(), sources=sources, kp_offsets=np.r_[0, np.cumsum(counts)],
        keypoints=rng.normal(size=(12, 3)).astype(np.float32), descriptors=rng.uniform(size=(12, 8)).astype(np.float32),
        params=PlacesParams(), scan_poses=scan_poses, clouds=clouds, intensity="sensor-default", sequence="s",
    ).save(path)  # fmt: skip


@functools.cache
def _small_vocabulary() -> Vocabulary:
    rng = np.random.default_rng(4)
    return train_vocabulary(
        [rng.integers(0, 256, (40, 32), dtype=np.uint8) for _ in range(6)], k=4, L=3, seed=0
    )


def _bow_database(path: Path) -> None:
    voc = _small_vocabulary()
    rng = np.random.default_rng(6)
    db = BowDatabase(voc, levels_up=1)
    for i in range(5):
        bow, nodes = voc.transform(rng.integers(0, 256, (20, 32), dtype=np.uint8), levels_up=1)
        db.add(bow, nodes if i != 2 else None, entry_id=100 + i)
    db.save(path)


def _load_places(p: Path) -> object:
    return PlacesDatabase.load(p)


KINDS = {
    "dbow-database": (
        _bow_database,
        lambda p: BowDatabase.load(p, _small_vocabulary()),
        lambda obj, p: obj.save(p),
    ),
    "hbst": (_hbst, HBST.load, lambda obj, p: obj.save(p)),
    "places-db": (_places, _load_places, lambda obj, p: obj.save(p)),
    "intensity-calibration": (_calibration, CalibrationTable.load, lambda obj, p: obj.save(p)),
}


# ------------------------------------------------------------------------------------- npz surgery helpers
def _members(path: Path) -> dict[str, bytes]:
    with zipfile.ZipFile(path) as zf:
        return {i.filename: zf.read(i) for i in zf.infolist()}


def _write_members(path: Path, members: dict[str, bytes]) -> None:
    with zipfile.ZipFile(path, "w") as zf:
        for name, blob in members.items():
            zf.writestr(name, blob)


def _npy(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, arr, allow_pickle=True)
    return buf.getvalue()


def _decode(members: dict[str, bytes]) -> tuple[dict[str, np.ndarray], dict]:
    arrays = {n[:-4]: np.load(io.BytesIO(b)) for n, b in members.items()}
    header = json.loads(arrays.pop("__header__").tobytes())
    return arrays, header


def _encode(arrays: dict[str, np.ndarray], header: dict) -> dict[str, bytes]:
    out = {f"{n}.npy": _npy(a) for n, a in arrays.items()}
    out["__header__.npy"] = _npy(np.frombuffer(json.dumps(header).encode(), np.uint8))
    return out


def _scaled(name: str, factor: int) -> Edit:
    return lambda a, h: a.__setitem__(name, a[name] * factor)


def _nan_at(name: str) -> Edit:
    def edit(a: dict, h: dict) -> None:
        a[name] = a[name].astype(np.float64)
        a[name].reshape(-1)[-1] = np.nan

    return edit


def _meta(key: str, value: object) -> Edit:
    return lambda a, h: h["meta"].__setitem__(key, value)


def _generic_edits(arrays: dict[str, np.ndarray]) -> dict[str, Edit]:
    """Edits every npz artifact must refuse: headers, members, dtypes."""
    edits: dict[str, Edit] = {
        "kind": lambda a, h: h.__setitem__("kind", "other"),
        "version": lambda a, h: h.__setitem__("format_version", 99),
        "version-string": lambda a, h: h.__setitem__("format_version", "1"),
        "meta-list": lambda a, h: h.__setitem__("meta", [1]),
        "extra-member": lambda a, h: a.__setitem__("bogus", np.zeros(3)),
        "pickled-member": lambda a, h: a.__setitem__(next(iter(a)), np.array([{"x": 1}], dtype=object)),
    }
    for name, arr in arrays.items():
        edits[f"drop-{name}"] = lambda a, h, n=name: a.pop(n)
        edits[f"rename-{name}"] = lambda a, h, n=name: a.__setitem__(n + "_", a.pop(n))
        other = np.complex64 if arr.dtype.kind == "f" else np.float64
        edits[f"dtype-{name}"] = lambda a, h, n=name, t=other: a.__setitem__(n, a[n].astype(t))
        if arr.ndim:
            edits[f"shape-{name}"] = lambda a, h, n=name: a.__setitem__(n, a[n][..., None])
    return edits


SPECIFIC: dict[str, dict[str, Edit]] = {
    "dbow-database": {
        "bow_lens-x1000": _scaled("bow_lens", 1000),
        "node_lens-x1000": _scaled("node_lens", 1000),
        "ids-duplicated": lambda a, h: a.__setitem__("ids", np.full_like(a["ids"], 7)),
        "words-beyond-vocabulary": lambda a, h: a.__setitem__("bow_words", a["bow_words"] + 10**6),
        "words-negative": lambda a, h: a.__setitem__("bow_words", a["bow_words"] - 10**6),
        "values-nan": _nan_at("bow_values"),
        "levels_up": _meta("levels_up", 99),
        "levels_up-string": _meta("levels_up", "1"),
        "other-vocabulary": _meta("vocabulary", "0123"),
    },
    "hbst": {
        "leaf_start-x1000": _scaled("leaf_start", 1000),
        "leaf_count+1": lambda a, h: a.__setitem__("leaf_count", a["leaf_count"] + 1),
        "image_id-x1000": _scaled("image_id", 1000),
        "images-duplicated": lambda a, h: a.__setitem__("images", np.full_like(a["images"], 10)),
        "split-out-of-range": lambda a, h: a.__setitem__(
            "split", np.where(a["split"] >= 0, 9999, a["split"])
        ),
        "child-x1000": _scaled("child", 1000),
        "descriptors-cut": lambda a, h: a.__setitem__("descriptors", a["descriptors"][:-3]),
        "n_bytes": _meta("n_bytes", 16),
        "no-n_bytes": _meta("n_bytes", None),
        "delta_max": _meta("delta_max", "x"),
        "leaf_size": _meta("leaf_size", -1),
    },
    "places-db": {
        "kp_offsets-x1000": _scaled("kp_offsets", 1000),
        "kp_offsets-decreasing": lambda a, h: a.__setitem__("kp_offsets", np.array([0, 7, 5, 12])),
        "source_counts-x1000": _scaled("source_counts", 1000),
        "cloud_counts-x1000": _scaled("cloud_counts", 1000),
        "poses-nan": _nan_at("poses"),
        "scan_poses-nan": _nan_at("scan_poses"),
        "keypoints-nan": _nan_at("keypoints"),
        "descriptors-nan": _nan_at("descriptors"),
        "poses-moved": lambda a, h: a["poses"].__setitem__((0, 0, 3), 5.0),
        "ids-duplicated": lambda a, h: a.__setitem__("ids", np.array([0, 0, 4])),
        "ids-beyond-map": lambda a, h: a.__setitem__("ids", a["ids"] + 100),
        "sources-beyond-map": lambda a, h: a.__setitem__("sources", a["sources"] + 100),
        "ids-negative": lambda a, h: a.__setitem__("ids", a["ids"] - 1),
        "descriptors-narrow": lambda a, h: a.__setitem__("descriptors", a["descriptors"][:, :4]),
        "keypoints-cut": lambda a, h: a.__setitem__("keypoints", a["keypoints"][:-1]),
        "dim": _meta("dim", 9),
        "params": _meta("params", [1, 2]),
        "params-bad-value": _meta("params", {"spacing_m": "far"}),
        "clouds-partial": lambda a, h: [a.pop("cloud_xyz"), a.pop("cloud_intensity")],
    },
    "intensity-calibration": {
        "values-nan": _nan_at("values"),
        "values-out-of-range": _scaled("values", 3),
        "counts-negative": lambda a, h: a.__setitem__("counts", -a["counts"] - 1),
        "counts-shape": lambda a, h: a.__setitem__("counts", a["counts"][:, :-1]),
        "n_beams": _meta("n_beams", 5),
        "n_raw": _meta("n_raw", 3),
        "raw_step-zero": _meta("raw_step", 0.0),
        "raw_step-nan": _meta("raw_step", float("nan")),
        "raw_step-string": _meta("raw_step", "1"),
        "max_range-negative": _meta("max_range", -3.0),
        "sensor-number": _meta("sensor", 16),
        "no-sensor": lambda a, h: h["meta"].pop("sensor"),
    },
}


def _outcome(load: Callable[[Path], object], path: Path) -> str:
    """ "error" for an ArtifactError, "loaded" for a load; any other exception propagates to the caller."""
    try:
        load(path)
    except ArtifactError:
        return "error"
    return "loaded"


def _same_content(a: Path, b: Path) -> bool:
    ma, mb = _members(a), _members(b)
    if ma.keys() != mb.keys():
        return False
    (xa, ha), (xb, hb) = _decode(ma), _decode(mb)
    return ha == hb and all(xa[k].dtype == xb[k].dtype and np.array_equal(xa[k], xb[k]) for k in xa)


@pytest.mark.parametrize("kind", list(KINDS))
def test_corrupted_artifacts_raise_artifact_error(tmp_path, kind):
    make, load, save = KINDS[kind]
    good = tmp_path / "good.npz"
    make(good)
    _fuzz(tmp_path, good, load, save, lambda arrays, header: SPECIFIC[kind], kind)


def _fuzz(
    tmp_path: Path,
    good: Path,
    load: Callable[[Path], object],
    save: Callable[[object, Path], None],
    specific: Callable[[dict[str, np.ndarray], dict], dict[str, Edit]],
    kind: str,
) -> None:
    """Corrupt the artifact ``good`` every way (truncation, generic and ``specific`` edits, flipped bytes): each
    copy must raise `ArtifactError` or load as the same artifact (its re-save equal to ``good``)."""
    load(good)  # the uncorrupted file loads
    data = good.read_bytes()
    members = _members(good)
    arrays, header = _decode(members)
    cases: dict[str, bytes | dict[str, bytes]] = {}
    for cut in (0, 1, 30, len(data) // 3, len(data) // 2, len(data) - 30, len(data) - 1):
        cases[f"truncated-at-{cut}"] = data[:cut]
    for name, edit in {**_generic_edits(arrays), **specific(arrays, header)}.items():
        a, h = {k: v.copy() for k, v in arrays.items()}, json.loads(json.dumps(header))
        edit(a, h)
        cases[name] = _encode(a, h)
    cases["header-not-json"] = {**members, "__header__.npy": _npy(np.frombuffer(b"{kind", np.uint8))}
    cases["header-a-list"] = {**members, "__header__.npy": _npy(np.frombuffer(b"[1]", np.uint8))}
    cases["header-floats"] = {**members, "__header__.npy": _npy(np.zeros(3))}
    cases["deflated"] = members
    rng = np.random.default_rng(3)
    flips = rng.choice(len(data), size=40, replace=False)
    failures, loaded_flips = [], 0
    for name, content in list(cases.items()) + [(f"flip-{i}", i) for i in flips]:
        path = tmp_path / f"{name}.npz"
        if isinstance(content, bytes):
            path.write_bytes(content)
        elif isinstance(content, dict):
            if name == "deflated":
                with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
                    for n, b in content.items():
                        zf.writestr(n, b)
            else:
                _write_members(path, content)
        else:
            flipped = bytearray(data)
            flipped[content] ^= 0x5A
            path.write_bytes(bytes(flipped))
        try:
            outcome = _outcome(load, path)
        except Exception as exc:  # the point of the test: nothing but ArtifactError escapes
            failures.append(f"{name}: {type(exc).__name__}: {exc}")
            continue
        if outcome == "loaded":
            resaved = tmp_path / f"{name}.resaved.npz"
            save(load(path), resaved)
            # a flipped byte outside the content (a zip timestamp, say) may load, but only as the same artifact
            if isinstance(content, np.integer) and _same_content(resaved, good):
                loaded_flips += 1
                continue
            failures.append(f"{name}: loaded silently")
    assert not failures, (
        f"{len(failures)} of {len(cases) + len(flips)} corruptions of a {kind}:\n" + "\n".join(failures)
    )
    assert loaded_flips < len(flips) // 2  # most flipped bytes are content, and caught


# ---------------------------------------------------------------------------------- every pipeline's database
@functools.cache
def _sim_scans() -> tuple:
    from placerec.sim import SimulatedSequence

    seq = SimulatedSequence(world="town", sensor="vlp16", n_scans=3, seed=5, clutter=False)
    return tuple(seq[i] for i in range(3)), seq.poses


def _pipeline_edits(arrays: dict[str, np.ndarray], header: dict) -> dict[str, Edit]:
    """Edits of a pipeline database: counts, widths and offsets x1000, NaN in every float array, repeated ids,
    a header made with other parameters or with other values (strings, NaN) for its other metadata."""
    edits: dict[str, Edit] = {"other-params": _meta("params", {"x": 1})}
    for key in set(header["meta"]) - {"params"}:
        edits[f"{key}-string"] = _meta(key, "x")
        edits[f"{key}-nan"] = _meta(key, float("nan"))
    for name, arr in arrays.items():
        if arr.dtype.kind in "iu" and arr.size and any(w in name for w in ("count", "width", "offset")):
            edits[f"{name}-x1000"] = _scaled(name, 1000)
        if arr.dtype.kind == "f" and arr.size:
            edits[f"{name}-nan"] = _nan_at(name)
    if arrays["ids"].size > 1:
        edits["ids-duplicated"] = lambda a, h: a.__setitem__("ids", np.full_like(a["ids"], a["ids"][0]))
    return edits


@pytest.mark.parametrize("name", sorted(PIPELINES))
def test_corrupted_pipeline_databases_raise_artifact_error(tmp_path, name):
    if name == "map-closures":
        pytest.importorskip("map_closures", reason="the optional peer 'map-closures' is not installed")
    scans, poses = _sim_scans()
    rec = make_pipeline(name)
    for i, scan in enumerate(scans):
        rec.add(i, scan, poses[i])
    good = tmp_path / "good.npz"
    rec.save(good)

    def load(path: Path) -> object:
        fresh = make_pipeline(name)
        fresh.load(path)
        return fresh

    _fuzz(tmp_path, good, load, lambda obj, p: obj.save(p), _pipeline_edits, name)


def test_visual_image_widths_are_bounded_on_describe_and_on_load(tmp_path, monkeypatch):
    from placerec.errors import ConfigError, ScanDataError
    from placerec.pipelines import visual
    from placerec.pipelines.visual import MAX_IMAGE_WIDTH

    scans, _ = _sim_scans()
    with pytest.raises(
        ConfigError, match=f"image.width: Input should be less than or equal to {MAX_IMAGE_WIDTH}"
    ):
        make_pipeline("orb-hbst", {"image": {"width": MAX_IMAGE_WIDTH + 8}})
    # a sensor with more columns than the bound is refused when described (the bound lowered to show it)
    monkeypatch.setattr(visual, "MAX_IMAGE_WIDTH", 256)
    with pytest.raises(ScanDataError, match="over 256 px"):
        make_pipeline("orb-hbst", {"image": {"width": 512}}).describe(scans[0])
    monkeypatch.undo()
    rec = make_pipeline("orb-hbst", {"image": {"width": 512}})
    rec.add(0, scans[0])
    rec.save(tmp_path / "db.npz")
    arrays, header = _decode(_members(tmp_path / "db.npz"))
    arrays["widths"] = arrays["widths"] * 2  # within the bound, but not the configured width
    _write_members(tmp_path / "wide.npz", _encode(arrays, header))
    with pytest.raises(ArtifactError, match=r"'widths' holds 1024 px; expected 512 \(image.width\)"):
        make_pipeline("orb-hbst", {"image": {"width": 512}}).load(tmp_path / "wide.npz")


# ------------------------------------------------------------------------------------------ description cache
def _cache_edits() -> dict[str, Edit]:
    return {
        "values-changed": lambda a, h: a.__setitem__("descriptors", a["descriptors"] + 1),
        "keypoints-cut": lambda a, h: a.__setitem__("keypoints", a["keypoints"][:-1]),
        "array-dropped": lambda a, h: a.pop("width"),
        "array-added": lambda a, h: a.__setitem__("extra", np.zeros(2)),
        "dtype-changed": lambda a, h: a.__setitem__("descriptors", a["descriptors"].astype(np.float32)),
        "describe_ms-nan": _meta("describe_ms", float("nan")),
        "describe_ms-negative": _meta("describe_ms", -1.0),
        "describe_ms-string": _meta("describe_ms", "7"),
        "describe_ms-missing": lambda a, h: h["meta"].pop("describe_ms"),
        "other-frontend": _meta("frontend", "orb-other"),
        "no-digest": lambda a, h: h["meta"].pop("sha1"),
        "version-2": lambda a, h: h.__setitem__("format_version", 2),
    }


def test_corrupt_description_cache_entries_are_recomputed_never_used(tmp_path, caplog):
    from placerec.experiment.cache import DescriptionCache

    rng = np.random.default_rng(7)
    desc = {
        "keypoints": rng.uniform(0, 500, (40, 2)).astype(np.float32),
        "descriptors": rng.integers(0, 256, (40, 32), dtype=np.uint8),
        "width": np.array(512, np.int64),
    }
    cache = DescriptionCache(tmp_path, "data")
    cache.put("orb-front", 0, desc, 12.5)
    path = tmp_path / "data" / "orb-front" / "000000.npz"
    got, ms = cache.get("orb-front", 0)
    assert ms == 12.5 and all(np.array_equal(got[k], desc[k]) for k in desc)
    good = path.read_bytes()
    arrays, header = _decode(_members(path))
    cases = {"truncated": good[: len(good) // 2]}
    for name, edit in _cache_edits().items():
        a, h = {k: v.copy() for k, v in arrays.items()}, json.loads(json.dumps(header))
        edit(a, h)
        cases[name] = _encode(a, h)
    used = []
    for name, content in cases.items():
        if isinstance(content, bytes):
            path.write_bytes(content)
        else:
            _write_members(path, content)
        caplog.clear()
        if cache.get("orb-front", 0) is not None:
            used.append(name)
        elif "recomputing the unusable cache entry" not in caplog.text:
            used.append(f"{name}: no warning")
    assert not used, f"corrupt cache entries used: {used}"


# -------------------------------------------------------------------------------------------- vocabularies
@pytest.fixture(scope="module")
def vocab_file(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("voc") / "v.dbow"
    save_vocabulary(_small_vocabulary(), path)
    return path


def _split_dbow(data: bytes) -> tuple[dict, bytes, int]:
    n_head = struct.unpack_from("<I", data, 12)[0]
    return json.loads(data[20 : 20 + n_head]), data, -(-(20 + n_head) // 64) * 64


def _join_dbow(header: dict, payload: bytes) -> bytes:
    blob = json.dumps(header, sort_keys=True).encode()
    head = b"PRDBOW\x00\x01" + struct.pack("<III", 2, len(blob), zlib.crc32(blob)) + blob
    return head + b"\0" * (-len(head) % 64) + payload


def _with_array(header: dict, payload: bytes, name: str, values: np.ndarray) -> tuple[dict, bytes]:
    """Replace one raw array in the payload (its CRC recomputed), as a writer with a bug would."""
    spec = header["arrays"][name]
    raw = np.ascontiguousarray(values, np.dtype(spec["dtype"])).tobytes()
    assert len(raw) == spec["stored_bytes"]
    spec["crc32"] = zlib.crc32(raw)
    a = spec["offset"]
    return header, payload[:a] + raw + payload[a + len(raw) :]


def test_corrupted_vocabularies_raise_artifact_error(tmp_path, vocab_file):
    data = vocab_file.read_bytes()
    good = load_vocabulary(vocab_file)
    header, _, base = _split_dbow(data)
    payload = data[base:]
    n = header["n_nodes"]
    parents = np.frombuffer(payload, "<i4", n, header["arrays"]["parents"]["offset"])
    weights = np.frombuffer(payload, "<f4", n, header["arrays"]["weights"]["offset"])

    def edited(**changes: object) -> dict:
        h = json.loads(json.dumps(header))
        for dotted, value in changes.items():
            node = h
            *path, last = dotted.split("__")
            for part in path:
                node = node[part]
            node[last] = value
        return h

    cases: dict[str, bytes] = {
        f"truncated-at-{c}": data[:c] for c in (8, 16, 40, base - 1, base + 10, len(data) - 1)
    }
    for key, value in {
        "k": 1, "L": 0, "n_nodes": n + 1, "n_words": header["n_words"] + 1, "kind": "float", "centre_dtype": "int8",
        "centre_scale": -1.0, "weighting": "bogus", "descriptor_size": 31, "meta": [], "arrays": [],
        "arrays__weights__dtype": "<f8", "arrays__weights__shape": [n - 1], "arrays__parents__codec": "lz4",
        "arrays__centres__offset": 10**9, "arrays__centres__offset ": None, "arrays__weights__stored_bytes": 10**12,
        "arrays__parents__crc32": 0, "arrays__centres__shape": [n, 10**9],
    }.items():  # fmt: skip
        cases[f"header-{key}"] = _join_dbow(edited(**{key.strip(): value}), payload)
    cases["header-no-arrays"] = _join_dbow({k: v for k, v in header.items() if k != "arrays"}, payload)
    cases["header-k-too-small"] = _join_dbow(edited(k=2), payload)
    cases["header-L-too-small"] = _join_dbow(edited(L=1), payload)
    nan_w = weights.copy()
    nan_w[-1] = np.nan
    chain = np.arange(-1, n - 1)  # every node the child of the one before: deeper than L
    star = np.r_[-1, np.zeros(n - 1, np.int64)]  # every node a child of the root: more than k children
    later = parents.copy()
    later[1] = 5  # a parent after its child
    for name, arr_name, values in [("weights-nan", "weights", nan_w), ("parents-chain", "parents", chain),
                                   ("parents-star", "parents", star), ("parents-later", "parents", later)]:  # fmt: skip
        cases[name] = _join_dbow(*_with_array(edited(), payload, arr_name, values))
    version3 = bytearray(data)
    version3[8:12] = struct.pack("<I", 3)
    cases["version-3"] = bytes(version3)
    rng = np.random.default_rng(5)
    flips = {f"flip-{i}": i for i in rng.choice(len(data), size=40, replace=False)}
    failures, loaded_flips = [], 0
    for name, content in list(cases.items()) + list(flips.items()):
        path = tmp_path / f"{name}.dbow"
        if isinstance(content, bytes):
            path.write_bytes(content)
        else:
            flipped = bytearray(data)
            flipped[content] ^= 0x5A
            path.write_bytes(bytes(flipped))
        try:
            voc = load_vocabulary(path)
        except ArtifactError:
            continue
        except Exception as exc:  # noqa: BLE001 - nothing but ArtifactError may escape
            failures.append(f"{name}: {type(exc).__name__}: {exc}")
            continue
        same = (voc.k, voc.L, voc.weighting, voc.meta) == (good.k, good.L, good.weighting, good.meta) and all(
            np.array_equal(getattr(voc, f), getattr(good, f)) for f in ("parents", "centres", "weights")
        )
        if name in flips and same:  # a flip in the zero padding between arrays changes nothing
            loaded_flips += 1
            continue
        failures.append(f"{name}: loaded silently")
    assert not failures, f"{len(failures)} corruptions of a vocabulary:\n" + "\n".join(failures)
    assert loaded_flips < len(flips) // 2


def test_load_caps_apply_to_vocabularies(vocab_file):
    with pytest.raises(ArtifactError, match="over the artifact load cap of 100 bytes"):
        load_vocabulary(vocab_file, limit=100)


# -------------------------------------------------------------------------------------------- atomic saves
@pytest.mark.parametrize("umask", [0o022, 0o002, 0o077])
def test_saved_files_get_the_users_umask(tmp_path, umask):
    old = os.umask(umask)
    try:
        save_artifact(tmp_path / "a.npz", "k", 1, {"x": np.zeros(2)})
        with atomic_write(tmp_path / "t.txt", "w") as fh:
            fh.write("x")
    finally:
        os.umask(old)
    for name in ("a.npz", "t.txt"):
        assert stat.S_IMODE((tmp_path / name).stat().st_mode) == 0o666 & ~umask


def _crash_mid_save(target: Path) -> None:
    """Another process starts saving ``target`` and dies before the rename (no cleanup code runs)."""
    crash = (
        "import os, sys\n"
        "from placerec.io.atomic import atomic_write\n"
        "with atomic_write(sys.argv[1]) as fh:\n"
        "    fh.write(b'half an artifact')\n"
        "    fh.flush()\n"
        "    os._exit(1)\n"
    )
    subprocess.run([sys.executable, "-c", crash, str(target)], check=False, cwd=Path(__file__).parents[1])


def test_temp_files_of_an_interrupted_save_are_removed_by_the_next_save(tmp_path):
    target = tmp_path / "db.npz"
    _crash_mid_save(target)
    left = [p.name for p in tmp_path.iterdir()]
    assert len(left) == 1 and left[0].startswith(".db.npz.") and left[0].endswith(".tmp")
    (tmp_path / ".notes.txt.tmp").write_bytes(b"a user's file that merely looks temporary")
    save_artifact(target, "k", 1, {"x": np.arange(3)})
    assert sorted(p.name for p in tmp_path.iterdir()) == [".notes.txt.tmp", "db.npz"]
    assert load_artifact(target, "k", (1,))[0]["x"].tolist() == [0, 1, 2]


def test_a_save_in_progress_keeps_its_temp_file_while_another_save_of_the_target_runs(tmp_path):
    target = tmp_path / "t.bin"
    with atomic_write(target) as outer:
        outer.write(b"outer")
        with atomic_write(target) as inner:
            inner.write(b"inner")
        assert target.read_bytes() == b"inner"
    assert target.read_bytes() == b"outer"
    assert [p.name for p in tmp_path.iterdir()] == ["t.bin"]


def test_the_folder_is_fsynced_after_the_rename(tmp_path, monkeypatch):
    target = tmp_path / "t.bin"
    synced = []
    real_fsync = os.fsync

    def recording_fsync(fd: int) -> None:  # the real fsync, noting what it was given and whether t.bin exists
        synced.append((stat.S_ISDIR(os.fstat(fd).st_mode), target.exists()))
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", recording_fsync)
    with atomic_write(target) as fh:
        fh.write(b"x")
    assert synced == [(False, False), (True, True)]  # the temp file before the rename, the folder after it


def test_a_failed_save_leaves_the_old_file_and_no_temp(tmp_path):
    target = tmp_path / "t.bin"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError), atomic_write(target) as fh:
        fh.write(b"new")
        raise RuntimeError("disk full")
    assert target.read_bytes() == b"old" and [p.name for p in tmp_path.iterdir()] == ["t.bin"]


def test_a_crash_after_this_process_saved_into_the_folder_is_still_cleaned_up(tmp_path, monkeypatch):
    listed = []
    real_listdir = os.listdir
    monkeypatch.setattr(os, "listdir", lambda p: listed.append(p) or real_listdir(p))
    for i in range(20):  # a cache filling up: the folder is listed once, not once per save
        save_artifact(tmp_path / f"{i}.npz", "k", 1, {"x": np.arange(i)})
    assert len(listed) == 1

    def temps() -> list[str]:
        return [e.name for e in os.scandir(tmp_path) if e.name.endswith(".tmp")]

    _crash_mid_save(tmp_path / "5.npz")  # another process dies mid-save after this one looked at the folder
    assert temps()
    save_artifact(tmp_path / "20.npz", "k", 1, {"x": np.arange(3)})
    assert len(listed) == 2 and not temps()


def _rss_anon_mb() -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("RssAnon:"):
                return int(line.split()[1]) / 1024
    pytest.skip("no /proc/self/status RssAnon on this system")


def test_memory_mapped_artifacts_cost_no_anonymous_memory_and_stay_copy_on_write(tmp_path):
    """``load_artifact(mmap=True)``: the arrays equal the saved ones, are writable without changing the file, and
    a 200 MB member adds (almost) no anonymous memory; a flipped data byte is still an ArtifactError (CRC)."""
    big = np.arange(25_000_000, dtype=np.float64)  # 200 MB
    path = tmp_path / "big.npz"
    save_artifact(path, "test", 1, {"big": big, "small": np.arange(5, dtype=np.int32)})
    del big
    before = _rss_anon_mb()
    arrays, _ = load_artifact(path, "test", (1,), mmap=True)
    grown = _rss_anon_mb() - before
    assert grown < 20, f"{grown:.0f} MB of anonymous memory for a memory-mapped 200 MB member"
    assert arrays["big"][12_345_678] == 12_345_678 and arrays["small"].tolist() == [0, 1, 2, 3, 4]
    arrays["small"][0] = 99  # copy-on-write: the file keeps its bytes
    assert load_artifact(path, "test", (1,), mmap=True)[0]["small"][0] == 0
    del arrays
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x01
    path.write_bytes(bytes(data))
    with pytest.raises(ArtifactError, match="CRC-32 mismatch"):
        load_artifact(path, "test", (1,), mmap=True)
    # a caller that vouches for the bytes another way (a map's manifest hashes) maps them without reading them
    from placerec.io.npz import mapped_without_crc

    with mapped_without_crc():
        arrays, _ = load_artifact(path, "test", (1,), mmap=True)
    assert arrays["small"].tolist() == [0, 1, 2, 3, 4]
    with pytest.raises(ArtifactError, match="CRC-32 mismatch"):  # only inside the block
        load_artifact(path, "test", (1,), mmap=True)
