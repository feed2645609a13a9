"""Scan readers and writers on synthetic files: round trips, field handling, organisation, LZF, registry."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from placerec.errors import ConfigError, ScanFormatError
from placerec.io import SCAN_READERS, SCAN_WRITERS, read_scan, write_scan
from placerec.io.lzf import LZFError, lzf_compress, lzf_decompress
from placerec.io.nclt import HDL32E_ELEVATIONS_DEG
from placerec.io.pcd import write_pcd
from placerec.types import Scan, SensorInfo


def make_scan(n: int = 500, seed: int = 0, ring: bool = True, time: bool = True, shape=None) -> Scan:
    rng = np.random.default_rng(seed)
    xyz = rng.normal(0, 15, (n, 3)).astype(np.float32)
    xyz[::17] = 0.0
    return Scan(
        xyz=xyz,
        intensity=rng.uniform(0, 1, n).astype(np.float32),
        ring=rng.integers(0, 64, n).astype(np.int16) if ring else None,
        time=rng.uniform(0, 0.1, n).astype(np.float32) if time else None,
        shape=shape,
    )


def assert_same_points(a: Scan, b: Scan, ring: bool = True, time: bool = True) -> None:
    np.testing.assert_array_equal(a.xyz, b.xyz)
    np.testing.assert_array_equal(a.intensity, b.intensity)
    if ring:
        np.testing.assert_array_equal(a.ring, b.ring)
    if time:
        np.testing.assert_array_equal(a.time, b.time)


def test_registry_lists_formats() -> None:
    assert set(SCAN_READERS) == {"kitti", "nclt", "pcd", "ply", "npy", "npz"}
    assert set(SCAN_WRITERS) == {"kitti", "pcd", "ply", "npz"}


def test_kitti_round_trip_and_size_check(tmp_path: Path) -> None:
    scan = make_scan()
    path = tmp_path / "000000.bin"
    write_scan(path, scan)
    back = read_scan(path)
    assert_same_points(scan, back, ring=False, time=False)
    assert back.sensor.intensity_max == 1.0 and back.source == str(path)
    path.write_bytes(path.read_bytes()[:-3])
    with pytest.raises(ScanFormatError, match=r"000000\.bin.*multiple of the KITTI record size 16"):
        read_scan(path)


def test_kitti_organised_layouts(tmp_path: Path) -> None:
    rows, cols = 4, 6
    img = np.arange(rows * cols * 4, dtype=np.float32).reshape(rows, cols, 4)  # row-major image
    col_major = tmp_path / "cm.bin"
    img.transpose(1, 0, 2).astype("<f4").tofile(col_major)
    s = read_scan(col_major, organized=True, layout=(rows, cols, "column-major"))
    assert s.shape == (rows, cols)
    np.testing.assert_array_equal(s.organized("xyz"), img[..., :3])
    np.testing.assert_array_equal(s.organized("ring")[:, 0], np.arange(rows))
    row_major = tmp_path / "rm.bin"
    img.astype("<f4").tofile(row_major)
    s2 = read_scan(row_major, organized=True, layout=(rows, cols))
    np.testing.assert_array_equal(s2.xyz, s.xyz)
    flat = read_scan(col_major, layout=(rows, cols, "column-major"))
    assert flat.shape is None and flat.ring is not None
    with pytest.raises(ScanFormatError, match="organised 5 x 6"):
        read_scan(col_major, organized=True, layout=(5, 6, "column-major"))
    with pytest.raises(ConfigError):
        read_scan(col_major, organized=True, layout=(4, 6, "diagonal"))
    with pytest.raises(ConfigError, match="does not take"):
        read_scan(col_major, colour="red")


def test_nclt_decoding(tmp_path: Path) -> None:
    xyz_m = np.array([[0.0, 0.0, 0.0], [-100.0, 27.5, 3.125], [10.0, -20.0, 0.005]])
    raw = np.round((xyz_m + 100.0) / 0.005).astype("<u2")
    rec = np.zeros(3, dtype=[("x", "<u2"), ("y", "<u2"), ("z", "<u2"), ("i", "u1"), ("l", "u1")])
    rec["x"], rec["y"], rec["z"] = raw.T
    rec["i"] = [0, 128, 255]
    rec["l"] = [0, 31, 7]
    path = tmp_path / "1.bin"
    rec.tofile(path)
    s = read_scan(path, format="nclt")
    np.testing.assert_allclose(s.xyz, xyz_m, atol=1e-4)
    np.testing.assert_array_equal(s.intensity, [0, 128, 255])
    np.testing.assert_array_equal(s.ring, [0, 31, 7])
    assert s.sensor.intensity_max == 255 and len(s.sensor.beam_elevations_deg) == 32
    assert HDL32E_ELEVATIONS_DEG[0] == -30.67 and HDL32E_ELEVATIONS_DEG[1] == -9.33
    assert HDL32E_ELEVATIONS_DEG[31] == pytest.approx(10.67, abs=0.01)
    rec["l"][1] = 40
    rec.tofile(path)
    with pytest.raises(ScanFormatError, match="laser id 40"):
        read_scan(path, format="nclt")
    path.write_bytes(path.read_bytes() + b"\x00")
    with pytest.raises(ScanFormatError, match="record size 8"):
        read_scan(path, format="nclt")


@pytest.mark.parametrize("data", ["binary", "binary_compressed", "ascii"])
def test_pcd_round_trip(tmp_path: Path, data: str) -> None:
    scan = make_scan(700)
    path = tmp_path / "a.pcd"
    write_scan(path, scan, data=data)
    assert f"DATA {data}".encode() in path.read_bytes()[:400]
    assert_same_points(scan, read_scan(path))


def test_pcd_organised_nan_and_empty(tmp_path: Path) -> None:
    scan = make_scan(24, shape=(4, 6))
    xyz = scan.xyz.copy()
    xyz[5] = np.nan
    scan = Scan(xyz=xyz, intensity=scan.intensity, ring=scan.ring, time=scan.time, shape=(4, 6))
    path = tmp_path / "o.pcd"
    write_pcd(path, scan, "binary_compressed")
    org = read_scan(path, organized=True)
    assert org.shape == (4, 6) and np.all(org.xyz[5] == 0)
    flat = read_scan(path)
    assert flat.shape is None and np.isnan(flat.xyz[5]).all()  # readers never drop NaN points
    empty = Scan(xyz=np.zeros((0, 3)), intensity=np.zeros(0))
    for d in ("binary", "binary_compressed", "ascii"):
        write_pcd(tmp_path / "e.pcd", empty, d)
        assert len(read_scan(tmp_path / "e.pcd")) == 0


def _pcd_bytes(
    fields, sizes, types, counts, rows: np.ndarray, data: str = "binary", width=None, height=1, points=None
) -> bytes:
    n = rows.shape[0]
    head = (
        f"VERSION 0.7\nFIELDS {' '.join(fields)}\nSIZE {' '.join(map(str, sizes))}\n"
        f"TYPE {' '.join(types)}\nCOUNT {' '.join(map(str, counts))}\nWIDTH {width or n}\nHEIGHT {height}\n"
        f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n if points is None else points}\nDATA {data}\n"
    )
    return head.encode() + (rows.tobytes() if data == "binary" else b"")


def test_pcd_field_order_types_and_names(tmp_path: Path) -> None:
    n = 50
    rng = np.random.default_rng(1)
    dt = np.dtype(
        [
            ("reflectivity", "<u2"),
            ("_", "u1", (3,)),
            ("z", "<f8"),
            ("ring", "<u1"),
            ("y", "<f4"),
            ("x", "<f4"),
            ("t", "<u4"),
            ("normal", "<f4", (3,)),
        ]
    )
    rows = np.zeros(n, dtype=dt)
    rows["x"], rows["y"], rows["z"] = rng.normal(size=(3, n))
    rows["reflectivity"] = rng.integers(0, 65535, n)
    rows["ring"] = rng.integers(0, 128, n)
    rows["t"] = rng.integers(0, 10**8, n)
    path = tmp_path / "f.pcd"
    path.write_bytes(
        _pcd_bytes(
            ["reflectivity", "_", "z", "ring", "y", "x", "t", "normal"],
            [2, 1, 8, 1, 4, 4, 4, 4],
            ["U", "U", "F", "U", "F", "F", "U", "F"],
            [1, 3, 1, 1, 1, 1, 1, 3],
            rows,
        )
    )
    s = read_scan(path)
    np.testing.assert_allclose(s.xyz, np.stack([rows["x"], rows["y"], rows["z"]], 1).astype(np.float32))
    np.testing.assert_array_equal(s.intensity, rows["reflectivity"])
    np.testing.assert_array_equal(s.ring, rows["ring"])
    np.testing.assert_allclose(s.time, rows["t"] * 1e-9, rtol=1e-6)
    assert s.sensor.intensity_max == 65535
    # 'i' as the intensity name, ascii data with nan/inf
    text = _pcd_bytes(["x", "y", "z", "i"], [4] * 4, ["F"] * 4, [1] * 4, np.zeros((3, 4)), data="ascii")
    path.write_bytes(text + b"1 2 3 4\nnan nan nan 0\n1e3 inf -2 0.5\n")
    s = read_scan(path)
    np.testing.assert_array_equal(s.intensity, [4, 0, 0.5])
    assert np.isnan(s.xyz[1]).all() and np.isinf(s.xyz[2, 1])


@pytest.mark.parametrize(
    "mutation, message",
    [
        (dict(points=99), "POINTS 99"),
        (dict(width=7, height=2, points=14), "expected 224"),
        (dict(types=["F", "F", "F", "Q"]), "unsupported TYPE Q"),
        (dict(sizes=[4, 4, 4, 2]), "unsupported TYPE F SIZE 2"),
        (dict(counts=[1, 1, 1]), "must match"),
        (dict(data="binary_lz4"), "not supported"),
    ],
)
def test_pcd_lying_headers(tmp_path: Path, mutation: dict, message: str) -> None:
    kw = dict(
        fields=["x", "y", "z", "intensity"],
        sizes=[4, 4, 4, 4],
        types=["F", "F", "F", "F"],
        counts=[1, 1, 1, 1],
        rows=np.zeros((10, 4), np.float32),
    )
    kw.update(mutation)
    path = tmp_path / "bad.pcd"
    path.write_bytes(_pcd_bytes(**kw))
    with pytest.raises(ScanFormatError, match=message) as err:
        read_scan(path)
    assert "bad.pcd" in str(err.value)


def test_pcd_reads_open3d_compressed_output(tmp_path: Path) -> None:
    """Cross-check our LZF decoder on binary_compressed files written by open3d (PCL-compatible liblzf)."""
    o3d = pytest.importorskip("open3d")
    rng = np.random.default_rng(2)
    pts = np.round(rng.normal(0, 10, (3000, 3)), 1)  # repetitive values give real back-references
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    path = tmp_path / "o3d.pcd"
    assert o3d.io.write_point_cloud(str(path), pcd, write_ascii=False, compressed=True)
    assert b"binary_compressed" in path.read_bytes()[:300]
    s = read_scan(path)
    np.testing.assert_allclose(s.xyz, pts.astype(np.float32), atol=1e-6)


@pytest.mark.parametrize("endian", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_ply_formats(tmp_path: Path, endian: str) -> None:
    rng = np.random.default_rng(3)
    n = 40
    e = ">" if endian.endswith("big_endian") else "<"
    dt = np.dtype(
        [
            ("x", e + "f4"),
            ("y", e + "f4"),
            ("z", e + "f8"),
            ("scalar_Intensity", e + "u2"),
            ("ring", e + "u1"),
        ]
    )
    v = np.zeros(n, dtype=dt)
    v["x"], v["y"], v["z"] = rng.normal(size=(3, n)).round(3)
    v["scalar_Intensity"] = rng.integers(0, 3000, n)
    v["ring"] = rng.integers(0, 16, n)
    head = (
        f"ply\nformat {endian} 1.0\ncomment test\nelement camera 1\nproperty float fx\n"
        f"element vertex {n}\nproperty float x\nproperty float y\nproperty double z\n"
        "property ushort scalar_Intensity\nproperty uchar ring\nelement face 1\n"
        "property list uchar int vertex_indices\nend_header\n"
    )
    if endian == "ascii":
        lines = "\n".join(
            " ".join(repr(float(r[k])) if k < 3 else str(int(r[k])) for k in range(5)) for r in v
        )
        body = b"1.5\n" + lines.encode() + b"\n3 0 1 2\n"
    else:
        body = (
            np.array([1.5], e + "f4").tobytes()
            + v.tobytes()
            + b"\x03"
            + np.array([0, 1, 2], e + "i4").tobytes()
        )
    path = tmp_path / "c.ply"
    path.write_bytes(head.encode() + body)
    s = read_scan(path)
    np.testing.assert_allclose(s.xyz, np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float32))
    np.testing.assert_array_equal(s.intensity, v["scalar_Intensity"])
    np.testing.assert_array_equal(s.ring, v["ring"])


def test_ply_writer_round_trip_and_errors(tmp_path: Path) -> None:
    scan = make_scan(300)
    path = tmp_path / "w.ply"
    write_scan(path, scan)
    assert_same_points(scan, read_scan(path))
    path.write_bytes(path.read_bytes()[:-10])
    with pytest.raises(ScanFormatError, match="truncated"):
        read_scan(path)
    path.write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty list uchar int x\nend_header\n"
    )
    with pytest.raises(ScanFormatError, match="list properties"):
        read_scan(path)
    path.write_bytes(
        b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n1 2\n"
    )
    with pytest.raises(ScanFormatError, match=r"no field\(s\) \['z'\]"):
        read_scan(path)


def test_npy_variants(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    a4 = rng.normal(size=(30, 4)).astype(np.float32)
    np.save(tmp_path / "a4.npy", a4)
    s = read_scan(tmp_path / "a4.npy")
    np.testing.assert_array_equal(s.xyz, a4[:, :3])
    np.testing.assert_array_equal(s.intensity, a4[:, 3])
    np.save(tmp_path / "a3.npy", a4[:, :3].astype(np.float64))
    assert np.all(read_scan(tmp_path / "a3.npy").intensity == 0)
    np.save(tmp_path / "img.npy", a4.reshape(5, 6, 4))
    assert read_scan(tmp_path / "img.npy", organized=True).shape == (5, 6)
    st = np.zeros(30, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("intensity", "u1"), ("ring", "u2")])
    st["x"] = a4[:, 0]
    st["intensity"] = 200
    st["ring"] = 7
    np.save(tmp_path / "st.npy", st)
    s = read_scan(tmp_path / "st.npy")
    assert s.sensor.intensity_max == 255 and np.all(s.ring == 7) and np.all(s.intensity == 200)
    np.save(tmp_path / "bad.npy", a4[:, :2])
    with pytest.raises(ScanFormatError, match=r"\(30, 2\)"):
        read_scan(tmp_path / "bad.npy")
    np.save(tmp_path / "obj.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(ScanFormatError, match="objects"):
        read_scan(tmp_path / "obj.npy")


def test_npz_round_trip(tmp_path: Path) -> None:
    sensor = SensorInfo(name="sim", beam_elevations_deg=(2.0, 0.0, -2.0), columns=8, intensity_max=255.0)
    base = make_scan(24, shape=(3, 8))
    scan = Scan(
        xyz=base.xyz,
        intensity=base.intensity,
        ring=base.ring,
        time=base.time,
        shape=(3, 8),
        sensor=sensor,
        timestamp=12.5,
    )
    write_scan(tmp_path / "s.npz", scan)
    back = read_scan(tmp_path / "s.npz", organized=True)
    assert_same_points(scan, back)
    assert back.shape == (3, 8) and back.sensor == sensor and back.timestamp == 12.5
    assert read_scan(tmp_path / "s.npz").shape is None
    np.savez(tmp_path / "min.npz", xyz=np.ones((5, 3)))
    assert len(read_scan(tmp_path / "min.npz")) == 5
    np.savez(tmp_path / "noxyz.npz", points=np.ones((5, 3)))
    with pytest.raises(ScanFormatError, match="no 'xyz'"):
        read_scan(tmp_path / "noxyz.npz")
    np.savez(tmp_path / "mism.npz", xyz=np.ones((5, 3)), intensity=np.ones(4))
    with pytest.raises(ScanFormatError, match="intensity"):
        read_scan(tmp_path / "mism.npz")


def test_missing_and_empty_files(tmp_path: Path) -> None:
    for fmt, suffix in [
        ("kitti", ".bin"),
        ("nclt", ".bin"),
        ("pcd", ".pcd"),
        ("ply", ".ply"),
        ("npy", ".npy"),
        ("npz", ".npz"),
    ]:
        with pytest.raises(ScanFormatError, match="no such"):
            read_scan(tmp_path / f"missing{suffix}", format=fmt)
        (tmp_path / f"empty{suffix}").write_bytes(b"")
        with pytest.raises(ScanFormatError, match="empty"):
            read_scan(tmp_path / f"empty{suffix}", format=fmt)
    with pytest.raises(ScanFormatError, match="suffix"):
        read_scan(tmp_path / "x.xyz")
    with pytest.raises(ConfigError, match="unknown scan format"):
        read_scan(tmp_path / "x.bin", format="las")


def test_writes_are_atomic(tmp_path: Path) -> None:
    path = tmp_path / "keep.pcd"
    write_scan(path, make_scan(10))
    before = path.read_bytes()
    with pytest.raises(ConfigError):
        write_scan(path, make_scan(10), data="zip")
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["keep.pcd"]


def test_lzf_round_trip_and_known_stream() -> None:
    rng = np.random.default_rng(5)
    samples = [
        b"",
        b"x",
        b"abcabcabcabcabcabc",
        bytes(9000),
        rng.bytes(5000),
        np.repeat(rng.integers(0, 4, 3000, dtype=np.uint8), 5).tobytes(),
        (rng.bytes(100) + bytes(3000)) * 7,
    ]
    for data in samples:
        comp = lzf_compress(data)
        assert lzf_decompress(comp, len(data)) == data
    assert len(lzf_compress(bytes(100_000))) < 2000
    # hand-made stream: literal "abcd", back-reference distance 4 length 10 (overlapping), literal "!"
    stream = bytes([3]) + b"abcd" + bytes([(7 << 5) | 0, 10 - 2 - 7, 3]) + bytes([0]) + b"!"
    assert lzf_decompress(stream, 15) == b"abcd" + b"abcdabcdab" + b"!"
    with pytest.raises(LZFError):
        lzf_decompress(stream, 16)
    with pytest.raises(LZFError):
        lzf_decompress(bytes([(1 << 5), 200]), 3)  # reference before the start
    with pytest.raises(LZFError):
        lzf_decompress(b"\x1f" + b"a" * 5, 32)  # literal past the end of the input


def test_binary_compressed_header_checks(tmp_path: Path) -> None:
    path = tmp_path / "c.pcd"
    write_pcd(path, make_scan(100), "binary_compressed")
    buf = path.read_bytes()
    off = buf.index(b"DATA binary_compressed\n") + len(b"DATA binary_compressed\n")
    comp, raw = struct.unpack_from("<II", buf, off)
    path.write_bytes(buf[:off] + struct.pack("<II", comp, raw + 4) + buf[off + 8 :])
    with pytest.raises(ScanFormatError, match="uncompressed size"):
        read_scan(path)
    path.write_bytes(buf[:-5])
    with pytest.raises(ScanFormatError, match="truncated"):
        read_scan(path)


def _reference_lzf_decode(src: bytes) -> bytes:
    """Byte-at-a-time decoder straight from the liblzf format description."""
    out = bytearray()
    ip = 0
    while ip < len(src):
        c = src[ip]
        ip += 1
        if c < 32:
            out += src[ip : ip + c + 1]
            ip += c + 1
        else:
            ln = c >> 5
            if ln == 7:
                ln += src[ip]
                ip += 1
            d = ((c & 31) << 8 | src[ip]) + 1
            ip += 1
            for _ in range(ln + 2):
                out.append(out[-d])
    return bytes(out)


def test_lzf_decoder_matches_reference_on_random_streams() -> None:
    """Streams with arbitrary distances, overlaps and chained references, unlike our own compressor's output."""
    rng = np.random.default_rng(6)
    for _ in range(300):
        stream, size = bytearray(), 0
        for _ in range(int(rng.integers(1, 300))):
            if size == 0 or rng.random() < 0.4:
                n = int(rng.integers(1, 33))
                stream += bytes([n - 1]) + rng.bytes(n)
                size += n
            else:
                d = (
                    int(rng.integers(1, min(size, 8192) + 1))
                    if rng.random() < 0.7
                    else int(rng.integers(1, 4))
                )
                d = min(d, size)
                n = int(rng.choice([3, 8, 9, 264])) if rng.random() < 0.5 else int(rng.integers(3, 265))
                off, code = d - 1, n - 2
                stream += (
                    bytes([code << 5 | off >> 8, off & 255])
                    if code < 7
                    else bytes([224 | off >> 8, code - 7, off & 255])
                )
                size += n
        assert lzf_decompress(bytes(stream), size) == _reference_lzf_decode(bytes(stream))


def test_import_is_light() -> None:
    """placerec.io must not import the optional or heavy packages at import time."""
    import subprocess
    import sys

    code = (
        "import sys, placerec.io; heavy = [m for m in ('ouster', 'rosbags', 'open3d', 'scipy.spatial') "
        "if m in sys.modules]; print(heavy)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
