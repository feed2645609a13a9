"""Vocabulary files: placerec's compact binary format and the ORB-SLAM2 / DBoW2 text format.

Binary format (``.dbow``, little-endian), written atomically (temp file, fsync, rename)::

    8 bytes   magic b"PRDBOW\\x00\\x01"
    uint32    format version (2; version 1 files, which lack the next field, are read too)
    uint32    header length H
    uint32    CRC-32 of the header
    H bytes   JSON header: k, L, weighting, scoring, kind ("binary"/"float"), descriptor_size, n_nodes,
              centre_dtype ("uint8", "float32", "float16", "int8") and centre_scale, meta, and for every array
              its dtype, shape, byte offset (from the start of the payload), stored bytes, codec and CRC-32
    padding   to a multiple of 64 bytes
    payload   parents int32 (n_nodes), weights float32 (n_nodes), centres (n_nodes, size), each padded to 64
              bytes, raw or zlib-compressed

Loading reads the file once and wraps the arrays with ``np.frombuffer`` (a 1.1M-node vocabulary loads in 0.3 s).
Every declared size is checked against the artifact load cap (`placerec.io.limits`) before it is read or
inflated, and the header, the array table, the checksums, finite weights and the tree's shape are validated
(`load_vocabulary`); any fault is an `ArtifactError` naming the file. Float centres can be stored smaller: ``centre_dtype="float16"`` (half the size, relative rounding
2^-11) or ``"int8"`` (a quarter: centres scaled so the largest component is 127 and rounded; for SURF, whose
components lie in [-1, 1], the step is below 0.01); with ``compress=True`` every array is zlib-compressed (codec
recorded per array). Centres are float32 again once loaded.

Text format (ORB-SLAM2's ``ORBvoc.txt``; DBoW2 forks' ``saveToTextFile``): first line ``k L scoring weighting``
(scoring 0 = L1-norm; weighting 0 = TF-IDF, 1 = TF, 2 = IDF, 3 = binary), then one line per node from node 1 in
id order: ``parent is_leaf d_1 ... d_n weight`` where the descriptor is n byte values (binary) or n numbers (float).
Parsing is vectorised (the 145 MB ``ORBvoc.txt`` is parsed in seconds, not minutes); convert it once with
``save_vocabulary(read_text_vocabulary(path), "orb.dbow")``.
"""

from __future__ import annotations

import json
import logging
import math
import struct
import warnings
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from placerec.errors import ArtifactError, short_repr
from placerec.io.atomic import atomic_write, json_object
from placerec.io.limits import check_size
from placerec.retrieval.dbow.vocabulary import Vocabulary

log = logging.getLogger(__name__)

__all__ = [
    "save_vocabulary",
    "load_vocabulary",
    "read_text_vocabulary",
    "write_text_vocabulary",
    "MAGIC",
    "FORMAT_VERSION",
]

MAGIC = b"PRDBOW\x00\x01"
FORMAT_VERSION = 2
_READ_VERSIONS = (1, 2)
_ALIGN = 64
_SCORING = {0: "l1", 1: "l2", 2: "chi-square", 3: "kl", 4: "bhattacharyya", 5: "dot-product"}
_WEIGHTING = {0: "tf-idf", 1: "tf", 2: "idf", 3: "binary"}


def save_vocabulary(
    voc: Vocabulary, path: str | Path, centre_dtype: str | None = None, compress: bool = False
) -> None:
    """Write ``voc`` in the binary format.

    ``centre_dtype``: None (uint8 for binary, float32 for float), or for float vocabularies "float16" or "int8"
    (centres scaled by ``127 / max|c|`` and rounded; the scale is stored). ``compress``: zlib each array.
    """
    if centre_dtype is None:
        centre_dtype = "uint8" if voc.binary else "float32"
    allowed = ("uint8",) if voc.binary else ("float32", "float16", "int8")
    if centre_dtype not in allowed:
        raise ArtifactError(f"{path}: centre_dtype {centre_dtype!r} not allowed for a {voc.kind} vocabulary")
    scale = 1.0
    if centre_dtype == "int8":
        top = float(np.abs(voc.centres).max()) if voc.centres.size else 0.0
        scale = top / 127.0 if top > 0 else 1.0
        centres = np.clip(np.rint(voc.centres / scale), -127, 127).astype(np.int8)
    else:
        centres = voc.centres.astype("<" + np.dtype(centre_dtype).str[1:])
    arrays = {
        "parents": np.ascontiguousarray(voc.parents, "<i4"),
        "weights": np.ascontiguousarray(voc.weights, "<f4"),
        "centres": np.ascontiguousarray(centres),
    }
    table, blobs, offset = {}, [], 0
    for name, arr in arrays.items():
        data = zlib.compress(arr.data, 6) if compress else bytes(arr.data)
        table[name] = {
            "dtype": arr.dtype.str,
            "shape": list(arr.shape),
            "offset": offset,
            "stored_bytes": len(data),
            "codec": "zlib" if compress else "raw",
            "crc32": zlib.crc32(data),
        }
        blobs.append(data)
        offset += _padded(len(data))
    header = {
        "k": voc.k,
        "L": voc.L,
        "weighting": voc.weighting,
        "scoring": voc.scoring,
        "kind": voc.kind,
        "descriptor_size": voc.descriptor_size,
        "n_nodes": voc.n_nodes,
        "n_words": voc.n_words,
        "centre_dtype": centre_dtype,
        "centre_scale": scale,
        "arrays": table,
        "meta": _jsonable(voc.meta),
    }
    blob = json.dumps(header, sort_keys=True).encode("utf-8")
    head = MAGIC + struct.pack("<III", FORMAT_VERSION, len(blob), zlib.crc32(blob)) + blob
    with atomic_write(path) as fh:
        fh.write(head + b"\0" * (_padded(len(head)) - len(head)))
        for data in blobs:
            fh.write(data)
            fh.write(b"\0" * (_padded(len(data)) - len(data)))


def load_vocabulary(path: str | Path, limit: int | None = None) -> Vocabulary:
    """Read a vocabulary: the binary format (by its magic) or else the ORB-SLAM2 text format.

    The file's size and every array's declared size are checked against the artifact load cap
    (`placerec.io.limits`, or ``limit`` bytes) before anything is read or decompressed; the header, each array's
    dtype, shape, offset, codec and checksum, finite weights and centres and the tree's shape (at most ``k``
    children per node, at most ``L`` levels) are validated. Anything wrong is an `ArtifactError` naming the file.
    """
    path = Path(path)
    if not path.is_file():
        raise ArtifactError(f"{path}: no such vocabulary file")
    check_size(path.stat().st_size, path, "vocabulary file size", ArtifactError, "artifact", limit)
    try:
        with open(path, "rb") as fh:
            if fh.read(len(MAGIC)) != MAGIC:
                return read_text_vocabulary(path)
            data = MAGIC + fh.read()
    except OSError as exc:
        raise ArtifactError(f"{path}: cannot read the vocabulary file ({exc.strerror or exc})") from None
    header, base = _read_binary_header(data, path)
    arrays = {name: _read_array(data, base, header, name, path, limit) for name in _ARRAY_DTYPES}
    end = base + max(
        header["arrays"][n]["offset"] + _padded(header["arrays"][n]["stored_bytes"]) for n in _ARRAY_DTYPES
    )
    if len(data) != end:
        raise ArtifactError(f"{path}: vocabulary file has {len(data)} bytes, its header describes {end}")
    centres = arrays["centres"]
    if header["kind"] == "binary":
        centres = centres.astype(np.uint8, copy=False)
    else:
        centres = centres.astype(np.float32) * np.float32(header["centre_scale"])
    for name, values in (("weights", arrays["weights"]), ("centres", centres)):
        if values.dtype.kind == "f" and not np.isfinite(values).all():
            raise ArtifactError(f"{path}: vocabulary {name} hold NaN or infinite values")
    _check_tree(arrays["parents"], header["k"], header["L"], path)
    voc = Vocabulary(
        header["k"], header["L"], arrays["parents"], centres, arrays["weights"], header["weighting"],
        header["scoring"], header["meta"],
    )  # fmt: skip
    if voc.n_words != header["n_words"]:
        raise ArtifactError(f"{path}: the tree has {voc.n_words} words, the header says {header['n_words']}")
    return voc


# the stored dtype of each array: parents and weights fixed, centres by ``centre_dtype`` (and kind)
_ARRAY_DTYPES = {"parents": ("<i4",), "weights": ("<f4",), "centres": None}
_CENTRE_DTYPES = {"binary": ("uint8",), "float": ("float32", "float16", "int8")}
_INT, _STR, _NUM, _OBJ = (
    (int, "an integer"),
    (str, "a string"),
    ((int, float), "a number"),
    (dict, "an object"),
)
_HEADER_TYPES: dict[str, tuple[type | tuple[type, ...], str]] = {
    "k": _INT, "L": _INT, "weighting": _STR, "scoring": _STR, "kind": _STR, "descriptor_size": _INT, "n_nodes": _INT,
    "n_words": _INT, "centre_dtype": _STR, "centre_scale": _NUM, "arrays": _OBJ, "meta": _OBJ,
}  # fmt: skip


def _read_binary_header(data: bytes, path: Path) -> tuple[dict[str, Any], int]:
    """The validated JSON header of a binary vocabulary and the offset where its payload starts."""
    if len(data) < len(MAGIC) + 12:
        raise ArtifactError(f"{path}: truncated vocabulary file (no header)")
    version, n_head, crc = struct.unpack_from("<III", data, len(MAGIC))
    if version not in _READ_VERSIONS:
        raise ArtifactError(
            f"{path}: vocabulary format version {version} is not supported (this placerec reads {list(_READ_VERSIONS)})"
        )
    head_start = len(MAGIC) + (8 if version == 1 else 12)
    head_end = head_start + n_head
    if head_end > len(data):
        raise ArtifactError(f"{path}: truncated vocabulary file (header of {n_head} bytes)")
    blob = data[head_start:head_end]
    if version > 1 and zlib.crc32(blob) != crc:
        raise ArtifactError(f"{path}: corrupt vocabulary file (checksum of the header)")
    header = json_object(blob, f"{path}: vocabulary header")
    for key, (types, expected) in _HEADER_TYPES.items():
        value = header.get(key)
        if not isinstance(value, types) or isinstance(value, bool):
            raise ArtifactError(
                f"{path}: vocabulary header {key!r} is {short_repr(value)}, expected {expected}"
            )
    kind = header["kind"]
    if kind not in _CENTRE_DTYPES or header["centre_dtype"] not in _CENTRE_DTYPES[kind]:
        raise ArtifactError(
            f"{path}: vocabulary kind {short_repr(kind)} with centre_dtype {short_repr(header['centre_dtype'])}; "
            f"expected one of {_CENTRE_DTYPES}"
        )
    scale = header["centre_scale"]
    if not (math.isfinite(scale) and scale > 0):
        raise ArtifactError(f"{path}: vocabulary centre_scale must be a positive number, got {scale}")
    if not (
        1 < header["k"] <= 1000
        and 0 < header["L"] <= 20
        and header["n_nodes"] > 0
        and header["descriptor_size"] > 0
    ):
        raise ArtifactError(
            f"{path}: implausible vocabulary header k={header['k']}, L={header['L']}, n_nodes={header['n_nodes']}, "
            f"descriptor_size={header['descriptor_size']}"
        )
    return header, _padded(head_end)


def _read_array(
    data: bytes, base: int, header: dict[str, Any], name: str, path: Path, limit: int | None
) -> np.ndarray:
    """One array of the payload, after checking its table entry against the header and the load cap."""
    spec = header["arrays"].get(name)
    if not isinstance(spec, dict):
        raise ArtifactError(f"{path}: vocabulary header has no entry for array {name!r}")
    n = header["n_nodes"]
    shape = [n, header["descriptor_size"]] if name == "centres" else [n]
    dtypes = _ARRAY_DTYPES[name] or (np.dtype(header["centre_dtype"]).newbyteorder("<").str,)
    if spec.get("dtype") not in dtypes or spec.get("shape") != shape:
        raise ArtifactError(
            f"{path}: vocabulary array {name!r} is {short_repr(spec.get('dtype'))} {short_repr(spec.get('shape'))}, "
            f"expected {dtypes[0]} {shape}"
        )
    dtype = np.dtype(spec["dtype"])
    nbytes = check_size(math.prod(shape) * dtype.itemsize, path, f"vocabulary array {name!r}", ArtifactError,
                        "artifact", limit)  # fmt: skip
    offset, stored, codec = spec.get("offset"), spec.get("stored_bytes"), spec.get("codec")
    if codec not in ("raw", "zlib"):
        raise ArtifactError(
            f"{path}: vocabulary array {name!r} has unknown codec {short_repr(codec)}; expected raw or zlib"
        )
    if not (isinstance(offset, int) and isinstance(stored, int) and offset >= 0 and stored >= 0):
        raise ArtifactError(f"{path}: vocabulary array {name!r} has no valid offset and stored_bytes")
    a = base + offset
    if a + stored > len(data):
        raise ArtifactError(f"{path}: truncated vocabulary file (array {name!r})")
    blob = memoryview(data)[a : a + stored]
    if zlib.crc32(blob) != spec.get("crc32"):
        raise ArtifactError(f"{path}: corrupt vocabulary file (checksum of {name!r})")
    raw: bytes | memoryview
    if codec == "zlib":
        try:
            inflater = zlib.decompressobj()
            raw = inflater.decompress(blob, nbytes + 1)  # never more than declared (+1 to notice excess)
        except zlib.error as exc:
            raise ArtifactError(f"{path}: corrupt vocabulary file (array {name!r}: {exc})") from None
        complete = inflater.eof
    else:
        raw, complete = blob, True
    if len(raw) != nbytes or not complete:
        raise ArtifactError(f"{path}: vocabulary array {name!r} holds {len(raw)} bytes, expected {nbytes}")
    return np.frombuffer(raw, dtype).reshape(shape)


def _check_tree(parents: np.ndarray, k: int, L: int, path: Path) -> None:
    """Parents must form a tree of at most ``k`` children per node and ``L`` levels below the root (checked in
    L vectorised steps, before `Vocabulary` builds tables sized by them)."""
    p = parents.astype(np.int64)
    n = p.size
    if n == 0 or p[0] != -1 or (p[1:] < 0).any() or (p[1:] >= np.arange(1, n)).any():
        raise ArtifactError(f"{path}: vocabulary parents must start with the root (-1), then earlier nodes")
    children = np.bincount(p[1:], minlength=n)
    if children.max(initial=0) > k:
        raise ArtifactError(f"{path}: a vocabulary node has {children.max()} children, more than k={k}")
    up = p.copy()
    up[0] = 0
    node = np.arange(n)
    for _ in range(L):
        node = up[node]
    if node.any():
        raise ArtifactError(f"{path}: the vocabulary tree is deeper than L={L} levels")


def write_text_vocabulary(voc: Vocabulary, path: str | Path) -> None:
    """Write ``voc`` in the ORB-SLAM2 text format (weights and float centres with 9 significant digits, which
    round-trips float32 exactly)."""
    scoring = {v: k for k, v in _SCORING.items()}[voc.scoring]
    weighting = {v: k for k, v in _WEIGHTING.items()}[voc.weighting]
    n = voc.n_nodes
    cols = [voc.parents[1:].astype(np.int64).astype(str), voc.is_leaf[1:].astype(np.int64).astype(str)]
    if voc.binary:
        cents = voc.centres[1:].astype(np.int64).astype(str)
    else:
        cents = np.char.mod("%.9g", voc.centres[1:].astype(np.float64))
    w = np.char.mod("%.9g", voc.weights[1:].astype(np.float64))
    table = np.column_stack([cols[0], cols[1], cents, w]) if n > 1 else np.zeros((0, 3), str)
    lines = [f"{voc.k} {voc.L}  {scoring} {weighting}"] + [" ".join(row) for row in table]
    with atomic_write(path, "w") as fh:
        fh.write("\n".join(lines) + "\n")


def read_text_vocabulary(path: str | Path, kind: str | None = None, limit: int | None = None) -> Vocabulary:
    """Read an ORB-SLAM2 / DBoW2 text vocabulary. ``kind`` "binary" or "float"; None = binary when every
    descriptor value is an integer in 0..255 (as in ORB vocabularies). The file size is checked against the
    artifact load cap (or ``limit``) first; parents, binary centres, finite weights and the tree's shape are
    validated as for the binary format."""
    path = Path(path)
    try:
        check_size(path.stat().st_size, path, "vocabulary file size", ArtifactError, "artifact", limit)
        text = path.read_text(encoding="ascii", errors="strict")
    except FileNotFoundError:
        raise ArtifactError(f"{path}: no such vocabulary file") from None
    except (UnicodeDecodeError, OSError) as exc:
        raise ArtifactError(f"{path}: not a text vocabulary ({exc})") from exc
    first, _, body = text.partition("\n")
    try:
        k, L, n1, n2 = (int(v) for v in first.split())
    except ValueError:
        raise ArtifactError(
            f"{path}: not a DBoW2 text vocabulary (first line must be 'k L scoring weighting', got {first[:60]!r})"
        ) from None
    if not (1 < k <= 1000 and 0 < L <= 20 and n1 in _SCORING and n2 in _WEIGHTING):
        raise ArtifactError(f"{path}: implausible vocabulary header {first!r}")
    lines = body.strip().split("\n", 1)
    if not lines[0].strip():
        raise ArtifactError(f"{path}: vocabulary has no nodes")
    n_cols = len(lines[0].split())
    n_lines = body.strip().count("\n") + 1
    try:
        with warnings.catch_warnings():
            warnings.simplefilter(
                "ignore", DeprecationWarning
            )  # NumPy < 2.3 warns when a token is not a number
            values = np.fromstring(body, dtype=np.float64, sep=" ")
    except ValueError:  # NumPy >= 2.3 raises instead
        values = np.zeros(0)
    if n_cols < 4 or values.size != n_lines * n_cols:
        raise ArtifactError(
            f"{path}: malformed node lines: expected {n_lines} lines of {n_cols} numbers "
            f"(as on the first), read {values.size} numbers"
        )
    table = values.reshape(-1, n_cols)
    if not np.isfinite(table).all():
        raise ArtifactError(f"{path}: node lines hold NaN or infinite values")
    if (table[:, 0] != np.round(table[:, 0])).any() or (np.abs(table[:, 0]) >= 2**31).any():
        raise ArtifactError(f"{path}: node parents must be integer node ids")
    parents = np.r_[-1, table[:, 0]].astype(np.int64)
    _check_tree(parents, k, L, path)
    desc = table[:, 2:-1]
    is_byte = bool(np.all((desc == np.round(desc)) & (desc >= 0) & (desc <= 255)))
    if kind is None:
        kind = "binary" if is_byte else "float"
    if kind not in ("binary", "float"):
        raise ArtifactError(f"{path}: kind must be 'binary' or 'float', got {kind!r}")
    if kind == "binary" and not is_byte:
        raise ArtifactError(f"{path}: a binary vocabulary's descriptor values must be integers in 0..255")
    centres = np.vstack([np.zeros((1, desc.shape[1])), desc])
    centres = centres.astype(np.uint8) if kind == "binary" else centres.astype(np.float32)
    weights = np.r_[0.0, table[:, -1]]
    is_leaf = table[:, 1] > 0
    voc = Vocabulary(k, L, parents, centres, weights, _WEIGHTING[n2], _SCORING[n1], {"source": str(path)})
    if not np.array_equal(voc.is_leaf[1:], is_leaf):
        log.warning("%s: leaf flags disagree with the tree structure; using the structure", path)
    return voc


def _padded(n: int) -> int:
    return -(-n // _ALIGN) * _ALIGN


def _jsonable(meta: dict[str, Any]) -> dict[str, Any]:
    return json.loads(json.dumps(meta, default=str))
