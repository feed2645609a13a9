"""Dataset layouts: every loader of `placerec.io.datasets.DATASET_LOADERS` on a small valid layout and on its
hostile variants — ground truth missing, not rigid (scaled x1000, sheared, zero, mirrored), NaN, times NaN or
decreasing, a calibration with two different ``Tr``, pose and scan counts that differ, odd scan names (superscript
digits, non-numbers, nanoseconds >= 10^9), HeLiPR Aeva records of ambiguous sizes."""

from __future__ import annotations

import functools
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from fuzz.corpus import Case
from placerec.errors import ConfigError, ScanFormatError
from placerec.io import open_sequence
from placerec.io.datasets import DATASET_LOADERS

N = 64
T0_NS = 1_566_535_000_000_000_000  # MulRan / HeLiPR style nanosecond stems
NCLT_T0 = 1_326_652_795_280_148  # microseconds
NCD_SEC = 1_583_836_591


def _points(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(-20, 20, (N, 3)), rng.uniform(0, 1, N)].astype(np.float32)


def _rot(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _rows3x4(n: int) -> list[np.ndarray]:
    """``n`` rigid 3x4 poses along x, turning slowly."""
    return [np.c_[_rot(0.1 * k), [2.0 * k, 0.5 * k, 0.0]] for k in range(n)]


#: how a pose is damaged: rotation scaled x1000, sheared, zero, mirrored (det -1), NaN, translation 10^9 m
DAMAGE: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "scaled-x1000": lambda P: np.c_[P[:, :3] * 1000, P[:, 3]],
    "sheared": lambda P: np.c_[P[:, :3] @ np.array([[1, 0.5, 0], [0, 1, 0], [0, 0, 1.0]]), P[:, 3]],
    "zero": lambda P: np.zeros_like(P),
    "mirrored": lambda P: np.c_[P[:, :3] @ np.diag([1.0, 1.0, -1.0]), P[:, 3]],
    "nan": lambda P: np.full_like(P, np.nan),
    "far-1e9m": lambda P: np.c_[P[:, :3], [1e9, 0, 0]],
}


# ------------------------------------------------------------------------------------------------ layouts
def kitti(root: Path, n: int = 2, damage: str | None = None) -> Path:
    seq = root / "sequences" / "00"
    (seq / "velodyne").mkdir(parents=True)
    for k in range(n):
        _points(k).tofile(seq / "velodyne" / f"{k:06d}.bin")
    rows = _rows3x4(n)
    if damage:
        rows[-1] = DAMAGE[damage](rows[-1])
    (root / "poses").mkdir()
    (root / "poses" / "00.txt").write_text(
        "".join(" ".join(f"{v:.9g}" for v in P.ravel()) + "\n" for P in rows)
    )
    tr = np.c_[_rot(np.pi / 2) @ np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0.0]]), [0.1, -0.05, -0.3]]
    (seq / "calib.txt").write_text("Tr: " + " ".join(f"{v:.12g}" for v in tr.ravel()) + "\n")
    (seq / "times.txt").write_text("".join(f"{0.1 * k:.6f}\n" for k in range(n)))
    return root


def mulran(root: Path, damage: str | None = None, stems: list[str] | None = None) -> Path:
    ouster = root / "sensor_data" / "Ouster"
    ouster.mkdir(parents=True)
    for k, stem in enumerate(stems or [str(T0_NS + k * 100_000_000) for k in range(2)]):
        _points(k).tofile(ouster / f"{stem}.bin")
    rows = _rows3x4(3)
    if damage:
        rows[1] = DAMAGE[damage](rows[1])
    times = [T0_NS - 50_000_000 + k * 100_000_000 for k in range(3)]
    (root / "global_pose.csv").write_text(
        "".join(
            f"{t}," + ",".join(f"{v:.9g}" for v in P.ravel()) + "\n" for t, P in zip(times, rows, strict=True)
        )
    )
    return root


def _quat_rows(n: int) -> list[list[float]]:
    """x y z qx qy qz qw rows along x (a slow yaw)."""
    return [[2.0 * k, 0.0, 0.0, 0.0, 0.0, float(np.sin(0.05 * k)), float(np.cos(0.05 * k))] for k in range(n)]


QUAT_DAMAGE: dict[str, Callable[[list[float]], list[float]]] = {
    "quaternion-zero": lambda r: r[:3] + [0.0, 0.0, 0.0, 0.0],
    "quaternion-nan": lambda r: r[:3] + [float("nan")] * 4,
    "position-inf": lambda r: [float("inf")] + r[1:],
    "far-1e9m": lambda r: [1e9] + r[1:],
}


def _pcd(path: Path, seed: int) -> None:
    from placerec.io import write_scan
    from placerec.types import Scan

    p = _points(seed)
    write_scan(path, Scan(xyz=p[:, :3], intensity=p[:, 3]), format="pcd")


def newer_college(root: Path, damage: str | None = None, names: list[str] | None = None) -> Path:
    folder = root / "raw_format" / "ouster_scan"
    folder.mkdir(parents=True)
    for k, name in enumerate(names or [f"cloud_{NCD_SEC}_{k * 100_000_000}.pcd" for k in range(2)]):
        _pcd(folder / name, k)
    rows = _quat_rows(3)
    if damage:
        rows[1] = QUAT_DAMAGE[damage](rows[1])
    (root / "ground_truth").mkdir()
    stamps = [(NCD_SEC, 0), (NCD_SEC, 100_000_000), (NCD_SEC, 200_000_000)]
    (root / "ground_truth" / "registered_poses.csv").write_text(
        "#sec,nsec,x,y,z,qx,qy,qz,qw\n"
        + "".join(
            f"{s},{ns}," + ",".join(f"{v:.9g}" for v in r) + "\n"
            for (s, ns), r in zip(stamps, rows, strict=True)
        )
    )
    return root


def helipr(
    root: Path, sensor: str = "Ouster", damage: str | None = None, stems: list[str] | None = None
) -> Path:
    from placerec.io.datasets.helipr import HELIPR_RECORDS

    dtype = HELIPR_RECORDS[sensor][0]
    folder = root / "LiDAR" / sensor
    folder.mkdir(parents=True)
    t0 = 1_700_000_000_000_000_000
    for k, stem in enumerate(stems or [str(t0 + k * 100_000_000) for k in range(2)]):
        rec = np.zeros(N, dtype=dtype)
        p = _points(k)
        for j, c in enumerate("xyz"):
            rec[c] = p[:, j]
        rec.tofile(folder / f"{stem}.bin")
    rows = _quat_rows(2)
    if damage:
        rows[1] = QUAT_DAMAGE[damage](rows[1])
    (root / "LiDAR_GT").mkdir()
    (root / "LiDAR_GT" / f"{sensor}_gt.txt").write_text(
        "".join(
            f"{t0 + k * 100_000_000} " + " ".join(f"{v:.9g}" for v in r) + "\n" for k, r in enumerate(rows)
        )
    )
    return root


def nclt(root: Path, rows: list[list[float]] | None = None, stems: list[str] | None = None) -> Path:
    date = root / "2012-01-15"
    (date / "velodyne_sync").mkdir(parents=True)
    rec = np.zeros(N, dtype=[("x", "<u2"), ("y", "<u2"), ("z", "<u2"), ("i", "u1"), ("l", "u1")])
    rec["x"], rec["y"], rec["z"], rec["l"] = 40000 + np.arange(N) * 50, 40000, 40000, np.arange(N) % 32
    for stem in stems or [str(NCLT_T0 + k * 100_000) for k in range(2)]:
        rec.tofile(date / "velodyne_sync" / f"{stem}.bin")
    if rows is None:
        rows = [[NCLT_T0 - 100_000 + k * 200_000, 2.0 * k, 0, 0, 0, 0, 0.1 * k] for k in range(3)]
    (root / "ground_truth").mkdir()
    (root / "ground_truth" / "groundtruth_2012-01-15.csv").write_text(
        "".join(",".join(f"{v:.17g}" if isinstance(v, float) else str(v) for v in r) + "\n" for r in rows)
    )
    return date


def mcap(path: Path, n_messages: int = 2) -> Path:
    from mcap.writer import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.LATEST)
    T = ts.types
    p = _points(0)
    arr = np.zeros(N, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4")])
    for j, c in enumerate(("x", "y", "z", "intensity")):
        arr[c] = p[:, j]
    fields = [
        T["sensor_msgs/msg/PointField"](name=name, offset=4 * k, datatype=7, count=1)
        for k, name in enumerate(arr.dtype.names or ())
    ]
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start()
        schema = w.register_schema("sensor_msgs/msg/PointCloud2", "ros2msg", b"")
        chan = w.register_channel("/points", "cdr", schema)
        for k in range(n_messages):
            header = T["std_msgs/msg/Header"](
                stamp=T["builtin_interfaces/msg/Time"](sec=100 + k, nanosec=5), frame_id="l"
            )
            msg = T["sensor_msgs/msg/PointCloud2"](
                header=header, height=1, width=N, fields=fields, is_bigendian=False, point_step=16,
                row_step=16 * N, data=np.frombuffer(arr.tobytes(), np.uint8).copy(), is_dense=True,
            )  # fmt: skip
            data = bytes(ts.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2"))
            w.add_message(chan, log_time=(100 + k) * 10**9, data=data, publish_time=(100 + k) * 10**9)
        w.finish()
    return path


@functools.cache
def _mcap_bytes(n_messages: int = 2) -> bytes:
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        return mcap(Path(d) / "x.mcap", n_messages).read_bytes()


@functools.cache
def _livox_mcap_bytes(line_type: int = 2, stamp_type: int = 8) -> bytes:
    """Two PointCloud2 messages in the Livox driver layout (x y z intensity f32, tag line u8, timestamp f64 ns;
    26-byte points) in a standalone .mcap; ``line_type`` / ``stamp_type`` the PointField datatypes written."""
    import tempfile

    from mcap.writer import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.LATEST)
    T = ts.types
    p = _points(1)
    arr = np.zeros(N, dtype={"names": ["x", "y", "z", "intensity", "tag", "line", "timestamp"],
                             "formats": ["<f4"] * 4 + ["u1", "u1", "<f8"],
                             "offsets": [0, 4, 8, 12, 16, 17, 18], "itemsize": 26})  # fmt: skip
    for j, c in enumerate("xyz"):
        arr[c] = p[:, j]
    arr["intensity"], arr["line"], arr["timestamp"] = (
        p[:, 3] * 255,
        np.arange(N) % 4,
        1e18 + np.arange(N) * 1e3,
    )
    layout = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 12, 7), ("tag", 16, 2), ("line", 17, line_type),
              ("timestamp", 18, stamp_type)]  # fmt: skip
    fields = [T["sensor_msgs/msg/PointField"](name=a, offset=o, datatype=d, count=1) for a, o, d in layout]
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "livox.mcap"
        with open(path, "wb") as fh:
            w = Writer(fh)
            w.start()
            chan = w.register_channel("/livox/points", "cdr", w.register_schema(PC2_TYPE, "ros2msg", b""))
            for k in range(2):
                header = T["std_msgs/msg/Header"](
                    stamp=T["builtin_interfaces/msg/Time"](sec=100 + k, nanosec=0), frame_id="livox_frame"
                )
                msg = T[PC2_TYPE](
                    header=header, height=1, width=N, fields=fields, is_bigendian=False, point_step=26,
                    row_step=26 * N, data=np.frombuffer(arr.tobytes(), np.uint8).copy(), is_dense=True,
                )  # fmt: skip
                t = (100 + k) * 10**9
                w.add_message(chan, log_time=t, data=bytes(ts.serialize_cdr(msg, PC2_TYPE)), publish_time=t)
            w.finish()
        return path.read_bytes()


PC2_TYPE = "sensor_msgs/msg/PointCloud2"


def _livox_scans(args: Any, result: Any) -> None:
    """A valid Livox PointCloud2 recording: two scans with rings from ``line`` and the non-repetitive pattern."""
    _sequence(2, poses=False)(args, result)
    for scan in result[1]:
        assert scan.sensor.pattern == "non-repetitive" and scan.ring is not None and scan.ring.max() == 3
        assert scan.time is not None and scan.time[0] == 0


# ------------------------------------------------------------------------------------------------ running
def _open(dataset: str, **options: Any) -> Callable[[Path], Any]:
    """Open ``path`` as ``dataset`` and read every scan (a loader may defer its checks to the first read)."""

    def run(path: Path) -> Any:
        seq = open_sequence(path, dataset=dataset, **options)
        scans = [seq[i] for i in range(len(seq))]
        return seq, scans

    return run


def _sequence(n: int | tuple[int, ...], poses: bool = True) -> Callable[[Any, Any], None]:
    allowed = (n,) if isinstance(n, int) else n

    def check(args: Any, result: Any) -> None:
        seq, scans = result
        assert len(seq) in allowed, (len(seq), allowed)
        assert all(len(s) > 0 and s.xyz.shape == (len(s), 3) for s in scans)
        if poses:
            P = seq.poses
            assert P is not None and P.shape == (len(seq), 4, 4) and np.isfinite(P).all()
            R = P[:, :3, :3]
            np.testing.assert_allclose(
                R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-3
            )
            assert (np.linalg.det(R) > 0).all()
        if seq.timestamps is not None and len(seq) > 1:
            assert np.isfinite(seq.timestamps).all() and (np.diff(seq.timestamps) > 0).all()

    return check


def _named(rel: str) -> Callable[[Path], str]:
    """The error must name this file (its name; the path relative to the case folder is ``rel``)."""
    return lambda path: Path(rel).name


def _edit(path: Path, fn: Callable[[str], str]) -> None:
    path.write_text(fn(path.read_text()))


def cases() -> list[Case]:
    out: list[Case] = []

    def case(layout: str, name: str, build: Callable[[Path], Path], expect: str = "error", **kw: Any) -> None:
        kw.setdefault("run", _open(layout))
        kw.setdefault("cli", lambda p, layout=layout: ["info", str(p), "--dataset", layout])
        out.append(Case("datasets", f"{layout}/{name}", build, kw.pop("run"), expect, subject=layout, **kw))

    # -------------------------------------------------------------------------------------------- kitti
    kopen = _open("kitti", sequence="00")
    kcli = lambda p: ["info", str(p / "sequences" / "00"), "--dataset", "kitti"]  # noqa: E731

    def kcase(name: str, build: Callable[[Path], Path], expect: str = "error", **kw: Any) -> None:
        case("kitti", name, build, expect, run=kw.pop("run", kopen), cli=kw.pop("cli", kcli), **kw)

    kcase("valid", lambda t: kitti(t / "k"), "ok", check=_sequence(2), fast=True)
    for damage in DAMAGE:
        kcase(
            f"pose-{damage}",
            lambda t, d=damage: kitti(t / "k", damage=d),
            names="00.txt",
            error=ScanFormatError,
        )
    kcase(
        "poses-missing", lambda t: _rm(kitti(t / "k"), "poses/00.txt"), "ok", check=_sequence(2, poses=False)
    )
    kcase("poses-one-more", lambda t: _append(kitti(t / "k"), "poses/00.txt", lambda s: s + s.splitlines()[0] + "\n"), names="00.txt")  # fmt: skip
    kcase("poses-one-short", lambda t: _append(kitti(t / "k"), "poses/00.txt", lambda s: s.splitlines()[0] + "\n"), names="00.txt")  # fmt: skip
    kcase("poses-11-columns", lambda t: _append(kitti(t / "k"), "poses/00.txt", lambda s: s.replace(" 0\n", "\n", 1)), names="00.txt")  # fmt: skip
    kcase("calib-missing", lambda t: _rm(kitti(t / "k"), "sequences/00/calib.txt"), names="calib.txt")
    kcase("calib-two-different-tr", lambda t: _append(kitti(t / "k"), "sequences/00/calib.txt", lambda s: s + s.replace("Tr: ", "Tr: 2")), names="calib.txt")  # fmt: skip
    kcase("calib-tr-mirrored", lambda t: _append(kitti(t / "k"), "sequences/00/calib.txt", lambda s: "Tr: " + " ".join(str(-float(v)) for v in s.split()[1:]) + "\n"), names="calib.txt")  # fmt: skip
    kcase("calib-tr-nan", lambda t: _append(kitti(t / "k"), "sequences/00/calib.txt", lambda s: "Tr: " + " ".join(["nan"] * 12) + "\n"), names="calib.txt")  # fmt: skip
    kcase("times-nan", lambda t: _append(kitti(t / "k"), "sequences/00/times.txt", lambda s: "0.0\nnan\n"), names="times.txt")  # fmt: skip
    kcase("times-decreasing", lambda t: _append(kitti(t / "k"), "sequences/00/times.txt", lambda s: "1.0\n0.5\n"), names="times.txt")  # fmt: skip
    kcase("times-count", lambda t: _append(kitti(t / "k"), "sequences/00/times.txt", lambda s: "0.0\n"), names="times.txt")  # fmt: skip
    kcase("times-text", lambda t: _append(kitti(t / "k"), "sequences/00/times.txt", lambda s: "0.0\nsoon\n"), names="times.txt")  # fmt: skip
    kcase("velodyne-empty", lambda t: _clear(kitti(t / "k"), "sequences/00/velodyne"), names="00")
    kcase("scan-truncated", lambda t: _append_bytes(kitti(t / "k"), "sequences/00/velodyne/000001.bin", lambda b: b[:-3]), cli=None, names="000001.bin")  # fmt: skip
    kcase("superscript-names", lambda t: _rename(kitti(t / "k"), "sequences/00/velodyne", ["¹.bin", "²³.bin"]), "either", check=_sequence(2), names="velodyne")  # fmt: skip
    kcase("sequence-missing", kitti_root_only := (lambda t: kitti(t / "k")), run=_open("kitti", sequence="07"), names="07", cli=None)  # fmt: skip
    del kitti_root_only

    # -------------------------------------------------------------------------------------------- mulran
    case("mulran", "valid", lambda t: mulran(t / "m"), "ok", check=_sequence(2), fast=True)
    for damage in DAMAGE:
        case("mulran", f"pose-{damage}", lambda t, d=damage: mulran(t / "m", damage=d), names="global_pose.csv", error=ScanFormatError)  # fmt: skip
    case("mulran", "poses-missing", lambda t: _rm(mulran(t / "m"), "global_pose.csv"), names="global_pose.csv", run=_open("mulran"))  # fmt: skip
    case("mulran", "times-nan", lambda t: _append(mulran(t / "m"), "global_pose.csv", lambda s: s.replace(str(T0_NS + 50_000_000), "nan", 1)), names="global_pose.csv")  # fmt: skip
    case("mulran", "times-decreasing", lambda t: _append(mulran(t / "m"), "global_pose.csv", lambda s: "\n".join(s.splitlines()[::-1]) + "\n"), "either", check=_sequence(2), names="global_pose.csv")  # fmt: skip
    case("mulran", "times-repeated", lambda t: _append(mulran(t / "m"), "global_pose.csv", lambda s: s.replace(str(T0_NS + 50_000_000), str(T0_NS - 50_000_000), 1)), names="global_pose.csv")  # fmt: skip
    case("mulran", "rows-short", lambda t: _append(mulran(t / "m"), "global_pose.csv", lambda s: s.replace(",0\n", "\n", 1)), names="global_pose.csv")  # fmt: skip
    case("mulran", "superscript-names", lambda t: mulran(t / "m", stems=["¹²³", "¹²³⁴"]), names="¹²³")
    case("mulran", "names-not-times", lambda t: mulran(t / "m", stems=["scan_a", "scan_b"]), names="scan_a")
    case("mulran", "scans-outside-gt", lambda t: mulran(t / "m", stems=[str(T0_NS + 10**12), str(T0_NS + 2 * 10**12)]), names="global_pose.csv")  # fmt: skip
    case("mulran", "scan-folder-missing", lambda t: _rmtree(mulran(t / "m"), "sensor_data"), names="Ouster", cli=None)  # fmt: skip

    # -------------------------------------------------------------------------------------------- newer college
    nc = "newer-college"
    gt = "registered_poses.csv"
    case(nc, "valid", lambda t: newer_college(t / "n"), "ok", check=_sequence(2), fast=True)
    for damage in QUAT_DAMAGE:  # poses made from quaternions: a ScanFormatError naming the file
        case(nc, f"pose-{damage}", lambda t, d=damage: newer_college(t / "n", damage=d), names=gt, error=ScanFormatError)  # fmt: skip
    case(nc, "poses-missing", lambda t: _rm(newer_college(t / "n"), f"ground_truth/{gt}"), names=gt)
    case(nc, "nanoseconds-1e9", lambda t: newer_college(t / "n", names=[f"cloud_{NCD_SEC}_0.pcd", f"cloud_{NCD_SEC}_1500000000.pcd"]), names="1500000000")  # fmt: skip
    case(nc, "nanoseconds-long", lambda t: newer_college(t / "n", names=[f"cloud_{NCD_SEC}_0.pcd", f"cloud_{NCD_SEC}_{'9' * 40}.pcd"]), names="9999")  # fmt: skip
    case(nc, "superscript-seconds", lambda t: newer_college(t / "n", names=[f"cloud_{NCD_SEC}_0.pcd", "cloud_¹²³_0.pcd"]), names="¹²³")  # fmt: skip
    case(nc, "name-not-cloud", lambda t: newer_college(t / "n", names=[f"cloud_{NCD_SEC}_0.pcd", "scan.pcd"]), names="scan.pcd")  # fmt: skip
    case(nc, "times-nan", lambda t: _append(newer_college(t / "n"), f"ground_truth/{gt}", lambda s: s.replace(f"{NCD_SEC},100000000", "nan,100000000")), names=gt)  # fmt: skip
    case(nc, "gt-text", lambda t: _append(newer_college(t / "n"), f"ground_truth/{gt}", lambda s: s.replace(f"{NCD_SEC},100000000,2", f"{NCD_SEC},100000000,two")), names=gt)  # fmt: skip
    case(nc, "scan-truncated", lambda t: _append_bytes(newer_college(t / "n"), f"raw_format/ouster_scan/cloud_{NCD_SEC}_100000000.pcd", lambda b: b[:-5]), cli=None, names=f"cloud_{NCD_SEC}_100000000.pcd")  # fmt: skip

    # -------------------------------------------------------------------------------------------- helipr
    hgt = "Ouster_gt.txt"
    case("helipr", "valid", lambda t: helipr(t / "h"), "ok", check=_sequence(2), fast=True)
    for damage in QUAT_DAMAGE:
        case("helipr", f"pose-{damage}", lambda t, d=damage: helipr(t / "h", damage=d), names=hgt, error=ScanFormatError)  # fmt: skip
    case("helipr", "poses-missing", lambda t: _rm(helipr(t / "h"), f"LiDAR_GT/{hgt}"), names=hgt)
    case("helipr", "times-nan", lambda t: _append(helipr(t / "h"), f"LiDAR_GT/{hgt}", lambda s: "nan" + s[s.index(" "):]), names=hgt)  # fmt: skip
    case("helipr", "superscript-names", lambda t: helipr(t / "h", stems=["¹²³", "¹²³⁴"]), names="¹²³")
    case("helipr", "record-size", lambda t: _append_bytes(helipr(t / "h"), "LiDAR/Ouster/1700000000100000000.bin", lambda b: b + b"x"), cli=None, names="1700000000100000000.bin")  # fmt: skip
    case("helipr", "max-gap-text", lambda t: helipr(t / "h"), run=_open("helipr", max_gap="0.05"), names="max_gap", error=ConfigError, cli=None)  # fmt: skip
    case("helipr", "max-gap-nan", lambda t: helipr(t / "h"), run=_open("helipr", max_gap=float("nan")), names="max_gap", error=ConfigError, cli=None)  # fmt: skip
    case("helipr", "max-gap-negative", lambda t: helipr(t / "h"), run=_open("helipr", max_gap=-1.0), names="max_gap", error=ConfigError, cli=None)  # fmt: skip
    case("helipr", "sensor-unknown", lambda t: helipr(t / "h"), run=_open("helipr", sensor="Lidar9"), names="Lidar9", error=ConfigError, cli=None)  # fmt: skip
    case("helipr", "two-sensors-no-choice", lambda t: _also(helipr(t / "h"), lambda r: (r / "LiDAR" / "Avia").mkdir()), names="sensor", error=ConfigError)  # fmt: skip
    # Aeva: 29-byte records, 25 bytes (no intensity) up to 1691936557946849179 ns; the size decides the layout,
    # a size that fits both (725 = 25 x 29 bytes) the content (or an error naming the file)
    for name, stem, size, expect in (
        ("aeva-new-25-byte-records", "1700000000000000000", 25 * 30, "ok"),
        ("aeva-old-29-byte-records", "1691936557000000000", 29 * 31, "ok"),
        ("aeva-neither-size", "1700000000000000000", 29 * 25 + 1, "error"),
        ("aeva-ambiguous-725-bytes-new", "1700000000000000000", 725, "either"),
        ("aeva-ambiguous-725-bytes-old", "1691936557000000000", 725, "either"),
        ("aeva-name-not-a-time", "scan", 29 * 4, "either"),
    ):
        case("helipr", name, lambda t, s=stem, n=size: _aeva(t, s, n), expect, run=_read_aeva, cli=None,
             check=_aeva_points, names=lambda p: p.name)  # fmt: skip

    # -------------------------------------------------------------------------------------------- nclt
    ngt = "groundtruth_2012-01-15.csv"
    base = [[NCLT_T0 - 100_000 + k * 200_000, 2.0 * k, 0, 0, 0, 0, 0.1 * k] for k in range(3)]

    def rows_with(k: int, col: int, value: float) -> list[list[float]]:
        rows = [list(r) for r in base]
        rows[k][col] = value
        return rows

    case("nclt", "valid", lambda t: nclt(t / "c"), "ok", check=_sequence(2), fast=True)
    case("nclt", "leading-nan-rows", lambda t: nclt(t / "c", [[NCLT_T0 - 900_000] + [float("nan")] * 6] + base), "ok", check=_sequence(2))  # fmt: skip
    case("nclt", "yaw-inf", lambda t: nclt(t / "c", rows_with(1, 6, float("inf"))), names=ngt)  # fmt: skip
    case("nclt", "far-1e9m", lambda t: nclt(t / "c", rows_with(1, 1, 1e9)), names=ngt)
    case("nclt", "times-nan", lambda t: nclt(t / "c", rows_with(1, 0, float("nan"))), names=ngt)  # fmt: skip
    case("nclt", "times-repeated", lambda t: nclt(t / "c", rows_with(1, 0, NCLT_T0 - 100_000)), names=ngt)
    case("nclt", "times-decreasing", lambda t: nclt(t / "c", base[::-1]), names=ngt)  # fmt: skip
    case("nclt", "poses-missing", lambda t: _rmtree(nclt(t / "c").parent, "ground_truth", ret=1), names="groundtruth_2012-01-15")  # fmt: skip
    case("nclt", "superscript-names", lambda t: nclt(t / "c", stems=["¹²³", "¹²³⁴"]), names="¹²³")
    case("nclt", "scans-outside-gt", lambda t: nclt(t / "c", stems=[str(NCLT_T0 + 10**10), str(NCLT_T0 + 2 * 10**10)]), names=ngt)  # fmt: skip

    # -------------------------------------------------------------------------------------------- mcap
    def mfile(name: str, data: Callable[[], bytes]) -> Callable[[Path], Path]:
        def build(t: Path) -> Path:
            (t / name).write_bytes(data())
            return t / name

        return build

    case("mcap", "valid", mfile("drive.mcap", _mcap_bytes), "ok", check=_sequence(2, poses=False), fast=True)
    case("mcap", "empty", mfile("empty.mcap", lambda: b""))
    case("mcap", "junk", mfile("junk.mcap", lambda: b"\x89MCAP0\r\nnot really"))
    case("mcap", "truncated-half", mfile("half.mcap", lambda: _mcap_bytes()[: len(_mcap_bytes()) // 2]), "either", check=_sequence((1, 2), poses=False))  # fmt: skip
    case("mcap", "truncated-head", mfile("head.mcap", lambda: _mcap_bytes()[:40]))
    case("mcap", "no-messages", mfile("none.mcap", lambda: _mcap_bytes(0)))
    case("mcap", "topic-absent", mfile("drive.mcap", _mcap_bytes), run=_open("mcap", topic="/lidar"), names="/lidar", cli=None)  # fmt: skip
    case("mcap", "directory", lambda t: _mkdir(t / "folder.mcap"), names="folder.mcap")
    # Livox driver layout (issue #28): ring from `line`, times from `timestamp`; other datatypes name the field
    case("mcap", "livox-valid", mfile("livox.mcap", _livox_mcap_bytes), "ok", check=_livox_scans)
    case("mcap", "livox-line-float32", mfile("livox.mcap", lambda: _livox_mcap_bytes(line_type=7)), names="'line'", error=ScanFormatError, cli=None)  # fmt: skip
    case("mcap", "livox-timestamp-uint32", mfile("livox.mcap", lambda: _livox_mcap_bytes(stamp_type=6)), names="'timestamp'", error=ScanFormatError, cli=None)  # fmt: skip
    return out


def _aeva(tmp: Path, stem: str, size: int) -> Path:
    path = tmp / f"{stem}.bin"
    rng = np.random.default_rng(1)
    path.write_bytes(rng.uniform(-1, 1, size // 4 + 1).astype(np.float32).tobytes()[:size])
    return path


def _read_aeva(path: Path) -> Any:
    from placerec.io.datasets.helipr import read_helipr_bin

    return read_helipr_bin(path, "Aeva")


def _aeva_points(path: Path, scan: Any) -> None:
    size = path.stat().st_size
    assert (
        len(scan) in (size // 25, size // 29) and size % len(scan) == 0 and scan.xyz.shape == (len(scan), 3)
    )


def _rm(root: Path, rel: str) -> Path:
    (root / rel).unlink()
    return root


def _rmtree(root: Path, rel: str, ret: int = 0) -> Path:
    shutil.rmtree(root / rel)
    return root / "2012-01-15" if ret else root


def _clear(root: Path, rel: str) -> Path:
    for f in (root / rel).iterdir():
        f.unlink()
    return root


def _rename(root: Path, rel: str, names: list[str]) -> Path:
    for f, name in zip(sorted((root / rel).iterdir()), names, strict=True):
        f.rename(f.with_name(name))
    return root


def _append(root: Path, rel: str, fn: Callable[[str], str]) -> Path:
    _edit(root / rel, fn)
    return root


def _append_bytes(root: Path, rel: str, fn: Callable[[bytes], bytes]) -> Path:
    p = root / rel
    p.write_bytes(fn(p.read_bytes()))
    return root


def _also(root: Path, fn: Callable[[Path], Any]) -> Path:
    fn(root)
    return root


def _mkdir(path: Path) -> Path:
    path.mkdir()
    return path


def registered() -> list[str]:
    return list(DATASET_LOADERS)
