"""Baseline place recognizers (geometry only) to compare placerec's intensity pipelines against."""

from placerec.baselines.scan_context import (
    ScanContext,
    ScanContextParams,
    make_descriptor,
    ring_key,
    scan_context_distance,
    sector_key,
)

__all__ = [
    "ScanContext",
    "ScanContextParams",
    "make_descriptor",
    "ring_key",
    "scan_context_distance",
    "sector_key",
]
