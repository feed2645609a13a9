"""Whether a Numba kernel will compile on its first call, so that a one-off wait can be announced."""

from __future__ import annotations

__all__ = ["needs_compile"]


def needs_compile(dispatcher) -> bool:
    """True when ``dispatcher`` has no compiled code in this process and none usable in its disk cache (the first
    use will compile). False when unsure (Numba internals differ)."""
    if dispatcher.signatures:
        return False
    try:
        return not dispatcher._cache._cache_file._load_index()
    except Exception:  # noqa: BLE001 - private Numba API; only used to tell the user about a one-off wait
        return False
