"""Integer fields of PCD / PLY files and ring values that do not fit their type are errors, not wrap-arounds."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from placerec.errors import ScanFormatError
from placerec.io import read_scan


def _ascii_pcd(path: Path, ring_type: str, ring_size: int, rings: list[str]) -> Path:
    header = (
        "VERSION 0.7\nFIELDS x y z intensity ring\nSIZE 4 4 4 4 {s}\nTYPE F F F F {t}\nCOUNT 1 1 1 1 1\n"
        "WIDTH {n}\nHEIGHT 1\nPOINTS {n}\nDATA ascii\n"
    ).format(s=ring_size, t=ring_type, n=len(rings))
    body = "".join(f"1 2 3 0.5 {r}\n" for r in rings)
    path.write_text(header + body)
    return path


def _binary_pcd(path: Path, ring_dtype: str, rings: np.ndarray) -> Path:
    kind = {"u": "U", "i": "I", "f": "F"}[np.dtype(ring_dtype).kind]
    size = np.dtype(ring_dtype).itemsize
    n = len(rings)
    header = (
        f"VERSION 0.7\nFIELDS x y z intensity ring\nSIZE 4 4 4 4 {size}\nTYPE F F F F {kind}\nCOUNT 1 1 1 1 1\n"
        f"WIDTH {n}\nHEIGHT 1\nPOINTS {n}\nDATA binary\n"
    )
    rec = np.zeros(
        n, [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("i", "<f4"), ("ring", "<" + ring_dtype[-2:])]
    )
    rec["x"], rec["ring"] = 1.0, rings
    path.write_bytes(header.encode() + rec.tobytes())
    return path


def _ply(path: Path, ring_type: str, rings: list[int], binary: bool = False) -> Path:
    fmt = "binary_little_endian" if binary else "ascii"
    header = (
        f"ply\nformat {fmt} 1.0\nelement vertex {len(rings)}\nproperty float x\nproperty float y\n"
        f"property float z\nproperty {ring_type} ring\nend_header\n"
    )
    if binary:
        np_type = {"uchar": "u1", "ushort": "<u2", "uint": "<u4", "int": "<i4"}[ring_type]
        rec = np.zeros(len(rings), [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("ring", np_type)])
        rec["x"], rec["ring"] = 1.0, rings
        path.write_bytes(header.encode() + rec.tobytes())
    else:
        path.write_text(header + "".join(f"1 2 3 {r}\n" for r in rings))
    return path


@pytest.mark.parametrize(
    "ring_type, size, value, expected",
    [
        ("U", 1, "300", r"'ring'.* holds 300 .*uint8 integers in 0\.\.255"),
        ("U", 2, "-1", r"'ring'.* holds -1 .*uint16 integers in 0\.\.65535"),
        ("I", 1, "1.5", r"'ring'.* holds 1\.5 .*int8"),
        ("I", 4, "70000", r"ring field 'ring' \(int32\) holds 70000 .*int16 integers in -32768\.\.32767"),
    ],
)
def test_ascii_pcd_integers_out_of_range(tmp_path, ring_type, size, value, expected):
    path = _ascii_pcd(tmp_path / "a.pcd", ring_type, size, ["3", value])
    with pytest.raises(ScanFormatError, match=r"a\.pcd: .*" + expected):
        read_scan(path)


def test_ascii_pcd_integers_at_the_type_limits_are_kept(tmp_path):
    s = read_scan(_ascii_pcd(tmp_path / "ok.pcd", "U", 1, ["0", "255"]))
    assert s.ring.tolist() == [0, 255]
    s = read_scan(_ascii_pcd(tmp_path / "ok2.pcd", "I", 4, ["-32768", "32767"]))
    assert s.ring.tolist() == [-32768, 32767]


@pytest.mark.parametrize(
    "dtype, value", [("<u2", 40000), ("<i4", 70000), ("<i4", -40000), ("<f4", 3.5), ("<f4", np.nan)]
)
def test_binary_pcd_ring_that_does_not_fit_int16(tmp_path, dtype, value):
    path = _binary_pcd(tmp_path / "b.pcd", dtype, np.array([1, value], dtype=dtype))
    with pytest.raises(ScanFormatError, match=r"b\.pcd: ring field 'ring'"):
        read_scan(path)


def test_binary_pcd_rings_that_fit_are_read(tmp_path):
    assert read_scan(_binary_pcd(tmp_path / "u2.pcd", "<u2", np.array([0, 63], "<u2"))).ring.tolist() == [
        0,
        63,
    ]
    assert read_scan(_binary_pcd(tmp_path / "f4.pcd", "<f4", np.array([0, 31], "<f4"))).ring.tolist() == [
        0,
        31,
    ]


@pytest.mark.parametrize("binary", [False, True])
def test_ply_ring_overflow(tmp_path, binary):
    if binary:
        path = _ply(tmp_path / "r.ply", "uint", [5, 70000], binary=True)
        expected = r"r\.ply: ring field 'ring' \(uint32\) holds 70000"
    else:
        path = _ply(tmp_path / "r.ply", "uchar", [5, 256])
        expected = r"r\.ply: PLY ascii integer property 'ring' holds 256 .*uint8 integers in 0\.\.255"
    with pytest.raises(ScanFormatError, match=expected):
        read_scan(path)
    ok = _ply(tmp_path / "ok.ply", "ushort", [5, 127], binary=binary)
    assert read_scan(ok).ring.tolist() == [5, 127]
