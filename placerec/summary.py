"""Summaries of scans and sequences (what ``placerec info`` prints).

Which LiDAR made a scan (`identify_sensor`, what ``placerec info`` prints as ``sensor``), and how sure that is.

Metadata first: a sensor record naming a model (``sensor.yaml`` beside the scan or its folder, an ``.npz``
sensor record, an Ouster metadata JSON read with a ``.pcap``, the simulator's sensor, a dataset layout), or a
beam table (per-beam elevations) that matches one model's field of view. The KITTI ``.bin`` reader's default
label says nothing: any sensor's scans are stored that way (MulRan's Ouster scans are). Without metadata the
point structure is matched against the known models: beam count (ring index, organised rows, a flat organised
``rows x columns`` file recognised by its point count and zero points, else the elevation histogram of
`estimate_beams`), the lowest and highest beam elevations (the lowest always sees the ground;
the highest may see only sky, so it bounds the model's top from below), and the intensity's kind. Field names
in a PCD/PLY header tell the driver family (Ouster ``reflectivity``/``ambient``/``near_ir``, Livox
``tag``/``line``/``offset_time``, Hesai ``timestamp`` with ``ring``). A structure match is reported as a guess,
with the models that fit about as well.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from placerec.types import Scan, SensorInfo, Sequence

__all__ = [
    "estimate_beams",
    "scan_summary",
    "sequence_summary",
    "artifact_summary",
    "SensorGuess",
    "MODELS",
    "identify_sensor",
    "model_of_name",
    "model_of_elevations",
]

_PCTS = (1, 5, 25, 50, 75, 95, 99)


def estimate_beams(scan: Scan, bin_deg: float = 0.05, min_share: float = 0.001) -> tuple[int, str]:
    """Number of beams (rows) of a scan and how it was found: ring index, organised shape or elevation peaks.

    Without ring or shape, elevation angles are histogrammed in ``bin_deg`` bins; runs of bins holding at least
    ``min_share`` of the points each count as one beam (works for spinning sensors with distinct elevations).
    """
    if scan.ring is not None and len(scan):
        return int(np.unique(scan.ring).size), "ring index"
    if scan.shape is not None:
        return scan.shape[0], "organised shape"
    xyz = scan.xyz[np.isfinite(scan.xyz).all(axis=1)]
    r = np.linalg.norm(xyz, axis=1)
    xyz, r = xyz[r > 1e-3], r[r > 1e-3]
    if r.size == 0:
        return 0, "no valid points"
    elev = np.degrees(np.arcsin(np.clip(xyz[:, 2] / r, -1.0, 1.0)))
    lo, hi = float(elev.min()), float(elev.max())
    nbins = max(1, int(np.ceil((hi - lo) / bin_deg)) + 1)
    hist, _ = np.histogram(elev, bins=nbins, range=(lo, lo + nbins * bin_deg))
    occupied = hist >= max(1, min_share * r.size)
    runs = int(np.count_nonzero(occupied[1:] & ~occupied[:-1]) + int(occupied[0]))
    return runs, "elevation histogram (estimate)"


def _percentiles(values: np.ndarray) -> dict[str, float]:
    values = values[np.isfinite(values)]
    if values.size == 0:
        return {}
    return {f"p{p}": float(v) for p, v in zip(_PCTS, np.percentile(values, _PCTS), strict=True)}


def scan_summary(scan: Scan) -> dict[str, Any]:
    """Point count, fields, percentiles of intensity and range, beams, organisation and sensor of one scan
    (``sensor``: the model and how sure that is, `identify_sensor`; ``sensor_detail``: what
    it rests on)."""
    finite = np.isfinite(scan.xyz).all(axis=1)
    valid = finite & np.any(scan.xyz != 0, axis=1)
    beams, how = estimate_beams(scan)
    guess = identify_sensor(scan)
    return {
        "source": scan.source,
        "points": len(scan),
        "valid_points": int(valid.sum()),
        "nonfinite_points": int((~finite).sum()),
        "fields": scan.fields,
        "organised_shape": scan.shape,
        "beams": beams,
        "beams_from": how,
        "sensor": guess.line(),
        "sensor_detail": guess.to_dict(),
        "intensity_percentiles": _percentiles(scan.intensity[valid]),
        "range_percentiles": _percentiles(scan.ranges[valid]),
    }


def sequence_summary(seq: Sequence) -> dict[str, Any]:
    """Length, poses, timestamps, trajectory length and the first scan's summary of a sequence."""
    poses = seq.poses
    out: dict[str, Any] = {"name": seq.name, "scans": len(seq), "poses": None, "timestamps": None}
    if poses is not None:
        steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
        out["poses"] = {"count": int(len(poses)), "trajectory_length_m": float(steps.sum())}
    ts = seq.timestamps
    if ts is not None and len(ts):
        out["timestamps"] = {"first": float(ts[0]), "last": float(ts[-1]), "count": int(len(ts))}
    if len(seq):
        out["first_scan"] = scan_summary(seq[0])
    return out


def artifact_summary(path: Any, arrays: dict[str, np.ndarray], header: dict[str, Any]) -> dict[str, Any]:
    """A saved artifact (`placerec.io.atomic.peek_artifact`): kind, version, entries, members and, for a database
    with verification clouds, what each entry costs: on disk, in RAM when built (in its ``verify.cloud_store``
    form: ``int16-zlib`` measured by packing up to 32 of its clouds), and how many entries' clouds the default
    ``verify.cloud_budget_mb`` keeps in RAM before spilling (a database loaded memory-mapped keeps its clouds as
    file pages instead)."""
    from placerec.quantise import PackedCloud
    from placerec.verify.candidates import CLOUDS_SHARE, VerifiedParams

    size = Path(path).stat().st_size
    out: dict[str, Any] = {
        "file": str(path),
        "kind": header["kind"],
        "format_version": header["format_version"],
        "file_mb": round(size / 1e6, 3),
    }
    ids = arrays.get("ids")
    n = int(ids.shape[0]) if ids is not None and ids.ndim == 1 else None
    if n:
        out["entries"] = n
        out["file_kib_per_entry"] = round(size / n / 1024, 2)
    out["members"] = {k: f"{a.dtype} {tuple(a.shape)}" for k, a in sorted(arrays.items())}
    counts, xyz = arrays.get("cloud_counts"), arrays.get("cloud_xyz")
    if counts is None or xyz is None or counts.ndim != 1 or not counts.size or int(counts.sum()) != len(xyz):
        return out
    verify = ((header.get("meta") or {}).get("params") or {}).get("verify") or {}
    form = verify.get("cloud_store", "int16-zlib")
    pts = float(counts.mean())
    ends = np.cumsum(counts)
    sample = np.unique(np.linspace(0, counts.size - 1, min(32, counts.size)).astype(int))
    packed = [
        PackedCloud.encode(np.asarray(xyz[ends[i] - counts[i] : ends[i]], np.float32), level=2).nbytes
        for i in sample
        if counts[i]
    ]
    per_entry = {
        "float32": 12 * pts,
        "int16": 6 * pts + 32,
        "int16-zlib": float(np.mean(packed)) if packed else 0.0,
    }
    ram = per_entry.get(form, per_entry["float32"])
    budget = VerifiedParams().cloud_budget_mb
    out["clouds"] = {
        "points_per_entry": round(pts, 1),
        "file_kib_per_entry": round(12 * pts / 1024, 2),
        "cloud_store": form,
        "ram_kib_per_entry_built": round(ram / 1024, 2),
        "default_cloud_budget_mb": budget,
        "entries_in_ram_within_budget": int(budget * 1e6 * CLOUDS_SHARE // ram) if budget and ram else None,
        "when_loaded": "memory-mapped: the clouds stay file pages, read when a candidate reaches ICP",
    }
    return out


@dataclass(frozen=True)
class _Model:
    name: str
    family: str
    beams: int
    top: float  # elevation of the top beam, degrees
    bottom: float  # of the bottom beam


def _ouster() -> list[_Model]:
    out = []
    for beams in (32, 64, 128):
        out.append(_Model(f"ouster os0-{beams}", "ouster", beams, 45.0, -45.0))
        out.append(_Model(f"ouster os1-{beams} (gen1, 33 deg field)", "ouster", beams, 16.6, -16.6))
        out.append(_Model(f"ouster os1-{beams} (gen2+, 45 deg field)", "ouster", beams, 22.5, -22.5))
        out.append(_Model(f"ouster os2-{beams}", "ouster", beams, 11.25, -11.25))
    return out


#: The models placerec knows: nominal beam count and elevations of the top and bottom beams (degrees).
MODELS: tuple[_Model, ...] = (
    _Model("velodyne vlp-16", "velodyne", 16, 15.0, -15.0),
    _Model("velodyne vlp-32c", "velodyne", 32, 15.0, -25.0),
    _Model("velodyne hdl-32e", "velodyne", 32, 10.67, -30.67),
    _Model("velodyne hdl-64e", "velodyne", 64, 2.0, -24.9),
    _Model("velodyne vls-128", "velodyne", 128, 15.0, -25.0),
    _Model("hesai pandar40p", "hesai", 40, 15.0, -25.0),
    _Model("hesai pandar64", "hesai", 64, 15.0, -25.0),
    _Model("hesai pandarxt-32", "hesai", 32, 15.0, -16.0),
    _Model("hesai qt64", "hesai", 64, 52.1, -52.1),
    *_ouster(),
)

# a record name -> (family, pattern); the beam count comes from the name's digits or the beam table
_NAME_PATTERNS = (
    ("ouster", re.compile(r"(?:ouster[-_ ]*)?os[-_ ]?([012])[-_ ]?(\d+)")),
    ("velodyne", re.compile(r"(vlp|hdl|vls|vlp)[-_ ]?(\d+)")),
    ("hesai", re.compile(r"(pandar\w*|xt[-_ ]?\d+|qt[-_ ]?\d+|at[-_ ]?128)")),
    ("livox", re.compile(r"(livox|avia|mid[-_ ]?\d+|horizon|tele[-_ ]?15|hap)")),
    ("robosense", re.compile(r"(?:robosense|\brs)[-_ ]*(e1r|m1|m2|m3|helios|bpearl|ruby)|\b(e1r)\b")),
)
_FIELD_FAMILIES = (
    ("ouster", {"reflectivity", "ambient", "near_ir", "signal"}, "Ouster ROS driver"),
    ("livox", {"tag", "line", "offset_time"}, "Livox driver"),
)
#: labels readers give when the format does not record the sensor
_NO_RECORD = {"unknown", "organised-bin", "velodyne-hdl64e (kitti)"}
_TOL_BOTTOM = 2.5  # degrees a measured bottom beam may differ from the model's
_TOL_TOP = 1.5  # degrees the measured top may exceed the model's before it costs
_FLAT_ROWS = (16, 32, 40, 64, 128)
_FLAT_COLS = (512, 1024, 2048, 4096)


@dataclass(frozen=True)
class SensorGuess:
    """``model`` (None: unknown), ``how`` ("metadata", "guess" or "unknown"), ``evidence`` (what it rests on)
    and ``alternatives`` (other models a guess fits about as well)."""

    model: str | None
    how: str
    evidence: tuple[str, ...] = ()
    alternatives: tuple[str, ...] = ()
    reader_label: str = "unknown"
    structure: dict = field(default_factory=dict)

    def line(self) -> str:
        """One line, e.g. ``ouster os1-64 (from metadata: ...)`` or ``likely velodyne hdl-64e (...; guess)``."""
        why = "; ".join(self.evidence)
        if self.model is None:
            return f"unknown ({why})" if why else "unknown"
        if self.how == "metadata":
            return f"{self.model} (from metadata: {why})"
        also = f"; also fits {', '.join(self.alternatives)}" if self.alternatives else ""
        return f"likely {self.model} ({why}{also}; guess)"

    def to_dict(self) -> dict:
        return {
            "model": self.model,
            "how": self.how,
            "evidence": list(self.evidence),
            "alternatives": list(self.alternatives),
            "reader_label": self.reader_label,
            **self.structure,
        }


def model_of_elevations(elev: tuple[float, ...] | list[float], tol: float = 2.0) -> str | None:
    """The model whose beam count and top/bottom elevations (within ``tol`` degrees) match a beam table."""
    e = np.asarray(elev, dtype=float)
    if e.size == 0:
        return None
    hits = [
        m.name
        for m in MODELS
        if m.beams == e.size and abs(float(e.max()) - m.top) <= tol and abs(float(e.min()) - m.bottom) <= tol
    ]
    return hits[0] if len(hits) == 1 else None


def model_of_name(name: str, elev: tuple[float, ...] | None = None) -> str | None:
    """A sensor record's name as a known model (``OS-1-64``, ``vlp16``, ``velodyne-hdl32e (nclt)``...), refined
    by the beam table when one is given; None when the name names no model placerec knows."""
    low = name.lower()
    if elev:
        table = model_of_elevations(elev)
        if table is not None and _name_family(low) in (None, _family(table)):
            return table
    for family, pat in _NAME_PATTERNS:
        m = pat.search(low)
        if m is None:
            continue
        if family == "ouster":
            beams = int(m.group(2))
            fits = [x for x in MODELS if x.name.startswith(f"ouster os{m.group(1)}-{beams}")]
            return fits[0].name if len(fits) == 1 else f"ouster os{m.group(1)}-{beams}"
        if family == "velodyne":
            prefix = f"velodyne {m.group(1)}-{m.group(2)}"
            names = [x.name for x in MODELS if x.name.startswith(prefix)]
            return names[0] if names else prefix
        if family == "robosense":
            return f"robosense {m.group(1) or m.group(2)}"
        return f"{family} {m.group(1)}" if family == "hesai" else "livox"
    return None


def _name_family(low: str) -> str | None:
    return next((fam for fam, pat in _NAME_PATTERNS if pat.search(low)), None)


def _family(model: str) -> str:
    return model.split()[0]


def _header_fields(path: Path) -> list[str]:
    """Field names in a PCD (FIELDS) or PLY (vertex properties) header; [] for other files."""
    suffix = path.suffix.lower()
    if suffix not in (".pcd", ".ply") or not path.is_file():
        return []
    try:
        with path.open("rb") as fh:
            head = fh.read(8192).decode("latin-1")
    except OSError:
        return []
    names: list[str] = []
    for line in head.splitlines():
        parts = line.split()
        if suffix == ".pcd" and parts[:1] == ["FIELDS"]:
            return [p.lower() for p in parts[1:]]
        if suffix == ".pcd" and parts[:1] == ["DATA"]:
            break
        if suffix == ".ply" and parts[:1] == ["property"] and len(parts) >= 3:
            names.append(parts[-1].lower())
        if suffix == ".ply" and parts[:1] == ["end_header"]:
            break
    return names


def _sensor_yaml(path: Path) -> tuple[SensorInfo, Path] | None:
    from placerec.errors import PlacerecError
    from placerec.io.file_sequence import load_sensor_yaml

    for folder in (path.parent, path.parent.parent):
        candidate = folder / "sensor.yaml"
        if candidate.is_file():
            try:
                return load_sensor_yaml(candidate), candidate
            except PlacerecError:
                return None
    return None


def _valid(scan: Scan) -> np.ndarray:
    """Points that are finite and farther than 1 m (zeros of an organised scan, the vehicle left out)."""
    with np.errstate(invalid="ignore"):
        return np.isfinite(scan.xyz).all(axis=1) & (np.linalg.norm(scan.xyz, axis=1) > 1.0)


def _elevations(xyz: np.ndarray) -> np.ndarray:
    r = np.linalg.norm(xyz, axis=1)
    return np.degrees(np.arcsin(np.clip(xyz[:, 2] / r, -1.0, 1.0)))


def _structure(scan: Scan) -> dict:
    """Beam count (and whether it is exact), bottom/top beam elevation, columns, intensity kind of ``scan``."""
    valid = _valid(scan)
    xyz = scan.xyz[valid]
    out: dict = {"points": len(scan), "valid_points": int(len(xyz))}
    if len(xyz) < 100:
        return out
    elev = _elevations(xyz)
    per_beam = None
    if scan.ring is not None:
        ring = scan.ring[valid]
        out["beams"], out["beams_from"] = int(np.unique(scan.ring).size), "ring index"
        per_beam = [
            float(np.median(elev[ring == r])) for r in np.unique(ring) if np.count_nonzero(ring == r) >= 20
        ]
    elif scan.shape is not None:
        rows, cols = scan.shape
        out["beams"], out["beams_from"], out["columns"] = rows, "organised rows", cols
        full = scan.xyz.reshape(rows, cols, 3)
        per_beam = []
        for r in range(rows):
            row = full[r][np.linalg.norm(full[r], axis=1) > 1.0]
            if len(row) >= max(20, 0.01 * cols):
                per_beam.append(float(np.median(_elevations(row))))
    else:
        est, _ = estimate_beams(scan)
        zeros = 1.0 - len(xyz) / max(1, len(scan))
        flat = [(r, c) for r in _FLAT_ROWS for c in _FLAT_COLS if r * c == len(scan)]
        if flat and zeros > 0.05:
            rows, cols = min(flat, key=lambda rc: abs(rc[0] - est))
            out["beams"], out["columns"] = rows, cols
            out["beams_from"] = (
                f"{len(scan)} points = {rows} x {cols} with {zeros:.0%} zero points (a flat organised scan)"
            )
        else:
            out["beams_estimate"], out["beams_from"] = est, "elevation histogram (estimate)"
    if per_beam:
        out["bottom_deg"], out["top_deg"] = round(min(per_beam), 2), round(max(per_beam), 2)
        if len(per_beam) > 2:
            out["spacing_deg"] = round(float(np.median(np.diff(np.sort(per_beam)))), 3)
    else:
        lo, hi = np.percentile(elev, [0.2, 99.8])
        out["bottom_deg"], out["top_deg"] = round(float(lo), 2), round(float(hi), 2)
        beams = out.get("beams", out.get("beams_estimate"))
        if beams and beams > 1:
            out["spacing_deg"] = round(float(hi - lo) / (beams - 1), 3)
    azim = np.degrees(np.arctan2(xyz[:, 1], xyz[:, 0]))
    hist, _ = np.histogram(azim, bins=72, range=(-180, 180))
    out["azimuth_coverage_deg"] = int(5 * np.count_nonzero(hist >= max(1, 0.001 * len(xyz))))
    inten = scan.intensity[np.isfinite(scan.intensity)]
    if inten.size:
        imax = float(inten.max())
        integer = bool(np.all(inten == np.round(inten)))
        out["intensity"] = (
            "0..1 (normalised)"
            if imax <= 1.0
            else "8-bit"
            if integer and imax <= 255
            else "16-bit"
            if integer and imax <= 65535
            else f"float up to {imax:.3g}"
        )
    return out


def _fit(structure: dict, family: str | None) -> list[tuple[float, _Model]]:
    """Known models ordered by how well ``structure`` fits them (lower is better); misfits left out."""
    if "bottom_deg" not in structure:
        return []
    bottom, top = structure["bottom_deg"], structure["top_deg"]
    exact, est = structure.get("beams"), structure.get("beams_estimate")
    fits = []
    for m in MODELS:
        if family is not None and m.family != family:
            continue
        if exact is not None and exact != m.beams:
            continue
        if est is not None and not 0.5 * m.beams <= est <= 1.15 * m.beams:
            continue
        miss = abs(bottom - m.bottom)
        over = top - m.top
        if miss > _TOL_BOTTOM or over > _TOL_TOP + 1.5:
            continue
        score = miss + max(0.0, over - _TOL_TOP) + 0.15 * max(0.0, -over)
        if est is not None:
            score += 0.02 * abs(est - m.beams)
        if m.family == "ouster" and structure.get("columns") in _FLAT_COLS:
            score -= 0.5
        if m.family == "ouster" and structure.get("intensity") == "16-bit":
            score -= 0.3
        if m.family == "velodyne" and structure.get("intensity") == "16-bit":
            score += 0.5
        fits.append((score, m))
    return sorted(fits, key=lambda sm: sm[0])


def _describe(structure: dict) -> str:
    beams = structure.get("beams")
    parts = [
        f"{beams} beams" if beams is not None else f"~{structure.get('beams_estimate')} beams (histogram)"
    ]
    if "bottom_deg" in structure:
        parts.append(f"elevation {structure['top_deg']:+.1f}..{structure['bottom_deg']:+.1f} deg")
    if "spacing_deg" in structure:
        parts.append(f"spacing ~{structure['spacing_deg']:.2f} deg")
    if structure.get("columns"):
        parts.append(f"{structure['columns']} columns")
    if structure.get("intensity"):
        parts.append(f"{structure['intensity']} intensity")
    return ", ".join(parts)


def identify_sensor(scan: Scan) -> SensorGuess:
    """The sensor of ``scan``: from metadata when a record names a model, else a guess from its structure."""
    source = Path(scan.source.split("#")[0]) if scan.source else None
    record, where = scan.sensor, "the reader's sensor record"
    if source is not None:
        if source.suffix.lower() == ".pcap":
            where = "the Ouster metadata json"
        elif source.suffix.lower() == ".npz":
            where = "the .npz sensor record"
        elif "(nclt)" in record.name:
            where = "the nclt velodyne_sync format (HDL-32E only)"
        elif m := re.search(r"\((mulran|helipr)\)", record.name):
            where = f"the {m.group(1)} dataset layout"
        found = _sensor_yaml(source) if record.name in _NO_RECORD else None
        if found is not None:
            record, yaml_path = found
            where = str(yaml_path)
    fields = _header_fields(source) if source is not None else []
    structure = _structure(scan)
    label = scan.sensor.name
    if record.name not in _NO_RECORD or record.beam_elevations_deg:
        model = model_of_name(record.name, record.beam_elevations_deg)
        if model is None and record.beam_elevations_deg:
            model = model_of_elevations(record.beam_elevations_deg)
        if model is not None:
            return SensorGuess(model, "metadata", (f"{where}: {record.name!r}",), (), label, structure)
    family, evidence = None, []
    for fam, names, driver in _FIELD_FAMILIES:
        hit = sorted(names & set(fields))
        if hit:
            family = fam
            evidence.append(f"fields {', '.join(hit)} of the {driver}")
    if family is None and {"ring", "timestamp"} <= set(fields):
        family = "hesai"
        evidence.append("fields ring, timestamp of the Hesai driver")
    if family == "livox" or (
        family is None and "beams_estimate" in structure and structure.get("azimuth_coverage_deg", 360) < 270
    ):
        if family is None:
            evidence.append(
                f"no ring index or organised rows and a {structure['azimuth_coverage_deg']} deg horizontal field"
                " (a spinning sensor sees 360; or a cropped scan): a non-repetitive scan pattern"
            )
        return SensorGuess("livox", "guess", tuple(evidence), (), label, structure)
    fits = _fit(structure, family)
    if not fits and family is not None:
        fits = _fit(structure, None)
    desc = _describe(structure) if "bottom_deg" in structure else "too few valid points"
    if not fits:
        return SensorGuess(None, "unknown", (desc, "no known model fits"), (), label, structure)
    best = fits[0][0]
    alternatives = tuple(m.name for s, m in fits[1:] if s - best < 0.5)
    if record.name != label or label not in _NO_RECORD:
        evidence.append(f"record {record.name!r} names no known model")
    return SensorGuess(fits[0][1].name, "guess", (desc, *evidence), alternatives, label, structure)
