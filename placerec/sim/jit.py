"""Numba compilation settings shared by the simulator's kernels, and argument flattening for array wrappers.

The simulator's per-hit arithmetic (noise, texture primitives, the intensity model, hit gathering) runs in small
Numba kernels: one pass over the hits instead of dozens of NumPy temporaries. Kernels are compiled on first use
and cached on disk (``__pycache__`` next to the module, or ``NUMBA_CACHE_DIR``), and release the GIL, so the two
halves of a sweep shade in parallel threads.
"""

from __future__ import annotations

import functools
import hashlib
from pathlib import Path

import numpy as np
from numba import njit as _numba_njit

from placerec.numba_cache import needs_compile

__all__ = ["njit", "inline", "needs_compile", "flat_args", "elementwise", "KERNEL_MODULES"]

#: the modules whose code the compiled kernels contain (helpers are inlined across modules, and module constants
#: such as the material parameter indices are frozen into the machine code)
KERNEL_MODULES = (
    "jit.py",
    "noise.py",
    "materials.py",
    "textures.py",
    "intensity.py",
    "world.py",
    "render.py",
)


@functools.cache
def _kernel_sources_stamp() -> bytes:
    h = hashlib.sha256()
    for name in KERNEL_MODULES:
        h.update((Path(__file__).parent / name).read_bytes())
    return h.digest()


def _stamped(dispatcher):
    """Key the dispatcher's disk cache on all `KERNEL_MODULES`, not only on its own file: Numba checks just the
    defining file, so an edit to an inlined helper elsewhere would otherwise load stale machine code."""
    cache_file = getattr(getattr(dispatcher, "_cache", None), "_cache_file", None)
    if cache_file is not None and hasattr(cache_file, "_source_stamp"):
        cache_file._source_stamp = (cache_file._source_stamp, _kernel_sources_stamp())
    return dispatcher


def njit(fn=None, **options):
    """``@njit``: nopython, cached on disk (keyed on all kernel sources), GIL released while running."""
    decorate = _numba_njit(cache=True, nogil=True, **options)
    return (lambda f: _stamped(decorate(f))) if fn is None else _stamped(decorate(fn))


def inline(fn):
    """``@inline``: a small per-hit helper, inlined into its callers at Numba IR level. Separately compiled Numba
    functions are not inlined by LLVM, and a call per helper per hit would cost more than the arithmetic."""
    return njit(fn, inline="always")


def flat_args(args: tuple, dtypes: tuple) -> tuple[tuple[int, ...], list[np.ndarray]]:
    """Broadcast ``args`` to one shape and return (shape, contiguous 1-D arrays of the given dtypes).

    One memory layout and dtype per argument means one compiled specialisation per kernel.
    """
    arrays = [np.asarray(a) for a in args]
    shape = np.broadcast_shapes(*(a.shape for a in arrays))
    flat = [
        np.ascontiguousarray(np.broadcast_to(a.astype(dt, copy=False), shape)).reshape(-1)
        for a, dt in zip(arrays, dtypes, strict=True)
    ]
    return shape, flat


def elementwise(kernel, args: tuple, dtypes: tuple, out_dtype, *extra) -> np.ndarray:
    """Run ``kernel(*flat_args, *extra, out)`` over the broadcast ``args`` and return ``out`` in their shape."""
    shape, flat = flat_args(args, dtypes)
    out = np.empty(flat[0].shape[0], dtype=out_dtype)
    kernel(*flat, *extra, out)
    return out.reshape(shape)
