"""Property tests: truncated or garbled files give a valid result or ScanFormatError, never another exception."""

from __future__ import annotations

import io
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from placerec.errors import ScanFormatError
from placerec.io import read_poses, read_scan
from placerec.io.kitti import write_kitti_bin
from placerec.io.numpy_io import write_npz
from placerec.io.pcd import write_pcd
from placerec.io.ply import write_ply
from placerec.types import Scan

N = 48


def _scan() -> Scan:
    rng = np.random.default_rng(0)
    xyz = np.round(rng.normal(0, 10, (N, 3)), 2)
    xyz[3] = np.nan  # readers must live with NaN points
    return Scan(
        xyz=xyz,
        intensity=rng.integers(0, 255, N),
        ring=rng.integers(0, 32, N),
        time=np.linspace(0, 0.1, N),
        shape=(4, 12),
    )


def _via(writer: Callable[[Path, Scan], None], suffix: str) -> bytes:
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / f"x{suffix}"
        writer(p, _scan())
        return p.read_bytes()


def _nclt() -> bytes:
    rec = np.zeros(N, dtype=[("x", "<u2"), ("y", "<u2"), ("z", "<u2"), ("i", "u1"), ("l", "u1")])
    rec["x"] = np.arange(N) * 100
    rec["l"] = np.arange(N) % 32
    return rec.tobytes()


def _npy() -> bytes:
    bio = io.BytesIO()
    np.save(bio, np.hstack([_scan().xyz, _scan().intensity[:, None]]))
    return bio.getvalue()


def _ply_ascii() -> bytes:
    s = _scan()
    head = (
        f"ply\nformat ascii 1.0\nelement vertex {N}\nproperty float x\nproperty float y\nproperty float z\n"
        "property uchar intensity\nend_header\n"
    )
    rows = "".join(f"{x} {y} {z} {int(i)}\n" for (x, y, z), i in zip(s.xyz, s.intensity, strict=True))
    return (head + rows).encode()


def _poses(fmt: str) -> bytes:
    rng = np.random.default_rng(1)
    if fmt == "kitti":  # rigid motions: random rotations and translations, 7 significant digits
        from scipy.spatial.transform import Rotation

        R = Rotation.random(6, random_state=1).as_matrix()
        rows = np.concatenate([R, rng.normal(size=(6, 3, 1)) * 10], axis=2).reshape(6, 12)
        return "".join(" ".join(f"{v:.6e}" for v in row) + "\n" for row in rows).encode()
    return "".join(
        f"{k * 0.1:.3f} " + " ".join(f"{v:.5f}" for v in rng.normal(size=7)) + "\n" for k in range(6)
    ).encode()


SAMPLES: dict[str, tuple[Callable[[], bytes], str, str | None]] = {
    "kitti": (lambda: _via(write_kitti_bin, ".bin"), ".bin", "kitti"),
    "nclt": (_nclt, ".bin", "nclt"),
    "pcd_ascii": (lambda: _via(lambda p, s: write_pcd(p, s, "ascii"), ".pcd"), ".pcd", None),
    "pcd_binary": (lambda: _via(lambda p, s: write_pcd(p, s, "binary"), ".pcd"), ".pcd", None),
    "pcd_binary_compressed": (
        lambda: _via(lambda p, s: write_pcd(p, s, "binary_compressed"), ".pcd"),
        ".pcd",
        None,
    ),
    "ply_ascii": (_ply_ascii, ".ply", None),
    "ply_binary": (lambda: _via(write_ply, ".ply"), ".ply", None),
    "npy": (_npy, ".npy", None),
    "npz": (lambda: _via(write_npz, ".npz"), ".npz", None),
    "poses_kitti": (lambda: _poses("kitti"), ".txt", "poses"),
    "poses_tum": (lambda: _poses("tum"), ".txt", "poses"),
}
_CACHE: dict[str, bytes] = {}


def _valid(name: str) -> bytes:
    if name not in _CACHE:
        _CACHE[name] = SAMPLES[name][0]()
    return _CACHE[name]


@st.composite
def mutated(draw: st.DrawFn, valid: bytes) -> bytes:
    kind = draw(st.sampled_from(["truncate", "flip_header", "flip_any", "delete"]))
    data = bytearray(valid)
    if kind == "truncate":
        return bytes(data[: draw(st.integers(0, len(data) - 1))])
    if kind == "delete":
        a = draw(st.integers(0, min(len(data), 400) - 1))
        b = draw(st.integers(a + 1, min(len(data), a + 40)))
        return bytes(data[:a] + data[b:])
    limit = min(len(data), 400) if kind == "flip_header" else len(data)
    for _ in range(draw(st.integers(1, 6))):
        pos = draw(st.integers(0, limit - 1))
        data[pos] = draw(st.one_of(st.sampled_from(b"0123456789 \n-.exFUIabc"), st.integers(0, 255)))
    return bytes(data)


def _read(name: str, path: Path) -> object:
    fmt = SAMPLES[name][2]
    if fmt == "poses":
        return read_poses(path)
    return read_scan(path, format=fmt, organized=True)


@pytest.mark.parametrize("name", sorted(SAMPLES))
def test_valid_samples_read(name: str, tmp_path: Path) -> None:
    path = tmp_path / f"ok{SAMPLES[name][1]}"
    path.write_bytes(_valid(name))
    out = _read(name, path)
    if isinstance(out, Scan):
        assert len(out) in (N, N // 2)  # NCLT records are 8 bytes, the rest N points


@pytest.mark.parametrize("name", sorted(SAMPLES))
@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_garbled_files_fail_cleanly(name: str, data: st.DataObject, tmp_path: Path) -> None:
    blob = data.draw(mutated(_valid(name)))
    path = tmp_path / f"garbled{SAMPLES[name][1]}"
    path.write_bytes(blob)
    try:
        out = _read(name, path)
    except ScanFormatError as exc:
        assert "garbled" in str(exc)  # the message names the file
        return
    if isinstance(out, Scan):
        assert out.xyz.shape == (len(out), 3) and out.intensity.shape == (len(out),)
    else:
        poses, _ = out
        assert poses.ndim == 3 and poses.shape[1:] == (4, 4) and np.isfinite(poses).all()


@pytest.mark.parametrize("shape", [(-2, -3), (-1, 4), (4, -1), (True, 4)])
def test_npy_headers_with_negative_or_non_integer_sizes_are_refused(shape: tuple, tmp_path: Path) -> None:
    """numpy's header parser takes a negative size; ``(-1, 4)`` read every point as if the shape were inferred."""
    header = {"descr": "<f4", "fortran_order": False, "shape": shape}
    data = np.arange(16, dtype="<f4").tobytes()
    bio = io.BytesIO()
    np.lib.format.write_array_header_1_0(bio, header)
    (tmp_path / "a.npy").write_bytes(bio.getvalue() + data)
    with pytest.raises(ScanFormatError, match=r"a\.npy: \.npy header declares shape .*expected non-negative"):
        read_scan(tmp_path / "a.npy")
    import zipfile

    with zipfile.ZipFile(tmp_path / "b.npz", "w") as zf:
        zf.writestr("xyz.npy", bio.getvalue() + data)
    with pytest.raises(ScanFormatError, match=r"b\.npz\[xyz\]: \.npy header declares shape"):
        read_scan(tmp_path / "b.npz")


def _make_unreadable(path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """chmod 000, or, as root (who reads any file), an `open` that refuses ``path`` with `PermissionError`."""
    import os

    if os.geteuid() != 0:
        path.chmod(0)
        return
    import builtins

    real_open = io.open

    def refusing_open(file: object, *args: object, **kwargs: object) -> object:
        if isinstance(file, (str, Path)) and Path(file) == path:
            raise PermissionError(13, "Permission denied", str(file))
        return real_open(file, *args, **kwargs)  # type: ignore[call-overload]

    monkeypatch.setattr(builtins, "open", refusing_open)
    monkeypatch.setattr(io, "open", refusing_open)


@pytest.mark.parametrize(
    "suffix", [".bin", ".npy", ".npz", ".pcd", ".ply", "poses.txt", "config.yaml", "db.npz"]
)
def test_unreadable_files_are_placerec_errors(
    suffix: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A file without read permission is the reader's own error naming the file, not a bare PermissionError."""
    from placerec.config import load_config
    from placerec.errors import ArtifactError, ConfigError
    from placerec.io.atomic import load_artifact, save_artifact

    path = tmp_path / ("a" + suffix if suffix.startswith(".") else suffix)
    read: Callable[[], object]
    if suffix == "poses.txt":
        path.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
        read, error = (lambda: read_poses(path)), ScanFormatError
    elif suffix == "config.yaml":
        path.write_text("{}\n")
        read, error = (lambda: load_config(path)), ConfigError
    elif suffix == "db.npz":
        save_artifact(path, "test-db", 1, {"x": np.zeros(3)})
        read, error = (lambda: load_artifact(path, "test-db", (1,))), ArtifactError
    else:
        writer = {".bin": write_kitti_bin, ".npz": write_npz, ".pcd": write_pcd, ".ply": write_ply}.get(
            suffix
        )
        if writer is None:
            np.save(path, np.ones((4, 3), np.float32))
        else:
            writer(path, _scan())
        read, error = (lambda: read_scan(path)), ScanFormatError
    _make_unreadable(path, monkeypatch)
    with pytest.raises(error, match=rf"{path}: cannot read .*Permission denied"):
        read()
