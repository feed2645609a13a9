"""Readers: every format of the scan registry (`placerec.io.registry.SCAN_READERS`) fed empty, missing,
truncated, lying, huge (sparse), wrong-magic, NaN/inf, directory, FIFO, unreadable and non-UTF-8-named files."""

from __future__ import annotations

import functools
import io
import struct
import tempfile
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from fuzz.corpus import Case
from fuzz.files import fifo, non_utf8, sparse, unreadable
from placerec.errors import ScanFormatError
from placerec.io import read_scan
from placerec.io.registry import SCAN_READERS
from placerec.types import Scan

N = 32  # points of every valid sample
SUFFIX = {"kitti": ".bin", "nclt": ".bin", "pcd": ".pcd", "ply": ".ply", "npy": ".npy", "npz": ".npz"}


def _scan() -> Scan:
    rng = np.random.default_rng(0)
    xyz = np.round(rng.uniform(-20, 20, (N, 3)), 3).astype(np.float32)
    return Scan(xyz=xyz, intensity=rng.integers(0, 255, N).astype(np.float32))


def _write(fmt: str, scan: Scan, **options: Any) -> bytes:
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / f"x{SUFFIX[fmt]}"
        if fmt == "nclt":
            rec = np.zeros(N, dtype=[("x", "<u2"), ("y", "<u2"), ("z", "<u2"), ("i", "u1"), ("l", "u1")])
            rec["x"], rec["y"], rec["z"] = 40000 + np.arange(N) * 50, 40000, 40000
            rec["i"], rec["l"] = np.arange(N), np.arange(N) % 32
            return rec.tobytes()
        if fmt == "npy":
            buf = io.BytesIO()
            np.save(buf, np.c_[scan.xyz, scan.intensity].astype(np.float32))
            return buf.getvalue()
        from placerec.io import write_scan

        write_scan(path, scan, format=fmt, **options)
        return path.read_bytes()


@functools.cache
def valid(fmt: str, variant: str = "") -> bytes:
    """A valid file of ``fmt`` with `N` points (``variant``: "ascii" PCD, "nan" / "inf" points in rows 3 and 7)."""
    scan = _scan()
    if variant in ("nan", "inf"):
        xyz = scan.xyz.copy()
        xyz[3] = np.nan if variant == "nan" else np.inf
        xyz[7, 1] = np.nan if variant == "nan" else -np.inf
        scan = Scan(xyz=xyz, intensity=scan.intensity)
    options = {"data": "ascii"} if variant == "ascii" else {}
    return _write(fmt, scan, **options)


def _npy_header(shape: tuple[int, ...], descr: str = "<f4") -> bytes:
    d = repr({"descr": descr, "fortran_order": False, "shape": shape}).encode()
    pad = 64 - (10 + len(d) + 1) % 64
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(d) + pad + 1) + d + b" " * pad + b"\n"


def _npz_with(member: str, blob: bytes) -> bytes:
    """The valid ``.npz`` with ``member`` replaced by ``blob`` (added when absent)."""
    members: dict[str, bytes] = {}
    with zipfile.ZipFile(io.BytesIO(valid("npz"))) as zf:
        members = {i.filename: zf.read(i) for i in zf.infolist()}
    members[member] = blob
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return out.getvalue()


def _header_edit(fmt: str, old: bytes, new: bytes) -> bytes:
    data = valid(fmt)
    assert old in data, (fmt, old)
    return data.replace(old, new, 1)


# ------------------------------------------------------------------------------------------------ the checks
def _scan_of(n: int | tuple[int, ...]) -> Callable[[Any, Any], None]:
    """A check: the result is a consistent `Scan` of ``n`` points (one of ``n`` when a tuple)."""
    allowed = (n,) if isinstance(n, int) else n

    def check(args: Any, scan: Any) -> None:
        assert isinstance(scan, Scan), type(scan)
        assert len(scan) in allowed, (len(scan), allowed)
        assert scan.xyz.shape == (len(scan), 3) and scan.intensity.shape == (len(scan),)

    return check


def _points_kept_or_dropped(bad_rows: int) -> Callable[[Any, Any], None]:
    """NaN / inf points are either kept as they are or dropped, never turned into other finite points."""

    def check(args: Any, scan: Any) -> None:
        _scan_of((N, N - bad_rows))(args, scan)
        good = _scan().xyz
        finite = np.isfinite(scan.xyz).all(axis=1)
        assert finite.sum() == N - bad_rows, finite.sum()
        np.testing.assert_allclose(
            np.sort(scan.xyz[finite], axis=0), np.sort(np.delete(good, [3, 7], axis=0), axis=0), atol=1e-3
        )

    return check


# ------------------------------------------------------------------------------------------------ the cases
def _file(name: str, data: bytes | Callable[[], bytes]) -> Callable[[Path], Path]:
    def build(tmp: Path) -> Path:
        path = tmp / name
        path.write_bytes(data() if callable(data) else data)
        return path

    return build


def _reader(fmt: str, **options: Any) -> Callable[[Path], Scan]:
    return lambda path: read_scan(path, format=fmt, **options)


def _cli(fmt: str) -> Callable[[Path], list[str]]:
    return lambda path: ["info", str(path), "--format", fmt]


def _format_cases(fmt: str) -> list[Case]:
    suffix = SUFFIX[fmt]
    stem = f"hostile_{fmt}"
    read = _reader(fmt)

    def case(name: str, build: Callable[[Path], Any], expect: str = "error", **kw: Any) -> Case:
        kw.setdefault("cli", _cli(fmt))
        return Case("readers", f"{fmt}/{name}", build, kw.pop("run", read), expect, subject=fmt, **kw)

    good = valid(fmt)
    cases = [
        case("valid", _file(stem + suffix, good), "ok", check=_scan_of(N), fast=True),
        case("empty", _file(stem + suffix, b""), error=ScanFormatError),
        case("missing", lambda tmp: tmp / f"absent{suffix}", error=ScanFormatError),
        case("directory", lambda tmp: _mkdir(tmp / f"folder{suffix}"), cli=None, error=ScanFormatError),
        case("fifo", lambda tmp: fifo(tmp / f"pipe{suffix}"), error=ScanFormatError),
        case("sparse-1e12-bytes", lambda tmp: sparse(tmp / f"huge{suffix}", 10**12, good[:200])),
        case("sparse-2GiB", lambda tmp: sparse(tmp / f"big{suffix}", 2 << 30, good[:200])),
        case(
            "permission-denied",
            _file(f"locked{suffix}", good),
            run=unreadable(read),
            cli=None,
            error=ScanFormatError,
        ),
        case(
            "non-utf8-name-valid",
            lambda tmp: _write_to(non_utf8(tmp, b"scan\xff\xfe", suffix), good),
            "ok",
            check=_scan_of(N),
        ),
        case(
            "non-utf8-name-empty",
            lambda tmp: non_utf8(tmp, b"bad\xff", suffix),
            names=lambda p: p.name,
            error=ScanFormatError,
        ),
        case("one-byte", _file(stem + suffix, good[:1]), error=ScanFormatError),
        case("last-byte-cut", _file(stem + suffix, good[:-1]), error=ScanFormatError),
    ]
    for frac in (3, 2):
        cut = len(good) // frac
        if fmt == "kitti":
            cut -= cut % 16 == 0  # a whole number of records would be a valid, shorter scan
        if fmt == "nclt":
            cut -= cut % 8 == 0
        cases.append(case(f"truncated-1/{frac}", _file(stem + suffix, good[:cut]), error=ScanFormatError))
    text = b"hello, world\n"  # 13 bytes: no format's magic, no whole number of KITTI or NCLT records
    cases.append(case("text-file", _file(stem + suffix, text), error=ScanFormatError))
    others = {".bin": "pcd", ".pcd": "ply", ".ply": "pcd", ".npy": "npz", ".npz": "npy"}
    other = valid(others[suffix])
    if fmt == "nclt":
        other = other[: len(other) - len(other) % 8 - 1]
    cases.append(case(f"holds-{others[suffix]}", _file(stem + suffix, other), error=ScanFormatError))
    if fmt != "nclt":  # NCLT stores integers
        for bad in ("nan", "inf"):
            cases.append(
                case(
                    f"{bad}-points",
                    _file(stem + suffix, functools.partial(valid, fmt, bad)),
                    "ok",
                    check=_points_kept_or_dropped(2),
                )
            )
    cases.extend(_lies(fmt, case, stem + suffix))
    return cases


def _mkdir(path: Path) -> Path:
    path.mkdir()
    return path


def _write_to(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def _lies(fmt: str, case: Callable[..., Case], name: str) -> list[Case]:
    """Headers that lie about counts and shapes: more points than stored, negative, huge."""
    out: list[Case] = []
    err = {"error": ScanFormatError}
    if fmt == "kitti":
        for layout in ((64, 1024, "column-major"), (-4, -8), (0, 32), (10**9, 10**9)):
            out.append(
                case(
                    f"layout-{'x'.join(str(v) for v in layout[:2])}",
                    _file(name, valid(fmt)),
                    run=_reader(fmt, layout=layout),
                    cli=None,
                    names="layout" if min(layout[:2]) <= 0 else None,
                )
            )
        out.append(case("layout-32x1", _file(name, valid(fmt)), "ok", run=_reader(fmt, layout=(32, 1)),
                        check=_scan_of(N), cli=None))  # fmt: skip
    if fmt == "pcd":
        for variant in ("", "ascii"):
            tag = variant or "binary"
            for key, old, new in (
                ("points-2n", b"POINTS 32\n", b"POINTS 64\n"),
                ("points-1e12", b"POINTS 32\n", b"POINTS 1000000000000\n"),
                ("points-negative", b"POINTS 32\n", b"POINTS -32\n"),
                ("width-negative", b"WIDTH 32\n", b"WIDTH -32\n"),
                ("width-2n", b"WIDTH 32\n", b"WIDTH 64\n"),
                ("height-1e9", b"HEIGHT 1\n", b"HEIGHT 1000000000\n"),
                ("size-0", b"SIZE 4 4 4 4\n", b"SIZE 0 4 4 4\n"),
                ("size-negative", b"SIZE 4 4 4 4\n", b"SIZE -4 4 4 4\n"),
                ("count-1e9", b"COUNT 1 1 1 1\n", b"COUNT 1000000000 1 1 1\n"),
                ("count-0", b"COUNT 1 1 1 1\n", b"COUNT 0 1 1 1\n"),
                ("fields-short", b"FIELDS x y z intensity\n", b"FIELDS x y z\n"),
                ("type-unknown", b"TYPE F F F F\n", b"TYPE Q F F F\n"),
                ("data-unknown", f"DATA {tag}\n".encode(), b"DATA zipped\n"),
            ):
                data = valid(fmt, variant).replace(old, new, 1)
                out.append(case(f"{tag}-{key}", _file(name, data), **err))
        out.append(
            case("compressed-sizes-lie", _file(name, _compressed_pcd_lie()), **err),
        )
    if fmt == "ply":
        for key, new in (
            ("vertex-2n", b"element vertex 64\n"),
            ("vertex-1e12", b"element vertex 1000000000000\n"),
            ("vertex-negative", b"element vertex -3\n"),
            ("vertex-text", b"element vertex many\n"),
        ):
            out.append(case(key, _file(name, _header_edit(fmt, b"element vertex 32\n", new)), **err))
        out.append(
            case(
                "property-list",
                _file(name, _header_edit(fmt, b"property float x\n", b"property list uchar int x\n")),
                **err,
            )
        )
        out.append(
            case("no-end-header", _file(name, _header_edit(fmt, b"end_header\n", b"end_heade\n")), **err)
        )
        out.append(case("format-unknown", _file(name, _header_edit(fmt, b"binary_little_endian", b"binary_middle_endian")), **err))  # fmt: skip
    if fmt == "npy":
        body = valid(fmt)[128:]
        for key, shape in (
            ("shape-2n", (64, 4)),
            ("shape-1e12", (10**12, 4)),
            ("shape-negative", (-1, 4)),
            ("shape-negative-cols", (32, -4)),
            ("shape-columns-2", (64, 2)),
            ("shape-scalar", ()),
        ):
            out.append(case(key, _file(name, _npy_header(shape) + body), **err))
        out.append(
            case("shape-organised", _file(name, _npy_header((2, 16, 4)) + body), "ok", check=_scan_of(N))
        )
        out.append(case("dtype-object", _file(name, _npy_header((32, 4), "|O") + body), **err))
        out.append(case("dtype-complex", _file(name, _npy_header((16, 4), "<c8") + body), **err))
        out.append(
            case("header-not-dict", _file(name, valid(fmt).replace(b"{'descr'", b"['descr'", 1)), **err)
        )
    if fmt == "npz":
        xyz_body = np.zeros((N, 3), np.float32).tobytes()
        for key, shape in (("xyz-2n", (64, 3)), ("xyz-1e12", (10**12, 3)), ("xyz-negative", (-1, 3))):
            out.append(case(key, _file(name, _npz_with("xyz.npy", _npy_header(shape) + xyz_body)), **err))
        out.append(case("xyz-wrong-width", _file(name, _npz_with("xyz.npy", _npy_header((48, 2)) + xyz_body)), **err))  # fmt: skip
        out.append(case("intensity-short", _file(name, _npz_with("intensity.npy", _npy_header((3,)) + bytes(12))), **err))  # fmt: skip
        out.append(case("sensor-not-json", _file(name, _npz_with("sensor.npy", _npy_header((4,), "|u1") + b"{bad")), **err))  # fmt: skip
        organised = {"run": _reader(fmt, organized=True), "cli": None, **err}
        for key, rows_cols in (
            ("shape-lies", [8, 8]),
            ("shape-negative", [-4, -8]),
            ("shape-three", [2, 4, 4]),
        ):
            blob = _npy_header((len(rows_cols),), "<i8") + np.array(rows_cols, "<i8").tobytes()
            out.append(case(key, _file(name, _npz_with("shape.npy", blob)), **organised))
        out.append(case("pickled-member", _file(name, _npz_with("xyz.npy", _npy_header((1,), "|O") + b"\x80\x04N.")), **err))  # fmt: skip
    if fmt == "nclt":
        out.append(case("odd-record", _file(name, valid(fmt) + b"\x00" * 4), **err))
    return out


def _compressed_pcd_lie() -> bytes:
    """A ``binary_compressed`` PCD whose two size words declare 10^9 compressed and uncompressed bytes."""
    head, _, _ = valid("pcd").partition(b"DATA binary\n")
    return head + b"DATA binary_compressed\n" + struct.pack("<II", 10**9, 10**9) + b"\x00" * 16


def cases() -> list[Case]:
    out: list[Case] = []
    for fmt in SCAN_READERS:
        if fmt not in SUFFIX:  # a new reader: it still needs its cases (tests/test_fuzz_corpus.py says so)
            continue
        out.extend(_format_cases(fmt))
    return out


__all__ = ["cases", "valid", "N", "SUFFIX"]
