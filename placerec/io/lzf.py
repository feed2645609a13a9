"""LZF (liblzf) compression as used by PCD ``binary_compressed`` files.

Stream format: a control byte ``c``. ``c < 32``: a literal run of ``c + 1`` bytes follows. Otherwise a
back-reference: length ``(c >> 5) + 2`` (when ``c >> 5 == 7`` one more byte is added to the length), distance
``((c & 31) << 8 | next byte) + 1`` back from the current output position; the copy may overlap itself.

Decompression is inherently sequential; `lzf_decompress` keeps the sequential part small (a hop from token to
token, then the back-references in order) and copies all literal runs in one vectorised step.
`lzf_compress` writes a valid LZF stream with a vectorised match search: for a fixed set of distances
(1, 2, 4, ... 4096 bytes) numpy finds, at every position, the longest run that repeats the data that many bytes
back, and a short greedy loop over the resulting tokens emits them. It does not search arbitrary distances like
liblzf's hash table, so it compresses a little less, but it runs at numpy speed and any LZF decoder
(PCL's included) reads its output.
"""

from __future__ import annotations

from bisect import bisect_left

import numpy as np

__all__ = ["lzf_compress", "lzf_decompress", "LZFError"]

_MAX_LIT = 32
_MAX_REF = 264  # 7 + 255 + 2
_MAX_OFF = 8192
_DISTANCES = (1, 2, 4, 8, 12, 16, 32, 64, 256, 1024, 4096)


_STEP = bytes(c + 2 if c < 32 else (3 if c >= 224 else 2) for c in range(256))  # token size by control byte


class LZFError(ValueError):
    """The compressed stream is corrupt or does not decompress to the announced size."""


def _ranges(starts: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """Concatenated ``arange(s, s + l)`` for every (s, l), vectorised."""
    total = int(lengths.sum())
    first = np.cumsum(lengths) - lengths
    return np.arange(total, dtype=np.int64) + np.repeat(starts - first, lengths)


def _tokens(src: bytes) -> np.ndarray:
    """Input offsets of all control bytes: the one step of LZF decoding that cannot be vectorised."""
    n = len(src)
    positions: list[int] = []
    append = positions.append
    step = _STEP
    ip = 0
    while ip < n:
        append(ip)
        ip += step[src[ip]]
    if ip != n:
        raise LZFError(f"the last token at input offset {positions[-1]} runs past the end of the input")
    return np.asarray(positions, dtype=np.int64)


def _copy_references(out: np.ndarray, op: np.ndarray, length: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Perform back-references (sorted by output offset) on ``out``, whose literal bytes are already placed.

    In waves: a reference whose source window holds no byte still to be written by a pending reference is
    ready; all ready ones are copied at once (``src + k % dist`` also covers overlapping copies). The first
    pending reference is always ready, so every wave progresses; when waves get small the rest is done by a
    plain loop in stream order.
    """
    while op.size:
        src = op - dist
        window_end = src + np.minimum(dist, length)
        first = np.searchsorted(op + length, src, side="right")
        ready = op[np.minimum(first, op.size - 1)] >= window_end
        ready[0] = True
        if ready.sum() < max(512, op.size // 16):  # small waves: the loop is cheaper
            break
        k = _ranges(np.zeros(int(ready.sum()), np.int64), length[ready])
        rep = np.repeat(np.arange(int(ready.sum())), length[ready])
        out[op[ready][rep] + k] = out[src[ready][rep] + k % dist[ready][rep]]
        op, length, dist = op[~ready], length[~ready], dist[~ready]
    if not op.size:
        return out
    buf = bytearray(out.tobytes())
    for o, ln, d in zip(op.tolist(), length.tolist(), dist.tolist(), strict=True):
        ref = o - d
        if d >= ln:
            buf[o : o + ln] = buf[ref : ref + ln]
        else:  # overlapping copy repeats the last `d` bytes
            buf[o : o + ln] = (bytes(buf[ref:o]) * (ln // d + 1))[:ln]
    return np.frombuffer(bytes(buf), dtype=np.uint8)


def lzf_decompress(src: bytes | bytearray | memoryview, out_size: int) -> bytes:
    """Decompress an LZF stream that must expand to exactly ``out_size`` bytes.

    A tight loop only hops from control byte to control byte (`_tokens`); numpy then decodes every token's
    length and distance, places all literal bytes with two boolean masks (they keep their order from input
    to output) and performs the back-references in vectorised waves (`_copy_references`).
    """
    if out_size < 0:
        raise LZFError(f"negative output size {out_size}")
    src = bytes(src)
    n = len(src)
    # A 3-byte back-reference yields at most 264 bytes: anything above is a lie, refuse it before allocating.
    if out_size > 88 * n + 32:
        raise LZFError(f"{n} compressed bytes cannot expand to {out_size} bytes")
    if n == 0:
        if out_size:
            raise LZFError(f"empty stream, expected {out_size} bytes")
        return b""
    tok = _tokens(src)
    arr = np.frombuffer(src, dtype=np.uint8)
    ctrl = arr[tok].astype(np.int64)
    lit = ctrl < 32
    ref = ~lit
    ext = ctrl >= 224
    length = np.where(lit, ctrl + 1, (ctrl >> 5) + 2)
    length[ext] += arr[tok[ext] + 1]
    dist = ((ctrl & 31) << 8 | arr[np.where(ref, tok + 1 + ext, 0)]) + 1
    op = np.cumsum(length) - length
    total = int(op[-1] + length[-1])
    if total != out_size:
        raise LZFError(f"stream decompresses to {total} bytes, expected {out_size}")
    bad = ref & (dist > op)
    if bad.any():
        k = int(np.argmax(bad))
        raise LZFError(
            f"back-reference {int(dist[k])} bytes before output offset {int(op[k])} points before the start"
        )
    payload = np.ones(n, dtype=bool)  # input bytes that are literal data
    payload[tok] = False
    payload[tok[ref] + 1] = False
    payload[tok[ext] + 2] = False
    r_op, r_len, r_dist = op[ref], length[ref], dist[ref]
    edges = np.zeros(out_size + 1, dtype=np.int8)  # output bytes written by references
    edges[r_op] = 1
    edges[r_op + r_len] -= 1
    from_literal = np.cumsum(edges[:-1], dtype=np.int8) == 0
    out = np.empty(out_size, dtype=np.uint8)
    out[from_literal] = arr[payload]
    return _copy_references(out, r_op, r_len, r_dist).tobytes()


def _best_matches(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per position: the longest usable match length (0 when < 3) and its distance, over `_DISTANCES`."""
    n = a.size
    best_len = np.zeros(n, dtype=np.int32)
    best_dist = np.zeros(n, dtype=np.int32)
    for d in _DISTANCES:
        if d >= n:
            break
        eq = np.zeros(n - d + 2, dtype=bool)
        np.equal(a[d:], a[:-d], out=eq[1:-1])
        edges = np.flatnonzero(eq[1:] != eq[:-1])  # alternating run starts and ends
        s, e = edges[0::2], edges[1::2]
        keep = (e - s) >= 3
        s, e = s[keep], e[keep]
        if s.size == 0:
            continue
        cover = e - s - 2  # positions of a run from which at least 3 bytes still match
        total = int(cover.sum())
        first = np.cumsum(cover) - cover
        pos = np.arange(total, dtype=np.int64) + np.repeat(s - first, cover)
        length = np.minimum(np.repeat(e, cover) - pos, _MAX_REF).astype(np.int32)
        pos += d
        better = length > best_len[pos]
        best_len[pos[better]] = length[better]
        best_dist[pos[better]] = d
    return best_len, best_dist


def lzf_compress(data: bytes | bytearray | memoryview) -> bytes:
    """Compress ``data`` into an LZF stream (see the module docstring for the method)."""
    a = np.frombuffer(bytes(data), dtype=np.uint8)
    n = a.size
    if n == 0:
        return b""
    best_len, best_dist = _best_matches(a)
    starts_arr = np.flatnonzero(best_len >= 3)
    starts = starts_arr.tolist()
    lens = best_len[starts_arr].tolist()
    offs = (best_dist[starts_arr] - 1).tolist()
    raw = a.tobytes()
    out = bytearray()
    i = 0
    k = 0
    ns = len(starts)
    while i < n:
        if k < ns and starts[k] < i:
            k = bisect_left(starts, i, k)
        j = starts[k] if k < ns else n
        while i < j:  # literal runs of at most 32 bytes
            c = min(_MAX_LIT, j - i)
            out.append(c - 1)
            out += raw[i : i + c]
            i += c
        if j >= n:
            break
        ln = lens[k]
        off = offs[k]
        code = ln - 2
        if code < 7:
            out += bytes(((code << 5) | (off >> 8), off & 0xFF))
        else:
            out += bytes(((7 << 5) | (off >> 8), code - 7, off & 0xFF))
        i = j + ln
        k += 1
    return bytes(out)
