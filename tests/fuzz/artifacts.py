"""Artifacts: a real saved artifact of every builder kind (`placerec.artifacts.BUILDERS`) and the database of every
registered pipeline (`placerec.recognizer.PIPELINES`), damaged: flipped bytes, truncated, wrong kind or version,
NaN in members, negative counts, members of the wrong shape or dtype, extra and missing members, not a zip."""

from __future__ import annotations

import functools
import io
import json
import shutil
import tempfile
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from fuzz.corpus import Case
from placerec.artifacts import BUILDERS
from placerec.errors import ArtifactError
from placerec.recognizer import PIPELINES

Edit = Callable[[dict[str, np.ndarray], dict], None]  # changes (arrays, header) in place


# ------------------------------------------------------------------------------------------------ good artifacts
def _calibration(path: Path) -> None:
    from placerec.calibration.table import CalibrationTable

    rng = np.random.default_rng(2)
    CalibrationTable(
        values=np.sort(rng.uniform(0, 1, (4, 16)), axis=1), raw_step=1.0, sensor="vlp16", max_range=30.0,
        counts=rng.integers(0, 9, (4, 16)),
    ).save(path)  # fmt: skip


def _load_calibration(path: Path) -> Any:
    from placerec.calibration.table import CalibrationTable

    return CalibrationTable.load(path)


def _places(path: Path) -> None:
    from placerec.three_d.places import PlacesDatabase, PlacesParams

    rng = np.random.default_rng(1)
    scan_poses = np.tile(np.eye(4), (6, 1, 1))
    scan_poses[:, 0, 3] = np.arange(6) * 3.0
    ids, counts = np.array([0, 2, 4]), np.array([5, 0, 7])
    clouds = [
        (rng.normal(size=(n, 3)).astype(np.float32), rng.uniform(size=n).astype(np.float32))
        for n in (9, 4, 6)
    ]
    PlacesDatabase(
        ids=ids, poses=scan_poses[ids].copy(), sources=[np.array([0, 1]), np.array([1, 2, 3]), np.array([3, 4, 5])],
        kp_offsets=np.r_[0, np.cumsum(counts)], keypoints=rng.normal(size=(12, 3)).astype(np.float32),
        descriptors=rng.uniform(size=(12, 8)).astype(np.float32), params=PlacesParams(), scan_poses=scan_poses,
        clouds=clouds, intensity="sensor-default", sequence="s",
    ).save(path)  # fmt: skip


def _load_places(path: Path) -> Any:
    from placerec.three_d.places import PlacesDatabase

    return PlacesDatabase.load(path)


def _votes(path: Path) -> None:
    from placerec.three_d.vote_model import VoteModel

    rng = np.random.default_rng(3)
    VoteModel(
        tau_edges=np.array([0.0, 0.5, 1.0]), sigma=np.array([1.0, 2.0]), lam=np.array([0.1, 0.2]), d_max=10.0,
        n_votes=np.array([5, 7]), distances=rng.uniform(0, 10, 12), taus=rng.uniform(0, 1, 12),
    ).save(path)  # fmt: skip


def _load_votes(path: Path) -> Any:
    from placerec.three_d.vote_model import VoteModel

    return VoteModel.load(path)


def _vocabulary(path: Path) -> None:
    from placerec.retrieval.dbow.io import save_vocabulary
    from placerec.retrieval.dbow.vocabulary import train_vocabulary

    rng = np.random.default_rng(4)
    voc = train_vocabulary(
        [rng.integers(0, 256, (40, 32), dtype=np.uint8) for _ in range(6)], k=4, L=3, seed=0
    )
    save_vocabulary(voc, path)


def _load_vocabulary(path: Path) -> Any:
    from placerec.retrieval.dbow.io import load_vocabulary

    return load_vocabulary(path)


def _superpoint(path: Path) -> None:
    from importlib.resources import files

    shutil.copyfile(Path(str(files("placerec") / "vocab" / "superpoint_lidar.npz")), path)


def _load_superpoint(path: Path) -> Any:
    from placerec.features.superpoint.weights import load_weights

    return load_weights(path)


#: builder kind -> (suffix, make a good artifact at a path, load one, whether it is a placerec npz artifact)
KINDS: dict[str, tuple[str, Callable[[Path], None], Callable[[Path], Any], bool]] = {
    "calibration": (".npz", _calibration, _load_calibration, True),
    "places-db": (".npz", _places, _load_places, True),
    "vote-model": (".npz", _votes, _load_votes, True),
    "vocabulary": (".dbow", _vocabulary, _load_vocabulary, False),
    "superpoint-weights": (".npz", _superpoint, _load_superpoint, True),
}


@functools.cache
def _sim_scans() -> tuple[tuple[Any, ...], np.ndarray]:
    from placerec.sim import SimulatedSequence

    seq = SimulatedSequence(world="town", sensor="vlp16", n_scans=3, seed=5, clutter=False)
    return tuple(seq[i] for i in range(3)), seq.poses


def _pipeline_db(name: str) -> Callable[[Path], None]:
    def make(path: Path) -> None:
        from placerec.recognizer import make_pipeline

        scans, poses = _sim_scans()
        rec = make_pipeline(name)
        for i, scan in enumerate(scans):
            rec.add(i, scan, poses[i])
        rec.save(path)

    return make


def _pipeline_load(name: str) -> Callable[[Path], Any]:
    def load(path: Path) -> Any:
        from placerec.recognizer import make_pipeline

        rec = make_pipeline(name)
        rec.load(path)
        return rec

    return load


@functools.cache
def good(kind: str) -> bytes:
    """The bytes of a valid artifact of ``kind`` (a builder kind, or ``db:<pipeline>``)."""
    make = _pipeline_db(kind[3:]) if kind.startswith("db:") else KINDS[kind][1]
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / f"good{'.dbow' if kind == 'vocabulary' else '.npz'}"
        make(path)
        return path.read_bytes()


# ------------------------------------------------------------------------------------------------ npz surgery
def _members(data: bytes) -> dict[str, bytes]:
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        return {i.filename: zf.read(i) for i in zf.infolist()}


def _npy(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, arr, allow_pickle=True)
    return buf.getvalue()


def _decode(data: bytes) -> tuple[dict[str, np.ndarray], dict]:
    arrays = {n[:-4]: np.load(io.BytesIO(b)) for n, b in _members(data).items()}
    return arrays, json.loads(arrays.pop("__header__").tobytes())


def _encode(arrays: dict[str, np.ndarray], header: dict) -> bytes:
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as zf:
        zf.writestr("__header__.npy", _npy(np.frombuffer(json.dumps(header).encode(), np.uint8)))
        for name, arr in arrays.items():
            zf.writestr(f"{name}.npy", _npy(arr))
    return out.getvalue()


def _edited(kind: str, edit: Edit) -> Callable[[], bytes]:
    def make() -> bytes:
        arrays, header = _decode(good(kind))
        arrays = {k: v.copy() for k, v in arrays.items()}
        edit(arrays, header)
        return _encode(arrays, header)

    return make


def _member_data_offset(data: bytes, index: int) -> tuple[int, int]:
    """(offset, size) of the ``index``-th largest member's stored bytes."""
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        infos = sorted(zf.infolist(), key=lambda i: -i.compress_size)
    info = infos[min(index, len(infos) - 1)]
    name_len, extra_len = int.from_bytes(data[info.header_offset + 26 : info.header_offset + 28], "little"), int.from_bytes(data[info.header_offset + 28 : info.header_offset + 30], "little")  # fmt: skip
    return info.header_offset + 30 + name_len + extra_len, info.compress_size


def _flipped(kind: str, where: str) -> Callable[[], bytes]:
    """A byte of the content flipped: in the middle (or the last byte) of the largest or second largest member's
    data (npz), or of the file (other formats)."""

    def make() -> bytes:
        data = bytearray(good(kind))
        if data[:2] == b"PK":
            start, size = _member_data_offset(bytes(data), 1 if where.startswith("second") else 0)
            pos = start + (size - 1 if where.endswith("last") else size // 2)
        else:  # the last byte of a vocabulary is padding: flip one of its JSON header instead
            pos = 24 if where.endswith("last") else len(data) // 2
        data[pos] ^= 0x5A
        return bytes(data)

    return make


def _is_count(name: str) -> bool:
    return any(w in name for w in ("offset", "_count", "_lens", "width", "leaf_start"))


def _edits(arrays: dict[str, np.ndarray], header: dict) -> dict[str, Edit]:
    """The member and header edits every npz artifact must refuse."""
    edits: dict[str, Edit] = {
        "kind-other": lambda a, h: h.__setitem__("kind", "other"),
        "kind-missing": lambda a, h: h.pop("kind"),
        "version-99": lambda a, h: h.__setitem__("format_version", 99),
        "version-negative": lambda a, h: h.__setitem__("format_version", -1),
        "version-string": lambda a, h: h.__setitem__("format_version", str(h["format_version"])),
        "version-nan": lambda a, h: h.__setitem__("format_version", float("nan")),
        "meta-list": lambda a, h: h.__setitem__("meta", [1]),
        "extra-member": lambda a, h: a.__setitem__("bogus", np.zeros(3)),
    }
    for name, arr in arrays.items():
        edits[f"{name}-missing"] = lambda a, h, n=name: a.pop(n)
        if arr.dtype.kind == "f" and arr.size:
            edits[f"{name}-nan"] = lambda a, h, n=name: a[n].reshape(-1).__setitem__(-1, np.nan)
            edits[f"{name}-inf"] = lambda a, h, n=name: a[n].reshape(-1).__setitem__(0, -np.inf)
        # counts, offsets and lengths must add up (ids and quantised points may be negative, and a table's
        # standalone statistics, like a calibration's counts, may be anything >= 0)
        if arr.dtype.kind == "i" and arr.size and _is_count(name):
            edits[f"{name}-negative"] = lambda a, h, n=name: a[n].reshape(-1).__setitem__(-1, -5)
        if arr.dtype.kind in "iu" and arr.size and _is_count(name):
            edits[f"{name}-x1000"] = lambda a, h, n=name: a.__setitem__(n, a[n] * 1000)
        other = np.complex64 if arr.dtype.kind == "f" else np.float64
        edits[f"{name}-dtype-{np.dtype(other).name}"] = lambda a, h, n=name, t=other: a.__setitem__(
            n, a[n].astype(t)
        )
        if arr.ndim:
            edits[f"{name}-extra-axis"] = lambda a, h, n=name: a.__setitem__(n, a[n][..., None])
            if arr.shape[0] > 1:
                edits[f"{name}-row-cut"] = lambda a, h, n=name: a.__setitem__(n, a[n][:-1])
    return edits


# ------------------------------------------------------------------------------------------------ the cases
def _artifact_cases(
    kind: str, subject: str, load: Callable[[Path], Any], suffix: str, npz: bool
) -> list[Case]:
    cases: list[Case] = []
    stem = f"art_{subject.replace(':', '_')}"

    def case(name: str, data: Callable[[], bytes], **kw: Any) -> None:
        def build(tmp: Path) -> Path:
            path = tmp / f"{stem}{suffix}"
            path.write_bytes(data())
            return path

        cases.append(
            Case("artifacts", f"{subject}/{name}", build, load, subject=subject, error=ArtifactError, **kw)
        )

    case("valid", lambda: good(kind), expect="ok", check=lambda p, obj: None, fast=True)
    case("empty", lambda: b"")
    case("truncated-half", lambda: good(kind)[: len(good(kind)) // 2])
    case("truncated-last-byte", lambda: good(kind)[:-1])
    case("truncated-22-bytes", lambda: good(kind)[:-22])  # the zip's end record gone
    case("not-an-artifact", lambda: b"hello, world\n" * 10)
    for where in ("largest-middle", "largest-last", "second-middle"):
        case(f"flipped-{where}", _flipped(kind, where))
    cases.append(
        Case(
            "artifacts",
            f"{subject}/missing",
            lambda t: t / f"absent{suffix}",
            load,
            subject=subject,
            error=ArtifactError,
        )  # fmt: skip
    )
    cases.append(
        Case(
            "artifacts",
            f"{subject}/directory",
            lambda t: _mkdir(t / f"dir{suffix}"),
            load,
            subject=subject,
            error=ArtifactError,
        )  # fmt: skip
    )
    if npz:
        arrays, header = _decode(good(kind))
        for name, edit in _edits(arrays, header).items():
            case(name, _edited(kind, edit))
        case("deflated", lambda: _deflated(good(kind)))
    return cases


def _deflated(data: bytes) -> bytes:
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, blob in _members(data).items():
            zf.writestr(name, blob)
    return out.getvalue()


def _mkdir(path: Path) -> Path:
    path.mkdir()
    return path


def _db_cases(name: str) -> list[Case]:
    """A pipeline database: the generic damage, and the edits of its arrays grouped by kind (`_every`): their
    names come from the database's arrays, and building one to list them would take seconds at collection."""
    subject = f"db:{name}"
    load = _pipeline_load(name)
    cases = []
    stem = f"db_{name}"

    def case(cname: str, data: Callable[[], bytes], **kw: Any) -> None:
        def build(tmp: Path) -> Path:
            path = tmp / f"{stem}.npz"
            path.write_bytes(data())
            return path

        cases.append(
            Case("artifacts", f"{subject}/{cname}", build, load, subject=subject, error=ArtifactError, **kw)
        )

    case("valid", lambda: good(subject), expect="ok", check=lambda p, obj: None)
    case("truncated-half", lambda: good(subject)[: len(good(subject)) // 2])
    case("flipped-largest-middle", _flipped(subject, "largest-middle"))
    case("flipped-second-last", _flipped(subject, "second-last"))
    for ename in ("kind-other", "version-99", "extra-member", "meta-list"):
        case(ename, _edited(subject, lambda a, h, e=ename: _edits(a, h)[e](a, h)))
    for what in ("nan", "inf", "negative", "dtype", "extra-axis", "row-cut", "missing", "x1000"):
        cases.append(_every(subject, load, stem, what))
    return cases


def _every(subject: str, load: Callable[[Path], Any], stem: str, what: str) -> Case:
    """One case applying, one at a time, every edit of kind ``what`` to the pipeline's database: each must be an
    `ArtifactError` naming the file (the case's error is the first edit that is not, if any)."""

    def build(tmp: Path) -> list[tuple[str, Path]]:
        arrays, header = _decode(good(subject))
        out = []
        for ename, edit in _edits(arrays, header).items():
            if ename.endswith(what) or f"-{what}" in ename:
                path = tmp / f"{stem}_{ename}.npz"
                path.write_bytes(_edited(subject, edit)())
                out.append((ename, path))
        return out

    def run(paths: list[tuple[str, Path]]) -> Any:
        from placerec.errors import PlacerecError

        for ename, path in paths:
            try:
                load(path)
            except PlacerecError as exc:
                if not isinstance(exc, ArtifactError) or path.name not in str(exc):
                    raise type(exc)(f"{ename}: {exc}") from exc
                continue
            raise AssertionError(f"{subject}: {ename} ({path.name}) loaded silently")
        return len(paths)

    return Case(
        "artifacts", f"{subject}/every-{what}", build, run, "ok", subject=subject, check=lambda a, n: None
    )


# ------------------------------------------------------------------------------------------------ map folders
@functools.cache
def _good_map() -> Path:
    """A valid map folder (3 simulated scans, a Scan Context database), built once per process."""
    from placerec.maps import MapWriter
    from placerec.recognizer import make_pipeline

    scans, poses = _sim_scans()
    rec = make_pipeline("scan-context")
    root = Path(tempfile.mkdtemp(prefix="placerec-fuzz-map-"))
    with MapWriter(root / "map", {"scan-context": (rec, 0.3)}, name="fuzz") as w:
        for i, scan in enumerate(scans):
            rec.add(i, scan, poses[i])
            w.add_keyframe(poses[i], scan.xyz)
        w.finish()
    return root / "map"


def _open_map(check: bool) -> Callable[[Path], Any]:
    def load(path: Path) -> Any:
        from placerec.maps import MapArtifact

        m = MapArtifact.open(path, check_hashes=check)
        m.recognizer()
        return m

    return load


def _map_edit(edit: Callable[[Path], None]) -> Callable[[Path], Path]:
    def build(tmp: Path) -> Path:
        path = tmp / "map_case"
        shutil.copytree(_good_map(), path)
        edit(path)
        return path

    return build


def _manifest_edit(change: Callable[[dict], None]) -> Callable[[Path], None]:
    def edit(path: Path) -> None:
        data = json.loads((path / "manifest.json").read_text())
        change(data)
        (path / "manifest.json").write_text(json.dumps(data))

    return edit


def _flip(name: str, where: float) -> Callable[[Path], None]:
    def edit(path: Path) -> None:
        f = path / name
        data = bytearray(f.read_bytes())
        data[int(where * (len(data) - 1))] ^= 0x5A
        f.write_bytes(bytes(data))

    return edit


def _truncate(name: str) -> Callable[[Path], None]:
    return lambda path: (path / name).write_bytes((path / name).read_bytes()[:-7])


def _map_cases() -> list[Case]:
    """A map folder (`placerec.maps`): its manifest, files and databases damaged; `placerec info MAP --check`."""
    subject = "map"
    files = ("keyframes.npz", "clouds.npz", "pipelines/scan-context.npz", "manifest.json")
    edits: dict[str, Callable[[Path], None]] = {
        "manifest-missing": lambda p: (p / "manifest.json").unlink(),
        "manifest-not-json": lambda p: (p / "manifest.json").write_bytes(b"\xff{not json"),
        "manifest-list": lambda p: (p / "manifest.json").write_text("[1, 2]"),
        "manifest-unknown-key": _manifest_edit(lambda d: d.update(colour="red")),
        "manifest-version-99": _manifest_edit(lambda d: d.update(format_version=99)),
        "manifest-kind-other": _manifest_edit(lambda d: d.update(kind="places-db")),
        "manifest-n-keyframes": _manifest_edit(lambda d: d.update(n_keyframes=7)),
        "manifest-n-keyframes-negative": _manifest_edit(lambda d: d.update(n_keyframes=-1)),
        "manifest-sessions": _manifest_edit(lambda d: d["sessions"][0].update(count=2)),
        "manifest-path-escapes": _manifest_edit(
            lambda d: d["files"].update({"../outside.npz": d["files"]["clouds.npz"]})
        ),
        "manifest-absolute-path": _manifest_edit(lambda d: d["pipelines"][0].update(file="/etc/passwd")),
        "manifest-hash-not-hex": _manifest_edit(lambda d: d["files"]["clouds.npz"].update(sha256="zz")),
        "manifest-size-huge": _manifest_edit(lambda d: d["files"]["clouds.npz"].update(bytes=10**18)),
        "manifest-pipeline-unknown": _manifest_edit(lambda d: d["pipelines"][0].update(name="no-such")),
        "manifest-pipeline-params": _manifest_edit(lambda d: d["pipelines"][0]["params"].update(bogus=1)),
        "file-extra": lambda p: (p / "notes.txt").write_text("x"),
        "file-missing-clouds": lambda p: (p / "clouds.npz").unlink(),
        "file-missing-database": lambda p: (p / "pipelines" / "scan-context.npz").unlink(),
        "file-is-a-folder": lambda p: ((p / "clouds.npz").unlink(), (p / "clouds.npz").mkdir()),
    }
    for name in files[:3]:
        edits[f"truncated-{name.replace('/', '-')}"] = _truncate(name)
        for where in (0.5, 1.0):
            edits[f"flipped-{name.replace('/', '-')}-{where:g}"] = _flip(name, where)
    cases = [
        Case(
            "artifacts",
            f"{subject}/valid",
            _map_edit(lambda p: None),
            _open_map(True),
            "ok",
            subject=subject,
            check=lambda p, m: None,
            cli=lambda p: ["info", str(p), "--check"],
        )  # fmt: skip
    ]
    for name, edit in edits.items():
        cases.append(
            Case(
                "artifacts",
                f"{subject}/{name}",
                _map_edit(edit),
                _open_map(True),
                subject=subject,
                names="map_case",
                cli=lambda p: ["info", str(p), "--check"],
            )  # fmt: skip
        )
    cases.append(
        Case(
            "artifacts",
            f"{subject}/not-a-folder",
            lambda t: _write(t / "map_case", b"x"),
            _open_map(False),
            subject=subject,
            error=ArtifactError,
            names="map_case",
        )  # fmt: skip
    )
    return cases


def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def cases() -> list[Case]:
    out: list[Case] = _map_cases()
    for kind in BUILDERS:
        if kind in KINDS:
            suffix, _, load, npz = KINDS[kind]
            out.extend(_artifact_cases(kind, kind, load, suffix, npz))
    for name in sorted(PIPELINES):
        if name == "map-closures":
            try:
                import map_closures  # noqa: F401
            except ImportError:
                continue
        out.extend(_db_cases(name))
    return out
