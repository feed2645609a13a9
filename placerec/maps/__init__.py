"""Maps that outlive a session: the map artifact (`placerec.maps.artifact`), relocalisation against it
(`placerec.maps.localizer`). ``placerec map build``, ``placerec localize`` and ``placerec slam --prior-map`` use
them; docs/maps.md shows the whole workflow."""

from placerec.maps.artifact import MapArtifact, MapGraph, MapMismatchError, MapWriter, is_map_folder
from placerec.maps.localizer import Fix, Localizer, LocalizerParams, TrackingParams

__all__ = [
    "MapArtifact",
    "MapWriter",
    "MapGraph",
    "MapMismatchError",
    "is_map_folder",
    "Localizer",
    "LocalizerParams",
    "TrackingParams",
    "Fix",
]
