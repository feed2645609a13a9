"""Trajectory files: KITTI (12 numbers a line: the top 3x4 of ``T_world_sensor``, row-major) and TUM
(``timestamp tx ty tz qx qy qz qw``). Blank lines and lines starting with ``#`` are skipped.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from placerec.errors import ScanFormatError
from placerec.io._common import check_file
from placerec.io.atomic import atomic_write
from placerec.types import check_poses, rigid_problem

__all__ = [
    "read_poses",
    "write_kitti_poses",
    "write_tum_poses",
    "quat_to_matrix",
    "matrix_to_quat",
    "POSE_FORMATS",
]

POSE_FORMATS = {"kitti": 12, "tum": 8}


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions (qx, qy, qz, qw), normalised here, to (N, 3, 3) rotation matrices."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    x, y, z, w = q.T
    R = np.empty((q.shape[0], 3, 3))
    R[:, 0, 0] = 1 - 2 * (y * y + z * z)
    R[:, 0, 1] = 2 * (x * y - z * w)
    R[:, 0, 2] = 2 * (x * z + y * w)
    R[:, 1, 0] = 2 * (x * y + z * w)
    R[:, 1, 1] = 1 - 2 * (x * x + z * z)
    R[:, 1, 2] = 2 * (y * z - x * w)
    R[:, 2, 0] = 2 * (x * z - y * w)
    R[:, 2, 1] = 2 * (y * z + x * w)
    R[:, 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices to (N, 4) unit quaternions (qx, qy, qz, qw): the inverse of `quat_to_matrix`."""
    from scipy.spatial.transform import Rotation

    R = np.asarray(R, dtype=np.float64)
    return Rotation.from_matrix(R).as_quat() if len(R) else np.empty((0, 4))


def _rows(path: Path, fmt: str | None) -> tuple[str, np.ndarray, list[int]]:
    p = check_file(path, "pose")
    try:
        text = p.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise ScanFormatError(f"{p}: pose file is not UTF-8 text ({exc})") from None
    except OSError as exc:
        raise ScanFormatError(f"{p}: cannot read pose file ({exc})") from None
    if fmt is not None and fmt not in POSE_FORMATS:
        raise ScanFormatError(f"{p}: unknown pose format {fmt!r} (expected one of {list(POSE_FORMATS)})")
    width = POSE_FORMATS[fmt] if fmt else None
    tokens: list[str] = []
    line_nos: list[int] = []
    for no, line in enumerate(text.splitlines(), 1):
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        if width is None:
            width = len(parts)
            fmt = next((k for k, v in POSE_FORMATS.items() if v == width), None)
            if fmt is None:
                raise ScanFormatError(
                    f"{p}:{no}: {width} columns; expected 12 (KITTI 3x4) or 8 (TUM "
                    "'timestamp tx ty tz qx qy qz qw')"
                )
        elif len(parts) != width:
            raise ScanFormatError(f"{p}:{no}: {len(parts)} columns, expected {width} ({fmt} poses)")
        tokens.extend(parts)
        line_nos.append(no)
    if not line_nos or fmt is None or width is None:
        raise ScanFormatError(f"{p}: no poses found (only blank or comment lines)")
    try:
        vals = np.array(tokens, dtype=np.float64).reshape(len(line_nos), width)
    except ValueError:
        for no, k in zip(line_nos, range(0, len(tokens), width), strict=True):
            for tok in tokens[k : k + width]:
                try:
                    float(tok)
                except ValueError:
                    raise ScanFormatError(f"{p}:{no}: {tok!r} is not a number") from None
        raise ScanFormatError(f"{p}: pose values are not numbers") from None  # pragma: no cover
    bad = ~np.isfinite(vals).all(axis=1)
    if bad.any():
        raise ScanFormatError(f"{p}:{line_nos[int(np.argmax(bad))]}: pose contains NaN or inf")
    return fmt, vals, line_nos


def read_poses(path: str | Path, format: str | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """Read a KITTI or TUM trajectory; format auto-detected from the column count (12 / 8) when None.

    Returns ``(poses, timestamps)``: (N, 4, 4) float64 ``T_world_sensor`` and the TUM timestamps (None for KITTI).
    Quaternions are normalised; a zero quaternion is an error.
    """
    p = Path(path)
    fmt, vals, line_nos = _rows(p, format)
    n = vals.shape[0]
    poses = np.zeros((n, 4, 4))
    poses[:, 3, 3] = 1.0
    if fmt == "kitti":
        poses[:, :3, :] = vals.reshape(n, 3, 4)
        problem = rigid_problem(poses)
        if problem is not None:
            raise ScanFormatError(f"{p}:{line_nos[problem[0]]}: pose is no rigid motion: {problem[1]}")
        return poses, None
    q = vals[:, 4:8]
    norm = np.linalg.norm(q, axis=1)
    if (norm < 1e-12).any():
        raise ScanFormatError(f"{p}:{line_nos[int(np.argmax(norm < 1e-12))]}: quaternion has zero norm")
    poses[:, :3, :3] = quat_to_matrix(q)
    poses[:, :3, 3] = vals[:, 1:4]
    problem = rigid_problem(poses)
    if problem is not None:
        raise ScanFormatError(f"{p}:{line_nos[problem[0]]}: pose is no rigid motion: {problem[1]}")
    return poses, vals[:, 0].copy()


def _write_text(path: str | Path, text: str) -> None:
    with atomic_write(path) as fh:
        fh.write(text.encode("utf-8"))


def write_kitti_poses(path: str | Path, poses: np.ndarray) -> None:
    """Write (N, 4, 4) poses as KITTI 3x4 lines (atomic)."""
    P = check_poses(poses, None, str(path))
    rows = P[:, :3, :].reshape(-1, 12)
    _write_text(path, "".join(" ".join(f"{v:.12e}" for v in r) + "\n" for r in rows))


def write_tum_poses(path: str | Path, poses: np.ndarray, timestamps: np.ndarray) -> None:
    """Write (N, 4, 4) poses with (N,) timestamps as TUM lines ``t tx ty tz qx qy qz qw`` (atomic)."""
    P = check_poses(poses, None, str(path))
    t = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    check_poses(P, t.shape[0], str(path))
    q = matrix_to_quat(P[:, :3, :3])
    lines = [
        f"{ti:.9f} " + " ".join(f"{v:.12e}" for v in (*xyz, *qi)) + "\n"
        for ti, xyz, qi in zip(t, P[:, :3, 3], q, strict=True)
    ]
    _write_text(path, "".join(lines))
