"""LZF (liblzf) compression as used by PCD ``binary_compressed`` files.

Stream format: a control byte ``c``. ``c < 32``: a literal run of ``c + 1`` bytes follows. Otherwise a
back-reference: length ``(c >> 5) + 2`` (when ``c >> 5 == 7`` one more byte is added to the length), distance
``((c & 31) << 8 | next byte) + 1`` back from the current output position; the copy may overlap itself.

Decompression is inherently sequential: `lzf_decompress` walks the tokens in a tight loop but copies every
literal run and back-reference as one slice, so its cost grows with the number of tokens, not of bytes.
`lzf_compress` writes a valid LZF stream with a vectorised match search: for a fixed set of distances
(1, 2, 4, ... 8192 bytes) numpy finds, at every position, the longest run that repeats the data that many bytes
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
_DISTANCES = (1, 2, 3, 4, 8, 12, 16, 32, 64, 256, 1024, 4096, 8192)


class LZFError(ValueError):
    """The compressed stream is corrupt or does not decompress to the announced size."""


def lzf_decompress(src: bytes | bytearray | memoryview, out_size: int) -> bytes:
    """Decompress an LZF stream that must expand to exactly ``out_size`` bytes."""
    if out_size < 0:
        raise LZFError(f"negative output size {out_size}")
    src = bytes(src)
    n = len(src)
    # A 3-byte back-reference yields at most 264 bytes: anything above is a lie, refuse it before allocating.
    if out_size > 88 * n + 32:
        raise LZFError(f"{n} compressed bytes cannot expand to {out_size} bytes")
    out = bytearray(out_size)
    ip = 0
    op = 0
    while ip < n:
        c = src[ip]
        ip += 1
        if c < 32:
            c += 1
            if ip + c > n:
                raise LZFError(f"literal run of {c} bytes at input offset {ip - 1} runs past the end of the input")
            if op + c > out_size:
                raise LZFError(f"output overflows {out_size} bytes at input offset {ip - 1}")
            out[op : op + c] = src[ip : ip + c]
            op += c
            ip += c
        else:
            ln = c >> 5
            if ln == 7:
                if ip >= n:
                    raise LZFError("truncated back-reference at the end of the input")
                ln += src[ip]
                ip += 1
            if ip >= n:
                raise LZFError("truncated back-reference at the end of the input")
            dist = ((c & 31) << 8 | src[ip]) + 1
            ip += 1
            ln += 2
            ref = op - dist
            if ref < 0:
                raise LZFError(f"back-reference {dist} bytes before output offset {op} points before the start")
            if op + ln > out_size:
                raise LZFError(f"output overflows {out_size} bytes at input offset {ip}")
            if dist >= ln:
                out[op : op + ln] = out[ref : ref + ln]
            else:  # overlapping copy repeats the last `dist` bytes
                pattern = bytes(out[ref:op])
                out[op : op + ln] = (pattern * (ln // dist + 1))[:ln]
            op += ln
    if op != out_size:
        raise LZFError(f"stream decompresses to {op} bytes, expected {out_size}")
    return bytes(out)


def _best_matches(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per position: the longest usable match length (0 when < 3) and its distance, over `_DISTANCES`."""
    n = a.size
    best_len = np.zeros(n, dtype=np.int32)
    best_dist = np.zeros(n, dtype=np.int32)
    for d in _DISTANCES:
        if d >= n:
            break
        eq = np.empty(n - d + 2, dtype=np.int8)
        eq[0] = eq[-1] = 0
        np.equal(a[d:], a[:-d], out=eq[1:-1].view(bool))
        edges = np.diff(eq)
        s = np.flatnonzero(edges == 1)
        e = np.flatnonzero(edges == -1)
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
