"""Intensity images from scans (cylindrical / per-beam / organised) with empty-row interpolation."""

from placerec.image.projection import (
    ImageParams,
    IntensityImage,
    detect_empty_rows,
    fill_empty_rows,
    from_organized,
    make_image,
    project_per_beam,
    project_uniform,
    to_uint8,
)

__all__ = [
    "ImageParams",
    "IntensityImage",
    "make_image",
    "project_uniform",
    "project_per_beam",
    "from_organized",
    "detect_empty_rows",
    "fill_empty_rows",
    "to_uint8",
]
