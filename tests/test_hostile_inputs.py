"""Hostile inputs end in documented placerec errors, fast: YAML alias bombs and deep nesting, zip bombs, headers
and sparse files that declare absurd sizes, huge values in error messages."""

from __future__ import annotations

import struct
import time
import zipfile
import zlib
from pathlib import Path

import numpy as np
import pytest

from placerec.artifacts.vocabulary import load_training_config
from placerec.config import load_config
from placerec.errors import ArtifactError, ConfigError, ScanFormatError, short_repr
from placerec.io import read_scan
from placerec.io._common import check_count
from placerec.io.atomic import load_artifact, save_artifact
from placerec.io.limits import DEFAULT_MAX_SCAN_BYTES, ENV_VARS, max_load_bytes
from placerec.io.sequences import load_sensor_yaml
from placerec.safe_yaml import load_yaml

# "billion laughs": 9 levels of 9 aliases, 9^9 ~ 387 million strings once expanded; ~370 bytes
BOMB = "a: &a [lol,lol,lol,lol,lol,lol,lol,lol,lol]\n" + "".join(
    f"{c}: &{c} [{', '.join([f'*{p}'] * 9)}]\n" for p, c in zip("abcdefgh", "bcdefghi", strict=True)
)


def _rejected_fast(fn, error, *args, match=None):
    t0 = time.perf_counter()
    with pytest.raises(error, match=match):
        fn(*args)
    assert time.perf_counter() - t0 < 1.0


def test_alias_bomb_is_rejected_fast_everywhere_yaml_is_read(tmp_path):
    assert len(BOMB) < 400
    cfg = tmp_path / "bomb.yaml"
    cfg.write_text(BOMB)
    _rejected_fast(load_config, ConfigError, cfg, match="100000 nodes once aliases are expanded")
    _rejected_fast(load_training_config, ConfigError, cfg, match="bomb.yaml")
    _rejected_fast(load_sensor_yaml, ScanFormatError, cfg, match="aliases")
    # an override value is YAML too
    _rejected_fast(load_config, ConfigError, None, ["name=" + "{" + BOMB.replace("\n", ", ") + "}"])


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("a: " + "[" * 600 + "]" * 600, "nesting deeper than 64"),  # RecursionError in yaml.safe_load
        ("a: &a [1, *a]\n", "recursive alias"),
        ("x: &x 1\n" + "".join(f"k{i}: *x\n" for i in range(1001)), "more than 1000 alias"),
    ],
)
def test_deep_recursive_and_alias_heavy_yaml_give_config_errors(tmp_path, text, match):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(text)
    _rejected_fast(load_config, ConfigError, cfg, match=match)


def test_oversized_yaml_is_refused_before_it_is_read(tmp_path):
    cfg = tmp_path / "big.yaml"
    with open(cfg, "wb") as fh:  # sparse: 10 GB that take no disk space
        fh.truncate(10**10)
    _rejected_fast(load_config, ConfigError, cfg, match="exceeds the limit")
    with pytest.raises(ConfigError, match="exceeds the limit of 10 bytes"):
        load_yaml("a: 1234567890", "<text>", max_bytes=10)


def test_plain_yaml_still_loads():
    assert load_yaml("a: &x [1, 2]\nb: *x\n", "<text>") == {"a": [1, 2], "b": [1, 2]}
    assert load_yaml("", "<text>") is None


def test_config_error_never_reprs_a_huge_value(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("dataset:\n  simulator:\n    n_scans: [" + ", ".join(["123456789"] * 3000) + "]\n")
    with pytest.raises(ConfigError) as exc:
        load_config(cfg)
    assert "n_scans" in str(exc.value) and len(str(exc.value)) < 400
    assert len(short_repr("x" * 10**6)) <= 80 and len(short_repr([[list(range(10**5))]] * 10**5)) <= 80


# ------------------------------------------------------------------------------------------- zip and size bombs
def _npy_header(shape: tuple[int, ...], descr: str = "<f4") -> bytes:
    d = repr({"descr": descr, "fortran_order": False, "shape": shape}).encode()
    pad = 64 - (10 + len(d) + 1) % 64
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(d) + pad + 1) + d + b" " * pad + b"\n"


def _zip_one_member(path: Path, name: str, data: bytes, method: int, declared: int, crc: int) -> None:
    """A one-member zip written byte by byte, so that the declared uncompressed size can be anything."""
    fn = name.encode()
    local = struct.pack(
        "<4sHHHHHIIIHH", b"PK\x03\x04", 20, 0, method, 0, 0, crc, len(data), declared, len(fn), 0
    )
    central = struct.pack(
        "<4sHHHHHHIIIHHHHHII",
        b"PK\x01\x02",
        20,
        20,
        0,
        method,
        0,
        0,
        crc,
        len(data),
        declared,
        len(fn),
        0,
        0,
        0,
        0,
        0,
        0,
    )
    cd_offset = len(local) + len(fn) + len(data)
    end = struct.pack("<4sHHHHIIH", b"PK\x05\x06", 0, 0, 1, 1, len(central) + len(fn), cd_offset, 0)
    path.write_bytes(local + fn + data + central + fn + end)


def _deflate_bomb(path: Path, n_points: int) -> int:
    """A scan ``.npz`` whose ``xyz.npy`` member is a real deflate stream of an (n_points, 3) float32 array of
    zeros (identical fully-flushed blocks repeated, so it is built in milliseconds). Returns its expanded size.
    The CRC is not computed (it would take seconds); the bomb is caught before it matters."""
    header = _npy_header((n_points, 3))
    chunk = 1 << 24
    total = n_points * 12
    assert total % chunk == 0

    def segment(data: bytes) -> bytes:
        co = zlib.compressobj(9, zlib.DEFLATED, -15)
        return co.compress(data) + co.flush(zlib.Z_FULL_FLUSH)

    stream = (
        segment(header)
        + segment(bytes(chunk)) * (total // chunk)
        + zlib.compressobj(9, zlib.DEFLATED, -15).flush()
    )
    _zip_one_member(path, "xyz.npy", stream, zipfile.ZIP_DEFLATED, len(header) + total, 0)
    return len(header) + total


def test_scan_npz_zip_bomb_is_refused_before_decompressing(tmp_path):
    bomb = tmp_path / "bomb.npz"
    expanded = _deflate_bomb(bomb, (3 << 30) // 12 // (1 << 24) * (1 << 24))
    assert bomb.stat().st_size < 4 << 20 and expanded > 3 * 10**9
    _rejected_fast(read_scan, ScanFormatError, bomb, match="over the scan load cap")


def test_npz_member_whose_header_lies_about_its_size(tmp_path):
    data = _npy_header((10**12, 3)) + bytes(48)
    path = tmp_path / "lie.npz"
    _zip_one_member(path, "xyz.npy", data, zipfile.ZIP_STORED, len(data), zlib.crc32(data))
    _rejected_fast(read_scan, ScanFormatError, path, match="declares shape")
    art = tmp_path / "lie_art.npz"
    save_artifact(art, "k", 1, {"a": np.zeros(4, np.float32)})
    with zipfile.ZipFile(art) as zf:
        members = {i.filename: zf.read(i) for i in zf.infolist()}
    members["a.npy"] = _npy_header((10**12,)) + bytes(16)
    with zipfile.ZipFile(art, "w") as zf:
        for name, blob in members.items():
            zf.writestr(name, blob)
    _rejected_fast(load_artifact, ArtifactError, art, "k", (1,), match=r"a\].*declares shape")


def test_artifact_refuses_compressed_members_and_declared_sizes_over_the_cap(tmp_path, monkeypatch):
    art = tmp_path / "a.npz"
    with zipfile.ZipFile(art, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("a.npy", _npy_header((4,)) + bytes(16))
    with pytest.raises(ArtifactError, match="codec"):
        load_artifact(art, "k", (1,))
    save_artifact(art, "k", 1, {"a": np.zeros(1000, np.float64)})
    monkeypatch.setenv(ENV_VARS["artifact"], "4000")
    with pytest.raises(ArtifactError, match="over the artifact load cap of 4000 bytes"):
        load_artifact(art, "k", (1,))
    monkeypatch.setenv(ENV_VARS["artifact"], "lots")
    with pytest.raises(ConfigError, match="PLACEREC_MAX_ARTIFACT_BYTES"):
        load_artifact(art, "k", (1,))


def test_sparse_files_claiming_huge_sizes_give_placerec_errors(tmp_path):
    for name in ("huge.bin", "huge.npy", "huge.pcd"):
        path = tmp_path / name
        with open(path, "wb") as fh:
            fh.truncate(10**12)  # 10^12 bytes declared, none stored
        _rejected_fast(read_scan, ScanFormatError, path, match="over the scan load cap")
    assert max_load_bytes("scan") == DEFAULT_MAX_SCAN_BYTES


def test_check_count_refuses_counts_the_file_cannot_hold():
    assert check_count(10, 16, 160, "f.pcd", "POINTS") == 10
    with pytest.raises(ScanFormatError, match="f.pcd: POINTS declares 11 items"):
        check_count(11, 16, 160, "f.pcd", "POINTS")
    with pytest.raises(ScanFormatError, match="over the scan load cap"):
        check_count(10**12, 16, 10**13, "f.pcd", "POINTS")


def test_compressed_pcd_expanding_beyond_the_scan_cap_is_refused_before_decompressing(tmp_path, monkeypatch):
    from placerec.io.pcd import write_pcd
    from placerec.types import Scan

    n = 100_000  # 1.6 MB of x, y, z, intensity once decompressed; LZF shrinks the zeros ~80 times
    path = tmp_path / "zeros.pcd"
    write_pcd(
        path, Scan(xyz=np.zeros((n, 3), np.float32), intensity=np.zeros(n, np.float32)), "binary_compressed"
    )
    assert len(read_scan(path)) == n
    monkeypatch.setenv(ENV_VARS["scan"], str(1 << 20))
    assert path.stat().st_size < 1 << 20
    with pytest.raises(
        ScanFormatError, match="binary_compressed uncompressed size declares 1600000 bytes, over"
    ):
        read_scan(path)


def test_a_corrupt_descriptor_cache_is_recomputed_not_used(tmp_path):
    from placerec.artifacts.vocabulary import VocabTrainingConfig, cached_descriptors

    folder = tmp_path / "velodyne"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(2):
        pts = np.c_[rng.normal(0, 10, (5000, 3)), rng.uniform(0, 1, 5000)].astype(np.float32)
        (folder / f"{i:06d}.bin").write_bytes(pts.tobytes())
    datasets = [{"source": "path", "path": str(folder)}]
    cfg = VocabTrainingConfig(
        simulator=None, datasets=datasets, descriptor_cache=str(tmp_path / "c"), n_images=2
    )
    fresh, labels = cached_descriptors(cfg)
    (cache,) = (tmp_path / "c").iterdir()
    with np.load(cache) as z:
        saved = {k: z[k] for k in z.files}
    for corrupt in ({**saved, "counts": saved["counts"] * 1000}, {**saved, "labels": saved["labels"][:1]}):
        np.savez(cache, **corrupt)
        again, again_labels = cached_descriptors(cfg)
        assert again_labels == labels and all(np.array_equal(a, b) for a, b in zip(again, fresh, strict=True))


@pytest.mark.parametrize("descr", ["|V0", "|S0", "<U0"])
def test_zero_size_dtypes_are_refused(tmp_path, descr):
    npy = tmp_path / "z.npy"
    npy.write_bytes(_npy_header((5,), descr))
    with pytest.raises(ScanFormatError, match="no bytes per element"):
        read_scan(npy)
    art, data = tmp_path / "z.npz", _npy_header((5,), descr)
    _zip_one_member(art, "a.npy", data, zipfile.ZIP_STORED, len(data), zlib.crc32(data))
    with pytest.raises(ArtifactError, match="no bytes per element"):
        load_artifact(art, "k", (1,))
